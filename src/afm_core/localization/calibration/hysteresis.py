"""Hysteresis of each axis driven open loop (book 7.2.2, eq. 5.22-5.23, Fig. 7.6a): with the
feed-forward off, a full-range voltage cycle with a pit every few steps on the descending and
the ascending sweep; with it back on, the rows are rescanned. Prandtl-Ishlinskii weights for
fixed thresholds by non-negative least squares, the input asymmetry by a 1-D search; the
measured creep is part of the model. Which detected pit is which punch: hysteresis_rows.py;
the open-loop cycle itself: hysteresis_cycle.py.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import optimize

from afm_core import checks
from afm_core.localization.calibration.experiment import (
    Experiment,
    GeometryError,
    StepProgress,
    check_box,
    indent_force,
    probe_pit_width,
    range_centre,
    range_scale,
)
from afm_core.localization.calibration.hysteresis_cycle import drive_cycle, drive_record
from afm_core.localization.calibration.hysteresis_rows import (
    RowsNotMatched,
    imaged_rows,
    rescan_disagreements,
)
from afm_core.localization.calibration.model import HysteresisFit
from afm_core.pzt import Creep, PlayOperatorBank, PrandtlIshlinskii

MODEL_DT = 2e-3  # s, time step of the drive reconstruction in the hysteresis fit


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
    sigmas = _loop_sigmas(
        lambda a: solve(a)[1] @ result.x, alpha, weights, thresholds, half, design, result.fun
    )
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
        "loop_fraction_sigma": sigmas[0],
        "asymmetry_sigma": sigmas[1],
    }


def _loop_sigmas(predict, alpha, weights, thresholds, half, design, residual) -> tuple:
    """(loop fraction, asymmetry) standard errors of a fit_hysteresis solution, linearised:
    the covariance s^2 (J^T J)^-1 of (weights, offset, alpha) from the design columns and the
    numerical derivative of the prediction in alpha, s^2 the residual variance per degree of
    freedom, propagated to the loop fraction by its numerical gradient. The residuals along a
    cycle are not independent (each move's error persists), so this is a lower bound; a
    slipped or mis-modelled fit shows as a large residual and so as a large sigma."""
    h = 1e-4
    j_alpha = (predict(alpha + h) - predict(alpha - h)) / (2 * h)
    jacobian = np.hstack([design, j_alpha[:, None]])
    dof = max(1, len(residual) - jacobian.shape[1])
    covariance = float(np.sum(residual**2)) / dof * np.linalg.pinv(jacobian.T @ jacobian)

    def fraction_of(w, a):
        return loop_measures(
            PrandtlIshlinskii(thresholds, w, asymmetric_polynomial(a, half)), half
        )[0]

    base = fraction_of(weights, alpha)
    gradient = np.zeros(jacobian.shape[1])
    for k in range(len(weights)):
        step = max(1e-3 * abs(weights[k]), 1e-6)
        shifted = weights.copy()
        shifted[k] += step
        gradient[k] = (fraction_of(shifted, alpha) - base) / step
    gradient[-1] = (fraction_of(weights, alpha + h) - base) / h
    fraction_sigma = float(np.sqrt(max(0.0, gradient @ covariance @ gradient)))
    return fraction_sigma, float(np.sqrt(max(0.0, covariance[-1, -1])))


FIT_PARAMETERS = (
    "thresholds",
    "weights",
    "polynomial",
    "asymmetry",
    "loop_fraction",
    "gain",
    "offset",
    "rms_residual",
    "loop_fraction_sigma",
    "asymmetry_sigma",
)  # the parts of fit_hysteresis's result that are the experiment's parameters


# The cycle's share of the half range H. An input asymmetry a moves the top tip of a cycle of
# amplitude c H out to about (c + |a| c^2) H (from_fraction's p(xi) at xi = c); the rescan
# box follows the tips but stays in the range. At 0.9 the PI fit covers 90 % of the range
# (exact on an ideal scanner), but with |a| = 0.1 the top tip is ~1 um from the range's end
# and the rows may not be matched (issue 37: loop 0.25, asymmetry 0.1); the experiment is then
# repeated once at RETRY_CYCLE_FRACTION on a fresh lane, where |a| up to 0.1 (the issue's
# range) keeps the tips ~4 um inside (the loop fraction then extrapolates from 80 % of the
# range: -3 % on an ideal scanner).
CYCLE_FRACTION = 0.9
RETRY_CYCLE_FRACTION = 0.8
# The retry's lane, across from the first: past the first's rescan box (2 um beyond its two
# lanes, branch_gap apart) and its own, with 1 um between.
RETRY_LANE_SHIFT = -11e-6  # m on REFERENCE_RANGE (experiment.range_scale)


def measure_hysteresis(instrument, axis: int, **options) -> Experiment:
    """`measure_hysteresis_once` (see there), repeated once at RETRY_CYCLE_FRACTION on a fresh
    lane when the rows cannot be matched at the cycle asked for (the tips of a wide,
    strongly asymmetric loop outside the rescan); the repeat ignores the first attempt's
    pits, its data say it was a repeat ("retried": the first attempt's reason) and carry
    both attempts' detections (all_detected, for the other axis' `ignore`)."""
    cycle = options.get("cycle_fraction", CYCLE_FRACTION)
    try:
        return measure_hysteresis_once(instrument, axis, **options)
    except RowsNotMatched as exc:
        if cycle <= RETRY_CYCLE_FRACTION:
            raise
        first = exc
    known = [] if options.get("ignore") is None else list(options["ignore"])
    retry = dict(options, cycle_fraction=RETRY_CYCLE_FRACTION, ignore=known + first.detected)
    scale = range_scale(instrument)
    lane = options.get("lane_offset")
    lane = LANE_OFFSET * scale if lane is None else lane
    retry["lane_offset"] = lane + RETRY_LANE_SHIFT * scale
    experiment = measure_hysteresis_once(instrument, axis, **retry)
    experiment.data["retried"] = f"at cycle_fraction {cycle}: {first}"
    experiment.data["all_detected"] = list(experiment.data["all_detected"]) + first.detected
    return experiment


# m on REFERENCE_RANGE (times experiment.range_scale on another scanner): the cycle's lane from
# the range centre across the cycled axis, the gap between its two rows, and how far the box
# checked against the range and the rescan box reach across beyond them
LANE_OFFSET = -8e-6
BRANCH_GAP = 3e-6
CYCLE_REACH = 3e-6
RESCAN_REACH = 2e-6


def measure_hysteresis_once(
    instrument,
    axis: int,
    *,
    creep: tuple | None = None,
    cycle_fraction: float = CYCLE_FRACTION,
    steps_per_sweep: int = 128,
    pit_every: int = 4,
    operators: int = 12,
    lane_offset: float | None = None,
    branch_gap: float | None = None,
    speed: float = 20e-6,
    settle: float = 300.0,
    pixel: float | None = None,
    rescans=("down", "up"),
    force: float | None = None,
    ignore=None,
    progress=None,
) -> Experiment:
    """PI hysteresis of one axis (0 = x, 1 = y) driven open loop (book 7.2.2, Fig. 7.6a).

    Feed-forward off; from the range centre the drive rises to the upper bound of the cycle
    (cycle_fraction of the half range), falls to the lower bound, rises again, in steps of 2 *
    bound / steps_per_sweep, with a pit every `pit_every` steps on the last two sweeps (the
    descending sweep on one lane, the ascending one `branch_gap` (raw drive) beside it, so the
    two rows of pits never mix; `ignore`: image positions of pits already on the sample, e.g.
    the other axis' cycle, which crosses this one's lane). Feed-forward back on, the pits are
    rescanned with the slow axis along the cycle: one monotone pass over the whole row, so the
    image has no fast-axis loop along it and its residual distortion is that of one branch of
    the compensated scanner (a smooth bulge of about model error x loop width / 2); `rescans`
    ("down", "up") images the row on the descending and on the ascending compensated branch and
    averages the pit positions, which cancels the even part of that bulge and the drift. Down
    first: the cycle ends at its top, so each pass starts where the tip already is; an up pass
    first, after a full-range move down and a reversal, placed the pits up to 1.3 um low over
    its first ~40 um in a box of +-0.95 of the half range and up to 0.27 um in the box below
    (issue 37: the asymmetry read 8-12 % low on a loop of 0.18, a = 0.08, even with a perfect
    feed-forward and no creep; the mechanism is not separated; down first: within 1 %). The box
    follows the loop's tips (`_rescan_box`). The fit (`fit_hysteresis`) uses thresholds r_k = k
    A / (2 operators) (A: cycle amplitude; the first rise of A wipes out the memory of every
    such operator, so the unknown state before the cycle does not matter) and the measured
    creep (time constants, fractions) when given. Derived loop_fraction and asymmetry are
    defined as in PrandtlIshlinskii.from_fraction. Lengths by default: LANE_OFFSET etc. x
    range_scale; the pixel from a probe pit's width (`_pit_width_and_pixel`, data["pixel"])."""
    limits = instrument.limits
    scale = range_scale(instrument)
    lane_offset = LANE_OFFSET * scale if lane_offset is None else lane_offset
    branch_gap = BRANCH_GAP * scale if branch_gap is None else branch_gap
    steps_per_sweep, pit_every, operators, speed, branch_gap = _checked_options(
        limits, axis, cycle_fraction, steps_per_sweep, pit_every, operators, speed, branch_gap
    )
    if not set(rescans) <= {"up", "down"} or not rescans:
        raise ValueError(f"rescans={rescans!r}: need 'up' and/or 'down'")
    force = indent_force(instrument, force)
    centre = range_centre(instrument)
    half = [limits.range_x, limits.range_y][axis] / 2
    amplitude = cycle_fraction * half
    lane = centre[1 - axis] + lane_offset
    lo, hi = _box(axis, centre, amplitude, (lane, lane + branch_gap), CYCLE_REACH * scale)
    advice = (
        f"pass a smaller lane_offset (now {lane_offset:.3g} m) or branch_gap ({branch_gap:.3g} m)"
    )
    check_box(f"hysteresis cycle ({'xy'[axis]})", instrument, lo, hi, advice)
    width, pixel = _pit_width_and_pixel(instrument, axis, lo, pixel, force)
    _check_line_spacing(instrument, axis, 2 * amplitude, width, cycle_fraction)
    step = 2 * amplitude / steps_per_sweep
    timeline, pits = drive_cycle(
        instrument,
        axis,
        (centre[axis], lane),
        amplitude,
        step,
        steps_per_sweep=steps_per_sweep,
        pit_every=pit_every,
        branch_gap=branch_gap,
        speed=speed,
        settle=settle,
        force=force,
        progress=StepProgress(
            progress,
            f"hysteresis_{'xy'[axis]}",
            "pit",
            2 * (steps_per_sweep // pit_every + 1),
            instrument,
        ),
    )
    # the cycle ended at its top with the feed-forward back on: the command is now where the
    # controller puts the top tip, the only place a compensated pass can start for certain
    top = float(instrument.commanded_position()[axis])
    box = _rescan_box(axis, centre, amplitude, half, (lane, lane + branch_gap), top, scale)
    branches = np.array([p[0] for p in pits])
    drives = np.array([p[1] for p in pits])
    moments = np.array([p[2] for p in pits])
    cycle = (branches, drives, moments, timeline.sampled(axis, MODEL_DT))
    pixels = rescan_pixels(instrument, axis, box, pixel)
    imaging = (instrument, axis, pixels, rescans, ignore, width)
    thresholds = np.arange(operators) * amplitude / (2 * operators)
    model = (centre[axis], half, thresholds, creep)
    fit, measured, disagreeing, all_detected = _imaged_fit(imaging, box, cycle, model)
    data = _record(fit, measured, disagreeing, all_detected, cycle[:3])
    data.update(
        cycle_fraction=cycle_fraction,
        # the rescan box along the cycled axis
        rescan_box=[float(box[0][axis]), float(box[1][axis])],
        pit_width=width if width > 0 else None,  # None: the pixel was given
        pixel=pixels,
        pits_punched=len(pits),
        **drive_record(timeline, axis, centre[axis], half),
    )
    return Experiment({key: fit[key] for key in FIT_PARAMETERS}, data)


def _record(fit, measured, disagreeing, all_detected, cycle) -> dict:
    """What the pits say: the found pits' branch, drive, time and imaged position (the mean of
    the rescans), the fit's prediction and the counts."""
    branches, drives, moments = cycle
    found = np.all(np.isfinite(measured), axis=0)
    return {
        "branch": branches[found].tolist(),
        "drive": drives[found].tolist(),
        "time": moments[found].tolist(),
        "position": measured[:, found].mean(axis=0).tolist(),
        "position_per_rescan": measured[:, found].tolist(),
        "predicted": fit["predicted"],
        "pits_found": int(found.sum()),
        "pits_rescans_disagree": int(disagreeing.sum()),
        # the four pits at the loop's tips (each branch's highest and lowest drive), where the
        # asymmetry shows most; outside the rescan box when the loop is strongly asymmetric
        "tip_pits_found": int(sum(found[_tip_pits(branches, drives)])),
        "all_detected": all_detected[0],
    }


# The rescan pixel: PIXEL, or the probe pit's width over PIT_PIXELS where that is finer. The
# pit detector needs MIN_PIT_PIXELS above its threshold and the centre fit a few more: the
# default tip's pits (20 nm apex, ~63 nm wide as detected) keep 30 nm; an 8 nm apex (~44 nm)
# got 24 nm, where at 30-35 nm a third of the pits or none were found (probe 57, F5).
PIXEL = 30e-9  # m
PIT_PIXELS = 1.8


def _pit_width_and_pixel(instrument, axis: int, lo, pixel, force: float) -> tuple:
    """(probe pit width or NaN, rescan pixel): `pixel` as given, else from a probe pit punched
    at the range centre along the cycled axis, on the near edge of the cycle's box across it
    (outside every rescan box of both cycles and their retries)."""
    if pixel is not None:
        return float("nan"), float(pixel)
    probe = range_centre(instrument)
    probe[1 - axis] = lo[1 - axis]
    width = probe_pit_width(instrument, float(probe[0]), float(probe[1]), force)
    return width, (min(PIXEL, width / PIT_PIXELS) if width > 0 else PIXEL)


def _check_line_spacing(instrument, axis: int, span: float, width: float, cycle_fraction):
    """GeometryError before the cycle runs when its rescan, at least `span` long along the
    cycle in at most max_pixels lines, has lines farther apart than a pit `width` wide (the
    probe pit's; NaN: unknown, not checked): on an instrument of 512 pixels a full-range cycle
    has a line every ~200 nm against pits of ~60 nm, and the experiment found 2 of 66 pits
    after half an hour of cycling, then advised a finer pixel, which cannot fit."""
    lines = instrument.limits.max_pixels - 1
    spacing = span / lines
    if not np.isfinite(width) or width >= spacing:
        return
    # the cycle whose rescan gets the line spacing this module chooses for such pits
    fitting = cycle_fraction * lines * width / (PIT_PIXELS * span)
    text = (
        f"hysteresis ({'xy'[axis]}): the rescan spans at least {span * 1e6:.3g} um along the "
        f"cycle, with this instrument's max_pixels {lines + 1} a line every "
        f"{spacing * 1e9:.0f} nm, wider than its pits ({width * 1e9:.0f} nm, a probe pit); "
    )
    # a smaller cycle fits the lines, but its loop is extrapolated beyond what was checked
    # (fit_checks warns): it is not advised
    if fitting >= RETRY_CYCLE_FRACTION:
        raise GeometryError(
            f"{text}a cycle_fraction of about {fitting:.2g} fits (the loop is then extrapolated "
            "from that cycle): afm calibrate --set hysteresis.cycle_fraction=VALUE"
        )
    needed = int(np.ceil(PIT_PIXELS * span / width)) + 1
    raise GeometryError(
        f"{text}no cycle_fraction of {RETRY_CYCLE_FRACTION} or more fits: this "
        f"experiment needs about {needed} pixels per line on this scanner (one rescan along "
        "the whole cycle), or pits wider than the lines (a blunter tip, or more force if the "
        "instrument allows)"
    )


def rescan_pixels(instrument, axis: int, box, pixel: float) -> list[float]:
    """The rescans' pixel (x, y) (m): `pixel`, coarser along the cycled (slow) axis only where
    the box is too long for max_pixels lines at it (a fine pixel on a full-range cycle)."""
    pixels = [float(pixel), float(pixel)]
    length = float(box[1][axis] - box[0][axis])
    pixels[axis] = max(pixel, length / (instrument.limits.max_pixels - 1))
    return pixels


def _imaged_fit(imaging, box, cycle, model) -> tuple:
    """The rows of pits imaged in `box` (imaged_rows), the pits the rescans disagree on left
    out, and fit_hysteresis on the rest: (fit, measured positions per rescan (NaN where not
    used), disagreeing, detections)."""
    instrument, axis, pixel, rescans, ignore, width = imaging
    branches, drives, moments, (times, drive) = cycle
    centre, half, thresholds, creep = model
    # pits under ~2 pixels wide are missed: a failure says how the two compared
    probe = f", a probe pit {width * 1e9:.0f} nm wide" if width > 0 else ""
    sizes = (
        f" (rescan pixel {max(pixel) * 1e9:.0f} nm{probe}; pits narrower than 2 pixels are "
        "missed: afm calibrate --set hysteresis.pixel=VALUE)"
    )
    try:
        measured, all_detected = imaged_rows(
            instrument, axis, box, pixel, rescans, branches, drives, ignore
        )
    except RowsNotMatched as exc:
        raise RowsNotMatched(f"{exc}{sizes}", exc.detected) from exc
    except RuntimeError as exc:
        raise RuntimeError(f"{exc}{sizes}") from exc
    disagreeing = rescan_disagreements(measured, branches)
    measured[:, disagreeing] = np.nan
    found = np.all(np.isfinite(measured), axis=0)
    if found.sum() < 2 * thresholds.size:
        raise RuntimeError(
            f"hysteresis ({'xy'[axis]}): only {int(found.sum())} of {len(branches)} pits found "
            f"in every rescan; need {2 * thresholds.size}{sizes}"
        )
    positions = measured[:, found].mean(axis=0)
    fit = fit_hysteresis(times, drive, centre, half, moments[found], positions, thresholds, creep)
    return fit, measured, disagreeing, all_detected


def _tip_pits(branches: np.ndarray, drives: np.ndarray) -> list[int]:
    """Indices of each branch's pits at the highest and the lowest drive."""
    tips = []
    for branch in ("descending", "ascending"):
        members = np.flatnonzero(branches == branch)
        tips += [
            int(members[np.argmax(drives[members])]),
            int(members[np.argmin(drives[members])]),
        ]
    return tips


def _checked_options(
    limits, axis, cycle_fraction, steps_per_sweep, pit_every, operators, speed, branch_gap
) -> tuple:
    """measure_hysteresis's options checked (ValueError naming the first bad one) and converted:
    (steps_per_sweep, pit_every, operators, speed, branch_gap)."""
    if axis not in (0, 1):
        raise ValueError(f"axis={axis}: must be 0 (x) or 1 (y)")
    if not (math.isfinite(cycle_fraction) and 0.2 <= cycle_fraction <= 0.9):
        raise ValueError(
            f"cycle_fraction={cycle_fraction}: must be within [0.2, 0.9] of the half "
            "range (the rescan needs the outer 10 % clear, see measure_hysteresis)"
        )
    steps_per_sweep = checks.count("steps_per_sweep", steps_per_sweep, 8, 4096)
    return (
        steps_per_sweep,
        checks.count("pit_every", pit_every, 1, steps_per_sweep // 4),
        checks.count("operators", operators, 2, 64),
        checks.positive("speed", speed, "m/s", upper=limits.max_speed),
        checks.positive("branch_gap", branch_gap, "m", upper=10e-6),
    )


def _box(
    axis: int, centre, amplitude: float, lanes, reach: float, margin: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper corner) of the box around the cycle: `amplitude` + `margin` either side of
    the centre along the cycled axis, from `reach` before the first of the `lanes` to `reach`
    after the second across it."""
    other = 1 - axis
    lo, hi = centre.copy(), centre.copy()
    lo[axis], hi[axis] = centre[axis] - amplitude, centre[axis] + amplitude
    lo[other], hi[other] = lanes[0] - reach, lanes[1] + reach
    lo[axis] -= margin
    hi[axis] += margin
    return lo, hi


# The rows' ends lie at the cycle's tips; the box reaches TIP_MARGIN beyond them: the end pits
# stay whole in the image and each pass starts a few pit spacings (~1 um) before the first
# pit. At 2 um the rows of a loop of 0.25 (a = -0.1, coupling 0.05, noise 4x, the tests'
# coarse cycle) were not matched at the top tip on both cycles; at 4 um the smaller one was.
TIP_MARGIN = 4.0e-6  # m on REFERENCE_RANGE (experiment.range_scale)


def _rescan_box(
    axis: int, centre, amplitude: float, half: float, lanes, top: float, scale: float = 1.0
) -> tuple:
    """The box the rows of pits are rescanned in: from TIP_MARGIN below the cycle's bottom
    tip to TIP_MARGIN above its top one (`top`: where the controller puts the top tip; the
    bottom one lies 2 amplitude x the tip-to-tip gain below it, 1 to a few %, which the
    margin covers), within the range. Centred on the tips, not on the range: an input
    asymmetry a moves both tips by about a x half (4.4 um at a = 0.08), and a pass must not
    start where the compensated scanner cannot go: a command beyond the loop's tips at full
    drive needs a drive past the range, the amplifier clamps it and the controller's inverse
    runs ahead of the scanner over the following tens of um (a fixed box of 0.95 of the half
    range biased the asymmetry by -4 % on a noise-free scanner, and failed to match the
    rows of a loop of 0.25 with a = -0.1). The tips are `amplitude` inside full drive, so
    the margin is reachable whenever TIP_MARGIN < (half - amplitude) x the branch slope.
    scale: experiment.range_scale, which the margins are multiplied by (the loop, its tips'
    spread and the cycle's pit spacing are fractions of the range)."""
    lo, hi = _box(axis, centre, amplitude, lanes, RESCAN_REACH * scale)
    margin = TIP_MARGIN * scale
    limit = 2.0 * half  # the range along the cycled axis: [0, 2 half]
    if math.isfinite(top) and abs(top - centre[axis] - amplitude) < 0.25 * half:
        lo[axis] = max(0.0, top - 2.0 * amplitude - margin)
        hi[axis] = min(limit, top + margin)
    else:  # an instrument that does not report the compensated command: the drive's span
        lo[axis] = max(0.0, lo[axis] - margin)
        hi[axis] = min(limit, hi[axis] + margin)
    return lo, hi


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
