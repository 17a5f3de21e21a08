"""The calibration experiments of book 7.2.2, run on an instrument, fitted, and written as one
`Calibration` (afm_core.localization.calibration) for the localizer.

ROS-free: every experiment takes an `afm_core.instrument.Instrument` (the simulated AFM, or
the DAQ driver on the real one) and uses only its public calls (move_tip, indent,
raster_scan, local_scan, commanded_position, time), plus two the experiments need:
`hold(seconds)` (falls back to waiting on the wall clock) and, for the hysteresis
experiment alone, a `feed_forward_enabled` switch (the controller's inverse-PI feed-forward
off = the raw drive the book applies). Each experiment returns an `Experiment`: the fitted
parameters and the raw data for a plot (plain lists, JSON-ready).

Where the pits go. Every experiment records the tip's position by punching a pit (book
Fig. 7.6a, 7.7a, 7.12a) and finds the pits again in a rescan (`afm_core.localization.pits`).
A rescan is taken with the same scanner, so it measures positions in the image frame, which
is the frame the localizer's maps are in; its own distortion is kept small by scanning the
long direction of a pit pattern along the slow axis (one monotone pass, no fast-axis loop),
see each experiment. Sites are chosen on flat substrate away from the scanner centre (where
the default sample's particles are) and apart from each other; all are offsets from the
range centre and can be changed.

The image frame. Because the rescans use the scanner being calibrated, everything is
measured in the frame of the instrument's own images, which is the frame the localizer's
maps are in. What every image shares cannot be seen: the tube's x/y coupling and its
rotation against the sample (so the scanner matrix comes out near the identity and the
line deflection near 0 deg on the simulator, whatever is configured), and the small-move
gain of the compensated scanner, which sets a small image's scale on each axis and with it
the scale of the drift velocities measured in it. With the simulator's 10 % feed-forward
model error a short move after a reversal goes ~6 % farther than commanded: a drift
frame's slow axis (one monotone pass after a reversal) moves 1.059 x the commanded pixel,
its fast axis 1.040 x (the same +6 %, less the ~2 % of creep that cannot follow a line
oscillating at 0.75 Hz), so the drift velocities are ~6 % (y) and ~4 % (x) low against the
true ones (with the model error 0: scales 1.000 and 0.981, creep alone, so y exact and x
~2 % high). An image cannot see its own scale; the absolute scale and orientation need a
reference of known size and direction (a calibration grating) imaged like the frames it is
for (size, line rate, approach); the long full-range rescans of the hysteresis experiment
are on the scanner's long branches, whose compensated gain is within ~1 % of 1.

Experiments (`run_calibration` runs the drift pairs first, then the others in this order):
- `measure_creep`: a large step, then pits along the other axis over `duration` s; creep
  time constants (shared) and fractions (per axis) by nonlinear least squares (eq. 5.29-5.31,
  Fig. 7.7).
- `measure_hysteresis`: feed-forward off, a full-range voltage cycle with a pit every 4th step
  on the descending and the ascending sweep, feed-forward on, rescan; PI weights for fixed
  thresholds by non-negative least squares, the input asymmetry by a 1-D search
  (eq. 5.22-5.23, Fig. 7.6a). The measured creep is part of the model.
- `measure_scanner_matrix`: a grid of pits at commanded offsets; the affine map commanded ->
  imaged displacement.
- `measure_motion_noise`: repeated moves of several lengths, a pit before and after each;
  variance of the separations about their mean vs distance: sigma^2 = a d + b (Fig. 7.6e,
  Fig. 7.20b).
- `measure_line_deflection`: pits at both ends of local scan lines (Fig. 7.12).
- `measure_drift`: frame-up / frame-down image pairs of a particle area, apart in time
  (eq. 5.32-5.36, Fig. 7.9); the same frames give the map error (Fig. 7.10) and the
  scan-region error (Fig. 7.11).
"""

from __future__ import annotations

import math
import time as wallclock
from dataclasses import dataclass, field
from datetime import datetime, timezone

import numpy as np
from scipy import linalg, optimize

from afm_core.imaging.frame_up_down import up_down_observations, up_down_velocity
from afm_core.imaging.landmarks import extract_landmarks
from afm_core.instrument import LineRequest, RasterScanData, ScanRequest, check_in_range
from afm_core.localization.calibration import Calibration, HysteresisFit
from afm_core.localization.pits import DetectedPit, find_pits
from afm_core.pzt import Creep, PlayOperatorBank, PrandtlIshlinskii

MAX_LINE_RATE = 10.0  # Hz, rescans: slower than the slew limit allows keeps the tracking honest
MODEL_DT = 2e-3  # s, time step of the drive reconstruction in the hysteresis fit


@dataclass
class Experiment:
    parameters: dict = field(default_factory=dict)  # fitted values, SI
    data: dict = field(default_factory=dict)  # raw data for a plot, SI, lists


# -- checks and small helpers -------------------------------------------------------------------


def _positive(name: str, value: float, upper: float | None = None, unit: str = "") -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name}={value}: must be finite and > 0{(' ' + unit) if unit else ''}")
    if upper is not None and value > upper:
        raise ValueError(
            f"{name}={value:.4g}: above the limit {upper:.4g}{(' ' + unit) if unit else ''}"
        )
    return value


def _count(name: str, value: int, minimum: int, maximum: int | None = None) -> int:
    if int(value) != value or value < minimum or (maximum is not None and value > maximum):
        limit = f"[{minimum}, {maximum}]" if maximum is not None else f">= {minimum}"
        raise ValueError(f"{name}={value}: need an integer {limit}")
    return int(value)


def _centre(instrument) -> np.ndarray:
    return 0.5 * np.array([instrument.limits.range_x, instrument.limits.range_y])


def _force(instrument, force: float | None) -> float:
    limit = instrument.limits.max_indent_force
    return min(1e-6, limit) if force is None else _positive("force", force, limit, "N")


def _check_box(name: str, instrument, lo, hi) -> None:
    """Every corner of the box [lo, hi] inside the scanner range (ValueError naming `name`)."""
    check_in_range(f"{name} (lower corner)", float(lo[0]), float(lo[1]), instrument.limits)
    check_in_range(f"{name} (upper corner)", float(hi[0]), float(hi[1]), instrument.limits)


def wait(instrument, seconds: float) -> None:
    """Let time pass with the command held: the instrument's hold() when it has one (the
    simulator), else the wall clock (hardware holds its last output by itself)."""
    if seconds <= 0:
        return
    hold = getattr(instrument, "hold", None)
    if hold is not None:
        hold(seconds)
    else:
        wallclock.sleep(seconds)


def _set_feed_forward(instrument, enabled: bool) -> None:
    if not hasattr(instrument, "feed_forward_enabled"):
        raise ValueError(
            "instrument: has no feed_forward_enabled switch; the hysteresis experiment drives the "
            "piezos open loop (raw voltages) and needs it"
        )
    instrument.feed_forward_enabled = enabled


class _Timeline:
    """The commanded position against the instrument clock, as issued: the command is held
    between calls and ramps linearly during a move, so the drive is piecewise linear in time."""

    def __init__(self, instrument):
        self.instrument = instrument
        self.times: list[float] = []
        self.commands: list[tuple[float, float]] = []
        self.mark()

    def mark(self) -> None:
        self.times.append(float(self.instrument.time))
        self.commands.append(tuple(float(c) for c in self.instrument.commanded_position()))

    def move(self, x: float, y: float, speed: float) -> None:
        self.mark()
        self.instrument.move_tip(x, y, speed)
        self.mark()

    def punch(self, force: float) -> float:
        """A pit where the tip is; returns the moment it is punched (instrument clock)."""
        self.mark()
        x, y = self.instrument.commanded_position()
        moment = float(self.instrument.time)
        self.instrument.indent(x, y, force, 0.0)
        self.mark()
        return moment

    def sampled(self, axis: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
        times = np.asarray(self.times)
        values = np.asarray(self.commands)[:, axis]
        grid = np.arange(times[0], times[-1] + dt, dt)
        return grid, np.interp(grid, times, values)


def _punch_at(instrument, x: float, y: float, speed: float, force: float) -> float:
    instrument.move_tip(x, y, speed)
    moment = float(instrument.time)
    instrument.indent(x, y, force, 0.0)
    return moment


def rescan(
    instrument, lo, hi, pixel: float, slow_axis: int, slow_up: bool = True, approach: float = 0.0
) -> RasterScanData:
    """A raster image of the box [lo, hi] (m) with square pixels of about `pixel` and its slow
    axis along `slow_axis` (0 = x: 90 deg scan; 1 = y: 0 deg). The slow axis moves once,
    monotonically, so a row of pits along it is imaged on one branch of the (compensated)
    scanner with no fast-axis loop in between. approach > 0: the tip first goes that far
    before the start along the slow axis, so the pass is on a long monotone stretch of the
    scanner's loop (small moves after a reversal have a different gain)."""
    limits = instrument.limits
    lo = np.maximum(np.asarray(lo, float), 0.0)
    hi = np.minimum(np.asarray(hi, float), [limits.range_x, limits.range_y])
    size = hi - lo
    pixels = np.maximum(16, np.ceil(size / pixel)).astype(int)
    if pixels.max() > limits.max_pixels:
        raise ValueError(
            f"pixel={pixel:.3g} m: the rescan of {size[0]:.3g} x {size[1]:.3g} m would need "
            f"{pixels.max()} pixels, above max_pixels {limits.max_pixels}"
        )
    fast = 1 - slow_axis
    rate = min(MAX_LINE_RATE, limits.max_line_rate, 0.95 * limits.max_speed / (2.0 * size[fast]))
    if approach > 0:
        start = lo.copy() if slow_up else hi.copy()
        start[slow_axis] = (
            max(0.0, start[slow_axis] - approach)
            if slow_up
            else min(start[slow_axis] + approach, [limits.range_x, limits.range_y][slow_axis])
        )
        instrument.move_tip(float(start[0]), float(start[1]), 0.5 * limits.max_speed)
    request = ScanRequest(
        float(lo[0]),
        float(lo[1]),
        float(size[0]),
        float(size[1]),
        int(pixels[0]),
        int(pixels[1]),
        scan_angle_deg=90.0 if slow_axis == 0 else 0.0,
        slow_scan_up=slow_up,
        line_rate=rate,
    )
    return instrument.raster_scan(request)


# -- matching detected pits to the punches ---------------------------------------------------------


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


def match_monotone(
    expected, detected, spacing: float | None = None, end_tolerance: float | None = None
) -> np.ndarray:
    """Pits along a line whose positions are a monotone, smooth (not necessarily linear)
    function of the expected values (e.g. the drive of a hysteresis sweep, the commanded
    positions along a lane): index into `detected` per expected value, -1 if none.

    Robust to missing and extra pits: the gaps between neighbouring detections, against the
    local typical gap (median of the nearby ones), say how many expected steps each spans
    (a missing pit leaves a double gap; of two detections much closer than typical the
    later is dropped); the run of indices is then placed where a cubic through
    (expected, detected) fits best. A smooth curve cannot tell a run shifted by one step
    when an end pit is missing; `end_tolerance` (m) settles it where the ends are known to
    land near their expected value (the tips of a hysteresis loop): placements whose first
    or last match is farther off lose. `spacing` is unused (kept for callers' clarity)."""
    expected, detected = np.asarray(expected, float), np.asarray(detected, float)
    result = np.full(len(expected), -1)
    if len(detected) < 4 or len(expected) < 4:
        return result
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
    index = np.concatenate([[0], np.cumsum(steps)])
    best, best_offset = np.inf, None
    for offset in range(0, len(e_sorted) - index[-1]):
        x = e_sorted[index + offset]
        if len(x) >= 5:
            coefficients = np.polyfit(x, d_sorted[kept], 3)
            misfit = float(np.sum((np.polyval(coefficients, x) - d_sorted[kept]) ** 2))
        else:
            misfit = float(np.sum((x - x.mean() - (d_sorted[kept] - d_sorted[kept].mean())) ** 2))
        if end_tolerance is not None:
            ends = np.abs(d_sorted[kept][[0, -1]] - x[[0, -1]])
            misfit += (
                1e6 * float(np.sum(np.maximum(ends - end_tolerance, 0.0) ** 2)) * (1 + misfit)
            )
        if misfit < best:
            best, best_offset = misfit, offset
    if best_offset is None:
        return result
    for position, i in zip(kept, index + best_offset):
        result[order_e[i]] = order_d[position]
    return result


# -- creep (eq. 5.29-5.31, Fig. 7.7) ------------------------------------------------------------------


def creep_deficit(t, time_constants, ramp_time: float) -> np.ndarray:
    """For a step applied as a ramp over [0, ramp_time]: how far each creep operator of eq.
    5.29 still lags behind the settled value at t >= ramp_time, per unit step, shape
    (len(t), len(time_constants)): (tau / T) (1 - e^{-T/tau}) e^{-(t - T)/tau} (-> e^{-t/tau}
    for T -> 0). The position is then x_inf - S sum_i c_i deficit_i(t)."""
    t = np.asarray(t, float)[:, None]
    tau = np.asarray(time_constants, float)[None, :]
    if ramp_time <= 0:
        return np.exp(-t / tau)
    return (tau / ramp_time) * -np.expm1(-ramp_time / tau) * np.exp(-(t - ramp_time) / tau)


WALK_MEASUREMENT_RATIO = (
    0.1  # a pit's own position noise (~1 nm)^2 over one move's walk step (~3 nm)^2
)


def walk_whitener(moves, pit_to_walk_ratio: float = WALK_MEASUREMENT_RATIO) -> np.ndarray:
    """Lower-triangular L^-1 that whitens positions carrying a random walk: each move between
    pits adds a persistent positioning error (book eq. 5.5's w, sigma^2 = a d + b per move), so
    the pit after the k-th move carries the sum of k such errors, on top of its own
    measurement noise; covariance (per walk variance) min(k_i, k_j) + ratio delta_ij, with
    `moves` the k of each pit. Ordinary least squares on such data is unbiased but lets the
    walk's slow wander pass for creep of the slow time constants; whitened, each residual
    counts once (generalised least squares)."""
    k = np.asarray(moves, float)
    covariance = np.minimum.outer(k, k) + pit_to_walk_ratio * np.eye(k.size)
    return linalg.solve_triangular(np.linalg.cholesky(covariance), np.eye(k.size), lower=True)


def fit_creep(
    runs: list[dict], n_constants: int = 3, guess=(1.0, 10.0, 100.0), drift_curvature: bool = False
) -> dict:
    """Nonlinear least squares (scipy.optimize.least_squares) over all runs at once: shared
    time constants, per group of runs (an axis) the fractions c_i >= 0 (of the commanded step
    S), per run the settled position x_inf and a drift velocity v:
        x(t) = x_inf + v (t - t_mid) [+ q (t - t_mid)^2] - S sum_i c_i deficit_i(t).
    The drift velocity wanders (it is not constant over minutes), which a straight line
    leaves to the slowest creep term; drift_curvature adds the q term that takes it up;
    repeated runs of one group average that wander out.
    A run: {"t": s after the step started, "x": m along the step, "step": S (m, signed),
    "ramp_time": s, optional "group" (default: each run its own), optional "moves": moves made
    before each pit (then the residuals are whitened for the positioning random walk,
    `walk_whitener`, starting from the ordinary fit, with a robust loss against a misread
    pit)}. Positions are fitted in nm (a well-scaled problem). "fractions": per group, in
    order of first appearance; "model": per run, the fitted curve at its pits (m)."""
    if len(guess) != n_constants:
        raise ValueError(f"guess={guess}: need {n_constants} time constants")
    groups = list(dict.fromkeys(run.get("group", k) for k, run in enumerate(runs)))
    prepared = []
    for k, run in enumerate(runs):
        t, x = np.asarray(run["t"], float), np.asarray(run["x"], float) * 1e9
        whitener = np.eye(t.size) if run.get("moves") is None else walk_whitener(run["moves"])
        prepared.append(
            (
                t,
                x,
                float(run["step"]) * 1e9,
                float(run["ramp_time"]),
                float(np.mean(t)),
                whitener,
                groups.index(run.get("group", k)),
            )
        )

    extra = 3 if drift_curvature else 2

    def unpack(theta):
        taus = np.exp(theta[:n_constants])
        fractions = theta[n_constants : n_constants * (1 + len(groups))].reshape(
            len(groups), n_constants
        )
        per_run = theta[n_constants * (1 + len(groups)) :].reshape(len(prepared), extra)
        return taus, fractions, per_run

    def residuals(theta, whiten=True):
        taus, fractions, per_run = unpack(theta)
        out = []
        for (t, x, step, ramp, t_mid, whitener, group), p in zip(prepared, per_run):
            model = (
                p[0]
                + p[1] * (t - t_mid)
                + (p[2] * (t - t_mid) ** 2 if drift_curvature else 0.0)
                - step * creep_deficit(t, taus, ramp) @ fractions[group]
            )
            out.append(whitener @ (model - x) if whiten else model - x)
        return np.concatenate(out)

    theta0 = list(np.log(guess)) + [0.005] * (n_constants * len(groups))
    lower = [-np.inf] * n_constants + [0.0] * (n_constants * len(groups))
    upper = [np.inf] * n_constants + [0.5] * (n_constants * len(groups))
    for t, x, *_ in prepared:
        theta0 += [x[-1]] + [0.0] * (extra - 1)
        lower += [-np.inf] * extra
        upper += [np.inf] * extra
    fit = optimize.least_squares(
        residuals,
        theta0,
        bounds=(lower, upper),
        x_scale="jac",
        method="trf",
        kwargs={"whiten": False},
    )
    if any(run.get("moves") is not None for run in runs):
        # started from the ordinary fit: the whitened cost alone has shallow valleys far off
        fit = optimize.least_squares(
            residuals,
            np.clip(fit.x, lower, upper),
            bounds=(lower, upper),
            x_scale="jac",
            method="trf",
            loss="soft_l1",
            f_scale=10.0,
        )
    taus, fractions, per_run = unpack(fit.x)
    order = np.argsort(taus)
    misfit = residuals(fit.x, whiten=False)
    rms = float(np.sqrt(np.mean(misfit**2))) * 1e-9
    ends = np.cumsum([len(t) for t, *_ in prepared])[:-1]
    models = [(x + r) * 1e-9 for (_, x, *_), r in zip(prepared, np.split(misfit, ends))]
    return {
        "time_constants": taus[order].tolist(),
        "fractions": [f[order].tolist() for f in fractions],
        "settled": [float(p[0]) * 1e-9 for p in per_run],
        "drift_velocity": [float(p[1]) * 1e-9 for p in per_run],
        "model": [m.tolist() for m in models],
        "rms_residual": rms,
        "success": bool(fit.success),
    }


def measure_creep(
    instrument,
    *,
    step: float = 50e-6,
    duration: float = 300.0,
    pits: int = 40,
    fast_pits: int = 8,
    repeats: int = 5,
    pit_spacing: float = 150e-9,
    settle: float = 300.0,
    lane_offset: float = 15e-6,
    pixel: float = 10e-9,
    force: float | None = None,
    guess=(1.0, 10.0, 100.0),
) -> Experiment:
    """Creep of each axis in normal (compensated) operation (book 7.2.2, Fig. 7.7).

    Per axis, `repeats` runs: rest at centre - step/2 for `settle` s (earlier creep dies
    out), step to centre + step/2 at full speed, then punch `pits` pits one `pit_spacing`
    apart along the other axis at lane_offset from the centre (each further run shifted along
    the step by what its rescan covers, so the rows stay apart): `fast_pits` back to back (the
    0.5 s constant), the rest at log-spaced times up to `duration` s (the book samples 25 s; the 50 s constant
    needs several of its own lengths to be told from drift, which is fitted too). The moves
    along the other axis do not move this one, so each pit's coordinate along the step is
    the creep curve at its moment. Each run is rescanned with the slow axis along the step,
    approached from 50 um before so the pass is on a long monotone stretch of the loop
    (uniform image gain). `fit_creep` then fits all runs at once, the fractions shared by the
    runs of an axis: one run's drift wanders by tens of nm over minutes, as much as the
    slowest creep term changes, and independent runs average it out."""
    limits = instrument.limits
    step = _positive("step", step, min(limits.range_x, limits.range_y) * 0.9, "m")
    duration = _positive("duration", duration, 3600.0, "s")
    pits = _count("pits", pits, 8, 400)
    fast_pits = _count("fast_pits", fast_pits, 1, pits - 4)
    repeats = _count("repeats", repeats, 1, 20)
    pit_spacing = _positive("pit_spacing", pit_spacing, 5e-6, "m")
    force = _force(instrument, force)
    centre = _centre(instrument)
    run_spacing = (
        0.05 * step + 1.5e-6
    )  # past the creep a rescan box reaches back (5 % of the step)
    plans = []
    for axis in (0, 1):
        other = 1 - axis
        for repeat in range(repeats):
            start, end = centre.copy(), centre.copy()
            start[axis] = centre[axis] - step / 2 + repeat * run_spacing
            end[axis] = centre[axis] + step / 2 + repeat * run_spacing
            start[other] = end[other] = centre[other] + lane_offset - pits * pit_spacing / 2
            last = end.copy()
            last[other] += (pits - 1) * pit_spacing
            _check_box(
                f"creep lane ({'xy'[axis]}, run {repeat})",
                instrument,
                np.minimum(start, last),
                np.maximum(end, last),
            )
            plans.append((axis, start, end))
    runs, data = [], {"x": [], "y": []}
    for axis, start, end in plans:
        other = 1 - axis
        instrument.move_tip(float(start[0]), float(start[1]), 0.5 * limits.max_speed)
        wait(instrument, settle)
        t0 = float(instrument.time)
        instrument.move_tip(float(end[0]), float(end[1]), limits.max_speed)
        ramp_time = float(instrument.time) - t0
        # log-spaced moments from just after the step; the early ones come faster than a pit can
        # be punched, so those go back to back (fast_pits of them at least)
        schedule = np.geomspace(ramp_time + 0.05, duration, pits)
        schedule[:fast_pits] = 0.0
        moments, lane = [], []
        for k, when in enumerate(schedule):
            wait(instrument, t0 + when - float(instrument.time))
            target = end.copy()
            target[other] += k * pit_spacing
            moments.append(
                _punch_at(instrument, float(target[0]), float(target[1]), limits.max_speed, force)
                - t0
            )
            lane.append(float(target[other]))
        reach = 0.05 * step + 0.5e-6  # creep is a few % of the step: the image covers up to 5 %
        lo, hi = end.copy(), end.copy()
        lo[axis] -= reach
        hi[axis] += 0.5e-6
        lo[other], hi[other] = lane[0] - 0.4e-6, lane[-1] + 0.4e-6
        scan = rescan(instrument, lo, hi, pixel, slow_axis=axis, approach=50e-6)
        detected = find_pits(scan)
        found = np.array([[p.x, p.y][other] for p in detected])
        index = match_monotone(lane, found, pit_spacing) if len(found) else np.full(len(lane), -1)
        ok = index >= 0
        name = "xy"[axis]
        if ok.sum() < 8:
            raise RuntimeError(
                f"creep ({name}, run {len(data[name])}): only {int(ok.sum())} of {pits} pits found "
                "in the rescan"
            )
        positions = np.array([[detected[j].x, detected[j].y][axis] for j in index[ok]])
        times = np.asarray(moments)[ok]
        # pit k comes after k moves along the lane (the step itself is common to all: x_inf)
        runs.append(
            {
                "t": times,
                "x": positions,
                "step": step,
                "ramp_time": ramp_time,
                "group": name,
                "moves": np.flatnonzero(ok) + 1,
            }
        )
        data[name].append(
            {
                "t": times.tolist(),
                "position": positions.tolist(),
                "step": step,
                "ramp_time": ramp_time,
                "pits_punched": pits,
                "pits_found": int(ok.sum()),
            }
        )
    fit = fit_creep(runs, guess=guess)
    for record, model in zip(data["x"] + data["y"], fit["model"]):
        record["model"] = model
    parameters = {
        "time_constants": fit["time_constants"],
        "fractions_x": fit["fractions"][0],
        "fractions_y": fit["fractions"][1],
        "drift_velocity": fit["drift_velocity"],
        "rms_residual": fit["rms_residual"],
        "success": fit["success"],
    }
    return Experiment(parameters, data)


# -- hysteresis (eq. 5.22-5.23, Fig. 7.6a) ---------------------------------------------------------


def asymmetric_polynomial(alpha: float, half: float) -> tuple[float, float, float]:
    """The input function of PrandtlIshlinskii.from_fraction: p(xi) = (1 - a^2) xi + a xi^2 +
    a^2 xi^3 in xi = x / half, as coefficients of x."""
    return (1.0 - alpha * alpha, alpha / half, alpha * alpha / half**2)


def major_loop(
    model: PrandtlIshlinskii, half: float, samples: int = 2001
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, ascending, descending) branches of the major loop of a full-span triangle cycle
    [-half, half], after a first sweep has wiped the memory."""
    x = np.linspace(-half, half, samples)
    cycle = np.concatenate([x, x[::-1][1:], x[1:]])
    model.reset(0.0)
    y = model.apply(cycle)
    descending = y[samples - 1 : 2 * samples - 1][::-1]
    ascending = y[2 * samples - 2 :]
    return x, ascending, descending


def loop_measures(model: PrandtlIshlinskii, half: float) -> tuple[float, float]:
    """(loop fraction, tip-to-tip gain) exactly as PrandtlIshlinskii.from_fraction defines the
    fraction: the largest vertical distance between the branches of the full-span major loop,
    divided by the output's tip-to-tip span (from_fraction makes that span equal the input's,
    so this is width / span there, and stays a pure shape measure when the gain is not 1)."""
    x, ascending, descending = major_loop(model, half)
    span = ascending[-1] - ascending[0]
    return float(np.max(descending - ascending) / span), float(span / (2 * half))


def _operator_design(
    times: np.ndarray,
    drive: np.ndarray,
    centre: float,
    thresholds: np.ndarray,
    alpha: float,
    half: float,
    creep: tuple | None,
    pit_times: np.ndarray,
) -> np.ndarray:
    """Columns: each play operator's output on p(drive - centre), through the creep operator
    (linear, DC gain 1, so creep of the weighted sum = weighted sum of the creeps), at the pit
    moments."""
    poly = asymmetric_polynomial(alpha, half)
    u = drive - centre
    v = ((poly[2] * u + poly[1]) * u + poly[0]) * u
    bank = PlayOperatorBank(thresholds)
    bank.reset(v[0])
    outputs = bank.apply(v)
    if creep is not None:
        time_constants, fractions = creep
        dt = float(times[1] - times[0])
        for k in range(outputs.shape[1]):
            operator = Creep(
                1.0 / np.asarray(time_constants),
                np.asarray(fractions),
                1.0 - float(np.sum(fractions)),
            )
            operator.reset(outputs[0, k])
            outputs[:, k] = operator.apply(outputs[:, k], dt)
    return np.stack(
        [np.interp(pit_times, times, outputs[:, k]) for k in range(outputs.shape[1])], axis=1
    )


def fit_hysteresis(
    times,
    drive,
    centre: float,
    half: float,
    pit_times,
    positions,
    thresholds,
    creep: tuple | None = None,
    alpha_bound: float = 0.3,
) -> dict:
    """Least-squares PI fit (book 7.2.2): for fixed thresholds the model is linear in the
    weights, position = offset + sum_i w_i (C F_{r_i}[p_alpha(drive - centre)])(t_pit), so
    the weights come from a bounded linear least squares (w_i >= 0: every branch slope
    positive, the model invertible; the offset free: where the rescan put the origin); the
    input asymmetry alpha (from_fraction's) by a bounded 1-D search around it. Positions in
    um inside (a well-scaled problem)."""
    times, drive = np.asarray(times, float), np.asarray(drive, float)
    pit_times, positions = np.asarray(pit_times, float), np.asarray(positions, float)
    thresholds = np.asarray(thresholds, float)
    target = positions * 1e6

    def solve(alpha):
        design = (
            _operator_design(times, drive, centre, thresholds, alpha, half, creep, pit_times) * 1e6
        )
        design = np.hstack([design, np.ones((len(pit_times), 1))])
        lower = np.r_[np.full(thresholds.size, 0.0), -np.inf]
        upper = np.r_[np.full(thresholds.size, np.inf), np.inf]
        lower[0] = 1e-6  # w_0 > 0: the model must stay invertible
        result = optimize.lsq_linear(design, target, bounds=(lower, upper), method="bvls")
        return result, design

    search = optimize.minimize_scalar(
        lambda a: float(np.sum(solve(a)[0].fun ** 2)),
        bounds=(-alpha_bound, alpha_bound),
        method="bounded",
        options={"xatol": 1e-5},
    )
    alpha = float(search.x)
    result, design = solve(alpha)
    weights, offset = result.x[:-1], result.x[-1]
    model = PrandtlIshlinskii(thresholds, weights, asymmetric_polynomial(alpha, half))
    fraction, gain = loop_measures(model, half)
    return {
        "thresholds": thresholds.tolist(),
        "weights": weights.tolist(),
        "polynomial": list(asymmetric_polynomial(alpha, half)),
        "asymmetry": alpha,
        "loop_fraction": fraction,
        "gain": gain,
        "offset": float(offset) * 1e-6,
        "predicted": (design @ result.x * 1e-6).tolist(),
        "rms_residual": float(np.sqrt(np.mean(result.fun**2))) * 1e-6,
    }


def measure_hysteresis(
    instrument,
    axis: int,
    *,
    creep: tuple | None = None,
    cycle_fraction: float = 0.9,
    steps_per_sweep: int = 128,
    pit_every: int = 4,
    operators: int = 12,
    lane_offset: float = -8e-6,
    branch_gap: float = 3e-6,
    speed: float = 20e-6,
    settle: float = 300.0,
    pixel: float = 30e-9,
    rescans=("up", "down"),
    force: float | None = None,
    ignore=None,
) -> Experiment:
    """PI hysteresis of one axis (0 = x, 1 = y) driven open loop (book 7.2.2, Fig. 7.6a).

    Feed-forward off; from the range centre the drive rises to the upper bound of the cycle
    (cycle_fraction of the half range), falls to the lower bound, rises again, in steps of
    2 * bound / steps_per_sweep, with a pit every `pit_every` steps on the last two sweeps
    (the descending sweep on one lane, the ascending one `branch_gap` (raw drive) beside it,
    so the two rows of pits never mix; `ignore`: image positions of pits already on the
    sample, e.g. the other axis' cycle, which crosses this one's lane). Feed-forward back
    on, the pits are rescanned with the slow axis
    along the cycle: one monotone pass over the whole row, so the image has no fast-axis loop
    along it and its residual distortion is that of one branch of the compensated scanner
    (a smooth bulge of about model error x loop width / 2); `rescans` ("up", "down") images
    the row on the ascending and on the descending compensated branch and averages the pit
    positions, which cancels the even part of that bulge and the drift. The fit
    (`fit_hysteresis`) uses thresholds r_k = k A / (2 operators) (A: cycle amplitude; the
    first rise of A wipes out the memory of every such operator, so the unknown state before
    the cycle does not matter) and the measured creep (time constants, fractions) when given.
    Derived loop_fraction and asymmetry are defined as in PrandtlIshlinskii.from_fraction."""
    limits = instrument.limits
    if axis not in (0, 1):
        raise ValueError(f"axis={axis}: must be 0 (x) or 1 (y)")
    if not (math.isfinite(cycle_fraction) and 0.2 <= cycle_fraction <= 0.9):
        raise ValueError(
            f"cycle_fraction={cycle_fraction}: must be within [0.2, 0.9] of the half range (the rescan "
            "needs the outer 10 % clear, see below)"
        )
    steps_per_sweep = _count("steps_per_sweep", steps_per_sweep, 8, 4096)
    pit_every = _count("pit_every", pit_every, 1, steps_per_sweep // 4)
    operators = _count("operators", operators, 2, 64)
    speed = _positive("speed", speed, limits.max_speed, "m/s")
    branch_gap = _positive("branch_gap", branch_gap, 10e-6, "m")
    if not set(rescans) <= {"up", "down"} or not rescans:
        raise ValueError(f"rescans={rescans!r}: need 'up' and/or 'down'")
    force = _force(instrument, force)
    centre = _centre(instrument)
    other = 1 - axis
    span = [limits.range_x, limits.range_y][axis]
    half = span / 2
    amplitude = cycle_fraction * half
    lane = centre[other] + lane_offset
    lo, hi = centre.copy(), centre.copy()
    lo[axis], hi[axis] = centre[axis] - amplitude, centre[axis] + amplitude
    lo[other], hi[other] = lane - 3e-6, lane + branch_gap + 3e-6
    _check_box(f"hysteresis cycle ({'xy'[axis]})", instrument, lo, hi)

    def point(a, b):
        p = np.empty(2)
        p[axis], p[other] = a, b
        return float(p[0]), float(p[1])

    instrument.move_tip(*point(centre[axis], lane), 0.5 * limits.max_speed)
    _set_feed_forward(instrument, False)
    try:
        # Open loop a raw drive is up to half a loop width (several um) from where the
        # compensated command puts the tip: keep the other axis' drive where the switch left it
        # (the tip stays on the lane) and move only the cycled axis, to the raw centre.
        lane_drive = float(instrument.commanded_position()[other])
        instrument.move_tip(*point(centre[axis], lane_drive), speed)
        wait(instrument, settle)
        timeline = _Timeline(instrument)
        step = 2 * amplitude / steps_per_sweep
        for k in range(1, steps_per_sweep // 2 + 1):
            timeline.move(*point(centre[axis] + k * step, lane_drive), speed)
        pits = []  # (branch, drive, moment)
        top, bottom = centre[axis] + amplitude, centre[axis] - amplitude
        for branch, start, sign, b in (
            ("descending", top, -1.0, lane_drive),
            ("ascending", bottom, 1.0, lane_drive + branch_gap),
        ):
            if branch == "ascending":
                timeline.move(
                    *point(bottom, b), speed
                )  # to the second lane, along the other axis only
            for k in range(steps_per_sweep + 1):
                drive = start + sign * k * step
                if k:
                    timeline.move(*point(drive, b), speed)
                if k % pit_every == 0:
                    pits.append((branch, drive, timeline.punch(force)))
    finally:
        _set_feed_forward(instrument, True)
    # The rescan covers where the pits can land: an asymmetric loop lifts or lowers the row's
    # ends by up to ~asymmetry x half range. It must stay clear of the range ends: the loop's
    # tips lie inside the range, so a compensated command there needs a drive past the range,
    # which the amplifier clamps; the controller's inverse then runs ahead of the scanner and
    # misplaces the pits over the following tens of um of the pass (with cycle_fraction 0.95
    # and a fixed 1.5 um margin this biased the fitted asymmetry by -4 % on a noise-free
    # scanner).
    margin = 0.05 * half
    lo[other], hi[other] = lane - 2e-6, lane + branch_gap + 2e-6
    box_lo, box_hi = lo.copy(), hi.copy()
    box_lo[axis] -= margin
    box_hi[axis] += margin
    branches = np.array([p[0] for p in pits])
    drives = np.array([p[1] for p in pits])
    moments = np.array([p[2] for p in pits])
    measured = np.full((len(rescans), len(pits)), np.nan)
    all_detected = []
    for row, direction in enumerate(rescans):
        scan = rescan(
            instrument, box_lo, box_hi, pixel, slow_axis=axis, slow_up=(direction == "up")
        )
        detected = find_pits(scan)
        if len(detected) < 8:
            raise RuntimeError(
                f"hysteresis ({'xy'[axis]}): only {len(detected)} pits found in the {direction} rescan"
            )
        if ignore is not None and len(ignore):
            # another image put them there: up to ~1 um off along this rescan's slow axis (the
            # compensation residual of a full-range pass), well within 0.3 um across it
            known = np.asarray(ignore, float).reshape(-1, 2)
            detected = _without_known(detected, known, axis)
        all_detected.append([[p.x, p.y] for p in detected])
        along = np.array([[p.x, p.y][axis] for p in detected])
        across = np.array([[p.x, p.y][other] for p in detected])
        # The two rows are about parallel (the coupling tilts both alike) but wander by the
        # moves' random error (~0.1 um over a cycle); their middle line, fitted robustly,
        # splits them, and pits far off both rows (another experiment's) are left out.
        keep = np.ones(len(detected), dtype=bool)
        for _ in range(5):
            line = np.polyfit(along[keep], across[keep], 1)
            offset = across - np.polyval(line, along)
            typical = np.median(np.abs(offset[keep]))
            keep = (np.abs(offset) < 2.0 * typical) & (np.abs(offset) > 0.25 * typical)
        for branch, sign in (("descending", -1.0), ("ascending", 1.0)):
            in_row = np.flatnonzero(keep & (np.sign(offset) == sign))
            wanted = np.flatnonzero(branches == branch)
            index = match_monotone(
                drives[wanted],
                along[in_row],
                pit_every * step,
                end_tolerance=0.3 * pit_every * step,
            )
            for i, j in zip(wanted, index):
                if j >= 0:
                    measured[row, i] = along[in_row[j]]
    found = np.all(np.isfinite(measured), axis=0)
    if found.sum() < 2 * operators:
        raise RuntimeError(
            f"hysteresis ({'xy'[axis]}): only {int(found.sum())} of {len(pits)} pits found in every "
            f"rescan; need {2 * operators}"
        )
    positions = measured[:, found].mean(axis=0)
    times, drive = timeline.sampled(axis, MODEL_DT)
    thresholds = np.arange(operators) * amplitude / (2 * operators)
    fit = fit_hysteresis(
        times, drive, centre[axis], half, moments[found], positions, thresholds, creep
    )
    parameters = {
        key: fit[key]
        for key in (
            "thresholds",
            "weights",
            "polynomial",
            "asymmetry",
            "loop_fraction",
            "gain",
            "offset",
            "rms_residual",
        )
    }
    data = {
        "branch": branches[found].tolist(),
        "drive": drives[found].tolist(),
        "time": moments[found].tolist(),
        "position": positions.tolist(),
        "position_per_rescan": measured[:, found].tolist(),
        "predicted": fit["predicted"],
        "pits_punched": len(pits),
        "pits_found": int(found.sum()),
        "all_detected": all_detected[0],
        # the drive as issued (piecewise linear between these knots), to refit or plot
        "drive_knots": {
            "time": list(timeline.times),
            "drive": [c[axis] for c in timeline.commands],
        },
        "centre": float(centre[axis]),
        "half_range": half,
    }
    return Experiment(parameters, data)


def _without_known(
    detected: list[DetectedPit], known: np.ndarray, slow_axis: int
) -> list[DetectedPit]:
    """`detected` less the pits that are `known` from another image. That image placed them up
    to ~1 um differently along this one's slow axis (the compensation residual of a
    full-range pass differs between the two), the same to ~0.3 um across it: the shift is
    the median over the candidate pairs, and each known pit removes at most the one detection
    nearest to where the shift puts it (a pit of this experiment close by stays)."""
    if not detected or not len(known):
        return detected
    fast = 1 - slow_axis
    points = np.array([[p.x, p.y] for p in detected])
    delta = points[None, :, :] - known[:, None, :]
    candidate = (np.abs(delta[..., slow_axis]) < 1.0e-6) & (np.abs(delta[..., fast]) < 0.3e-6)
    if not candidate.any():
        return detected
    shift = np.zeros(2)
    shift[slow_axis] = np.median(delta[..., slow_axis][candidate])
    distance = np.linalg.norm(points[None, :, :] - (known + shift)[:, None, :], axis=2)
    drop = {int(np.argmin(row)) for row in distance if row.min() < 0.3e-6}
    return [p for j, p in enumerate(detected) if j not in drop]


def refit_hysteresis(
    experiment: Experiment, creep: tuple | None = None, operators: int | None = None
) -> dict:
    """`fit_hysteresis` again on a measure_hysteresis experiment's data (another creep model,
    another number of operators)."""
    data = experiment.data
    knots = data["drive_knots"]
    times = np.arange(knots["time"][0], knots["time"][-1] + MODEL_DT, MODEL_DT)
    drive = np.interp(times, knots["time"], knots["drive"])
    thresholds = np.asarray(experiment.parameters["thresholds"])
    if operators is not None:
        thresholds = np.arange(operators) * (thresholds[1] * thresholds.size) / operators
    return fit_hysteresis(
        times,
        drive,
        data["centre"],
        data["half_range"],
        data["time"],
        data["position"],
        thresholds,
        creep,
    )


def hysteresis_fit_of(experiment: Experiment) -> HysteresisFit:
    p = experiment.parameters
    return HysteresisFit(
        thresholds=list(p["thresholds"]),
        weights=list(p["weights"]),
        polynomial=list(p["polynomial"]),
        loop_fraction=float(p["loop_fraction"]),
        asymmetry=float(p["asymmetry"]),
    )


# -- scanner matrix ----------------------------------------------------------------------------------


def measure_scanner_matrix(
    instrument,
    *,
    site=(-20e-6, 20e-6),
    grid: int = 5,
    spacing: float = 1e-6,
    pixel: float = 10e-9,
    force: float | None = None,
) -> Experiment:
    """Imaged displacement per commanded displacement in normal (compensated) operation: a
    grid x grid pattern of pits `spacing` apart, punched row by row (serpentine, moves as
    short as the localizer's), rescanned; the affine fit image = M command + b gives M.

    What M can show: a rescan uses the same scanner, so a coupling or rotation common to all
    motion (the tube's x/y coupling, its rotation against the sample) is in the image as well
    and cancels; M measures the motion against the image frame, the frame the localizer's maps
    are in (gain differences between moves and raster lines, e.g. the compensation residual
    of short moves). The absolute coupling and rotation need an external reference (a
    calibration grating of known orientation)."""
    limits = instrument.limits
    grid = _count("grid", grid, 2, 20)
    spacing = _positive("spacing", spacing, 10e-6, "m")
    force = _force(instrument, force)
    origin = _centre(instrument) + np.asarray(site, float)
    commands = np.array(
        [
            origin + spacing * np.array([i if j % 2 == 0 else grid - 1 - i, j])
            for j in range(grid)
            for i in range(grid)
        ]
    )
    _check_box(
        "scanner-matrix grid",
        instrument,
        commands.min(axis=0) - 0.5e-6,
        commands.max(axis=0) + 5e-6,
    )
    # Come from beyond the far corner, so every move of the pattern is a short move after a
    # reversal, as in manipulation (the compensated gain of a short move after a reversal
    # differs from that of a long monotone run by the model error of the feed-forward).
    beyond = commands.max(axis=0) + 4e-6
    instrument.move_tip(float(beyond[0]), float(beyond[1]), 0.5 * limits.max_speed)
    for x, y in commands:
        _punch_at(instrument, float(x), float(y), 0.1 * limits.max_speed, force)
    scan = rescan(
        instrument,
        commands.min(axis=0) - 0.5e-6,
        commands.max(axis=0) + 0.5e-6,
        pixel,
        slow_axis=1,
    )
    detected = find_pits(scan)
    found = np.array([[p.x, p.y] for p in detected]).reshape(-1, 2)
    index = match_points(commands, found, 0.3 * spacing)
    ok = index >= 0
    if ok.sum() < 4:
        raise RuntimeError(f"scanner matrix: only {int(ok.sum())} of {len(commands)} pits found")
    design = np.hstack([commands[ok] - origin, np.ones((int(ok.sum()), 1))])
    solution, *_ = np.linalg.lstsq(design, found[index[ok]] - origin, rcond=None)
    matrix = solution[:2].T
    residual = found[index[ok]] - origin - design @ solution
    return Experiment(
        {"scanner_matrix": matrix.tolist(), "rms_residual": float(np.sqrt(np.mean(residual**2)))},
        {"commanded": commands[ok].tolist(), "imaged": found[index[ok]].tolist()},
    )


# -- motion noise (Fig. 7.6e, Fig. 7.20b) -----------------------------------------------------------------


def fit_variance_line(distances, variances, counts) -> tuple[float, float]:
    """sigma^2 = a d + b by weighted least squares: a sample variance from n values has a
    standard deviation of about sigma^2 sqrt(2 / (n - 1)), so the weights are (n - 1) / 2 / v^2,
    iterated with the fitted line in place of the noisy v."""
    d, v, n = (np.asarray(a, float) for a in (distances, variances, counts))
    expected = np.maximum(v, 1e-30)
    for _ in range(5):
        w = np.sqrt((n - 1) / 2) / expected
        (a, b), *_ = np.linalg.lstsq(
            np.stack([d, np.ones_like(d)], axis=1) * w[:, None], v * w, rcond=None
        )
        expected = np.maximum(a * d + b, 0.1 * np.maximum(v, 1e-30))
    return float(a), float(b)


def measure_motion_noise(
    instrument,
    *,
    distances=(0.25e-6, 0.5e-6, 1e-6, 2e-6, 4e-6),
    trials: int = 40,
    row_spacing: float = 200e-9,
    site=(-45e-6, -45e-6),
    speed: float = 10e-6,
    settle: float = 300.0,
    pixel: float = 15e-9,
    force: float | None = None,
) -> Experiment:
    """Motion error variance against distance (book Fig. 7.6e; Fig. 7.20b sigma^2 = a d + b).

    For each axis and each distance d: `trials` trials, each a pit A, one move of d along the
    axis, a pit B; trial k is row k of a lane (row_spacing apart across the axis), so every
    trial after the first has the same history (the same moves at the same speeds before it)
    and the deterministic part of B - A (gain, compensation residual, creep, drift over a
    trial) is the same in every trial: it is removed as the mean (and a linear trend over the
    trials, for anything slow). The spread left is the random error of that one move, along
    the axis (slope_x / slope_y) and across it (the cross slope), plus the pit-position noise
    (part of the intercept b). Rescan with the fast axis along the moves: A and B of a trial
    are on one line, measured by the same trace."""
    limits = instrument.limits
    distances = [float(_positive("distances[]", d, 20e-6, "m")) for d in distances]
    if len(distances) < 2:
        raise ValueError(f"distances={distances}: need at least two distances for a line")
    trials = _count("trials", trials, 5, 400)
    row_spacing = _positive("row_spacing", row_spacing, 5e-6, "m")
    speed = _positive("speed", speed, limits.max_speed, "m/s")
    force = _force(instrument, force)
    origin = _centre(instrument) + np.asarray(site, float)
    # Lanes side by side, 1 um apart: the x lanes (rows stacked along y) in a band along x,
    # the y lanes (columns stacked along x) in a band along y above them.
    extent = (trials - 1) * row_spacing
    lanes, cursor = [], 0.0
    for d in distances:
        lanes.append((0, d, origin + np.array([cursor, 0.0])))
        cursor += 1.3 * d + 1e-6
    cursor = extent + 1e-6
    for d in distances:
        lanes.append((1, d, origin + np.array([0.0, cursor])))
        cursor += 1.3 * d + 1e-6
    for axis, d, start in lanes:
        end = start.copy()
        end[axis] += d
        end[1 - axis] += extent
        _check_box(
            f"motion-noise lane ({'xy'[axis]}, d={d:.3g} m)",
            instrument,
            start - 0.5e-6,
            end + 0.5e-6,
        )
    data, samples = {"x": [], "y": []}, []
    for axis, d, start in lanes:
        other = 1 - axis
        first = start.copy()
        instrument.move_tip(float(first[0]), float(first[1]), 0.5 * limits.max_speed)
        wait(instrument, settle)
        for k in range(trials):
            a = start.copy()
            a[other] += k * row_spacing
            b = a.copy()
            b[axis] += d
            _punch_at(instrument, float(a[0]), float(a[1]), speed, force)
            _punch_at(instrument, float(b[0]), float(b[1]), speed, force)
        hi = start.copy()
        hi[axis] += d
        hi[other] += (trials - 1) * row_spacing
        # the compensated gain of a move depends on the scanner's history (up to ~10 % off here)
        reach = np.full(2, 0.4e-6)
        reach[axis] += 0.15 * d
        scan = rescan(instrument, start - reach, hi + reach, pixel, slow_axis=other)
        detected = find_pits(scan)
        along = np.array([[p.x, p.y][axis] for p in detected])
        across = np.array([[p.x, p.y][other] for p in detected])
        # rows: pits closer than a third of the row spacing across the axis belong together
        order = np.argsort(across)
        separations = []
        row_index = []
        group = [order[0]] if len(order) else []
        for i in list(order[1:]) + [None]:
            if i is not None and across[i] - across[group[-1]] < row_spacing / 3:
                group.append(i)
                continue
            if len(group) == 2:
                left, right = sorted(group, key=lambda j: along[j])
                if abs(along[right] - along[left] - d) < 0.3 * d + 100e-9:
                    separations.append((along[right] - along[left], across[right] - across[left]))
                    row_index.append(round((across[left] - across[order[0]]) / row_spacing))
            group = [i] if i is not None else []
        separations = np.array(separations).reshape(-1, 2)
        row_index = np.array(row_index)
        keep = row_index > 0  # the first trial has another history
        separations, row_index = separations[keep], row_index[keep]
        if len(separations) < 5:
            raise RuntimeError(
                f"motion noise ({'xy'[axis]}, d={d:.3g} m): only {len(separations)} trials measured"
            )
        residual = []
        for component in (0, 1):
            trend = np.polyfit(row_index, separations[:, component], 1)
            residual.append(separations[:, component] - np.polyval(trend, row_index))
        n = len(separations)
        var_along = float(np.sum(residual[0] ** 2) / (n - 2))
        var_across = float(np.sum(residual[1] ** 2) / (n - 2))
        samples.append((axis, d, n - 1, var_along, var_across))
        data["xy"[axis]].append(
            {
                "distance": d,
                "trials": n,
                "mean_separation": float(separations[:, 0].mean()),
                "variance_along": var_along,
                "variance_across": var_across,
            }
        )
    parameters = {}
    for axis in (0, 1):
        rows = [s for s in samples if s[0] == axis]
        a, b = fit_variance_line(
            [r[1] for r in rows], [r[3] for r in rows], [r[2] + 1 for r in rows]
        )
        parameters[f"slope_{'xy'[axis]}"], parameters[f"offset_{'xy'[axis]}"] = a, b
    cross_a, cross_b = fit_variance_line(
        [r[1] for r in samples], [r[4] for r in samples], [r[2] + 1 for r in samples]
    )
    parameters["cross_slope"], parameters["cross_offset"] = cross_a, cross_b
    # one slope from every component (along and across, both axes): the best estimate when
    # the noise is isotropic, as the simulator's is; compare the per-axis ones with it
    pooled_a, pooled_b = fit_variance_line(
        [r[1] for r in samples] * 2,
        [r[3] for r in samples] + [r[4] for r in samples],
        [r[2] + 1 for r in samples] * 2,
    )
    parameters["pooled_slope"], parameters["pooled_offset"] = pooled_a, pooled_b
    return Experiment(parameters, data)


# -- scan-line deflection (Fig. 7.12) ----------------------------------------------------------------


def measure_line_deflection(
    instrument,
    *,
    lines: int = 20,
    length: float = 1e-6,
    line_spacing: float = 0.4e-6,
    site=(20e-6, -25e-6),
    speed: float = 1e-6,
    pixel: float = 10e-9,
    force: float | None = None,
) -> Experiment:
    """Deflection of local scan lines (book Fig. 7.12): for each line, a pit at its start,
    the local scan, a pit where it ended; half the lines horizontal, half vertical. The angle
    between the pit-to-pit vector and the commanded direction (counter-clockwise positive)
    over all lines gives mean and sigma. As for the scanner matrix, a deflection common to
    lines and raster scans cancels: this is the deflection against the image (the map)."""
    limits = instrument.limits
    lines = _count("lines", lines, 2, 200)
    length = _positive("length", length, 20e-6, "m")
    force = _force(instrument, force)
    origin = _centre(instrument) + np.asarray(site, float)
    starts, ends = [], []
    for k in range(lines):
        if k % 2 == 0:  # horizontal lines, stacked along y
            s = origin + np.array([0.0, (k // 2) * line_spacing])
            e = s + np.array([length, 0.0])
        else:  # vertical lines, to the right of the horizontal block
            s = origin + np.array([length + 1e-6 + (k // 2) * line_spacing, 0.0])
            e = s + np.array([0.0, length])
        starts.append(s)
        ends.append(e)
    starts, ends = np.array(starts), np.array(ends)
    everything = np.vstack([starts, ends])
    _check_box(
        "line-deflection site",
        instrument,
        everything.min(axis=0) - 0.5e-6,
        everything.max(axis=0) + 0.5e-6,
    )
    samples = max(
        2, int(round(length / 10e-9))
    )  # 10 nm per sample: the line is not what is measured
    for s, e in zip(starts, ends):
        _punch_at(instrument, float(s[0]), float(s[1]), 0.1 * limits.max_speed, force)
        instrument.local_scan(
            LineRequest(float(s[0]), float(s[1]), float(e[0]), float(e[1]), samples, speed)
        )
        x, y = instrument.commanded_position()
        instrument.indent(x, y, force, 0.0)
    scan = rescan(
        instrument,
        everything.min(axis=0) - 0.4e-6,
        everything.max(axis=0) + 0.4e-6,
        pixel,
        slow_axis=1,
    )
    detected = np.array([[p.x, p.y] for p in find_pits(scan)]).reshape(-1, 2)
    index = match_points(everything, detected, 0.3 * line_spacing)
    n = len(starts)
    angles = []
    for k in range(n):
        i, j = index[k], index[n + k]
        if i < 0 or j < 0:
            continue
        measured = detected[j] - detected[i]
        commanded = ends[k] - starts[k]
        angle = math.atan2(
            commanded[0] * measured[1] - commanded[1] * measured[0], float(commanded @ measured)
        )
        angles.append(math.degrees(angle))
    if len(angles) < 2:
        raise RuntimeError(f"line deflection: only {len(angles)} of {n} lines measured")
    angles = np.array(angles)
    return Experiment(
        {"mean_deg": float(angles.mean()), "sigma_deg": float(angles.std(ddof=1))},
        {"angles_deg": angles.tolist(), "length": length},
    )


# -- drift, map error, scan-region error (eq. 5.32-5.36, Fig. 7.9-7.11) ---------------------------------


def _particle_area(instrument, area) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = np.asarray(area[:2], float), np.asarray(area[:2], float) + np.asarray(area[2:], float)
    _check_box("drift area", instrument, lo, hi)
    if not np.all(hi > lo):
        raise ValueError(f"area={area}: width and height must be > 0")
    return lo, hi


def measure_drift(
    instrument,
    *,
    area=(54.1e-6, 53.85e-6, 2.0e-6, 3.0e-6),
    pairs: int = 20,
    pixel: float = 15.625e-9,
    frame_time: float = 256.0,
    interval: float = 3600.0,
    search: float = 6e-6,
    settle: float = 300.0,
) -> Experiment:
    """Drift velocity statistics (book 5.3.3, 7.2.2, Fig. 7.9): `pairs` frame-up / frame-down
    image pairs of an area with at least two particles on different lines, a pair starting
    every `interval` s (the drift velocity wanders slowly; samples closer than its
    correlation time are not independent, so the mean and sigma of a few close pairs say
    little). Each pair gives one velocity (afm_core.imaging.frame_up_down.velocity_from_up_down,
    eq. 5.35-5.36), timed at the pair's middle; it averages the velocity over the stretches of
    the two frames where the particles are imaged (about a minute each, ~280 s before and
    after the middle with the defaults), not over the whole pair, and the moments are kept per pair
    (data["particle_times"]: [t_up, t_down] lists) so it can be compared with a known drift
    (afm_core.imaging.frame_up_down.sampled_velocity). Its scale is the frames' image scale (module
    doc: the compensated scanner's small-move gain).

    Before each pair a quick `search`-wide image finds the particles again (the sample
    drifts micrometres over hours), the frames are centred on them and the tip rests
    `settle` s at the frame's start: creep after a move of a few micrometres (2 % of it,
    the slowest part with a 50 s time constant) would otherwise look like a drift of tenths
    of nm/s. For the same reason the frame reaches well beyond the particles along the slow
    axis (area's height): the slow axis' own creep lag settles while the margin is scanned.
    The tip rests `settle` s before the frame down too (see there).
    The frame time is a compromise: slow frames make the particles' time separation
    T'_u + T'_d long, so the per-pair error (centroid noise / T') stays well below the
    spread being measured, but a pair averages the velocity over its length, which lowers
    the measured spread by about T_pair / (6 x correlation time) (5 % for 512 s pairs and
    1800 s). The frames are kept for the map error and scan-region error (`map_errors`)."""
    limits = instrument.limits
    lo, hi = _particle_area(instrument, area)
    pairs = _count("pairs", pairs, 2, 100000)
    pixel = _positive("pixel", pixel, 1e-6, "m")
    frame_time = _positive("frame_time", frame_time, 86400.0, "s")
    interval = _positive("interval", interval, None, "s")
    size = hi - lo
    pixels = np.maximum(16, np.round(size / pixel)).astype(int)
    if pixels.max() > limits.max_pixels:
        raise ValueError(
            f"pixel={pixel:.3g} m: the frame needs {pixels.max()} pixels, "
            f"above max_pixels {limits.max_pixels}"
        )
    line_rate = pixels[1] / frame_time
    if 2.0 * size[0] * line_rate > limits.max_speed or line_rate > limits.max_line_rate:
        raise ValueError(
            f"frame_time={frame_time} s: {pixels[1]} lines of {size[0]:.3g} m would exceed the slew "
            f"limit {limits.max_speed} m/s or max_line_rate {limits.max_line_rate} Hz"
        )
    centre = 0.5 * (lo + hi)
    velocities, moments, frames, particle_times = [], [], [], []
    for k in range(pairs):
        start = float(instrument.time)
        centre = _find_particle_cluster(instrument, centre, search, size)
        lo = np.clip(centre - size / 2, 0.0, [limits.range_x - size[0], limits.range_y - size[1]])
        # rest at the middle of the first line: the fast axis then oscillates about where its
        # creep has settled (resting at the line's start, the slow creep would follow the line
        # mean for the first minutes of the frame and look like drift along x)
        instrument.move_tip(
            float(lo[0] + 0.5 * size[0]),
            float(lo[1] + 0.5 * size[1] / pixels[1]),
            0.1 * limits.max_speed,
        )
        wait(instrument, settle)
        request = dict(
            origin_x=float(lo[0]),
            origin_y=float(lo[1]),
            size_x=float(size[0]),
            size_y=float(size[1]),
            pixels_x=int(pixels[0]),
            pixels_y=int(pixels[1]),
            line_rate=float(line_rate),
        )
        up = instrument.raster_scan(ScanRequest(slow_scan_up=True, **request))
        # rest again before the frame down: it then starts from a settled creep state as the
        # frame up did, and the slow axis' creep lag builds up alike in both (mirror images),
        # so its effect on the particles' separations is the same in both frames and cancels
        # (reversing at once, the lag would swing from -L to +L during the frame down)
        instrument.move_tip(
            float(lo[0] + 0.5 * size[0]),
            float(lo[1] + size[1] - 0.5 * size[1] / pixels[1]),
            0.1 * limits.max_speed,
        )
        wait(instrument, settle)
        down = instrument.raster_scan(ScanRequest(slow_scan_up=False, **request))
        observations = up_down_observations(up, down)
        velocities.append(up_down_velocity(observations))
        particle_times.append([observations.t_up.tolist(), observations.t_down.tolist()])
        moments.append(0.5 * (up.start_time + float(instrument.time)))
        frames.extend([up, down])
        if k < pairs - 1:
            wait(instrument, start + interval - float(instrument.time))
    v = np.array(velocities)
    parameters = {
        "mean_velocity": v.mean(axis=0).tolist(),
        "sigma_velocity": v.std(axis=0, ddof=1).tolist(),
        "pairs": pairs,
    }
    return Experiment(
        parameters,
        {
            "time": moments,
            "velocity": v.tolist(),
            "particle_times": particle_times,
            "frames": frames,
        },
    )


def _find_particle_cluster(instrument, centre, search: float, frame) -> np.ndarray:
    """Centre of the particles in a quick search image around `centre` (the middle of their
    bounding box); the search area doubles (three times at most) while none is found, and
    `centre` itself is returned when still none is."""
    limits = instrument.limits
    for attempt in range(4):
        reach = search * 2**attempt
        size = np.array([min(reach, limits.range_x), min(reach, limits.range_y)])
        lo = np.clip(
            np.asarray(centre) - size / 2,
            0.0,
            [limits.range_x - size[0], limits.range_y - size[1]],
        )
        rate = min(MAX_LINE_RATE, limits.max_line_rate, 0.95 * limits.max_speed / (2.0 * size[0]))
        pixels = int(min(limits.max_pixels, 128 * 2**attempt))
        scan = instrument.raster_scan(
            ScanRequest(
                float(lo[0]),
                float(lo[1]),
                float(size[0]),
                float(size[1]),
                pixels,
                pixels,
                line_rate=rate,
            )
        )
        marks = extract_landmarks(
            np.asarray(scan.height, float),
            scan.pixel_size_x,
            scan.pixel_size_y,
            scan.origin_x,
            scan.origin_y,
            min_height=30e-9,
        )
        if marks:
            break
    if not marks:
        return np.asarray(centre, float)
    points = np.array([[m.x, m.y] for m in marks])
    # the cluster: the particles within a frame's reach of the one nearest the old centre
    first = points[np.argmin(np.linalg.norm(points - centre, axis=1))]
    near = points[np.all(np.abs(points - first) < np.asarray(frame) * 0.8, axis=1)]
    return 0.5 * (near.min(axis=0) + near.max(axis=0))


def map_errors(
    frames: list[RasterScanData], lines: int = 11, min_height: float = 30e-9
) -> Experiment:
    """Map error (book Fig. 7.10) and scan-region error (Fig. 7.11) from repeated images of
    the same particles.

    Map error: in each image the particles' centres (afm_core.imaging.landmarks, centre of
    gravity over height thresholds); the image is registered on the first particle P1 (its
    centre is the control point) and the spread of P2's position relative to it over the
    images is the map sigma, per axis. Scan-region error: in each image, `lines` rows (and
    columns) through P2 within +-0.5 of its apparent radius stand in for real-time local scan
    lines; on each the particle centre is the midpoint of the two half-height crossings
    (eq. 5.10); the spread of those against the image's own centre of P2, pooled over rows
    and columns, is the scan-region sigma."""
    if len(frames) < 3:
        raise ValueError(f"frames: {len(frames)} images; need at least 3")
    relative, region = [], []
    reference = None
    for scan in frames:
        height = np.asarray(scan.height, float)
        marks = extract_landmarks(
            height,
            scan.pixel_size_x,
            scan.pixel_size_y,
            scan.origin_x,
            scan.origin_y,
            min_height=min_height,
        )
        if len(marks) < 2:
            continue
        # relative to the frame's centre: the frames follow the drifting particles, so that is
        # where the same particle is found again
        frame_centre = [
            scan.origin_x + 0.5 * height.shape[1] * scan.pixel_size_x,
            scan.origin_y + 0.5 * height.shape[0] * scan.pixel_size_y,
        ]
        points = np.array([[m.x, m.y] for m in marks]) - frame_centre
        if reference is None:
            reference = points[:2].copy()
        nearest = [int(np.argmin(np.linalg.norm(points - r, axis=1))) for r in reference]
        if nearest[0] == nearest[1]:
            continue
        p1, p2 = marks[nearest[0]], marks[nearest[1]]
        relative.append([p2.x - p1.x, p2.y - p1.y])
        level = np.median(height)
        top = level + 0.5 * p2.height
        row0 = (p2.y - scan.origin_y) / scan.pixel_size_y - 0.5
        col0 = (p2.x - scan.origin_x) / scan.pixel_size_x - 0.5
        reach_rows = 0.5 * p2.half_width / scan.pixel_size_y
        reach_cols = 0.5 * p2.half_width / scan.pixel_size_x
        for offset in np.linspace(-1.0, 1.0, lines):
            row = int(round(row0 + offset * reach_rows))
            col = int(round(col0 + offset * reach_cols))
            if 0 <= row < height.shape[0]:
                mid = _crossing_midpoint(height[row], top, col0)
                if mid is not None:
                    region.append((mid - col0) * scan.pixel_size_x)
            if 0 <= col < height.shape[1]:
                mid = _crossing_midpoint(height[:, col], top, row0)
                if mid is not None:
                    region.append((mid - row0) * scan.pixel_size_y)
    relative = np.array(relative)
    if len(relative) < 3:
        raise ValueError(f"frames: two particles found in only {len(relative)} images; need 3")
    region = np.array(region)
    return Experiment(
        {
            "map_sigma": relative.std(axis=0, ddof=1).tolist(),
            "scan_region_sigma": float(region.std(ddof=1)) if len(region) > 1 else float("nan"),
        },
        {"relative_position": relative.tolist(), "region_offsets": region.tolist()},
    )


def _crossing_midpoint(profile: np.ndarray, level: float, near: float) -> float | None:
    """Midpoint (fractional index) of the two crossings of `level` around index `near` (eq. 5.10)."""
    above = profile > level
    centre = int(round(near))
    if not (0 <= centre < profile.size) or not above[centre]:
        return None
    left = centre
    while left > 0 and above[left - 1]:
        left -= 1
    right = centre
    while right < profile.size - 1 and above[right + 1]:
        right += 1
    if left == 0 or right == profile.size - 1:
        return None
    # linear interpolation of each crossing between the pixel below and the one above the level
    x_left = left - 1 + (level - profile[left - 1]) / (profile[left] - profile[left - 1])
    x_right = right + (profile[right] - level) / (profile[right] - profile[right + 1])
    return 0.5 * (x_left + x_right)


# -- everything ---------------------------------------------------------------------------------------


def run_calibration(
    instrument,
    *,
    creep: dict | None = None,
    hysteresis: dict | None = None,
    scanner_matrix: dict | None = None,
    motion_noise: dict | None = None,
    line_deflection: dict | None = None,
    drift: dict | None = None,
    source: str | None = None,
) -> tuple[Calibration, dict]:
    """All experiments, in an order where each can use what the previous measured (creep
    before hysteresis: the hysteresis fit includes it; drift, map and scan-region errors
    first, before there are pits). Each keyword is that experiment's options
    (see its function). Returns the Calibration and a report {experiment: {"parameters",
    "data"}} (the drift frames are left out of the report; `map_errors` has used them)."""
    report: dict = {}
    started = wallclock.perf_counter()
    clock0 = float(instrument.time)
    # Drift first: it needs no pits, and on the simulator every image gets slower with every
    # pit on the sample (hundreds by the end), which matters for ~100 hours of frame pairs.
    drift_result = measure_drift(instrument, **(drift or {}))
    frames = drift_result.data.pop("frames")
    report["drift"] = drift_result
    report["map_errors"] = map_errors(frames)
    del frames
    result = measure_creep(instrument, **(creep or {}))
    report["creep"] = result
    creep_x = (result.parameters["time_constants"], result.parameters["fractions_x"])
    creep_y = (result.parameters["time_constants"], result.parameters["fractions_y"])
    options = dict(hysteresis or {})
    report["hysteresis_x"] = measure_hysteresis(instrument, 0, creep=creep_x, **options)
    report["hysteresis_y"] = measure_hysteresis(
        instrument, 1, creep=creep_y, ignore=report["hysteresis_x"].data["all_detected"], **options
    )
    report["scanner_matrix"] = measure_scanner_matrix(instrument, **(scanner_matrix or {}))
    report["motion_noise"] = measure_motion_noise(instrument, **(motion_noise or {}))
    report["line_deflection"] = measure_line_deflection(instrument, **(line_deflection or {}))
    noise = report["motion_noise"].parameters
    errors = report["map_errors"].parameters
    stamp = datetime.now(timezone.utc).isoformat(timespec="seconds")
    calibration = Calibration(
        source=source or f"afm_core.localization.calibrate.run_calibration, {stamp}",
        scanner_matrix=report["scanner_matrix"].parameters["scanner_matrix"],
        hysteresis_x=hysteresis_fit_of(report["hysteresis_x"]),
        hysteresis_y=hysteresis_fit_of(report["hysteresis_y"]),
        creep_time_constants=list(result.parameters["time_constants"]),
        creep_fractions_x=list(result.parameters["fractions_x"]),
        creep_fractions_y=list(result.parameters["fractions_y"]),
        motion_noise_slope_x=max(0.0, noise["slope_x"]),
        motion_noise_slope_y=max(0.0, noise["slope_y"]),
        motion_noise_cross_slope=max(0.0, noise["cross_slope"]),
        motion_noise_offset=max(0.0, 0.5 * (noise["offset_x"] + noise["offset_y"])),
        drift_mean_velocity=list(drift_result.parameters["mean_velocity"]),
        drift_sigma_velocity=list(drift_result.parameters["sigma_velocity"]),
        map_sigma=list(errors["map_sigma"]),
        scan_region_sigma=float(errors["scan_region_sigma"]),
        line_deflection_mean_deg=float(report["line_deflection"].parameters["mean_deg"]),
        line_deflection_sigma_deg=float(report["line_deflection"].parameters["sigma_deg"]),
    )
    summary = {
        name: {"parameters": value.parameters, "data": value.data}
        for name, value in report.items()
    }
    summary["instrument_seconds"] = float(instrument.time) - clock0
    summary["wall_seconds"] = wallclock.perf_counter() - started
    return calibration, summary


# -- against the simulator's configuration (tests, bench) -------------------------------------------------


def creep_step_response(time_constants, fractions, t) -> np.ndarray:
    """Creep part of the unit step response, sum_i c_i (1 - e^{-t/tau_i}) (eq. 5.29-5.31)."""
    t = np.asarray(t, float)[:, None]
    return (-np.expm1(-t / np.asarray(time_constants, float)[None, :])) @ np.asarray(
        fractions, float
    )


def branch_error(fit: HysteresisFit, true_model: PrandtlIshlinskii, half: float) -> float:
    """Largest distance between the fitted and the true major-loop branches (both, full span),
    after the best common shift (the fit's offset is where the rescan put the origin), as a
    fraction of the true loop width: how far the fitted model would misplace the tip, in
    units of what hysteresis does at most."""
    fitted = PrandtlIshlinskii(fit.thresholds, fit.weights, fit.polynomial)
    _, fa, fd = major_loop(fitted, half)
    _, ta, td = major_loop(true_model, half)
    difference = np.concatenate([fa - ta, fd - td])
    shift = 0.5 * (difference.max() + difference.min())
    return float(np.max(np.abs(difference - shift)) / np.max(td - ta))


def compare_with_simulator(calibration: Calibration, report: dict, config) -> list[dict]:
    """Recovered against configured values of a simulated instrument (afm_core.sim.config
    SimConfig), one row per quantity: name, recovered, true, relative error (None where the
    true value is 0 or there is none to compare with), and what is compared."""
    scanner, drift = config.scanner, config.drift
    rows = []

    def row(name, recovered, true, note=""):
        relative = None if true in (None, 0) else (recovered - true) / abs(true)
        rows.append(
            {
                "name": name,
                "recovered": recovered,
                "true": true,
                "relative_error": relative,
                "note": note,
            }
        )

    for axis, fit, span in (
        ("x", calibration.hysteresis_x, scanner.range_x),
        ("y", calibration.hysteresis_y, scanner.range_y),
    ):
        true_model = PrandtlIshlinskii.from_fraction(
            span,
            scanner.hysteresis_fraction,
            int(scanner.hysteresis_operators),
            scanner.hysteresis_asymmetry,
        )
        row(
            f"hysteresis_{axis}.loop_fraction",
            fit.loop_fraction,
            scanner.hysteresis_fraction,
            "loop width / tip-to-tip span of the full-range major loop",
        )
        row(
            f"hysteresis_{axis}.asymmetry",
            fit.asymmetry,
            scanner.hysteresis_asymmetry,
            "alpha of from_fraction",
        )
        row(
            f"hysteresis_{axis}.branch_error",
            branch_error(fit, true_model, span / 2),
            None,
            "max branch misfit / true loop width (relative_error = the value)",
        )
        rows[-1]["relative_error"] = rows[-1]["recovered"]
        gain = report[f"hysteresis_{axis}"]["parameters"]["gain"]
        row(f"hysteresis_{axis}.gain", gain, 1.0, "tip-to-tip output / input span")
    taus, true_taus = calibration.creep_time_constants, list(scanner.creep_time_constants)
    for i, (tau, true_tau) in enumerate(zip(taus, sorted(true_taus))):
        row(f"creep.time_constant[{i}]", tau, true_tau, "s")
    order = np.argsort(true_taus)
    true_fractions = np.asarray(scanner.creep_fractions)[order]
    t = np.linspace(0.0, 25.0, 501)
    true_curve = creep_step_response(np.sort(true_taus), true_fractions, t)
    for axis, fractions in (
        ("x", calibration.creep_fractions_x),
        ("y", calibration.creep_fractions_y),
    ):
        for i, (c, true_c) in enumerate(zip(fractions, true_fractions)):
            row(f"creep.fractions_{axis}[{i}]", c, float(true_c))
        curve = creep_step_response(taus, fractions, t)
        row(
            f"creep.step_response_{axis}",
            float(np.max(np.abs(curve - true_curve)) / true_curve[-1]),
            None,
            "max |fitted - true| creep over 0-25 s / true creep at 25 s (relative_error = the value)",
        )
        rows[-1]["relative_error"] = rows[-1]["recovered"]
    row("drift.mean_velocity_x", calibration.drift_mean_velocity[0], drift.mean_velocity_x, "m/s")
    row("drift.mean_velocity_y", calibration.drift_mean_velocity[1], drift.mean_velocity_y, "m/s")
    row(
        "drift.sigma_velocity_x",
        calibration.drift_sigma_velocity[0],
        drift.sigma_velocity_x,
        "m/s",
    )
    row(
        "drift.sigma_velocity_y",
        calibration.drift_sigma_velocity[1],
        drift.sigma_velocity_y,
        "m/s",
    )
    noise = report["motion_noise"]["parameters"]
    for name in ("pooled_slope", "slope_x", "slope_y", "cross_slope"):
        row(
            f"motion_noise.{name}",
            noise[name],
            scanner.positioning_noise_slope,
            "m^2/m (the simulator's noise is isotropic: every slope is the configured one)",
        )
    row(
        "motion_noise.offset",
        calibration.motion_noise_offset,
        scanner.positioning_noise_offset,
        "m^2 (includes the pit-position noise of two pits)",
    )
    matrix = np.asarray(calibration.scanner_matrix)
    row(
        "scanner_matrix - I (max abs)",
        float(np.max(np.abs(matrix - np.eye(2)))),
        None,
        "against the image frame: coupling and rotation cancel; configured coupling "
        f"{scanner.coupling_x_to_y}, rotation {scanner.deflection_deg} deg (absolute)",
    )
    row(
        "line_deflection_mean_deg",
        calibration.line_deflection_mean_deg,
        None,
        f"against the image frame; configured absolute rotation {scanner.deflection_deg} deg cancels",
    )
    row("line_deflection_sigma_deg", calibration.line_deflection_sigma_deg, None, "")
    row("map_sigma_x", calibration.map_sigma[0], None, "book Fig. 7.10: 5.0 nm")
    row("map_sigma_y", calibration.map_sigma[1], None, "book Fig. 7.10: 4.5 nm")
    row("scan_region_sigma", calibration.scan_region_sigma, None, "book Fig. 7.11: 4.7 nm")
    return rows
