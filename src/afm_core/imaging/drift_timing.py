"""Does a 0/90 deg pair agree with the timing the drift compensation assumed? (issue 35)

The drift compensation (afm_core.imaging.drift_compensation) reads every feature region's
offset vector as D(t90) - D(t0) at its pixels' acquisition times, so it trusts the times: the
line period within each scan and the gap between the scans' starts. The images measure the
drift twice over, and the two measures depend on the times differently:
- within a scan, successive lines are displaced by the drift during one line period: the
  affine part of each offset vector (p2 .. p5) is D' times the line period, whatever the gap;
- between the scans, the translation part (p0, p1) is the drift accumulated from a point's
  0 deg moment to its 90 deg moment, which the gap dominates.
So the images fix the gap in units of the line period: a wrong gap shows as a translation that
disagrees with the within-scan velocity.

The implied gap: the 90 deg scan's times shifted by an unknown delta, and the drift fitted as
the correction fits it (drift_fit: a cubic B-spline in time, the features' whitened offset
vectors, the random-walk prior on the velocity). The profile J(delta) = min over the drift of
(data chi-square + prior) is minimised over delta; its curvature gives the standard error
(var = 2 / J''). The prior is what makes the gap identifiable at all when the drift wanders:
the drift during the time between the scans is not observed, only bounded by how fast the
velocity can change, and J's curvature includes that freedom. Before the profile the features'
covariances are scaled by chi2 / dof where the fit is worse than they allow (so an
underestimated offset error widens the gap's error instead of faking precision).

A stretch common to every region (du/dx and dv/dy, p2 and p5, the same in each) is fitted as
a nuisance (`_SCALE`), not read as drift: the fast axes of the two scans differ, and whatever
stretches a feature along its scan's fast axis (x/y calibration, feedback, pixel timing) looks
like a velocity along the other scan's slow axis. The velocity then comes from the regions'
translations at their different times and the shears; with two or three regions and a slow
drift that is often too little, and the check says it cannot tell rather than warn.

"Drift too small": a shift of the 90 deg times changes the offsets by the drift velocity during
that scan; that velocity comes from a low-order model (per axis v (t - t_m) + a (t - t_m)^2 / 2
with a free between-scan constant, linear least squares), and when it is not significantly
non-zero the gap cannot be told (and a wrong gap does no harm either).

What cannot be told: a common time scale. Scaling every time (line period and gap) by k and
the drift by 1/k gives the same images, so a wrong line rate is invisible when the gap is tied
to it (the CLI default, "right after the 0 deg scan"): the images fix gap / line period only.
`line_rate_ratio` is the line rate the images imply if the given gap (in seconds) is right.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize

from afm_core.imaging.drift_fit import (
    KNOT_LINES,
    TimeSpline,
    feature_observations,
    velocity_prior,
    whitened_blocks,
    whitening,
)
from afm_core.instrument import RasterScanData

# Warn when the implied gap differs from the assumed by more than GAP_SIGMAS standard errors
# (two-sided false-alarm rate 0.27 % for Gaussian errors) ...
GAP_SIGMAS = 3.0
# ... and by more than this share of the mean time between a point's 0 deg and 90 deg moments:
# the between-scan drift is read over that time, so a gap error of this share biases the drift
# it implies by about as much (the project's drift-velocity acceptance is 10 %).
GAP_SHARE = 0.10
# The drift during the 90 deg scan is "too small to tell the gap" when it is not significantly
# non-zero: its chi-square (2 degrees of freedom) below the 99.73 % point (the 3-sigma level).
VELOCITY_CHI2_2DOF = 11.83
_GRID = 25  # profile points over the searched gap range before the local refinement
_MOVES = 2  # times the range is moved on when the minimum is at its edge
_NM = 1e9
_UNIT = np.array([_NM, _NM, 1, 1, 1, 1])  # offsets in nm and dimensionless gradients
# A scale difference between the two scans common to every feature region (du/dx, dv/dy: p2,
# p5) is fitted as a nuisance, not read as drift: the scanner's x and y calibrations, and
# imaging along the fast axis (feedback, pixel timing), stretch each feature differently at 0
# and 90 deg; on simulated pairs such a common stretch of ~2e-3 (3-10 of the features' own
# standard errors) made 2-3 regions imply a gap 25-50 % short and warn at the right gap.
# SCALE_SIGMA: its weak prior (keeps the normal equations regular; far above any such stretch).
SCALE_SIGMA = 0.05
_SCALE = np.zeros((6, 2))
_SCALE[2, 0] = _SCALE[5, 1] = 1.0


@dataclass
class TimingCheck:
    """The pair's timing as the images see it (SI: s, m/s). None where it cannot be told."""

    gap_assumed: float  # s, start of the 0 deg scan to the start of the 90 deg scan
    line_period: float  # s, as given (both scans)
    gap_implied: float | None = None  # s, the gap the images imply (least squares)
    gap_error: float | None = None  # s, its standard error
    line_rate_ratio: float | None = None  # implied / given line rate, were the gap right
    line_rate_ratio_error: float | None = None
    velocity: tuple | None = None  # (vx, vy) m/s, the drift during the 90 deg scan
    velocity_error: tuple | None = None  # m/s, standard errors
    # consistency of the offsets with one drift of time (the correction's model): data
    # chi-square at the assumed and at the implied gap, over `values` offset-vector numbers
    # with `dof` degrees of freedom left by the fit
    chi2_assumed: float = math.nan
    chi2_implied: float = math.nan
    values: int = 0
    dof: float = 0.0
    checked: bool = False  # False: the images cannot tell the gap (see notes)
    warnings: list = field(default_factory=list)  # text naming assumption, given and implied
    notes: list = field(default_factory=list)  # why something could not be checked


def _start(scan: RasterScanData) -> float:
    return float(scan.start_time + np.min(scan.line_start_times))


def _low_order_velocity(obs, t_m: float, period: float):
    """The drift velocity during the 90 deg scan (nm per line period, with covariance) and the
    between-scan constant, from D = v s + a s^2 / 2 (s: time - t_m in line periods) plus a free
    constant in D(t90) - D(t0) and the common scale (_SCALE): linear least squares with
    chi2 / dof scaling."""
    rows, rhs, s90 = [], [], []
    for o in obs:
        white = whitening(o.cov * np.outer(_UNIT, _UNIT))
        half = o.projection.shape[1] // 2
        proj = o.projection * _UNIT[:, None] / _NM  # per nm of displacement
        a0, a90 = (o.t0 - t_m) / period, (o.t90 - t_m) / period
        terms = np.stack([a90 - a0, 0.5 * (a90**2 - a0**2), np.ones_like(a0)], axis=1)
        mx, my = white @ proj[:, :half] @ terms, white @ proj[:, half:] @ terms
        columns = [mx[:, 0], my[:, 0], mx[:, 1], my[:, 1], mx[:, 2], my[:, 2]]
        rows.append(np.column_stack(columns + [white @ _SCALE]))  # + the common scale
        rhs.append(white @ (o.z * _UNIT))
        s90.append(a90)
    design, z = np.vstack(rows), np.concatenate(rhs)
    sol, *_ = np.linalg.lstsq(design, z, rcond=None)
    chi2 = float(np.sum((design @ sol - z) ** 2))
    cov = np.linalg.pinv(design.T @ design) * max(1.0, chi2 / max(len(z) - design.shape[1], 1))
    mid90 = float(np.mean(np.concatenate(s90)))
    lin = np.array([[1, 0, mid90, 0], [0, 1, 0, mid90]], float)
    return lin @ sol[:4], lin @ cov[:4, :4] @ lin.T, sol[4:6]


class _Profile:
    """J(shift): the correction's drift model (spline, prior) plus the common stretch
    (_SCALE) refitted with the 90 deg times shifted by `shift` seconds, on one knot grid for
    every shift (so J is smooth in it)."""

    def __init__(self, obs, spline: TimeSpline, weight: float = 1.0):
        self.obs, self.spline, self.weight = obs, spline, weight
        prior = velocity_prior(spline)
        # only differences of D are observed: fix D = 0 at the grid's start (any gauge will do)
        anchor = np.kron(np.eye(2), spline.rows(spline.t0 + 2 * spline.h).toarray())
        fixed = prior.T @ prior + anchor.T @ anchor  # the normal matrix's constant part
        # the common scale (_SCALE): two more unknowns, the same columns for every shift
        self.fixed = np.zeros((fixed.shape[0] + 2,) * 2)
        self.fixed[:-2, :-2] = fixed
        self.fixed[-2:, -2:] = np.eye(2) / SCALE_SIGMA**2
        self.scale = np.vstack([whitening(o.cov * np.outer(_UNIT, _UNIT)) @ _SCALE for o in obs])

    def fit(self, shift: float, count: bool = False):
        """(J, data chi-square, effective number of drift parameters the data fix, or 0 unless
        `count`). Normal equations: the prior and the gauge keep them well posed, and they
        are several times faster than an orthogonal solve, which matters for the profile."""
        blocks = whitened_blocks(self.obs, self.spline, shift)
        data = np.hstack([np.vstack([d for d, _ in blocks]), self.scale]) / self.weight
        z = np.concatenate([r for _, r in blocks]) / self.weight
        normal = data.T @ data + self.fixed
        coeffs = np.linalg.solve(normal, data.T @ z)
        chi2 = float(np.sum((data @ coeffs - z) ** 2))
        total = chi2 + float(coeffs @ self.fixed @ coeffs)
        if not count:
            return total, chi2, 0.0
        used = float(np.sum((data @ np.linalg.inv(normal)) * data))  # trace of the hat matrix
        return total, chi2, used

    def __call__(self, shift: float) -> float:
        return self.fit(shift)[0]


def _implied_shift(profile: _Profile, lo: float, hi: float, period: float):
    """The shift minimising J on [lo, hi] (a grid, then Brent in the best cell), its standard
    error from J's curvature there (var = 2 / J''), and -1 / 1 when the grid's minimum is at
    its lower / upper end (0 inside)."""
    grid = np.linspace(lo, hi, _GRID)
    values = [profile(s) for s in grid]
    best = int(np.argmin(values))
    cell = grid[1] - grid[0]
    a, b = grid[max(best - 1, 0)], grid[min(best + 1, _GRID - 1)]
    found = optimize.minimize_scalar(
        profile, bounds=(a, b), method="bounded", options={"xatol": 0.01 * period}
    )
    shift, centre = float(found.x), float(found.fun)
    edge = -1 if best == 0 else (1 if best == _GRID - 1 else 0)  # where the minimum ran off
    step = max(period, 0.02 * cell)
    for _ in range(3):  # a step comparable to the error measures the parabola, not rounding
        curvature = (profile(shift + step) + profile(shift - step) - 2 * centre) / step**2
        if not curvature > 0:
            return shift, math.inf, edge
        error = math.sqrt(2.0 / curvature)
        if 0.2 * error <= step <= error:
            break
        step = 0.5 * error
    return shift, error, edge


def _search(obs, lo: float, hi: float, period: float):
    """The implied shift of the 90 deg times on [lo, hi] (moved up to _MOVES times when the
    minimum is at its edge): (shift, error, chi2 at 0, chi2 at shift, effective parameters),
    or None when there is no minimum. The features' covariances are first scaled by the
    fit's chi2 / dof where it exceeds 1; the chi-squares are reported against the features'
    own errors."""
    t0 = np.concatenate([o.t0 for o in obs])
    t90 = np.concatenate([o.t90 for o in obs])
    for _ in range(_MOVES + 1):
        spline = TimeSpline(
            min(t0.min(), t90.min() + lo) - period,
            max(t0.max(), t90.max() + hi) + period,
            KNOT_LINES * period,
        )
        _, chi2, used = _Profile(obs, spline).fit(0.5 * (lo + hi), count=True)
        weight = math.sqrt(max(1.0, chi2 / max(6 * len(obs) - used, 1.0)))
        profile = _Profile(obs, spline, weight)
        shift, error, edge = _implied_shift(profile, lo, hi, period)
        if edge == 0:
            break
        width = hi - lo
        lo, hi = lo + edge * 0.75 * width, hi + edge * 0.75 * width
    if edge != 0 or not math.isfinite(error):
        return None
    _, chi2_assumed, _ = profile.fit(0.0)
    _, chi2_implied, used = profile.fit(shift, count=True)
    return shift, error, chi2_assumed * weight**2, chi2_implied * weight**2, used


def check_timing(fits, scan0: RasterScanData, scan90: RasterScanData, keep=None):
    """The timing the images imply (module doc), for the feature fits of a pair
    ((blob, centre, RegionFit, rows, cols) each, as drift_compensation makes them). keep: which
    features the drift fit used (default all). Returns a TimingCheck."""
    obs = feature_observations(fits, scan0, scan90)
    if keep is not None:
        obs = [o for o, used in zip(obs, np.asarray(keep, bool)) if used]
    period = float(scan0.line_period)
    gap = _start(scan90) - _start(scan0)
    result = TimingCheck(gap_assumed=gap, line_period=period, values=6 * len(obs))
    if len(obs) < 2:  # the low-order model has 6 unknowns; one region gives 6 numbers
        result.notes.append(
            f"cannot check the gap: {len(obs)} feature region(s), too few to test one drift"
        )
        return result
    t_m = 0.5 * (_start(scan0) + _start(scan90))
    v90, v90_cov, constant = _low_order_velocity(obs, t_m, period)
    result.velocity = tuple(float(v) / _NM / period for v in v90)  # nm per line -> m/s
    result.velocity_error = tuple(float(np.sqrt(v90_cov[i, i])) / _NM / period for i in (0, 1))
    duration = period * len(scan0.line_start_times)
    t0 = np.concatenate([o.t0 for o in obs])
    t90 = np.concatenate([o.t90 for o in obs])
    spacing = KNOT_LINES * period
    if float(v90 @ np.linalg.pinv(v90_cov) @ v90) < VELOCITY_CHI2_2DOF:
        speed = math.hypot(*result.velocity) * 1e9
        spread = math.hypot(*result.velocity_error) * 1e9
        result.notes.append(
            f"cannot check the gap: drift too small ({speed:.3f} +- {spread:.2g} nm/s during "
            f"the 90 deg scan from {len(obs)} feature regions, not significantly non-zero)"
        )
        spline = TimeSpline(min(t0.min(), t90.min()), max(t0.max(), t90.max()), spacing)
        _, result.chi2_assumed, used = _Profile(obs, spline).fit(0.0, count=True)
        result.dof = result.values - used
        return result
    # search around the low-order estimate (constant ~ v90 * shift), wide enough for a wandering
    # drift to move the answer: half the implied gap or one scan, whichever is longer
    guess = period * float(constant @ v90 / (v90 @ v90))
    half = max(0.5 * abs(gap + guess), duration)
    found = _search(obs, min(guess - half, 0.0), max(guess + half, 0.0), period)
    if found is None:
        result.notes.append(
            "cannot check the gap: the images do not fix it (the drift fit's misfit has no "
            "minimum: the drift changed too much within or between the scans)"
        )
        return result
    shift, error, result.chi2_assumed, result.chi2_implied, used = found
    result.dof = result.values - used
    result.gap_implied, result.gap_error, result.checked = gap + shift, error, True
    if gap != 0.0 and result.gap_implied > 0.0:
        result.line_rate_ratio = result.gap_implied / gap
        result.line_rate_ratio_error = error / abs(gap)
    separation = abs(float(np.mean(t90 - t0)))
    if abs(shift) > GAP_SIGMAS * error and abs(shift) > GAP_SHARE * separation:
        text = (
            f"gap: {gap:.4g} s assumed from the start of the 0 deg scan to the start of the 90 "
            f"deg scan, the images imply {result.gap_implied:.4g} +- {error:.2g} s (at the given "
            f"line period {period:.4g} s)"
        )
        if result.line_rate_ratio is not None:
            text += (
                f"; or, if that gap is right, the line rate is {result.line_rate_ratio:.3g} +- "
                f"{result.line_rate_ratio_error:.2g} x the given {1.0 / period:.4g} Hz"
            )
        result.warnings.append(text + "; the drift fitted with the assumed timing is biased")
    return result
