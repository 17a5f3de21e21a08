"""Which detected pit is which punch: the calibration experiments punch pits at known commands
and find them again in a rescan (afm_core.localization.calibration.pits), shifted, with some
missing and some extra (another experiment's, noise).

- `match_points`: a 2-D pattern (a grid, the ends of scan lines): the common shift that
  brings most pits within a gate, then mutual nearest neighbours.
- `match_monotone`: a row of pits whose positions are a monotone, smooth function of the
  commands (a hysteresis sweep, a creep lane): the gaps between detections say how many
  punches each spans, the run is placed where a cubic fits best.
"""

from __future__ import annotations

import numpy as np


def match_points(expected, detected, gate: float) -> np.ndarray:
    """For each expected point (n, 2) the index of its detected pit (m, 2), -1 if none: first
    the common shift that brings most points within `gate` (every expected-detected offset is
    a candidate), then mutual nearest neighbours after the median shift of those."""
    expected, detected = (
        np.asarray(expected, float).reshape(-1, 2),
        np.asarray(detected, float).reshape(-1, 2),
    )
    result = np.full(len(expected), -1)
    if not len(expected) or not len(detected):
        return result
    anchors = expected[np.linspace(0, len(expected) - 1, min(len(expected), 12)).astype(int)]
    candidates = (detected[None, :, :] - anchors[:, None, :]).reshape(-1, 2)
    best, best_count = np.zeros(2), -1
    for shift in candidates:
        d = np.linalg.norm(expected[:, None, :] + shift - detected[None, :, :], axis=2)
        count = int((d.min(axis=1) < gate).sum())
        if count > best_count:
            best, best_count = shift, count
    for _ in range(2):
        d = np.linalg.norm(expected[:, None, :] + best - detected[None, :, :], axis=2)
        nearest = d.argmin(axis=1)
        inliers = d[np.arange(len(expected)), nearest] < gate
        if inliers.any():
            best = np.median(detected[nearest[inliers]] - expected[inliers], axis=0)
    d = np.linalg.norm(expected[:, None, :] + best - detected[None, :, :], axis=2)
    nearest, back = d.argmin(axis=1), d.argmin(axis=0)
    for i, j in enumerate(nearest):
        if back[j] == i and d[i, j] < gate:
            result[i] = j
    return result


def match_monotone(expected, detected, end_tolerance: float | None = None) -> np.ndarray:
    """Pits along a line whose positions are a monotone, smooth (not necessarily linear)
    function of the expected values (e.g. the drive of a hysteresis sweep, the commanded
    positions along a lane): index into `detected` per expected value, -1 if none.

    Robust to missing and extra pits: the gaps between neighbouring detections, against the
    local typical gap (median of the nearby ones), say how many expected steps each spans
    (a missing pit leaves a double gap; of two detections much closer than typical the
    later is dropped); the run of indices is then placed where a cubic through
    (expected, detected) fits best. A smooth curve cannot tell a run shifted by one step
    when an end pit is missing; `end_tolerance` (m) settles it where the ends are known to
    land near their expected value: placements whose first or last match is farther off
    lose. (The hysteresis rows do not use it: an asymmetric loop moves their ends by more
    than a pit spacing; see `monotone_placements`.)"""
    expected, detected = np.asarray(expected, float), np.asarray(detected, float)
    best, best_result = np.inf, np.full(len(expected), -1)
    for misfit, result in monotone_placements(expected, detected):
        if end_tolerance is not None:
            matched = result >= 0
            x, d = expected[matched], detected[result[matched]]
            order = np.argsort(x)
            ends = np.abs(d[order][[0, -1]] - x[order][[0, -1]])
            misfit += (
                1e6 * float(np.sum(np.maximum(ends - end_tolerance, 0.0) ** 2)) * (1 + misfit)
            )
        if misfit < best:
            best, best_result = misfit, result
    return best_result


def monotone_placements(
    expected, detected, smooth_spacing: bool = False
) -> list[tuple[float, np.ndarray]]:
    """Every placement of the run of `detected` along the sorted `expected` values that
    `match_monotone` considers (the gaps between detections fix the run's shape, only its
    start is open): (misfit of a cubic through (expected, detected), index into `detected`
    per expected value or -1). Empty when there are fewer than 4 of either. A caller that
    knows more about the ends (e.g. that two rows share them) chooses among these.

    smooth_spacing: the steps each gap spans are those under which the spacing per step
    changes least from gap to gap (`_smooth_step_counts`), not round(gap / the local median
    gap); for rows whose spacing changes fast (a wide hysteresis loop: threefold from a tip
    to the middle, where a missing pit's double gap is 1.5 local medians)."""
    expected, detected = np.asarray(expected, float), np.asarray(detected, float)
    if len(detected) < 4 or len(expected) < 4:
        return []
    order_e, order_d = np.argsort(expected), np.argsort(detected)
    e_sorted, d_sorted = expected[order_e], detected[order_d]
    kept = np.arange(len(d_sorted))
    for _ in range(3):
        gaps = np.diff(d_sorted[kept])
        typical = np.array([np.median(gaps[max(0, i - 3) : i + 4]) for i in range(len(gaps))])
        close = np.flatnonzero(gaps < 0.5 * typical)
        if not close.size:
            break
        kept = np.delete(kept, close[0] + 1)
    if smooth_spacing:
        while len(kept) > len(e_sorted):
            # more detections than punches: the end one farther from its neighbour is not ours
            ends = np.diff(d_sorted[kept])[[0, -1]]
            kept = kept[1:] if ends[0] > ends[1] else kept[:-1]
        steps = _smooth_step_counts(np.diff(d_sorted[kept]), len(e_sorted) - 1)
        return _placed(e_sorted, d_sorted, order_e, order_d, kept, steps, len(expected))
    gaps = np.diff(d_sorted[kept])
    typical = np.array([np.median(gaps[max(0, i - 3) : i + 4]) for i in range(len(gaps))])
    # the expected values are about uniformly spaced (sweeps, lanes): a gap spans
    # round(gap / typical) of their steps
    ratio = gaps / typical
    steps = np.maximum(1, np.round(ratio)).astype(int)
    while steps.sum() > len(e_sorted) - 1 and len(kept) > 4:
        # more steps than expected pits: the least convincing double gap was a wide single one;
        # with none left, the end detection farther from its neighbour is not of this row
        multiple = np.flatnonzero(steps > 1)
        if multiple.size:
            steps[multiple[np.argmin(ratio[multiple] - steps[multiple])]] -= 1
        elif ratio[0] > ratio[-1]:
            kept, ratio, steps = kept[1:], ratio[1:], steps[1:]
        else:
            kept, ratio, steps = kept[:-1], ratio[:-1], steps[:-1]
    return _placed(e_sorted, d_sorted, order_e, order_d, kept, steps, len(expected))


def _placed(e_sorted, d_sorted, order_e, order_d, kept, steps, size) -> list:
    """Every start of the run with these `steps` between the `kept` detections: (misfit of a
    cubic through it, index into the detections per expected value or -1)."""
    index = np.concatenate([[0], np.cumsum(steps)])
    placements = []
    for offset in range(0, len(e_sorted) - index[-1]):
        x = e_sorted[index + offset]
        if len(x) >= 5:
            coefficients = np.polyfit(x, d_sorted[kept], 3)
            misfit = float(np.sum((np.polyval(coefficients, x) - d_sorted[kept]) ** 2))
        else:
            misfit = float(np.sum((x - x.mean() - (d_sorted[kept] - d_sorted[kept].mean())) ** 2))
        result = np.full(size, -1)
        for position, i in zip(kept, index + offset):
            result[order_e[i]] = order_d[position]
        placements.append((misfit, result))
    return placements


# Steps one gap may span (five pits missing in a row); more is no longer one row.
MAX_GAP_STEPS = 6
# Cost per missing pit, in the units of the squared change of log spacing: it only breaks the
# tie between "every gap spans k steps" and "every gap spans one" (the same smoothness), far
# below a miscounted gap ((log 2)^2 = 0.48) and above a smooth row's change between
# neighbours (a threefold change over 25 pits: (log 3 / 24)^2 = 0.002).
MISSING_PIT_COST = 0.02


def _smooth_step_counts(gaps: np.ndarray, max_total: int) -> np.ndarray:
    """How many steps each gap between neighbouring detections spans (>= 1, sum <= max_total):
    the counts under which the spacing per step, gap / count, changes least (squared log
    ratio) from each gap to the next, plus MISSING_PIT_COST per missing pit; by dynamic
    programming over (this gap's count, steps so far)."""
    gaps = np.maximum(np.asarray(gaps, float), 1e-15)
    if not len(gaps):
        return np.zeros(0, dtype=int)
    counts = np.arange(1, MAX_GAP_STEPS + 1)
    inf = np.inf
    # cost[g - 1, t]: the best so far with this gap spanning g steps and t steps in all
    cost = np.full((MAX_GAP_STEPS, max_total + 1), inf)
    for g in counts[counts <= max_total]:
        cost[g - 1, g] = MISSING_PIT_COST * (g - 1)
    choices = []
    for i in range(1, len(gaps)):
        jump = (
            np.log(gaps[i] / counts)[:, None] - np.log(gaps[i - 1] / counts)[None, :]
        ) ** 2 + MISSING_PIT_COST * (counts[:, None] - 1)
        new = np.full_like(cost, inf)
        choice = np.zeros(cost.shape, dtype=int)
        for g in counts:
            shifted = np.full_like(cost, inf)
            shifted[:, g:] = cost[:, : max_total + 1 - g]
            total = shifted + jump[g - 1][:, None]
            choice[g - 1] = np.argmin(total, axis=0)
            new[g - 1] = total[choice[g - 1], np.arange(max_total + 1)]
        cost = new
        choices.append(choice)
    g, t = np.unravel_index(np.argmin(cost), cost.shape)
    steps = [int(g) + 1]
    for choice in reversed(choices):
        previous = int(choice[g, t])
        t -= g + 1
        g = previous
        steps.append(g + 1)
    return np.array(steps[::-1], dtype=int)
