"""How the blind tip estimate chooses its denoising threshold N_TH (afm_core.imaging.
tip_estimation.estimate_tip's threshold="auto", "consensus" or "book"). Each rule sweeps N_TH
with `ThresholdSweep`, which warm-starts every estimate from the one at the next higher
threshold (exact: the limit does not depend on the start as long as it is an upper bound of
it).

"auto" (`runaway_threshold`): walk N_TH down a geometric ladder (coarse, then fine near the
runaway) and watch how fast the estimate moves per unit of threshold. Above the noise runaway a
refined tip pixel sits at its bound + N_TH, so the estimate follows the threshold at most one
for one; where noise starts to feed on itself (a cut admits contacts that cut further), the
estimate drops many times faster than the threshold. The choice is the fine rung just above
that runaway and its gentle start: the sharpest estimate that is still the threshold's and not
the noise's (a jump below a rung whose apex ring is still unresolved is the apex's first
refinement, and the descent goes on past it). The error is steep on both sides of it (just
below, the runaway cuts the tip into a needle; one coarse rung above, it is 1.3-2x blunter), so
the runaway is resolved on fine rungs. Without any runaway, the lowest rung at or above 3 sigma
(single noise excursions). It needs only the image (the noise sigma sizes the ladder; the
choice does not scale with it: the best threshold is 0-35 sigmas on the corpus, set by where
the runaway begins, and the image's sigma is 2-10x high at coarse pixels). On a dedicated spike
characterizer the best can lie higher, where the cuts made by feature tops that noise displaced
by a pixel are balanced by the blunting (docs/imaging.md).

"consensus" (`consensus_threshold`): the threshold whose estimate is closest, over its top
`depth`, to the feature-consensus tip (the median over the feature points of their
apex-contact bounds). Within a few % of the best on a characterizer whose spikes are far
sharper than the tip; on blunter samples the median is blunter than the tip and the choice
2-10x too high. (It was "auto" until 2026-11.)

"book" (`book_threshold`, book 4.3.2): sweep N_TH upwards; the critical threshold is the
first whose tip top has several apexes, the choice the local maximum of the change rate of
the area between successive estimates nearest to it. On the simulated characterizer the top
splits where the background noise stops collapsing the estimate (~7 sigma), about half the
error-minimising threshold.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from afm_core.imaging.tip_refinement import TipRefiner, feature_points, refine_tip

RULES = ("auto", "consensus", "book")  # the threshold= names estimate_tip accepts


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


class ThresholdSweep:
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


def sweep_table(tips: dict, pixel_size: float, band: float) -> list:
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


def book_threshold(sweep: ThresholdSweep, thresholds, sigma: float, pixel_size, band):
    """Book 4.3.2 on a uniform sweep 0, s, 2s, ... (s = sigma/2) or the given thresholds.
    Returns (chosen, critical, sweep table)."""
    ths = (
        np.sort(np.asarray(thresholds, float))
        if thresholds is not None
        else np.arange(0, 41) * (sigma / 2)
    )
    for th in ths[::-1]:
        sweep.run(th)
    table = sweep_table(sweep.tips, pixel_size, band)
    chosen, critical = _book_choice(
        np.array([s[0] for s in table]),
        np.array([s[2] for s in table]),
        np.array([s[3] for s in table]),
    )
    if chosen is None:
        chosen = float(ths[int(np.argmax([s[3] for s in table]))])
    return chosen, critical, table


# The sweep runs down a geometric ladder of thresholds from LADDER_TOP noise sigmas (where no
# feature point refines the tip yet) towards LADDER_BOTTOM sigmas. Coarse rungs COARSE_RATIO
# apart cross the calm part; near the runaway the rungs are FINE_RATIO apart. The error is
# steep on both sides of the best threshold (one 2^(1/3) rung above it cost 1.3-2x on the
# corpus): the runaway must be located to a fine rung, and the choice is the rung just above.
COARSE_RATIO = 2.0 ** (1.0 / 3.0)
FINE_RATIO = 2.0 ** (1.0 / 6.0)
LADDER_TOP = 64.0
LADDER_BOTTOM = 0.25
# Above the runaway every refined tip pixel sits at (its bound + N_TH): the estimate moves
# with the threshold at most one for one (rate <= ~1). A rung on which it drops more than
# RUNAWAY times the threshold step is noise feeding on itself: cuts that admit new contacts
# that cut further. A rate of a few is already out of the shifting regime; 3 keeps clear of
# the rates of 1-2 that the blunting regime reaches on blunt samples.
RUNAWAY = 3.0
# A coarse rung moving more than CALM times the threshold's rate has left the one-for-one
# regime: the descent goes back one coarse rung and continues on the fine ladder (a fine rung
# can run away inside a coarse step whose average rate is still below RUNAWAY).
CALM = 2.0
# The runaway starts gently: the fine rungs just above the jump that still move more than
# RUNAWAY_EDGE times as fast as the threshold (outside the one-for-one regime) belong to it.
RUNAWAY_EDGE = CALM
# Passes per rung on the way down (each rung starts from the one above, so refinement carries
# on down the ladder); only the chosen rung is run to convergence.
DESCENT_PASSES = 2
# The estimate has begun to follow the threshold once a rung moves it at between half and
# CALM times the threshold's rate (higher up, no feature point refines it and it stays at the
# flat start; its first moves off the start can be jumps, not a runaway).
FOLLOWING = 0.5
# Without a runaway the estimate follows the threshold to the bottom of the ladder; below a few
# sigmas single noise excursions still cut it (each bound is a difference of two noisy
# heights). The choice is then the lowest rung at or above SINGLE_EXCURSION sigmas: a
# one-sided 0.13 % excursion of one Gaussian height (tip_guard.NOISE_K, the same bound the
# estimate's uncertainty uses).
SINGLE_EXCURSION = 3.0


def _change_rate(upper: np.ndarray, lower: np.ndarray, step: float, depth: float) -> float:
    """RMS change from the estimate at the higher threshold to the one at the lower, over the
    top `depth` of the higher one (at least the apex's 3x3 neighbours), per unit threshold."""
    region = upper >= -depth
    h = upper.shape[0] // 2
    region[h - 1 : h + 2, h - 1 : h + 2] = True
    return float(np.sqrt(np.mean((upper - lower)[region] ** 2)) / step)


def _ladder(sigma: float, ratio: float, top: float) -> np.ndarray:
    """Thresholds from `top` down by `ratio` to LADDER_BOTTOM sigma, then 0."""
    rungs = int(np.ceil(np.log(top / (sigma * LADDER_BOTTOM)) / np.log(ratio)))
    return np.append(top / ratio ** np.arange(rungs + 1), 0.0)


def runaway_threshold(
    sweep: ThresholdSweep, sigma: float, depth: float, thresholds, resolves=None
):
    """The lowest threshold above the noise runaway: walk down the ladder (or the given
    thresholds), each estimate warm-started from the one above, and stop at the first rung
    whose change rate exceeds RUNAWAY once the estimate follows the threshold; the choice is
    the lowest rung above it that moved no faster than RUNAWAY_EDGE. The ladder is coarse
    (COARSE_RATIO) until a rung moves faster than CALM, then fine (FINE_RATIO) from the rung
    above that. Following down to the bottom without a runaway: the lowest rung at or above
    SINGLE_EXCURSION sigma; never following: the rung above the fastest change.
    resolves(tip, threshold) -> bool (None: always): whether an estimate constrains at least
    the apex's ring. A jump below a rung that does not is the estimate's first refinement of
    its apex (a plate cannot be cut into a needle by noise it has not yet taken in): the
    descent goes on past it, and no later back-off climbs above it. Returns (chosen, rates:
    threshold -> change rate from the rung above)."""
    fine = thresholds is not None
    ladder = (
        np.sort(np.asarray(thresholds, float))[::-1]
        if fine
        else _ladder(sigma, COARSE_RATIO, sigma * LADDER_TOP)
    )
    rates: dict = {}
    following = False
    ceiling = np.inf  # no choice above the rung where the apex was first resolved
    previous = sweep.run(ladder[0], cap=DESCENT_PASSES)
    j = 1
    while j < len(ladder):
        tip = sweep.run(ladder[j], cap=DESCENT_PASSES)
        rate = _change_rate(previous, tip, ladder[j - 1] - ladder[j], depth)
        if not fine and following and rate > CALM:
            # go back one coarse rung and resolve this step on the fine ladder
            fine = True
            ladder = _ladder(sigma, FINE_RATIO, float(ladder[j - 1]))
            previous, j = sweep.tips[float(ladder[0])], 1
            continue
        rates[float(ladder[j])] = rate
        if following and rate > RUNAWAY:
            above = j - 1
            # (the fine ladder's top is the calm coarse rung, with its rate from the coarse
            # step; a given ladder's top has none)
            while (
                above > 0
                and rates.get(float(ladder[above]), 0.0) > RUNAWAY_EDGE
                and ladder[above - 1] <= ceiling
            ):
                above -= 1
            chosen = sweep.run(ladder[above])  # converged
            if resolves is None or resolves(chosen, float(ladder[above])):
                return float(ladder[above]), rates
            # the jump refined the apex itself: go on down from the rung below it
            ceiling, following = float(ladder[j]), False
        # the first moves off the flat start can be jumps; following needs a calm rung
        following = following or FOLLOWING < rate <= CALM
        previous = tip
        j += 1
    if following:
        # followed the threshold down to the bottom without running away: the noise never
        # fed on itself, and what limits the threshold is single noise excursions
        floor = min(
            (t for t in sweep.tips if t >= SINGLE_EXCURSION * sigma), default=max(sweep.tips)
        )
        sweep.run(floor)
        return float(floor), rates
    fastest = max(rates, key=rates.get)
    above = min(t for t in sweep.tips if t > fastest)
    sweep.run(above)
    return float(above), rates


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


def consensus_threshold(
    sweep: ThresholdSweep, image, tip_size: int, sigma: float, depth: float, thresholds
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
