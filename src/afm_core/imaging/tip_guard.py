"""Guard rails for blind tip estimates and reconstructions (issue 35): which part of the tip
the image constrained, and which part of a reconstruction the tip's uncertainty leaves open.

Conventions: afm_core.physics.tip_morphology (t(u) <= 0, apex 0 at the centre; i = dilate(s,
t), r = erode(i, t)). The blind estimate (afm_core.imaging.tip_refinement) starts from the flat
upper bound 0 and lowers a tip pixel w only where some image point bounds it: the bound is
i(x' + c - w) - i(x') + T(c) >= -(image height range), and the pixel is set to bound + N_TH.

Unconstrained tip pixels (`tip_constraint`). Two kinds of pixel carry no information about
the tip's shape:
  * still at the flat start 0: no image point bounded them. The apex is 0 by convention, and
    the pixels around it that stay at 0 because their data bound lies within N_TH of 0 (the
    apex plateau) ARE constrained: the plateau is the set of 0-pixels in the apex band (the
    pixels within N_TH + 3 sigma of 0, 8-connected to the apex: the estimate's resolution); it
    counts as constrained when ringed by lowered pixels, else only within the
    distance of the nearest lowered pixel (where the data did reach around the apex). Other
    0-pixels are unconstrained: in a reconstruction each acts as a second apex.
  * at the floor: bounded only by the image's full height range, t(w) <= -(range) + N_TH
    (+ noise), i.e. the image says only "the tip is below the tallest feature" there. The
    flank of a tip window deeper than the tallest feature lies there; its true height can be
    anything lower. (The window speed-up of refine_tip leaves the outer part at the feature
    pre-estimate, which is a data bound like any other, so it is judged by the same rules.)
Per-pixel uncertainty (m, how far the true tip may lie below the estimate): infinite on
unconstrained pixels, 0 at the apex, and on constrained pixels `TipEstimate.uncertainty` if
the estimator filled it, else N_TH + 3 sigma (the refinement leaves each pixel up to N_TH
above its data bound, and the bound is a difference of image heights that moves with the
noise sigma: 3 sigma is a one-sided 0.13 % excursion of one height).

Reconstruction check (`check_reconstruction`). r = erode(i, t); r_upper = erode(i, t - U)
with the sharpest plausible tip (U = uncertainty; unconstrained pixels excluded, i.e. set far
below the image). If the true tip lies within [t - U, t] on the constrained pixels, then
r_upper >= r_true >= s: r_upper is an upper bound of the surface, and r_upper - r >= 0 bounds
how far r may have cut into the object. It splits into the part the constrained uncertainty
allows (r_upper - r_c, r_c = erode with the unconstrained pixels excluded but the constrained
ones as estimated) and the part made only by unconstrained pixels, r_c - r. A pixel is
flagged when the latter exceeds 3 sigma of the image noise: the reconstruction removed more
there than the tip's uncertainty allows, by more than noise explains.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from afm_core.imaging.tip_refinement import estimate_noise
from afm_core.physics.tip_morphology import erode

NOISE_K = 3.0  # sigmas: a one-sided 0.13 % excursion of one Gaussian height
# floor pixels: within the noise of both image heights of the bound (3 sigma each) of the
# deepest bound the image can give, -(range) + N_TH
FLOOR_NOISE_K = 2 * NOISE_K
# refuse an automatic estimate when not even the apex's 8 neighbours are all constrained:
# the result would be a needle (or a flat plate) the data did not produce
MIN_SUPPORTED_RADIUS = 1  # px


class TipGuardWarning(UserWarning):
    """A blind tip estimate or a reconstruction that the image does not support."""


@dataclass
class TipConstraint:
    unconstrained: np.ndarray  # (k, k) bool: tip pixels the image did not constrain
    uncertainty: np.ndarray  # (k, k) m: inf where unconstrained, 0 at the apex
    count: int  # unconstrained pixels
    share: float  # of the k*k window
    at_start: int  # of them, still at the flat start 0 (outside the apex plateau)
    at_floor: int  # of them, bounded only by the image's height range
    radius: int  # px: every pixel within this distance of the apex is constrained
    depth: float  # m: how deep the tip is constrained all around (top of the ring at radius)
    supported_size: int  # 2 * radius + 1: the largest window the image supports all round
    uncertainty_source: str  # "estimator" or "fallback: threshold + 3 sigma"
    warnings: list = field(default_factory=list)

    def summary(self, pixel_size: float | None = None) -> str:
        """One line for people (nm)."""
        k = self.unconstrained.shape[0]
        where = f"{self.radius} px" + (
            f" ({self.radius * pixel_size * 1e9:.1f} nm)" if pixel_size else ""
        )
        return (
            f"tip constraint: {self.count} of {k * k} pixels ({100 * self.share:.1f} %) "
            f"unconstrained ({self.at_start} at the flat start, {self.at_floor} at the floor); "
            f"constrained all round within {where} of the apex, {self.depth * 1e9:.1f} nm "
            f"deep; uncertainty: {self.uncertainty_source}"
        )


def _distance(k: int) -> np.ndarray:
    h = k // 2
    a, b = np.mgrid[-h : h + 1, -h : h + 1]
    return np.hypot(a, b)


def unconstrained_pixels(
    tip: np.ndarray, threshold: float = 0.0, noise: float = 0.0, height_range: float = np.inf
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(unconstrained, at_start, at_floor) bool masks of a blind estimate (module notes).
    height_range: the characteriser image's max - min (inf: no floor test)."""
    tip = np.asarray(tip, float)
    k = tip.shape[0]
    h = k // 2
    scale = max(float(np.abs(tip).max()), float(height_range) if np.isfinite(height_range) else 0)
    eps = 1e-9 * max(scale, np.finfo(float).tiny)
    zero = tip >= -eps
    floor_level = -(height_range - threshold) + FLOOR_NOISE_K * noise
    floor = (tip <= floor_level) & ~zero if floor_level < 0 else ~zero
    lowered = ~zero & ~floor
    # the apex band: pixels within the estimate's resolution (threshold + 3 sigma) of 0,
    # 8-connected to the apex; 0-pixels in it are the apex plateau
    band = tip >= -(threshold + NOISE_K * noise) - eps
    labels, _ = ndimage.label(band, structure=np.ones((3, 3)))
    region = labels == labels[h, h]
    dist = _distance(k)
    rim = np.zeros_like(region)
    rim[0, :] = rim[-1, :] = rim[:, 0] = rim[:, -1] = True
    if (region & rim).any() or (ndimage.binary_dilation(region) & floor).any():
        # not ringed by lowered pixels: trust it only as far as the data reached the apex
        reach = float(dist[lowered].min()) if lowered.any() else 0.0
        region &= dist < reach
    plateau = zero & region
    plateau[h, h] = True
    at_start = zero & ~plateau
    return at_start | floor, at_start, floor


def tip_constraint(
    tip: np.ndarray,
    threshold: float = 0.0,
    noise: float = 0.0,
    height_range: float = np.inf,
    uncertainty: np.ndarray | None = None,
) -> TipConstraint:
    """Which part of the blind estimate `tip` the image constrained (module notes).

    threshold: the N_TH the estimate used (m); noise: the image noise sigma (m); height_range:
    the characteriser image's max - min (m; inf skips the floor test); uncertainty: the
    estimator's own per-pixel uncertainty (m) on constrained pixels, or None for the fallback
    threshold + 3 sigma. Warnings name the part the image supports."""
    tip = np.asarray(tip, float)
    if tip.ndim != 2 or tip.shape[0] != tip.shape[1] or tip.shape[0] % 2 == 0:
        raise ValueError(f"tip: shape {tip.shape}, expected a square odd-sized grid")
    k = tip.shape[0]
    h = k // 2
    unconstrained, at_start, floor = unconstrained_pixels(tip, threshold, noise, height_range)
    if uncertainty is None:
        unc = np.full(tip.shape, float(threshold) + NOISE_K * float(noise))
        source = "fallback: threshold + 3 sigma"
    else:
        unc = np.array(uncertainty, float)
        if unc.shape != tip.shape:
            raise ValueError(f"uncertainty: shape {unc.shape}, expected {tip.shape}")
        source = "estimator"
    unc[unconstrained] = np.inf
    unc[h, h] = 0.0
    dist = _distance(k)
    d_min = float(dist[unconstrained].min()) if unconstrained.any() else np.inf
    radius = h if d_min > h else int(np.ceil(d_min)) - 1
    ring = np.rint(dist) == radius
    depth = float(-tip[ring].max()) if radius > 0 else 0.0
    count = int(unconstrained.sum())
    out = TipConstraint(
        unconstrained,
        unc,
        count,
        count / (k * k),
        int(at_start.sum()),
        int(floor.sum()),
        radius,
        depth,
        2 * radius + 1,
        source,
    )
    if radius < h:
        supports = (
            f"only within {radius} px ({depth * 1e9:.1f} nm deep) of the apex; a smaller "
            f"--tip-size (e.g. {2 * radius + 1}) is all it supports"
            if radius > 0
            else "nowhere around the apex (not even its 8 neighbours): the estimate is no tip"
        )
        out.warnings.append(
            f"the image constrains the tip {supports} (tip_size={k}: {count} of {k * k} "
            f"pixels unconstrained, {int(at_start.sum())} at the flat start 0, "
            f"{int(floor.sum())} bounded only by the image's height range); a reconstruction "
            "with this tip may cut into objects there"
        )
    return out


def guard_estimate(estimate, image: np.ndarray, refuse: bool) -> None:
    """Fill `estimate.unconstrained`, `.uncertainty`, `.constraint` and `.warnings` of a
    TipEstimate from its image (afm_core.imaging.tip_estimation calls this at the end), and
    emit each warning as a TipGuardWarning. refuse (the automatic threshold): ValueError when
    not even the apex's neighbours are constrained (radius < MIN_SUPPORTED_RADIUS); a fixed
    threshold is the caller's choice and only warns."""
    image = np.asarray(image, float)
    noise = estimate_noise(image) if estimate.noise is None else float(estimate.noise)
    c = tip_constraint(
        estimate.tip,
        estimate.threshold,
        noise,
        float(image.max() - image.min()),
        estimate.uncertainty,
    )
    k = estimate.tip.shape[0]
    if refuse and c.radius < MIN_SUPPORTED_RADIUS:
        raise ValueError(
            f"tip_size={k}: the image constrains no ring of tip pixels around the apex at the "
            f"chosen threshold {estimate.threshold * 1e9:.2f} nm (constrained radius "
            f"{c.radius} px < {MIN_SUPPORTED_RADIUS} px, {c.count} of {k * k} pixels "
            "unconstrained): it needs features sharper than the tip and taller than the window "
            "is deep, or a smaller tip_size"
        )
    estimate.unconstrained, estimate.uncertainty, estimate.constraint = (
        c.unconstrained,
        c.uncertainty,
        c,
    )
    estimate.warnings.extend(c.warnings)
    for text in c.warnings:
        warnings.warn(text, TipGuardWarning, stacklevel=3)


# --------------------------------------------------------------------------------------------
# The reconstruction check


@dataclass
class ReconstructionCheck:
    reconstruction: np.ndarray  # r = erode(image, tip), m
    upper: np.ndarray  # r_upper = erode(image, tip - uncertainty), m: >= the surface
    uncertain_removal: np.ndarray  # r_upper - r >= 0, m: how far r may lie below the surface
    unconstrained_removal: np.ndarray  # the part of it made only by unconstrained tip pixels
    flagged: np.ndarray  # bool: unconstrained_removal > tolerance
    tolerance: float  # m: NOISE_K x noise
    noise: float  # m: the image noise sigma used
    max_removal: float  # m: largest uncertain_removal over the flagged pixels (0 if none)
    location: tuple | None  # (row, col) of it
    feature_height: float  # m: r_upper there above the background (median of r)
    flagged_share: float  # flagged feature pixels / feature pixels (r_upper > bg + tolerance)
    warnings: list = field(default_factory=list)


def check_reconstruction(
    image: np.ndarray,
    tip: np.ndarray,
    uncertainty: np.ndarray | None,
    *,
    noise: float | None = None,
    pixel_size: float | None = None,
    origin: tuple[float, float] = (0.0, 0.0),
) -> ReconstructionCheck:
    """Reconstruct `image` (m) with `tip` and flag where it removes more than the tip's
    uncertainty allows (module notes). uncertainty: per-pixel (m; inf = unconstrained, e.g.
    TipEstimate.uncertainty); None: derived from the tip alone (`tip_constraint` without
    threshold or floor test, 3 sigma of this image on the constrained pixels), which a warning
    says. noise: the image noise sigma (default `estimate_noise(image)`). pixel_size, origin
    (m): to name the location in nm (x = origin_x + (col + 0.5) * pixel_size)."""
    image = np.asarray(image, float)
    tip = np.asarray(tip, float)
    if image.ndim != 2:
        raise ValueError(f"image: shape {image.shape}, expected a 2-D height map")
    sigma = estimate_noise(image) if noise is None else float(noise)
    notes = []
    if uncertainty is None:
        uncertainty = tip_constraint(tip, 0.0, sigma).uncertainty
        notes.append(
            "the tip carries no uncertainty: unconstrained pixels taken as those left at 0 "
            "outside the apex plateau, the rest as known to 3 sigma of the image noise "
            f"({NOISE_K * sigma * 1e9:.2f} nm); write the tip with `afm image tip -o tip.npz` "
            "to keep the estimator's"
        )
    unc = np.asarray(uncertainty, float)
    if unc.shape != tip.shape:
        raise ValueError(f"uncertainty: shape {unc.shape}, expected the tip's {tip.shape}")
    # unconstrained pixels out of the erosion: so low that i(y - u) - t(u) > max(i) >= r(y)
    far = float(tip.min()) - 2.0 * float(np.ptp(image)) - 1.0
    known = np.isfinite(unc)
    r = erode(image, tip)
    r_known = erode(image, np.where(known, tip, far))
    upper = erode(image, np.where(known, tip - np.where(known, unc, 0.0), far))
    removal = upper - r
    from_unknown = r_known - r
    tol = NOISE_K * sigma
    flagged = from_unknown > tol
    background = float(np.median(r))
    features = (upper - background > tol) | flagged
    out = ReconstructionCheck(
        r,
        upper,
        removal,
        from_unknown,
        flagged,
        tol,
        sigma,
        0.0,
        None,
        0.0,
        float(flagged.sum() / max(int(features.sum()), 1)),
        notes,
    )
    if flagged.any():
        idx = np.unravel_index(int(np.argmax(np.where(flagged, removal, -np.inf))), r.shape)
        out.max_removal = float(removal[idx])
        out.location = (int(idx[0]), int(idx[1]))
        out.feature_height = float(upper[idx] - background)
        where = f"pixel (row {idx[0]}, col {idx[1]})"
        if pixel_size:
            x = origin[0] + (idx[1] + 0.5) * pixel_size
            y = origin[1] + (idx[0] + 0.5) * pixel_size
            where = f"({x * 1e9:.1f}, {y * 1e9:.1f}) nm, {where}"
        out.warnings.append(
            f"the tip is uncertain where it removes up to {out.max_removal * 1e9:.1f} nm of a "
            f"{out.feature_height * 1e9:.1f} nm feature at {where}: tip pixels the image "
            f"never constrained cut {int(flagged.sum())} pixels "
            f"({100 * out.flagged_share:.1f} % of the feature pixels) by more than 3 sigma "
            f"({tol * 1e9:.2f} nm); heights and widths there may lie up to that much below "
            "the surface (`upper` bounds it); use a smaller tip window or a tip estimated "
            "from sharper or taller features"
        )
    for text in out.warnings:
        warnings.warn(text, TipGuardWarning, stacklevel=2)
    return out
