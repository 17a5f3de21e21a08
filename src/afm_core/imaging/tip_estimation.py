"""Blind tip estimation and image reconstruction (book ch. 4, SPEC 2; Villarrubia 1994/1997).

Conventions (the project's; afm_core.physics.tip_morphology): a tip is a square odd-sized grid
t(u) <= 0 with its apex at the centre pixel, t(0) = 0, u = (row, column) offset from the apex.
Imaging is grey dilation i(x) = max_u [ s(x + u) + t(u) ] (`dilate`), reconstruction its
adjoint erosion r(y) = min_u [ i(y - u) - t(u) ] (`erode`), the tightest surface under the
tip everywhere, so that erode(dilate(s, t), t) >= s, with equality wherever the tip touches s.
(Villarrubia's and Gwyddion's P is the reflected tip: P(d) = t(-d), i = s (+) P.)

The blind estimate at a denoising threshold N_TH is Villarrubia's refinement from the flat
upper bound (afm_core.imaging.tip_refinement, with the book's speed-ups); this module chooses
N_TH, and gives the certainty map of a reconstruction and the error of an estimate.

The threshold: a number (m), or chosen from the image by one of the rules in
afm_core.imaging.tip_thresholds: "auto" (the default: the lowest threshold above the noise
runaway), "consensus" (for a characterizer whose features are far sharper than the tip) or
"book" (book 4.3.2). Evidence: docs/imaging.md and bench/results/tip-corpus.md.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from afm_core.imaging.tip_guard import MIN_SUPPORTED_RADIUS, guard_estimate, tip_constraint
from afm_core.imaging.tip_refinement import (
    TipRefiner,
    estimate_noise,
    feature_points,
    refine_tip,
    work_window,
)
from afm_core.imaging.tip_thresholds import (
    RULES,
    ThresholdSweep,
    book_threshold,
    consensus_threshold,
    runaway_threshold,
    sweep_table,
)
from afm_core.physics.tip_morphology import erode


@dataclass
class TipEstimate:
    tip: np.ndarray  # (n, n) heights, m, apex 0 at centre, <= 0 elsewhere
    threshold: float  # m, the denoising threshold used
    iterations: int  # passes over the image (feature passes + full passes)
    seconds: float
    # [(threshold, rms_change, apex_count, area_change)] for auto
    sweep: list = field(default_factory=list)
    # auto/book: lowest swept threshold whose top has several apexes
    critical_threshold: float | None = None
    noise: float | None = None  # auto/consensus/book: the image noise estimate used
    feature_points: int = 0
    window: int = 0  # tip window the full passes worked on (speed-up b)
    # auto: threshold -> the estimate's RMS change from the rung above, per unit threshold;
    # consensus: threshold -> RMS difference from the feature-consensus tip
    scores: dict = field(default_factory=dict)
    # afm_core.imaging.tip_guard: pixels the image did not constrain, per-pixel uncertainty
    # (m, how far the true tip may lie below; inf where unconstrained; the estimator's own if
    # it fills it before the guard runs, else threshold + 3 sigma), warnings for people
    unconstrained: np.ndarray | None = None
    uncertainty: np.ndarray | None = None
    warnings: list = field(default_factory=list)
    constraint: object = None  # tip_guard.TipConstraint: counts, supported radius and depth


# --------------------------------------------------------------------------------------------
# The automatic threshold


def _checked_start(est: TipRefiner, th: float, start) -> np.ndarray | None:
    """A fixed threshold's start (an upper bound of the result, clipped to <= 0), checked."""
    if not 0 <= th < np.inf:  # also refuses NaN, which would refine nothing silently
        raise ValueError(f"threshold={th}: must be a finite number >= 0 (m)")
    if start is not None:
        start = np.minimum(np.asarray(start, float), 0.0)
        if start.shape != (est.k, est.k):
            raise ValueError(f"start: shape {start.shape}, expected {(est.k, est.k)}")
    return start


def estimate_tip(
    image: np.ndarray,
    tip_size: int,
    threshold: float | str = "auto",
    pixel_size: float = 1.0,
    max_iterations: int = 50,
    *,
    depth: float = 20e-9,
    noise: float | None = None,
    thresholds=None,
    use_features: bool = True,
    limit_radius: bool = True,
    start: np.ndarray | None = None,
) -> TipEstimate:
    """Blind tip estimate (tip_size x tip_size, odd) from `image` (heights, m; pixel_size only
    scales the reported area changes).

    threshold: the denoising threshold N_TH (m); "auto" (the default), "consensus" or "book"
    to choose it (afm_core.imaging.tip_thresholds). All sweep N_TH, warm-starting each
    estimate from the one at the next higher threshold (exact, as the limit does not depend
    on the start as long as it is an upper bound of it), and record per threshold the change
    from the previous estimate, the number of apexes on the tip's top and the area change
    rate (book 4.3.2).

    "book": the book's rule on a uniform sweep 0, s, 2s, ... (s = sigma/2, sigma the image
    noise estimate, or the given `thresholds`): the critical threshold is where the top goes
    from one apex to several, the choice the local maximum of the area change rate nearest to
    it.
    "auto": the lowest threshold above the noise runaway. From LADDER_TOP sigma down a
    ladder of rungs COARSE_RATIO apart (FINE_RATIO once a rung moves faster than CALM, from
    the rung above it; or the given `thresholds`), the RMS change of the estimate over its
    top `depth` (m) per unit threshold is watched; the first rung where it exceeds RUNAWAY
    (once the estimate has begun to follow the threshold) is noise running away; the rung
    above it and above the gentle start of the runaway (rates over RUNAWAY_EDGE) is chosen,
    and the sweep stops there. Without a runaway down to the bottom, the
    lowest rung at or above SINGLE_EXCURSION sigma.
    "consensus": the threshold whose estimate best matches (RMS over its top `depth`) the
    feature-consensus tip; for characterizers whose features are far sharper than the tip.

    start (fixed threshold only): an upper bound of the result to start from instead of the
    flat 0, e.g. the estimate at a higher threshold; the result is the same, only faster."""
    t_start = time.perf_counter()
    image = np.asarray(image, float)
    est = TipRefiner(image, tip_size)
    if not isinstance(threshold, str):
        th = float(threshold)
        start = _checked_start(est, th, start)
        features = (
            feature_points(image, tip_size, noise) if use_features and start is None else None
        )
        window = work_window(est, features, th) if limit_radius else est.k
        tip, passes, _ = refine_tip(est, th, max_iterations, start, features, window)
        out = TipEstimate(tip, th, passes, 0.0, [])
    else:
        if threshold not in RULES:
            raise ValueError(f"threshold={threshold!r}: a number (m) or one of {', '.join(RULES)}")
        sigma = estimate_noise(image) if noise is None else float(noise)
        features = feature_points(image, tip_size, sigma) if use_features else None
        window = work_window(est, features, 0.0) if limit_radius else est.k
        sweep = ThresholdSweep(est, features, window, max_iterations)
        if (
            sigma <= 1e-6 * max(float(image.max() - image.min()), np.finfo(float).tiny)
            and thresholds is None
        ):
            # noiseless: the exact algorithm (N_TH = 0) is the answer
            tip, passes, _ = refine_tip(est, 0.0, max_iterations, None, features, window)
            table = sweep_table({0.0: tip}, pixel_size, est.eps)
            out = TipEstimate(tip, 0.0, passes, 0.0, table, noise=sigma)
        else:
            out = _swept_threshold(
                sweep, image, tip_size, threshold, sigma, pixel_size, depth, thresholds
            )
    out.feature_points, out.window = 0 if features is None else len(features), window
    out.seconds = time.perf_counter() - t_start
    # what the image constrained; refuses only an automatic choice that constrains nothing
    guard_estimate(out, image, refuse=isinstance(threshold, str))
    return out


def _swept_threshold(
    sweep: ThresholdSweep, image, tip_size, threshold, sigma, pixel_size, depth, thresholds
) -> TipEstimate:
    """estimate_tip with a threshold rule ("auto", "consensus", "book") on a noisy image
    (feature_points, window and seconds: filled in by the caller)."""
    band = 0.05 * sigma if sigma > 0 else sweep.est.eps
    scores: dict = {}
    if threshold == "book":
        chosen, critical, table = book_threshold(sweep, thresholds, sigma, pixel_size, band)
    else:
        if threshold == "auto":
            span = float(image.max() - image.min())
            need = min(MIN_SUPPORTED_RADIUS, tip_size // 2)

            def resolves(tip, th):  # what guard_estimate refuses an automatic choice for
                return tip_constraint(tip, th, sigma, span).radius >= need

            chosen, scores = runaway_threshold(sweep, sigma, depth, thresholds, resolves)
        else:
            chosen, scores = consensus_threshold(sweep, image, tip_size, sigma, depth, thresholds)
        table = sweep_table(sweep.tips, pixel_size, band)
        counts = [s[2] for s in table]
        critical = (
            next((s[0] for s in table if s[2] > 1), None) if counts and counts[0] <= 1 else None
        )
    return TipEstimate(
        sweep.tips[chosen],
        chosen,
        sweep.passes,
        0.0,
        table,
        critical_threshold=critical,
        noise=sigma,
        scores=dict(sorted(scores.items())),
    )


def estimate_tip_plain(
    image: np.ndarray, tip_size: int, threshold: float = 0.0, max_iterations: int = 50
) -> TipEstimate:
    """Villarrubia's original algorithm, without the speed-ups: every interior point, every
    contact allowed by eq. 4.33 and every tip pixel, pass after pass until no change. The
    reference the fast estimate must agree with (slow: use small images)."""
    t_start = time.perf_counter()
    est = TipRefiner(np.asarray(image, float), tip_size)
    tip = np.zeros((est.k, est.k))
    tf = tip.ravel()
    flat, off, eps, th = est.flat, est.off, est.eps, float(threshold)
    points = est.flat_index(*np.nonzero(est.interior()))
    passes = 0
    while passes < max_iterations:
        passes += 1
        changed = 0
        for g in points:
            i0 = flat[g]
            valid = np.flatnonzero(flat[g + off] - i0 + tf >= -eps)
            bound = (
                flat[(g + off[valid])[:, None] - off[None, :]] + (tf[valid] - i0)[:, None]
            ).max(axis=0)
            lower = bound + th < tf - eps
            if lower.any():
                tf[lower] = bound[lower] + th
                changed += 1
        if not changed:
            break
    return TipEstimate(tip, th, passes, time.perf_counter() - t_start, [], window=est.k)


# --------------------------------------------------------------------------------------------
# Certainty map and error


def certainty_map(
    image: np.ndarray, tip: np.ndarray, tolerance: float | None = None
) -> np.ndarray:
    """Villarrubia's certainty map: True at the points y of the reconstruction
    r = erode(image, tip) that the tip, with its apex at some image point x, touches there and
    nowhere else (i(x) - t(u) = r(x+u) for the single u = y - x; with t <= 0 the tip's
    surface at x+u is i(x) - t(u) above the apex). The tip at x touches the
    true surface somewhere, and r >= s, so a single touch of r is that touch: r(y) = s(y).
    Only apexes x at least two tip half-widths from the edge are used, so that every r the
    tip can touch is computed from the image alone (touches beyond the edge are unseen)."""
    image = np.asarray(image, float)
    tip = np.asarray(tip, float)
    ny, nx = image.shape
    k = tip.shape[0]
    h = k // 2
    out = np.zeros(image.shape, bool)
    if ny <= 4 * h or nx <= 4 * h:
        return out
    r = erode(image, tip)
    if tolerance is None:
        tolerance = 1e-9 * max(float(image.max() - image.min()), np.finfo(float).tiny)
    ix = image[2 * h : ny - 2 * h, 2 * h : nx - 2 * h]
    my, mx = ix.shape
    count = np.zeros(ix.shape, np.int32)
    where = np.zeros(ix.shape, np.int32)
    for a in range(k):
        for b in range(k):
            rs = r[h + a : h + a + my, h + b : h + b + mx]  # r(x + u), u = (a - h, b - h)
            touch = np.abs(ix - tip[a, b] - rs) <= tolerance  # tip surface at x+u: i(x) - t(u)
            count += touch
            where[touch] = a * k + b
    single = count == 1
    cy, cx = np.nonzero(single)
    u = where[single]
    out[cy + h + u // k, cx + h + u % k] = True
    return out


def tip_error(estimate, true_tip: np.ndarray, depth: float) -> float:
    """RMS difference (m) between an estimated and the true tip over the top `depth` of the
    true tip (where true_tip >= -depth), both centred on their apex (height 0), compared on
    their common window."""
    est = np.asarray(estimate.tip if isinstance(estimate, TipEstimate) else estimate, float)
    true = np.asarray(true_tip, float)
    k = min(est.shape[0], true.shape[0])
    ce, ct = est.shape[0] // 2, true.shape[0] // 2
    e = est[ce - k // 2 : ce + k // 2 + 1, ce - k // 2 : ce + k // 2 + 1] - est[ce, ce]
    t = true[ct - k // 2 : ct + k // 2 + 1, ct - k // 2 : ct + k // 2 + 1] - true[ct, ct]
    sel = t >= -depth
    return float(np.sqrt(np.mean((e[sel] - t[sel]) ** 2)))
