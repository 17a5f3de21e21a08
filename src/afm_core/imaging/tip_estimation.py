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

Automatic threshold (book 4.3.2). `estimate_tip(..., threshold="book")` applies the book's
rule: sweep N_TH upwards, the critical threshold is the first whose tip top has several
apexes, the choice the local maximum of the change rate of the area between successive
estimates nearest to it. On the simulated characterizer (blunt 10 nm apex, 1.6 nm pixels,
0.3 nm noise) this fails: the top splits where the background noise stops collapsing the
estimate into a needle (~2.2 nm, 7 sigma), and the area rate peaks right there (error 6-9 nm),
while the error minimum lies about twice higher (~4.4 nm, error ~1.1 nm), where the flank
cuts made by feature tops that noise displaced by a pixel (their only admissible contact is
then the apex) are balanced by the blunting. The default "auto" keeps the book's sweep
(warm-started downwards: exact, since the limit is the same from any upper bound) and
records its data, but chooses the threshold whose estimate is closest, over its top `depth`,
to the feature-consensus tip: the median over the feature points of their apex-contact
bounds, which a minority of displaced tops does not pull down. This lands within ~4 % of the
best fixed threshold's error on the characterizer (seeds 0-7, noise 0.1-1 nm).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from afm_core.imaging.tip_guard import guard_estimate
from afm_core.imaging.tip_refinement import (
    TipRefiner,
    estimate_noise,
    feature_points,
    refine_tip,
    work_window,
)
from afm_core.physics.tip_morphology import erode

_REL_EPS = 1e-9  # relative (to the image's height range) tolerance for "no change"


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
    noise: float | None = None  # auto: the image noise estimate used to size the sweep
    feature_points: int = 0
    window: int = 0  # tip window the full passes worked on (speed-up b)
    # auto: threshold -> RMS difference from the consensus tip
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


def feature_consensus_tip(image: np.ndarray, features: np.ndarray, tip_size: int) -> np.ndarray:
    """The median over the feature points x_j of their apex-contact bounds
    i(x_j - w) - i(x_j): the tip that a typical sharp feature images. Unlike the blind
    estimate's minimum it is not an upper bound, but it is not pulled down by the few
    features whose top is noise-displaced (the blind estimate's main error), so it serves
    as the reference that the automatic threshold matches."""
    image = np.asarray(image, float)
    h = tip_size // 2
    ny, nx = image.shape
    pts = [
        (y, x)
        for y, x in np.asarray(features).reshape(-1, 2)
        if h <= y < ny - h and h <= x < nx - h
    ]
    if not pts:
        return np.zeros((tip_size, tip_size))
    bounds = np.stack(
        [image[y - h : y + h + 1, x - h : x + h + 1][::-1, ::-1] - image[y, x] for y, x in pts]
    )
    return np.median(bounds, axis=0)


def apex_count(tip: np.ndarray, band: float) -> int:
    """Number of highest points on the tip top (book 4.3.2): the local maxima (8-neighbour,
    non-strict) within `band` of the apex height; a flat top of m pixels counts m."""
    top = tip >= tip.max() - band
    peaks = tip >= ndimage.maximum_filter(tip, size=3, mode="constant", cval=-np.inf)
    return int((top & peaks).sum())


def _book_choice(
    ths: np.ndarray, counts: np.ndarray, rates: np.ndarray
) -> tuple[float | None, float | None]:
    """Book 4.3.2 literally: the critical threshold is the first (sweeping upwards) whose
    tip top has several apexes; the choice is the local maximum of the area change rate
    nearest to it (rate k: between thresholds k-1 and k). (None, None) if no split."""
    multi = np.flatnonzero(counts > 1)
    if multi.size == 0:
        return None, None
    ic = int(multi[0])
    peaks = [
        j
        for j in range(1, len(ths))
        if rates[j] >= rates[j - 1] and (j + 1 >= len(ths) or rates[j] >= rates[j + 1])
    ]
    if not peaks:
        return float(ths[ic]), float(ths[ic])
    j = min(peaks, key=lambda j: (abs(j - ic), -rates[j]))
    return float(ths[j]), float(ths[ic])


def _sweep_table(tips: dict, pixel_size: float, band: float) -> list:
    """[(threshold, rms_change, apex_count, area_change)] in increasing threshold; the changes
    are from the next lower computed threshold (rms in m; area_change: volume between the
    successive tips per unit threshold, m^3/m)."""
    out = []
    prev = prev_th = None
    for th in sorted(tips):
        tip = tips[th]
        if prev is None:
            rms = area = 0.0
        else:
            diff = tip - prev
            rms = float(np.sqrt(np.mean(diff**2)))
            area = float(np.abs(diff).sum() * pixel_size**2 / (th - prev_th))
        out.append((float(th), rms, apex_count(tip, band), area))
        prev, prev_th = tip, th
    return out


class _ThresholdSweep:
    """Blind estimates at several thresholds of one image, each warm-started from itself or
    from the estimate at the next higher threshold (exact: the limit does not depend on the
    start as long as it is an upper bound of it)."""

    def __init__(self, est: TipRefiner, features, window: int, max_iterations: int):
        self.est, self.features, self.window = est, features, window
        self.max_iterations = max_iterations
        self.tips: dict = {}
        self.converged: dict = {}
        self.passes = 0

    def run(self, th: float, cap: int | None = None) -> np.ndarray:
        """The estimate at th: converged (cap = max_iterations) or after `cap` passes."""
        cap = self.max_iterations if cap is None else cap
        th = float(th)
        tips = self.tips
        if th in tips and (self.converged[th] or cap < self.max_iterations):
            return tips[th]
        above = [t for t in tips if t > th]
        start = tips[th] if th in tips else (tips[min(above)] if above else None)
        tip, p, done = refine_tip(
            self.est, th, cap, start, self.features if start is None else None, self.window
        )
        tips[th], self.converged[th] = tip, done or cap >= self.max_iterations
        self.passes += p
        return tip


def _book_threshold(sweep: _ThresholdSweep, thresholds, sigma: float, pixel_size, band):
    """Book 4.3.2 on a uniform sweep 0, s, 2s, ... (s = sigma/2) or the given thresholds.
    Returns (chosen, critical, sweep table)."""
    ths = (
        np.sort(np.asarray(thresholds, float))
        if thresholds is not None
        else np.arange(0, 41) * (sigma / 2)
    )
    for th in ths[::-1]:
        sweep.run(th)
    table = _sweep_table(sweep.tips, pixel_size, band)
    chosen, critical = _book_choice(
        np.array([s[0] for s in table]),
        np.array([s[2] for s in table]),
        np.array([s[3] for s in table]),
    )
    if chosen is None:
        chosen = float(ths[int(np.argmax([s[3] for s in table]))])
    return chosen, critical, table


def _coarse_minimum(score, scores: dict, sigma: float, span: float) -> float:
    """One pass per threshold (each from the estimate above it, an upper bound), downwards
    from 20 sigma in 2 sigma steps until well past the minimum; the top doubles while the
    minimum is at it. Returns the best threshold."""
    coarse, top = 2.0 * sigma, 20.0 * sigma
    while True:
        best = None
        for j in range(int(round(top / coarse)), 0, -1):
            th = j * coarse
            q = score(th, cap=1)
            if best is None or q < scores[best]:
                best = th
            if th < best - 1.5 * coarse and q > 1.2 * scores[best]:
                break
        if best < top - 0.5 * coarse or top > span:
            return best
        top *= 2.0  # the minimum is at the top: look higher


def _fine_minimum(score, scores: dict, converged: dict, sigma: float, coarse_best: float):
    """Converged estimates at the coarse minimum, then +-sigma and +-sigma/2 around the best
    converged one (one pass is not enough to rank close thresholds at high noise)."""
    score(coarse_best)
    for step in (sigma, 0.5 * sigma):
        best = min((t for t in scores if converged[t]), key=lambda t: (scores[t], -t))
        for th in (best + step, best - step):
            if th > 0:
                score(th)
    return min((t for t in scores if converged[t]), key=lambda t: (scores[t], -t))


def _auto_threshold(
    sweep: _ThresholdSweep, image, tip_size: int, sigma: float, depth: float, thresholds
):
    """The threshold whose estimate is closest (RMS over its top `depth`) to the
    feature-consensus tip. Returns (chosen, scores: threshold -> RMS)."""
    features = sweep.features
    reference = feature_consensus_tip(
        image,
        features if features is not None else feature_points(image, tip_size, sigma),
        tip_size,
    )
    region = reference >= -depth
    scores: dict = {}

    def score(th: float, cap: int | None = None) -> float:
        th = float(th)
        tip = sweep.run(th, cap)
        scores[th] = float(np.sqrt(np.mean((tip - reference)[region] ** 2)))
        return scores[th]

    if thresholds is not None:
        for th in np.sort(np.asarray(thresholds, float))[::-1]:
            score(th)
        return min(scores, key=lambda t: (scores[t], -t)), scores
    best = _coarse_minimum(score, scores, sigma, float(image.max() - image.min()))
    return _fine_minimum(score, scores, sweep.converged, sigma, best), scores


def _checked_start(est: TipRefiner, th: float, start) -> np.ndarray | None:
    """A fixed threshold's start (an upper bound of the result, clipped to <= 0), checked."""
    if th < 0:
        raise ValueError(f"threshold={th}: must be >= 0")
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

    threshold: the denoising threshold N_TH (m); "auto" (the default) or "book" to choose it.
    Both sweep N_TH and record, per threshold, the change from the previous estimate, the
    number of apexes on the tip's top and the area change rate (book 4.3.2), warm-starting
    each estimate from the one at the next higher threshold (the limit does not depend on
    the start as long as it is an upper bound of it, so this is exact and fast).

    "book": the book's rule on a uniform sweep 0, s, 2s, ... (s = sigma/2, sigma the image
    noise estimate, or the given `thresholds`): the critical threshold is where the top goes
    from one apex to several, the choice the local maximum of the area change rate nearest to
    it.
    "auto": the threshold whose estimate best matches (RMS over its top `depth`, m) the
    feature-consensus tip (`feature_consensus_tip`): a coarse descent from 20 sigma (doubled
    while the minimum is at the top) in 2 sigma steps with one pass per threshold (each
    starting from the estimate above it), then converged estimates at the coarse minimum and
    at +-sigma, +-sigma/2 around the best; the choice is the best converged one. The sweep
    lists every threshold tried (the coarse ones after one pass). See the module notes for
    why this and not the book's rule.

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
        if threshold not in ("auto", "book"):
            raise ValueError(f"threshold={threshold!r}: a number (m), 'auto' or 'book'")
        sigma = estimate_noise(image) if noise is None else float(noise)
        features = feature_points(image, tip_size, sigma) if use_features else None
        window = work_window(est, features, 0.0) if limit_radius else est.k
        sweep = _ThresholdSweep(est, features, window, max_iterations)
        if (
            sigma <= 1e-6 * max(float(image.max() - image.min()), np.finfo(float).tiny)
            and thresholds is None
        ):
            # noiseless: the exact algorithm (N_TH = 0) is the answer
            tip, passes, _ = refine_tip(est, 0.0, max_iterations, None, features, window)
            table = _sweep_table({0.0: tip}, pixel_size, est.eps)
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
    sweep: _ThresholdSweep, image, tip_size, threshold, sigma, pixel_size, depth, thresholds
) -> TipEstimate:
    """estimate_tip with threshold "book" or "auto" on a noisy image (feature_points, window
    and seconds: filled in by the caller)."""
    band = 0.05 * sigma if sigma > 0 else sweep.est.eps
    scores: dict = {}
    if threshold == "book":
        chosen, critical, table = _book_threshold(sweep, thresholds, sigma, pixel_size, band)
    else:
        chosen, scores = _auto_threshold(sweep, image, tip_size, sigma, depth, thresholds)
        table = _sweep_table(sweep.tips, pixel_size, band)
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
