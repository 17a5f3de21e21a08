"""Landmarks from a height map: particles (spheres) and tubes/rods, with their uncertainty.

Book 5.2 and 7.2.2 (SPEC sections 2-3). A landmark is a feature of the sample whose centre
the tip can find again by a local scan: the Kalman filter compares what a local scan line
sees with the landmark's position in the map, weighted by the landmark's covariance.

How a map becomes landmarks (`extract_landmarks`):

1. Substrate: a plane fitted robustly to the non-feature pixels (iteratively, from the
   lower half of the pixels; pixels more than a few robust sigmas or half of `min_height`
   above it are features and are left out, and so are pits below it), so a tilted user
   image works as well as a levelled one. Heights are taken above
   that plane.
2. Features: the peaks of the levelled map that rise at least `min_height` above the
   substrate. Touching particles are told apart by their saddle: a peak is a feature of
   its own when it stands out of the saddle that joins it to a higher one by at least
   max(min_height / 2, 10 % of its height) (a topographic prominence, computed by
   flooding the map from the top), so noise on a particle's top never makes a second one.
3. Centre (book 7.2.2): binarise at each height threshold (fractions `thresholds` of the
   peak height above the substrate, 0.3 ... 0.7 by default) and take the centre of gravity
   of the connected region around the peak; the centre is the mean over the thresholds.
   A particle joined to another by a saddle uses the same fractions of the part above its
   saddle, where the two regions are apart and each centroid is unbiased.
4. Uncertainty: the book calibrates the map error by the spread of particle centres over
   repeated images and thresholds (Fig. 7.10: sigma 5.0 nm in x, 4.5 nm in y). The
   covariance is that model (`MapErrorModel`) plus this map's own spread of the centroid
   across the thresholds (a lopsided or noisy particle moves with the threshold).
5. Kind and shape from the region's second moments: elongation = sqrt(largest / smallest
   eigenvalue). Below `tube_elongation` a feature is a "sphere", otherwise elongated: a
   "tube" (carbon-nanotube-like, at most `tube_max_height` high) or a "rod" (taller). The
   orientation is the principal axis (rad from +x, in (-pi/2, pi/2]).
6. Size. Heights are not broadened by the tip, lateral sizes are (book 4: a 20 nm high
   tube imaged 49 nm wide): a sphere or a cylinder lying on the substrate is as high as it
   is wide, so `radius` = apparent height / 2. For an elongated feature the level set at
   any threshold of a tip-dilated capsule is a stadium (all points within a half-width w
   of the axis segment); from the region's area A and its extent E along the axis,
   A = 2 w L + pi w^2 and E = L + 2 w give w and the axis length L = E - 2 w, in which the
   tip broadening and the round ends cancel. `length` is that L (the end-to-end apparent
   length at half height is length + 2 * half_width).

Regions touching the image border are skipped: part of the particle is outside the image,
so the centre of gravity of what is inside is biased towards the image's interior.

The map should be drift-corrected first (afm_core.imaging.drift_compensation) when it is to be a
localization map: this module measures the image as it is.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

PROMINENCE_FRACTION = (
    0.1  # a peak is a feature of its own if it stands out this much of its height ...
)
PROMINENCE_MIN_HEIGHT = 0.5  # ... and at least this fraction of min_height out of its saddle
_EIGHT = np.ones((3, 3), dtype=bool)


@dataclass
class Landmark:
    """One landmark, in the map's frame (pixel (row, col) centre at origin + (col + 0.5) * pixel_x,
    origin + (row + 0.5) * pixel_y). SI units: m, m^2, rad."""

    id: int
    kind: str  # "sphere" | "tube" | "rod"
    x: float  # m, centre (mean centre of gravity over the thresholds)
    y: float  # m
    covariance: np.ndarray = field(
        compare=False
    )  # 2x2, m^2: map error model + spread over thresholds
    radius: float  # m, apparent height / 2 (true radius of a sphere or cylinder on the substrate)
    height: float  # m, apparent height above the substrate
    length: float  # m, axis length of a tube/rod (tip broadening removed); 0 for a sphere
    orientation: float  # rad from +x in (-pi/2, pi/2], axis of a tube/rod; 0 for a sphere
    half_width: float = (
        0.0  # m, apparent (tip-broadened) half-width at half height; sphere: apparent radius
    )
    elongation: float = 1.0  # sqrt of the ratio of the region's principal second moments
    thresholds_used: int = 0  # how many height thresholds the centre was averaged over


@dataclass(frozen=True)
class MapErrorModel:
    """Standard deviation of a landmark centre in a map (book Fig. 7.10: 5.0 / 4.5 nm)."""

    sigma_x: float = 5.0e-9  # m
    sigma_y: float = 4.5e-9  # m


def extract_landmarks(
    height: np.ndarray,
    pixel_size_x: float,
    pixel_size_y: float,
    origin_x: float = 0.0,
    origin_y: float = 0.0,
    min_height: float = 10e-9,
    thresholds: Sequence[float] = (0.3, 0.4, 0.5, 0.6, 0.7),
    error_model: MapErrorModel = MapErrorModel(),
    tube_elongation: float = 3.0,
    tube_max_height: float = 50e-9,
) -> list[Landmark]:
    """Landmarks of a height map (rows = y, metres), sorted by position (row of the centre,
    then x) with ids 0, 1, ... in that order, so the same map always gives the same ids.

    Features lower than `min_height` above the substrate are ignored, and so are features
    whose region touches the image border (their centre of gravity would be biased).
    Raises ValueError naming the argument for bad input (not a 2-D array, NaN or infinite
    pixels, non-positive pixel size, thresholds outside (0, 1), ...).
    """
    h = _validated(
        height,
        pixel_size_x,
        pixel_size_y,
        origin_x,
        origin_y,
        min_height,
        thresholds,
        error_model,
        tube_elongation,
        tube_max_height,
    )
    fractions = sorted(float(t) for t in thresholds)
    h = h - substrate_plane(h, min_height)
    detect = 0.5 * fractions[0] * min_height  # below every threshold level of every feature
    seeds = _peaks(h, detect, min_height)
    if not seeds:
        return []
    blobs, _ = ndimage.label(h > detect, structure=_EIGHT)
    slices = ndimage.find_objects(blobs)
    seed_pixels = {(p // h.shape[1], p % h.shape[1]) for p, _ in seeds}
    grid = _Grid(h.shape, pixel_size_x, pixel_size_y, origin_x, origin_y)
    found = []
    for peak, saddle in seeds:
        row, col = divmod(peak, h.shape[1])
        window = slices[blobs[row, col] - 1]
        measured = _measure(h, window, (row, col), saddle, fractions, seed_pixels, grid)
        if measured is not None:
            found.append(measured)
    landmarks = [
        _landmark(m, fractions, error_model, tube_elongation, tube_max_height) for m in found
    ]
    landmarks.sort(key=lambda lm: (math.floor((lm.y - origin_y) / pixel_size_y), lm.x))
    for number, landmark in enumerate(landmarks):
        landmark.id = number
    return landmarks


def scan_landmarks(scan, **options) -> list[Landmark]:
    """extract_landmarks of a scan-like record (height, pixel_size_x/_y, origin_x/_y: a
    RasterScanData or HeightMap), its pixel grid and position taken from it; `options` are
    extract_landmarks' keywords (min_height, tube_elongation, ...)."""
    return extract_landmarks(
        np.asarray(scan.height, float),
        scan.pixel_size_x,
        scan.pixel_size_y,
        scan.origin_x,
        scan.origin_y,
        **options,
    )


def substrate_plane(h: np.ndarray, min_height: float, iterations: int = 20) -> np.ndarray:
    """The substrate as a plane a + b col + c row fitted to the non-feature pixels.

    Starts from the lower half of the pixels (on a tilted but otherwise bare substrate that
    half already defines the plane; features are high), then refits on the pixels within
    3 robust sigmas of the plane (but never more than min_height / 2 above it, and at
    least 5 % of min_height either side), until that set stops changing."""
    rows, cols = np.indices(h.shape, dtype=float)
    design = np.stack(
        [np.ones(h.size), cols.ravel() / max(h.shape[1], 1), rows.ravel() / max(h.shape[0], 1)], 1
    )
    z = h.ravel()
    keep = z <= np.median(z)
    plane = np.full(z.size, float(np.median(z)))
    for _ in range(iterations):
        if keep.sum() < 3:
            break
        weighted = design * keep[:, None]  # normal equations: 3 x 3, fast on big maps
        coef, *_ = np.linalg.lstsq(weighted.T @ design, weighted.T @ z, rcond=None)
        plane = design @ coef
        resid = z - plane
        inliers = resid[keep]
        sigma = 1.4826 * float(np.median(np.abs(inliers - np.median(inliers))))
        band = max(3.0 * sigma, 0.05 * min_height)
        new_keep = (resid > -band) & (resid < min(band, 0.5 * min_height))
        if new_keep.sum() < 3 or np.array_equal(new_keep, keep):
            break
        keep = new_keep
    return plane.reshape(h.shape)


# -- internals ------------------------------------------------------------------------------


@dataclass
class _Grid:
    shape: tuple
    px: float
    py: float
    ox: float
    oy: float


@dataclass
class _Measured:
    centres: np.ndarray  # (n, 2) centroid per usable threshold
    fractions: list  # the thresholds used
    elongations: list
    orientations: list  # rad, per threshold
    extents: list  # m along the principal axis
    areas: list  # m^2
    height: float


def _validated(
    height, px, py, ox, oy, min_height, thresholds, error_model, tube_elongation, tube_max_height
):
    try:
        h = np.asarray(height, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"height: not a numeric array ({exc})") from exc
    if h.ndim != 2:
        raise ValueError(
            f"height: must be a 2-D array (rows = y), got {h.ndim}-D of shape {h.shape}"
        )
    if min(h.shape) < 1:
        raise ValueError(f"height: empty array of shape {h.shape}")
    bad = int(np.count_nonzero(~np.isfinite(h)))
    if bad:
        raise ValueError(f"height: {bad} NaN or infinite pixel(s); fill or crop them first")
    for name, value in (
        ("pixel_size_x", px),
        ("pixel_size_y", py),
        ("min_height", min_height),
        ("tube_max_height", tube_max_height),
    ):
        if not (
            isinstance(value, (int, float, np.floating, np.integer))
            and math.isfinite(value)
            and value > 0
        ):
            raise ValueError(f"{name}={value!r}: must be a finite number > 0 (m)")
    for name, value in (("origin_x", ox), ("origin_y", oy)):
        if not (isinstance(value, (int, float, np.floating, np.integer)) and math.isfinite(value)):
            raise ValueError(f"{name}={value!r}: must be a finite number (m)")
    try:
        values = [float(t) for t in thresholds]
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"thresholds={thresholds!r}: must be a sequence of numbers in (0, 1)"
        ) from exc
    if not values or not all(0.0 < t < 1.0 for t in values) or len(set(values)) != len(values):
        raise ValueError(
            f"thresholds={thresholds!r}: must be distinct fractions of the peak height in (0, 1)"
        )
    if not (math.isfinite(tube_elongation) and tube_elongation > 1.0):
        raise ValueError(f"tube_elongation={tube_elongation!r}: must be a finite ratio > 1")
    for name in ("sigma_x", "sigma_y"):
        value = getattr(error_model, name, None)
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
            raise ValueError(f"error_model.{name}={value!r}: must be a finite number >= 0 (m)")
    return h


def _peaks(h: np.ndarray, level: float, min_height: float) -> list[tuple[int, float]]:
    """(flat index of the peak pixel, saddle height) of every feature, flooding the pixels
    above `level` from the top (union-find, 8-connected). When two regions meet, the lower
    peak is a feature of its own if it stands out of the meeting height enough; the saddle
    of a feature is the highest level at which it meets another feature (-inf if never)."""
    ny, nx = h.shape
    width = nx + 2  # padded by one never-flooded pixel all round
    padded = np.full((ny + 2, width), -np.inf)
    padded[1:-1, 1:-1] = h
    flat = padded.ravel()
    above = np.flatnonzero(flat > level)
    order = above[np.argsort(-flat[above], kind="stable")]
    parent = np.full(flat.size, -1, dtype=np.int64).tolist()
    values = flat.tolist()
    steps = (-width - 1, -width, -width + 1, -1, 1, width - 1, width, width + 1)
    peak: dict[int, int] = {}
    confirmed: dict[int, list] = {}
    saddle: dict[int, float] = {}

    def find(i: int) -> int:
        root = i
        while parent[root] != root:
            root = parent[root]
        while parent[i] != root:
            parent[i], i = root, parent[i]
        return root

    def stands_out(top: float, z: float) -> bool:
        return top >= min_height and top - z >= max(
            PROMINENCE_MIN_HEIGHT * min_height, PROMINENCE_FRACTION * top
        )

    for i in order.tolist():
        roots = {find(i + s) for s in steps if parent[i + s] >= 0}
        if not roots:
            parent[i] = i
            peak[i], confirmed[i] = i, []
            continue
        if len(roots) == 1:
            parent[i] = roots.pop()
            continue
        ranked = sorted(roots, key=lambda root: (-values[peak[root]], peak[root]))
        main = ranked[0]
        parent[i] = main
        z = values[i]
        for other in ranked[1:]:
            joining = confirmed.pop(other)
            if stands_out(values[peak[other]], z):
                joining.append(peak[other])
            if joining:
                for seed in joining + [peak[main]]:
                    saddle.setdefault(seed, z)
                confirmed[main].extend(joining)
            del peak[other]
            parent[other] = main
    seeds = []
    for root, top in peak.items():
        for seed in confirmed[root] + ([top] if values[top] >= min_height else []):
            row, col = divmod(seed, width)
            seeds.append(((row - 1) * nx + (col - 1), saddle.get(seed, -math.inf)))
    return sorted(seeds)


def _measure(h, window, seed, saddle, fractions, seed_pixels, grid: _Grid) -> _Measured | None:
    sub = h[window]
    r0, c0 = window[0].start, window[1].start
    local = (seed[0] - r0, seed[1] - c0)
    top = float(h[seed])
    base = max(0.0, saddle)
    others = np.array(
        [
            (r - r0, c - c0)
            for r, c in seed_pixels
            if (r, c) != seed and 0 <= r - r0 < sub.shape[0] and 0 <= c - c0 < sub.shape[1]
        ],
        dtype=int,
    ).reshape(-1, 2)
    out = _Measured(np.empty((0, 2)), [], [], [], [], [], top)
    centres = []
    lowest_region = None
    for fraction in fractions:
        labels, _ = ndimage.label(sub > base + fraction * (top - base), structure=_EIGHT)
        region = labels == labels[local]
        if region[others[:, 0], others[:, 1]].any():
            continue  # still joined to another feature: centroid biased
        rows, cols = np.nonzero(region)
        rows_g, cols_g = rows + r0, cols + c0
        if (
            rows_g.min() == 0
            or cols_g.min() == 0
            or rows_g.max() == grid.shape[0] - 1
            or cols_g.max() == grid.shape[1] - 1
        ):
            return None  # cut by the image border: skip the feature
        xs = grid.ox + (cols_g + 0.5) * grid.px
        ys = grid.oy + (rows_g + 0.5) * grid.py
        mx, my = float(xs.mean()), float(ys.mean())
        dx, dy = xs - mx, ys - my
        cxx = float(np.mean(dx * dx)) + grid.px**2 / 12.0  # a pixel is a square, not a point
        cyy = float(np.mean(dy * dy)) + grid.py**2 / 12.0
        cxy = float(np.mean(dx * dy))
        spread = math.hypot(0.5 * (cxx - cyy), cxy)
        big, small = 0.5 * (cxx + cyy) + spread, 0.5 * (cxx + cyy) - spread
        angle = 0.5 * math.atan2(2.0 * cxy, cxx - cyy)
        ux, uy = math.cos(angle), math.sin(angle)
        along = dx * ux + dy * uy
        centres.append((mx, my))
        out.fractions.append(fraction)
        out.elongations.append(math.sqrt(big / max(small, 1e-300)))
        out.orientations.append(angle)
        out.extents.append(
            float(along.max() - along.min()) + abs(ux) * grid.px + abs(uy) * grid.py
        )
        out.areas.append(rows.size * grid.px * grid.py)
        if lowest_region is None:
            lowest_region = region
    if not centres:
        return None
    # apparent height: the highest 3x3 mean in the region (a third of the pixel noise; flattens a
    # sphere's top by only pixel^2 / (3 R))
    out.height = float(ndimage.uniform_filter(sub, size=3, mode="nearest")[lowest_region].max())
    out.centres = np.asarray(centres)
    return out


def _stadium(extent: float, area: float) -> tuple[float, float]:
    """Half-width w and axis length L of a stadium with end-to-end extent E and area A:
    A = 2 w L + pi w^2, E = L + 2 w  =>  (4 - pi) w^2 - 2 E w + A = 0 (the smaller root)."""
    k = 4.0 - math.pi
    disc = extent * extent - k * area
    w = (extent - math.sqrt(disc)) / k if disc > 0 else extent / 2.0
    w = min(w, extent / 2.0)
    return w, extent - 2.0 * w


def _landmark(
    m: _Measured, fractions, error_model: MapErrorModel, tube_elongation, tube_max_height
) -> Landmark:
    n = len(m.centres)
    x, y = (float(v) for v in m.centres.mean(axis=0))
    covariance = np.diag([error_model.sigma_x**2, error_model.sigma_y**2]).astype(float)
    if n >= 2:
        covariance = covariance + np.cov(m.centres, rowvar=False)
    covariance = 0.5 * (covariance + covariance.T)
    elongation = float(np.mean(m.elongations))
    half = int(np.argmin([abs(f - 0.5) for f in m.fractions]))  # the threshold nearest half height
    radius = 0.5 * m.height
    if elongation < tube_elongation:
        return Landmark(
            -1,
            "sphere",
            x,
            y,
            covariance,
            radius,
            m.height,
            0.0,
            0.0,
            half_width=math.sqrt(m.areas[half] / math.pi),
            elongation=elongation,
            thresholds_used=n,
        )
    doubled = np.mean(np.exp(2j * np.asarray(m.orientations)))
    orientation = 0.5 * float(np.angle(doubled))
    if orientation <= -math.pi / 2:
        orientation += math.pi
    shapes = [_stadium(e, a) for e, a in zip(m.extents, m.areas)]
    length = float(np.mean([L for _, L in shapes]))
    kind = "tube" if m.height <= tube_max_height else "rod"
    return Landmark(
        -1,
        kind,
        x,
        y,
        covariance,
        radius,
        m.height,
        length,
        orientation,
        half_width=shapes[half][0],
        elongation=elongation,
        thresholds_used=n,
    )
