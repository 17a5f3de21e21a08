"""Motion error against distance moved (book 7.2.2, Fig. 7.6e; Fig. 7.20b sigma^2 = a d + b):
repeated moves of several lengths, a pit before and after each; the variance of the
separations about their mean against the distance. What it measures is the noise model of
afm_core.localization.motion_noise (MotionNoise).

The frame: the separations are read off the rescans, so the slopes are variances in the images'
frame per metre commanded, which is the frame the localizer works in (its state is where the
images put the tip, its moves are commanded, its observations are local scans; motion.py). They
are not variances in true metres: a scanner whose feed-forward is off makes short moves and the
short strokes of a rescan alike longer or shorter than commanded (the lanes' mean separation
stays d), and the noise in the image is the true noise times (image / true length)^2. On the
simulator, loop 0.18 with the controller's model 10 % off: image / true 0.90 at the lanes, slope
-13 % against the configured (true-metre) value, -15 % against the lanes' true pits' own
separations; with an exact model: 1.02, +7 % and +5 % (issue 37's "-14.1 %"). The localizer needs
the image-frame value; simulator_comparison converts the configured one to it.
"""

from __future__ import annotations

import math

import numpy as np

from afm_core import checks
from afm_core.localization.calibration.experiment import (
    Experiment,
    GeometryError,
    StepProgress,
    check_box,
    indent_force,
    punch_at,
    range_centre,
    range_scale,
    rescan,
    wait,
)
from afm_core.localization.calibration.fit_checks import ACCURACY_TARGET, Z_95, Z_CONSISTENT
from afm_core.localization.calibration.hysteresis import LANE_OFFSET
from afm_core.localization.calibration.pits import DetectedPit, find_pits


def fit_variance_line(distances, variances, counts) -> tuple[float, float]:
    """sigma^2 = a d + b by weighted least squares: a sample variance from n values has a
    standard deviation of about sigma^2 sqrt(2 / (n - 1)), so the weights are (n - 1) / 2 / v^2,
    iterated with the fitted line in place of the noisy v."""
    a, b, _ = variance_line(distances, variances, counts)
    return a, b


def variance_line(distances, variances, counts) -> tuple[float, float, float]:
    """`fit_variance_line` and the standard error of its slope a: with the weights the
    inverse standard deviations of the sample variances (from the fitted line, so not from
    the data's own scatter), the covariance is (X^T W X)^-1."""
    d, v, n = (np.asarray(a, float) for a in (distances, variances, counts))
    expected = np.maximum(v, 1e-30)
    for _ in range(5):
        w = np.sqrt((n - 1) / 2) / expected
        design = np.stack([d, np.ones_like(d)], axis=1) * w[:, None]
        (a, b), *_ = np.linalg.lstsq(design, v * w, rcond=None)
        expected = np.maximum(a * d + b, 0.1 * np.maximum(v, 1e-30))
    w = np.sqrt((n - 1) / 2) / expected
    design = np.stack([d, np.ones_like(d)], axis=1) * w[:, None]
    covariance = np.linalg.pinv(design.T @ design)
    return float(a), float(b), float(np.sqrt(max(0.0, covariance[0, 0])))


# The precision the slope is measured to: its 95 % interval within ACCURACY_TARGET of the
# value (what fit_checks asks of it). A first round of `trials` per lane gives the slope's
# standard error; where that is short of it, a second round of lanes at `extra_site` adds
# the trials the pooled fit needs (the variance of the slope falls as 1 / trials), times
# PLAN_MARGIN: the first round's standard error is itself estimated (its variances scatter
# by sqrt(2 / (trials - 2)) each, ~7 % on the pooled slope), and the plan must not fall short
# when it came out low. The second round's lanes (at most 25 x 45 um at max_trials 100) lie at
# extra_site, left of the hysteresis y cycle's lanes and their repeat (x in -21..-3 um of the
# centre), above the x cycle's (y -21..-3 um), left of the scanner matrix's grid, and 4.5 um
# inside the 49.5 um from the centre that the compensated scanner reaches with an asymmetry
# of 0.1 (a rescan past it is clamped, see hysteresis._rescan_box; at 1.1 um inside, x -48 um,
# the 0.25 um x lane of the widest loop kept 3 trials).
PLAN_MARGIN = 1.2
# On REFERENCE_RANGE (experiment.range_scale): the distances moved (on a smaller range those up
# to MAX_DISTANCE x the scale, at least the two shortest), the first and the second round's
# lanes from the range centre (m)
DISTANCES = (0.25e-6, 0.5e-6, 1e-6, 2e-6, 4e-6)
MAX_DISTANCE = 4.4e-6  # m on REFERENCE_RANGE: the longest distance kept is this share of the range
SITE = np.array([-45e-6, -45e-6])
EXTRA_SITE = np.array([-45e-6, 0.0])
MIN_TRIALS = 12  # a lane cut to fit a small range keeps at least these (else GeometryError)


def measure_motion_noise(
    instrument,
    *,
    distances=None,
    trials: int = 40,
    row_spacing: float = 200e-9,
    site=None,
    speed: float = 10e-6,
    settle: float = 300.0,
    pixel: float = 15e-9,
    force: float | None = None,
    progress=None,
    precision: float | None = ACCURACY_TARGET,
    max_trials: int = 100,
    extra_site=None,
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
    are on one line, measured by the same trace.

    precision (relative, or None): when the pooled slope's 95 % interval is wider than this
    share of it, a second round of lanes at `extra_site` adds the trials the pooled fit needs
    (PLAN_MARGIN), at most `max_trials` per lane (the time budget: each lane's rescan grows
    with its trials); data["rounds"] says what was planned and why.

    distances, site and extra_site default to DISTANCES, SITE and EXTRA_SITE on a 110 um
    scanner, the same fractions of a smaller range (experiment.range_scale), where a round's
    lanes have as many trials as fit in the range (at least MIN_TRIALS, else GeometryError;
    a second round that does not fit is not run, data["rounds"] says so)."""
    limits = instrument.limits
    scale = range_scale(instrument)
    # the default sites' lanes stay clear of the hysteresis rows; a site given only has to fit
    top = np.array([limits.range_x, limits.range_y])
    clear = _clear_of_hysteresis(instrument) if site is None else top
    site = SITE * scale if site is None else np.asarray(site, float)
    extra_site = EXTRA_SITE * scale if extra_site is None else np.asarray(extra_site, float)
    if distances is None:
        distances = [d for d in DISTANCES if d <= MAX_DISTANCE * scale] or DISTANCES[:1]
        distances = distances if len(distances) > 1 else DISTANCES[:2]
    distances = [checks.positive("distances[]", d, "m", upper=20e-6) for d in distances]
    if len(distances) < 2:
        raise ValueError(f"distances={distances}: need at least two distances for a line")
    trials = checks.count("trials", trials, 5, 400)
    max_trials = checks.count("max_trials", max_trials, 5, 400)
    row_spacing = checks.positive("row_spacing", row_spacing, "m", upper=5e-6)
    speed = checks.positive("speed", speed, "m/s", upper=limits.max_speed)
    force = indent_force(instrument, force)
    options = (row_spacing, speed, settle, pixel, force, progress)
    trials = _fitting_trials(instrument, site, distances, (trials, MIN_TRIALS), row_spacing, clear)
    samples, data = _round(instrument, site, distances, trials, options, 0)
    parameters = _fitted_slopes(samples)
    data["rounds"] = [{"site": list(site), "trials": trials}]
    width = Z_95 * parameters["pooled_slope_sigma"] / max(abs(parameters["pooled_slope"]), 1e-300)
    if precision is not None and width > precision:
        wanted = math.ceil((trials - 2) * ((width / precision) ** 2 * PLAN_MARGIN - 1.0)) + 2
        largest = max(np.sqrt(max(r[3], r[4], 0.0)) for r in samples)
        spacing = float(max(row_spacing, ROW_SIGMAS * largest))
        more = min(max(wanted, 5), max_trials, int(MAX_EXTENT / spacing) + 1)
        try:
            more = _fitting_trials(
                instrument, extra_site, distances, (more, 5), spacing, np.array([clear[0], top[1]])
            )
        except GeometryError as exc:
            data["rounds"].append({"site": list(extra_site), "trials": 0, "why": str(exc)})
            parameters["move_gains"] = _move_gains(data)
            return Experiment(parameters, data)
        extra, extra_data = _round(
            instrument, extra_site, distances, more, (spacing, *options[1:]), 1
        )
        samples += extra
        for axis in "xy":
            data[axis] += extra_data[axis]
        parameters = _fitted_slopes(samples)
        data["rounds"].append(
            {
                "site": list(extra_site),
                "trials": more,
                "row_spacing": spacing,
                "why": f"95 % interval of the slope {width:.1%} of it after the first round, "
                f"aim {precision:.0%}: {wanted} trials per lane planned, {more} run "
                f"(max_trials {max_trials}, {MAX_EXTENT * 1e6:.1f} um per lane at "
                f"{spacing * 1e9:.0f} nm rows)",
            }
        )
    parameters["move_gains"] = _move_gains(data)
    return Experiment(parameters, data)


def _move_gains(data: dict) -> list[list[float]]:
    """Per lane [axis, d, g, standard error of g]: how long a commanded move of d is in the
    images (its trials' mean separation / d). The slopes are variances in the images' frame
    per metre commanded; where g departs from 1 the moves and the images disagree on the
    frame at that length (a compensated scanner that is not linear there: on the widest
    loop of issue 37, g 1.06-1.09 at 1-4 um and 1.00 at 0.25 um), and the slope measured
    through it is off by up to |g^2 - 1| (fit_checks flags it)."""
    gains = []
    for axis in (0, 1):
        for lane in data["xy"[axis]]:
            d, n = lane["distance"], max(lane["trials"], 2)
            error = math.sqrt(lane["variance_along"] / n) / d
            gains.append([axis, d, lane["mean_separation"] / d, error])
    return gains


def calibrated_slopes(parameters: dict) -> dict:
    """The slopes the calibration keeps (motion_noise_slope_x / _y / cross_slope): the pooled
    slope for every component that agrees with it, the component's own where it does not.
    Each component has half the pooled slope's samples or fewer, so its own 95 % interval is
    ~14 % wide where the pooled one meets 10 % (issue 37's narrowest instrument: cross slope
    -11 % on its own, unflagged). Agreeing means what fit_checks' agreement check calls ok
    (within Z_CONSISTENT of the component's standard error or within ACCURACY_TARGET of the
    pooled value); one that disagrees is warned about there and keeps its own value."""
    pooled = parameters["pooled_slope"]
    kept = {}
    for name in ("slope_x", "slope_y", "cross_slope"):
        value, sigma = parameters[name], parameters[f"{name}_sigma"]
        difference = abs(value - pooled)
        agrees = difference <= Z_CONSISTENT * sigma or difference <= ACCURACY_TARGET * max(
            abs(value), abs(pooled), 1e-300
        )
        kept[name] = max(0.0, pooled if agrees else value)
    return kept


def _round(instrument, site, distances, trials: int, options, number) -> tuple[list, dict]:
    """Round `number` of lanes (every distance, both axes) at `site`: the samples (axis, d,
    trials - 1, variance along, variance across) and the per-lane data (with the round and the
    trials punched: a simulator's pits can be matched to the lanes, simulator_comparison)."""
    row_spacing, speed, settle, pixel, force, progress = options
    limits = instrument.limits
    origin = range_centre(instrument) + np.asarray(site, float)
    lanes = _lanes(instrument, origin, distances, (trials - 1) * row_spacing)
    data, samples = {"x": [], "y": []}, []
    steps = StepProgress(
        progress, "motion_noise", f"lane of {trials} trials", len(lanes), instrument
    )
    for lane, (axis, d, start) in enumerate(lanes, start=1):
        instrument.move_tip(float(start[0]), float(start[1]), 0.5 * limits.max_speed)
        wait(instrument, settle)
        detected = _punched_lane(
            instrument, axis, d, start, trials, row_spacing, speed, force, pixel
        )
        separations, row_index = _trial_separations(detected, axis, d, row_spacing)
        keep = row_index > 0  # the first trial has another history
        separations, row_index = separations[keep], row_index[keep]
        if len(separations) < 5:
            raise RuntimeError(
                f"motion noise ({'xy'[axis]}, d={d:.3g} m): only {len(separations)} trials "
                "measured"
            )
        residual = []
        for component in (0, 1):
            trend = np.polyfit(row_index, separations[:, component], 1)
            residual.append(separations[:, component] - np.polyval(trend, row_index))
        n = len(separations)
        var_along = float(np.sum(residual[0] ** 2) / (n - 2))
        var_across = float(np.sum(residual[1] ** 2) / (n - 2))
        samples.append((axis, d, n - 1, var_along, var_across))
        steps.step(lane)
        data["xy"[axis]].append(
            {
                "round": number,
                "punched": trials,
                "distance": d,
                "trials": n,
                "mean_separation": float(separations[:, 0].mean()),
                "variance_along": var_along,
                "variance_across": var_across,
                # raw data: each measured trial's row and its separation along the move
                "rows": row_index.tolist(),
                "separations": separations[:, 0].tolist(),
            }
        )
    return samples, data


# Between neighbouring lanes: a lane's rescan reaches 0.4 um + 0.15 d past its pits, and
# shows another lane's pits up to ~1.5 um from where that lane's own rescan put them (the
# compensation residual of a slow pass against a fast stroke; issue 37: 0.75 um after a
# full-range excursion, which with 1 um between lanes put an x-lane pair into a y-lane image).
LANE_GAP = 3e-6  # m


MIN_LANE_GAP = 1e-6  # m: LANE_GAP x experiment.range_scale on a small range, not below this


def _clear_of_hysteresis(instrument) -> np.ndarray:
    """The upper corner (m) the first round's lanes stay below: their rescans (reaching up to
    MIN_LANE_GAP past the pits) clear of the hysteresis cycles' rows (at hysteresis.LANE_OFFSET
    from the centre across each axis, the full range along it), which are punched before;
    on a 110 um scanner the default lanes are 4.3 um inside."""
    return range_centre(instrument) + LANE_OFFSET * range_scale(instrument) - MIN_LANE_GAP


def _fitting_trials(instrument, site, distances, counts, row_spacing, upper) -> int:
    """The most trials per lane, up to counts[0] (at least counts[1]), whose lanes at `site`
    fit in the range below `upper` (GeometryError naming the options when not even
    counts[1] do; counts[0] below that: those or the error)."""
    trials, least = counts
    origin = range_centre(instrument) + np.asarray(site, float)
    reason = None
    for count in range(trials, min(least, trials) - 1, -1):
        try:
            lanes = _lanes(instrument, origin, distances, (count - 1) * row_spacing)
        except GeometryError as exc:
            reason = exc
            continue
        top = _lanes_top(lanes, (count - 1) * row_spacing)
        if np.all(top <= upper):
            return count
        reason = (
            f"motion-noise lanes up to {top[0] * 1e6:.3g}, {top[1] * 1e6:.3g} um: past "
            f"{upper[0] * 1e6:.3g}, {upper[1] * 1e6:.3g} um (the hysteresis cycles' lanes)"
        )
    raise GeometryError(
        f"{reason} (with {min(least, trials)} trials); pass a site (one given only has to fit "
        "in the range; keep it clear of the other experiments' pits: afm calibrate --set "
        f"motion_noise.site=X,Y; now {site[0]:.3g}, {site[1]:.3g} m), fewer or shorter "
        f"distances (now {', '.join(f'{d:.3g}' for d in distances)} m) or a smaller "
        f"row_spacing ({row_spacing:.3g} m)"
    )


def _lanes_top(lanes, extent: float) -> np.ndarray:
    """The upper corner of the lanes' pits (m)."""
    top = np.full(2, -np.inf)
    for axis, d, start in lanes:
        end = np.array(start, float)
        end[axis] += d
        end[1 - axis] += extent
        top = np.maximum(top, end)
    return top


def _lanes(instrument, origin, distances, extent: float) -> list[tuple]:
    """(axis, distance, start) of every lane, checked against the scanner range. Lanes side by
    side, LANE_GAP apart (MIN_LANE_GAP on a small range): the x lanes (rows stacked along y,
    `extent` tall) in a band along x, the y lanes (columns stacked along x) in a band along y
    above them."""
    gap = max(MIN_LANE_GAP, LANE_GAP * range_scale(instrument))
    lanes, cursor = [], 0.0
    for d in distances:
        lanes.append((0, d, origin + np.array([cursor, 0.0])))
        cursor += 1.3 * d + gap
    cursor = extent + gap
    for d in distances:
        lanes.append((1, d, origin + np.array([0.0, cursor])))
        cursor += 1.3 * d + gap
    for axis, d, start in lanes:
        end = start.copy()
        end[axis] += d
        end[1 - axis] += extent
        check_box(
            f"motion-noise lane ({'xy'[axis]}, d={d:.3g} m)",
            instrument,
            start - 0.5e-6,
            end + 0.5e-6,
        )
    return lanes


def _punched_lane(
    instrument, axis, d, start, trials, row_spacing, speed, force, pixel
) -> list[DetectedPit]:
    """The trials of one lane (pit A, a move of d along `axis`, pit B; trial k on row k), then
    the rescan of the lane and the pits found in it."""
    other = 1 - axis
    for k in range(trials):
        a = start.copy()
        a[other] += k * row_spacing
        b = a.copy()
        b[axis] += d
        punch_at(instrument, float(a[0]), float(a[1]), speed, force)
        punch_at(instrument, float(b[0]), float(b[1]), speed, force)
    hi = start.copy()
    hi[axis] += d
    hi[other] += (trials - 1) * row_spacing
    # the compensated gain of a move depends on the scanner's history (up to ~10 % off here)
    reach = np.full(2, 0.4e-6)
    reach[axis] += 0.15 * d
    scan = rescan(instrument, start - reach, hi + reach, pixel, slow_axis=other)
    return find_pits(scan)


# A trial's two pits differ across the axis by the move's cross error, neighbouring trials by
# the row spacing minus it: half the spacing splits them with equal odds either way. A third
# (before) dropped the trials whose cross error passed 67 nm: 4.5 % of them at noise 4x and
# 4 um (sigma 33 nm), the largest errors, so the variances read 10-20 % low (issue 37).
ROW_SPLIT = 0.5
# The second round's row spacing: at least ROW_SIGMAS standard deviations of the largest cross
# error the first round measured, so half of it is 4 sigma (6e-5 of the trials split).
ROW_SIGMAS = 8.0
# The tallest lane of the second round (100 trials at 200 nm: the area extra_site has).
MAX_EXTENT = 19.8e-6  # m


def _trial_separations(
    detected: list[DetectedPit], axis: int, d: float, row_spacing: float
) -> tuple[np.ndarray, np.ndarray]:
    """B - A (along, across) of every row holding exactly two pits about d apart, and the
    row's index (trial number)."""
    other = 1 - axis
    along = np.array([[p.x, p.y][axis] for p in detected])
    across = np.array([[p.x, p.y][other] for p in detected])
    # rows: pits closer than ROW_SPLIT of the row spacing across the axis belong together
    order = np.argsort(across)
    separations = []
    row_index = []
    group = [order[0]] if len(order) else []
    for i in list(order[1:]) + [None]:
        if i is not None and across[i] - across[group[-1]] < ROW_SPLIT * row_spacing:
            group.append(i)
            continue
        if len(group) == 2:
            left, right = sorted(group, key=lambda j: along[j])
            if abs(along[right] - along[left] - d) < 0.3 * d + 100e-9:
                separations.append((along[right] - along[left], across[right] - across[left]))
                row_index.append(round((across[left] - across[order[0]]) / row_spacing))
        group = [i] if i is not None else []
    return np.array(separations).reshape(-1, 2), np.array(row_index)


def _fitted_slopes(samples: list[tuple]) -> dict:
    """sigma^2 = a d + b per axis (along), across (the cross slope) and pooled, from the
    samples (axis, d, trials - 1, variance along, variance across), each slope with its
    standard error (`<name>_sigma`)."""
    parameters = {}
    for axis in (0, 1):
        rows = [s for s in samples if s[0] == axis]
        name = f"slope_{'xy'[axis]}"
        parameters[name], parameters[f"offset_{'xy'[axis]}"], parameters[f"{name}_sigma"] = (
            variance_line([r[1] for r in rows], [r[3] for r in rows], [r[2] + 1 for r in rows])
        )
    parameters["cross_slope"], parameters["cross_offset"], parameters["cross_slope_sigma"] = (
        variance_line(
            [r[1] for r in samples], [r[4] for r in samples], [r[2] + 1 for r in samples]
        )
    )
    # one slope from every component (along and across, both axes): the best estimate when
    # the noise is isotropic, as the simulator's is; compare the per-axis ones with it
    parameters["pooled_slope"], parameters["pooled_offset"], parameters["pooled_slope_sigma"] = (
        variance_line(
            [r[1] for r in samples] * 2,
            [r[3] for r in samples] + [r[4] for r in samples],
            [r[2] + 1 for r in samples] * 2,
        )
    )
    return parameters
