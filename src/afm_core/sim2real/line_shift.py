"""How far each scan line of an image sits along its fast axis from its neighbours: a noise
statistic (`raster.line_shift`) that tells a lateral per-line offset from white height noise.

A line shifted by d along its fast axis reads h(s + d) ~ h(s) + d h'(s): its height error is the
local slope along the fast axis times one number common to the whole line, large on a
particle's flanks and nothing on flat substrate. White height noise is independent from sample
to sample and does not depend on the slope. So each line that crosses a particle is compared with
the mean of its two neighbours (what the line would be without a shift of its own: to first
order along the slow axis the two neighbours' curvature cancels), and its own shift is the least
squares d of that difference against the neighbours' slope, d = sum(diff x slope) / sum(slope^2).
With independent offsets of sd s per line, d estimates d_i - (d_(i-1) + d_(i+1)) / 2, whose sd is
s sqrt(3 / 2); the statistic is the robust sd of the lines' d over sqrt(3 / 2), in m. White noise
of sd n gives each d an error of about n sqrt(3 / 2) / sqrt(sum slope^2): a few hundredths of a
nanometre on the protocol's particles, so the model's own statistic is near zero and a jitter of
a few nanometres stands out. The statistic is invariant to a z gain (heights and slopes scale
alike). Its noise is modelled whole (the replicas and the substrate's other realizations, as for
the other noise statistics), without an overdispersion factor: a factor taken after the best
noise term's fit would scale the statistic's excess away, which is the evidence itself.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.stats import median_abs_deviation

LINE_SHIFT_GROUP = "raster.line_shift"
CROSSING_HEIGHT = 20e-9  # m above the image's median: a line crossing a particle (landmarks')
MIN_CROSSINGS = 8  # lines crossing a particle an image needs for the statistic
SHIFT_VARIANCE = 1.5  # var(d_i - (d_(i-1) + d_(i+1)) / 2) / var(d) for independent offsets
# k var(robust sd of k normal draws) / sd^2 for large k: 1 / (2 x 0.3675, the efficiency of the
# normal-scaled median absolute deviation)
MAD_VARIANCE = 1.36


def line_shifts(lines: np.ndarray, pixel: float) -> np.ndarray:
    """(lines,) each interior line's least-squares shift (m) along the fast axis against the
    mean of its two neighbours, NaN where the neighbours cross no particle (too little slope).
    `lines`: (n, samples) heights (m), one scan line per row in fast-axis order; `pixel`: the
    sample spacing along the line (m)."""
    lines = np.asarray(lines, float)
    if pixel <= 0 or not math.isfinite(pixel):
        raise ValueError(f"pixel={pixel!r}: expected a positive sample spacing in m")
    out = np.full(lines.shape[0], np.nan)
    if lines.shape[0] < 3 or lines.shape[1] < 3:
        return out
    level = float(np.median(lines))
    ref = 0.5 * (lines[:-2] + lines[2:])
    slope = np.gradient(ref, pixel, axis=1)
    diff = lines[1:-1] - ref
    crossing = (ref.max(axis=1) - level) > CROSSING_HEIGHT
    power = np.sum(slope**2, axis=1)
    ok = crossing & (power > 0)
    out[1:-1][ok] = np.sum(diff * slope, axis=1)[ok] / power[ok]
    return out


def line_shift_noise(lines: np.ndarray, pixel: float) -> tuple[float, int]:
    """(the sd (m) of an independent per-line lateral offset the image shows, robust, see the
    module's docstring; the number of lines it is taken over); NaN when fewer than
    MIN_CROSSINGS lines cross a particle."""
    d = line_shifts(lines, pixel)
    d = d[np.isfinite(d)]
    if d.size < MIN_CROSSINGS:
        return math.nan, int(d.size)
    return float(median_abs_deviation(d, scale="normal") / math.sqrt(SHIFT_VARIANCE)), int(d.size)


def statistic_variance(value: float, lines: int) -> float:
    """The sampling variance (m^2) of a line-shift statistic `value` taken over `lines` lines:
    a robust sd of k draws is known to MAD_VARIANCE sd^2 / k. The per-line estimates of an image
    without a shift of its own carry what the particles' sampling phase and the slow-axis
    curvature leave in them (0.27-0.46 nm on one null session's four images), which a
    re-simulation with the particles a nanometre elsewhere does not repeat line by line; only
    their spread is common, to this precision."""
    return MAD_VARIANCE * value**2 / max(lines, 1)
