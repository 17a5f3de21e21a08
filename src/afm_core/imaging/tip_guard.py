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
    apex plateau) ARE constrained. The two are told apart by where the data did reach: a
    0-pixel is unconstrained if it lies farther from the apex than every pixel the data
    lowered to within the estimate's resolution (N_TH + 3 sigma) of 0, or if it lies behind
    a drop: some pixel between it and the apex is lower than that resolution (a tip does
    not rise moving outward from its apex, so the data would have bounded it too, had any
    feature reached it). In a reconstruction each such pixel acts as a second apex. An
    estimate left entirely at 0 (below the floor test's limit) is a plate within its
    resolution: constrained, but warned about as resolving no shape.
  * at the floor: bounded only by the image's full height range, t(w) <= -(range) + N_TH
    (+ noise), i.e. the image says only "the tip is below the tallest feature" there. The
    flank of a tip window deeper than the tallest feature lies there; its true height can be
    anything lower. (The window speed-up of refine_tip leaves the outer part at the feature
    pre-estimate, which is a data bound like any other, so it is judged by the same rules.)
Per-pixel uncertainty (m, how far the true tip may lie below the estimate): 0 at the apex;
infinite on unconstrained pixels and, when some lie within the window's inscribed circle, on
every pixel farther out than the nearest of them (the rules above see only the flat start and
the image-wide floor; a pixel bounded through the image of a neighbouring feature looks like
a measured one, and on the characteriser all such pixels lay beyond that radius); on the
other pixels `TipEstimate.uncertainty` if the estimator filled it, else N_TH + 3 sigma (the
refinement leaves each pixel up to N_TH above its data bound, and the bound is a difference
of image heights that moves with the noise sigma: 3 sigma is a one-sided 0.13 % excursion
of one height).

Reconstruction check (`check_reconstruction`). r = erode(i, t); r_upper = erode(i, t - U)
with the sharpest plausible tip (U = uncertainty; unconstrained pixels excluded, i.e. set far
below the image). If the true tip lies within [t - U, t] on the constrained pixels, then
r_upper >= r_true >= s: r_upper is an upper bound of the surface, and r_upper - r >= 0 bounds
how far r may have cut into the object. It splits into the part the constrained uncertainty
allows (r_upper - r_c, r_c = erode with the unconstrained pixels excluded but the constrained
ones as estimated) and the part made only by unconstrained pixels, r_c - r. A pixel is
flagged when
  * r_c - r exceeds 3 sigma of the image noise: the reconstruction removed more there than
    the tip's uncertainty allows, by more than noise explains; or
  * r_upper - r exceeds both 3 sigma and UNCERTAIN_SHARE (25 %) of the height of the feature
    the pixel belongs to (the 8-connected region of r_upper more than 3 sigma above its
    median, counted only if its peak stands 6 sigma above): the uncertainty the tip does
    state is then too large for the feature. This catches an estimate at a threshold near
    the image's height range, a plate whose constrained uncertainty allows anything; or
  * the image minus its opening by the tip, i - dilate(erode(i, t), t), exceeds what noise
    explains (`opening_limit`) plus the tip's largest stated (finite) uncertainty: every image
    the tip took is open under it (i = s (+) t gives dilate(erode(i, t), t) = i), and a tip up
    to U blunter than that one leaves up to U; beyond, the tip is blunter than the one that
    took the image by more than it says it may be (a tip from another image, a worn tip, an
    estimate bounded only by features blunter than this image's, or a flat plate), and the
    reconstruction cut into the object by about the residual or more. It catches tips whose
    pixels the uncertainty calls known. Only residual regions holding a local maximum of the
    image count (`_crest_regions`): a window smaller than the tip's reach leaves residuals on
    flanks without cutting anything.
All are warnings with the numbers; the reconstruction is still returned (and written).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage, stats

from afm_core.imaging.tip_refinement import estimate_noise
from afm_core.physics.tip_morphology import dilate, erode

NOISE_K = 3.0  # sigmas: a one-sided 0.13 % excursion of one Gaussian height
# floor pixels: within the noise of both image heights of the bound (3 sigma each) of the
# deepest bound the image can give, -(range) + N_TH
FLOOR_NOISE_K = 2 * NOISE_K
# refuse an automatic estimate when not even the apex's 8 neighbours are all constrained:
# the result would be a needle (or a flat plate) the data did not produce
MIN_SUPPORTED_RADIUS = 1  # px
# a reconstruction pixel is flagged when its uncertain removal exceeds this share of the
# height of the feature it belongs to: the uncertainty is then comparable to the tip
# broadening the reconstruction exists to remove (the book's 20 nm nanotube: 49 nm imaged,
# ~29 nm reconstructed), so its heights and widths are no longer measured, only bounded
UNCERTAIN_SHARE = 0.25
FEATURE_NOISE_K = 2 * NOISE_K  # sigmas a feature's peak must stand above the background
# the opening test: the chance that the noise alone flags some pixel of an image the tip did
# take (Gaussian noise; the residual is a difference of two noisy heights)
OPENING_FALSE_ALARM = 0.01


class TipGuardWarning(UserWarning):
    """A blind tip estimate or a reconstruction that the image does not support."""


@dataclass
class TipConstraint:
    unconstrained: np.ndarray  # (k, k) bool: tip pixels the image did not constrain
    uncertainty: np.ndarray  # (k, k) m: inf where unconstrained or beyond radius, 0 at apex
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


def _inward_minimum(tip: np.ndarray) -> np.ndarray:
    """Per pixel w: the lowest tip height on the segment from the apex to w, w excluded
    (sampled at h + 1 points, nearest pixel)."""
    k = tip.shape[0]
    h = k // 2
    a, b = np.mgrid[-h : h + 1, -h : h + 1]
    steps = np.arange(h + 1) / (h + 1)  # 0 (the apex) .. < 1
    rows = np.rint(a[..., None] * steps).astype(int)
    cols = np.rint(b[..., None] * steps).astype(int)
    values = tip[rows + h, cols + h]
    values[(rows == a[..., None]) & (cols == b[..., None])] = np.inf  # w itself
    return values.min(axis=-1)


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
    zero[h, h] = False  # the apex is 0 by convention
    floor_level = -(height_range - threshold) + FLOOR_NOISE_K * noise
    if floor_level >= 0:  # the threshold swallows the image's whole height range
        floor = np.ones(tip.shape, bool)
        floor[h, h] = False
        return floor, np.zeros(tip.shape, bool), floor
    floor = tip <= floor_level
    band = threshold + NOISE_K * noise  # the estimate's resolution
    dist = _distance(k)
    near = (tip < -eps) & (tip >= -band - eps)  # lowered, but to within the band of 0
    if not (tip < -eps).any():
        reach = np.inf  # a plate: the whole window within the resolution (warned about)
    else:
        reach = float(dist[near].max()) if near.any() else 0.0
    behind_drop = _inward_minimum(tip) < -band - eps
    at_start = zero & ((dist > reach) | behind_drop)
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
    dist = _distance(k)
    d_min = float(dist[unconstrained].min()) if unconstrained.any() else np.inf
    radius = h if d_min > h else int(np.ceil(d_min)) - 1
    if radius < h:
        # beyond the first unconstrained pixel a pixel may be bounded only through another
        # feature's image (the characteriser shows such pixels, estimated 10-35 nm too high,
        # all outside this radius): no uncertainty is claimed there
        unc[dist > radius] = np.inf
    unc[h, h] = 0.0
    ring = np.rint(dist) == radius
    depth = max(0.0, float(-tip[ring].max())) if radius > 0 else 0.0
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
            f"pixels unconstrained, {int(at_start.sum())} at the flat start (0), "
            f"{int(floor.sum())} bounded only by the image's height range); a reconstruction "
            "with this tip may cut into objects there"
        )
    band = float(threshold) + NOISE_K * float(noise)
    if radius > 0 and depth <= band:
        out.warnings.append(
            f"the estimate drops only {depth * 1e9:.2f} nm out to {radius} px from the apex, "
            f"no more than its resolution (threshold + 3 sigma = {band * 1e9:.2f} nm): the "
            f"tip's shape is not resolved at this threshold (tip_size={k}); a reconstruction "
            "with it erodes by a near-flat plate and cuts into objects narrower than that"
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
    if refuse and c.radius < min(MIN_SUPPORTED_RADIUS, k // 2):
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
    feature_height: np.ndarray  # m: per pixel, the peak of its feature in r_upper (0 off them)
    flagged: np.ndarray  # bool: by_unconstrained | too_uncertain
    by_unconstrained: np.ndarray  # bool: unconstrained_removal > NOISE_K sigma
    too_uncertain: np.ndarray  # bool: uncertain_removal > max(NOISE_K sigma, share x feature)
    noise: float  # m: the image noise sigma used
    background: float  # m: median of r_upper, the level feature heights are measured from
    max_removal: float  # m: largest uncertain_removal over the flagged pixels (0 if none)
    location: tuple | None  # (row, col) of it
    height_there: float  # m: the feature height at that location
    flagged_share: float  # flagged feature pixels / feature pixels
    warnings: list = field(default_factory=list)
    # image - dilate(reconstruction, tip) >= 0, m: where the tip cannot have made the image
    opening_residual: np.ndarray | None = None
    too_blunt: np.ndarray | None = None  # bool: opening_residual > opening_limit
    opening_limit: float = 0.0  # m


def _features(upper: np.ndarray, background: float, sigma: float) -> np.ndarray:
    """Per pixel, the peak height (above background) of the feature it belongs to: the
    8-connected regions of upper > background + 3 sigma whose peak stands FEATURE_NOISE_K
    sigma above it (a pure-noise pixel does so with probability ~1e-9); 0 elsewhere."""
    above = upper - background
    labels, count = ndimage.label(above > NOISE_K * sigma, structure=np.ones((3, 3)))
    if count == 0:
        return np.zeros(upper.shape)
    peaks = np.asarray(ndimage.maximum(above, labels, index=np.arange(1, count + 1)), float)
    peaks[peaks <= FEATURE_NOISE_K * sigma] = 0.0
    return np.concatenate([[0.0], peaks])[labels]


def _sharpest(tip: np.ndarray, unc: np.ndarray, image: np.ndarray):
    """(tip with unconstrained pixels excluded, sharpest plausible tip): excluded pixels are
    set so low that i(y - u) - t(u) > max(i) >= r(y), i.e. they never touch."""
    far = float(tip.min()) - 2.0 * float(np.ptp(image)) - 1.0
    known = np.isfinite(unc)
    return np.where(known, tip, far), np.where(known, tip - np.where(known, unc, 0.0), far)


def _apex_at_zero(tip: np.ndarray) -> tuple[np.ndarray, float]:
    """(the tip with its apex at 0, the apex's height before). The apex is the centre pixel,
    which must be the highest: a tip whose highest pixel lies elsewhere would shift the
    reconstruction sideways by that offset, and which pixel the file meant as the apex is
    unknown, so it is refused (ValueError naming the pixel)."""
    c = tip.shape[0] // 2
    apex = float(tip[c, c])
    tolerance = 1e-6 * max(float(np.ptp(tip)), np.finfo(float).tiny)
    if float(tip.max()) > apex + tolerance:
        row, col = np.unravel_index(int(np.argmax(tip)), tip.shape)
        raise ValueError(
            f"tip: its highest pixel (row {row}, column {col}) is "
            f"{(float(tip.max()) - apex) * 1e9:.3g} nm above the centre pixel ({c}, {c}); the "
            "apex must be the centre pixel and the highest (t <= 0 around it): centre the tip"
        )
    return tip - apex, apex


def opening_limit(pixels: int, sigma: float, height_span: float) -> float:
    """m: the largest opening residual noise explains on an image of `pixels` pixels with noise
    sigma: sqrt(2) sigma times the one-sided Gaussian quantile at OPENING_FALSE_ALARM / pixels
    (6.9 sigma at 128 x 128, 7.6 sigma at 512 x 512), plus rounding (1e-9 of the height span)."""
    k = math.sqrt(2.0) * float(stats.norm.isf(OPENING_FALSE_ALARM / max(int(pixels), 1)))
    return k * float(sigma) + 1e-9 * float(height_span)


def _crest_regions(image: np.ndarray, above: np.ndarray) -> np.ndarray:
    """The 8-connected regions of `above` that hold a local maximum of the image (no
    8-neighbour higher). A window smaller than the tip's reach leaves an opening residual
    where the image was made by a part of the tip outside the window, with no cut (erosion
    with a cropped tip stays above the surface); such a pixel has a neighbour at least as
    high towards that contact (the tip does not rise away from its apex), so it is no local
    maximum, while a tip too blunt for a crest leaves its residual on the crest itself."""
    if not above.any():
        return above
    labels, _ = ndimage.label(above, structure=np.ones((3, 3)))
    crest = above & (image >= ndimage.maximum_filter(image, size=3))
    kept = np.unique(labels[crest])
    return np.isin(labels, kept[kept > 0])


def check_reconstruction(
    image: np.ndarray,
    tip: np.ndarray,
    uncertainty: np.ndarray | None,
    *,
    noise: float | None = None,
    pixel_size: float | None = None,
    origin: tuple[float, float] = (0.0, 0.0),
) -> ReconstructionCheck:
    """Reconstruct `image` (m) with `tip` and flag where the tip's uncertainty leaves the
    result open (module notes). uncertainty: per-pixel (m; inf = unconstrained, e.g.
    TipEstimate.uncertainty); None: derived from the tip alone (`tip_constraint` without
    threshold or floor test, 3 sigma of this image on the constrained pixels), which a warning
    says. noise: the image noise sigma (default `estimate_noise(image)`). pixel_size, origin
    (m): to name the location in nm (x = origin_x + (col + 0.5) * pixel_size)."""
    image = np.asarray(image, float)
    tip = np.asarray(tip, float)
    if image.ndim != 2:
        raise ValueError(f"image: shape {image.shape}, expected a 2-D height map")
    if tip.ndim != 2 or tip.shape[0] != tip.shape[1] or tip.shape[0] % 2 == 0:
        raise ValueError(f"tip: shape {tip.shape}, expected a square odd-sized grid")
    sigma = estimate_noise(image) if noise is None else float(noise)
    notes = []
    tip, apex = _apex_at_zero(tip)
    if apex != 0.0:
        notes.append(
            f"the tip's apex was at {apex * 1e9:+.3g} nm, not 0 (Gwyddion's tips have their base "
            "at 0); it was moved to 0, else the whole reconstruction would be off by that much"
        )
    if uncertainty is None:
        uncertainty = tip_constraint(tip, 0.0, sigma).uncertainty
        notes.append(
            "the tip carries no uncertainty (a .gwy tip, or not from `afm image tip`): its "
            "unconstrained pixels are taken as those left at 0 away from the apex, the rest as "
            f"known to 3 sigma of this image's noise ({NOISE_K * sigma * 1e9:.2f} nm); write the "
            "tip as .npz to keep the estimator's"
        )
    unc = np.asarray(uncertainty, float)
    if unc.shape != tip.shape:
        raise ValueError(f"uncertainty: shape {unc.shape}, expected the tip's {tip.shape}")
    if np.any(unc < 0):
        raise ValueError("uncertainty: must be >= 0 (m; inf where unconstrained)")
    known_tip, sharp_tip = _sharpest(tip, unc, image)
    r = erode(image, tip)
    upper = erode(image, sharp_tip)
    removal = upper - r
    from_unknown = erode(image, known_tip) - r
    tol = NOISE_K * sigma
    background = float(np.median(upper))
    height = _features(upper, background, sigma)
    by_unknown = from_unknown > tol
    too_uncertain = (height > 0) & (removal > np.maximum(tol, UNCERTAIN_SHARE * height))
    residual = np.maximum(image - dilate(r, tip), 0.0)
    # a tip up to its stated uncertainty blunter than the true one leaves up to that much
    stated = float(unc[np.isfinite(unc)].max())
    limit = opening_limit(image.size, sigma, float(np.ptp(image))) + stated
    too_blunt = _crest_regions(image, residual > limit)
    flagged = by_unknown | too_uncertain | too_blunt
    out = ReconstructionCheck(
        r,
        upper,
        removal,
        from_unknown,
        height,
        flagged,
        by_unknown,
        too_uncertain,
        sigma,
        background,
        0.0,
        None,
        0.0,
        float(flagged.sum() / max(int(((height > 0) | flagged).sum()), 1)),
        notes,
        residual,
        too_blunt,
        limit,
    )
    if (by_unknown | too_uncertain).any():
        _describe(out, pixel_size, origin)
    if too_blunt.any():
        _describe_blunt(out, pixel_size, origin)
    for text in out.warnings:
        warnings.warn(text, TipGuardWarning, stacklevel=2)
    return out


def _where(idx, pixel_size, origin) -> str:
    where = f"pixel (row {idx[0]}, col {idx[1]})"
    if pixel_size:
        x = origin[0] + (idx[1] + 0.5) * pixel_size
        y = origin[1] + (idx[0] + 0.5) * pixel_size
        where = f"({x * 1e9:.1f}, {y * 1e9:.1f}) nm, {where}"
    return where


def _describe_blunt(out: ReconstructionCheck, pixel_size, origin) -> None:
    """A warning naming the largest opening residual and where (the opening test)."""
    residual = out.opening_residual
    idx = np.unravel_index(int(np.argmax(np.where(out.too_blunt, residual, -1.0))), residual.shape)
    out.warnings.append(
        f"the tip cannot have taken this image: at {int(out.too_blunt.sum())} pixels the image "
        f"is sharper than the tip allows (eroding and re-dilating it with the tip loses up to "
        f"{float(residual[idx]) * 1e9:.1f} nm, at {_where(idx, pixel_size, origin)}; noise and "
        f"the tip's stated uncertainty explain {out.opening_limit * 1e9:.2f} nm): the tip is "
        "blunter there than the one that took the image, and the reconstruction cut into the "
        "objects by about that much or more; estimate the tip from this image (or a sharper "
        "characteriser), or check that the tip did not change between the scans"
    )


def _describe(out: ReconstructionCheck, pixel_size, origin) -> None:
    """The largest flagged removal, where, and a warning naming the numbers."""
    removal = out.uncertain_removal
    uncertain = out.by_unconstrained | out.too_uncertain
    idx = np.unravel_index(int(np.argmax(np.where(uncertain, removal, -np.inf))), removal.shape)
    out.max_removal = float(removal[idx])
    out.location = (int(idx[0]), int(idx[1]))
    out.height_there = float(out.feature_height[idx])
    where = _where(idx, pixel_size, origin)
    causes = []
    if out.by_unconstrained.any():
        causes.append(
            f"tip pixels the image never constrained cut {int(out.by_unconstrained.sum())} "
            f"pixels by more than 3 sigma ({NOISE_K * out.noise * 1e9:.2f} nm)"
        )
    if out.too_uncertain.any():
        causes.append(
            f"at {int(out.too_uncertain.sum())} pixels the tip's uncertainty leaves more than "
            f"{UNCERTAIN_SHARE:.0%} of the feature's height open"
        )
    out.warnings.append(
        f"the tip is uncertain where it removes up to {out.max_removal * 1e9:.1f} nm of a "
        f"{out.height_there * 1e9:.1f} nm feature at {where}: {'; '.join(causes)} "
        f"({100 * out.flagged_share:.1f} % of the feature pixels); heights and widths there "
        "may lie up to that much below the surface (`upper` bounds it from above); use a "
        "smaller tip window or a tip estimated from sharper, taller features"
    )
