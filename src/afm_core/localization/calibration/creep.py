"""Creep of each axis (book 7.2.2, eq. 5.29-5.31, Fig. 7.7): a large step, then pits along the
other axis over minutes, rescanned; time constants (shared by the axes) and fractions (per
axis) by nonlinear least squares over repeated runs, whitened for the random walk of the
moves between pits.
"""

from __future__ import annotations

import numpy as np
from scipy import linalg, optimize, stats

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
from afm_core.localization.calibration.fit_checks import Z_95
from afm_core.localization.calibration.matching import match_monotone
from afm_core.localization.calibration.pits import find_pits


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


# A term faster than this is part of the step, not creep (the fit ran a free fast constant to
# exp(-655) = 0 s on creep 3x, which the Calibration refuses: the whole run was lost). At the
# bound it is flagged (fit_checks: faster than the first pit).
SHORTEST_TIME_CONSTANT = 1e-3  # s


def fit_creep(
    runs: list[dict],
    n_constants: int = 3,
    guess=(1.0, 10.0, 100.0),
    drift_curvature: bool = False,
    longest: float = np.inf,
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
    prepared = _prepared_runs(runs, groups)

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

    # `longest`: the time constants are bounded by it (a term slower than the record is a
    # straight line there, the drift's; unbounded it ran off to 1e305 s on creep 3x)
    theta0 = list(np.log(np.minimum(guess, 0.5 * longest))) + [0.005] * (n_constants * len(groups))
    lower = [float(np.log(SHORTEST_TIME_CONSTANT))] * n_constants + [0.0] * (
        n_constants * len(groups)
    )
    upper = [float(np.log(longest))] * n_constants + [0.5] * (n_constants * len(groups))
    for _, x, *_ in prepared:
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
    covariance = _covariance(fit)
    response, response_sigma = _step_response_sigmas(fit, covariance, unpack, len(groups))
    # the time constants are fitted as logarithms: their standard errors are relative
    log_sigma = np.sqrt(np.maximum(np.diag(covariance)[:n_constants], 0.0))
    fraction_sigma = np.sqrt(
        np.maximum(np.diag(covariance)[n_constants : n_constants * (1 + len(groups))], 0.0)
    ).reshape(len(groups), n_constants)
    return {
        "time_constants": taus[order].tolist(),
        "time_constants_sigma": (taus * log_sigma)[order].tolist(),
        "fractions": [f[order].tolist() for f in fractions],
        "fractions_sigma": [f[order].tolist() for f in fraction_sigma],
        "step_response_25s": response,
        "step_response_25s_sigma": response_sigma,
        "settled": [float(p[0]) * 1e-9 for p in per_run],
        "drift_velocity": [float(p[1]) * 1e-9 for p in per_run],
        "model": [m.tolist() for m in models],
        "rms_residual": rms,
        "success": bool(fit.success),
        # the cost least_squares minimised (x2: a chi-square for unit-variance residuals) and
        # its degrees of freedom, for comparing fits with fewer terms (fit_creep_terms)
        "cost": 2.0 * float(fit.cost),
        "dof": max(1, len(fit.fun) - len(fit.x)),
    }


# A term dropped from the creep model must leave the fit's cost within this quantile of the
# chi-square of the parameters it removes (scaled by the larger fit's residual variance).
DROP_QUANTILE = 0.95


def fit_creep_terms(runs: list[dict], guess, longest: float) -> tuple[dict, list[dict]]:
    """`fit_creep` with as many terms as the data hold: started with one per `guess`, a term
    whose fraction no axis tells from 0 (each within Z_95 of its standard errors) is dropped
    and the rest refitted, while one is left and the cost rises by no more than chance. A tube
    with one or two creep time constants otherwise gets three terms of which one runs to the
    shortest bound with a fraction of 0, or two sit on the same constant: their fractions'
    linearised errors are then unbounded and take the step response's with them (a single
    10 s term: fitted right to 0.3 %, stated +- 7 % of the step, "cannot be trusted").
    Returns the fit and the dropped terms ({"time_constant", "fractions_upper95"})."""
    fit = fit_creep(runs, n_constants=len(guess), guess=guess, longest=longest)
    dropped: list[dict] = []
    while len(fit["time_constants"]) > 1:
        fractions = np.asarray(fit["fractions"], float)  # groups x terms
        sigmas = np.asarray(fit["fractions_sigma"], float)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(sigmas > 0, fractions / sigmas, np.where(fractions > 0, np.inf, 0.0))
        seen = z.max(axis=0)
        weakest = int(np.argmin(seen))
        if seen[weakest] >= Z_95:
            break
        taus = [t for i, t in enumerate(fit["time_constants"]) if i != weakest]
        smaller = fit_creep(runs, n_constants=len(taus), guess=taus, longest=longest)
        variance = fit["cost"] / fit["dof"]
        removed = 1 + fractions.shape[0]  # the time constant and one fraction per group
        if smaller["cost"] - fit["cost"] > variance * stats.chi2.ppf(DROP_QUANTILE, removed):
            break
        dropped.append(
            {
                "time_constant": fit["time_constants"][weakest],
                "fractions_upper95": (fractions[:, weakest] + Z_95 * sigmas[:, weakest]).tolist(),
            }
        )
        fit = smaller
    return fit, dropped


def _prepared_runs(runs: list[dict], groups: list) -> list[tuple]:
    """Per run of `fit_creep`: (t, x in nm, step in nm, ramp time, mean t, whitener, index of
    its group)."""
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
    return prepared


def measure_creep(
    instrument,
    *,
    step: float | None = None,
    duration: float = 300.0,
    pits: int = 40,
    fast_pits: int = 8,
    repeats: int = 5,
    pit_spacing: float = 150e-9,
    settle: float = 300.0,
    lane_offset: float | None = None,
    pixel: float = 10e-9,
    force: float | None = None,
    guess=(1.0, 10.0, 100.0),
    progress=None,
) -> Experiment:
    """Creep of each axis in normal (compensated) operation (book 7.2.2, Fig. 7.7).

    Per axis, `repeats` runs: rest at centre - step/2 for `settle` s (earlier creep dies
    out), step to centre + step/2 at full speed, then punch `pits` pits one `pit_spacing`
    apart along the other axis at lane_offset from the centre (each further run shifted along
    the step by what its rescan covers, so the rows stay apart): `fast_pits` back to back (the
    0.5 s constant), the rest at log-spaced times up to `duration` s (the book samples 25 s;
    the 50 s constant needs several of its own lengths to be told from drift, which is fitted
    too). The moves along the other axis do not move this one, so each pit's coordinate
    along the step is the creep curve at its moment. Each run is rescanned with the slow axis
    along the step, approached from 50 um before so the pass is on a long monotone stretch of
    the loop (uniform image gain). `fit_creep` then fits all runs at once, the fractions
    shared by the runs of an axis: one run's drift wanders by tens of nm over minutes, as
    much as the slowest creep term changes, and independent runs average it out.

    step and lane_offset default to 50 um and 15 um on a 110 um scanner, the same fractions
    of the range on another (experiment.range_scale); a repeat whose run does not fit in the
    range is left out (data["runs_dropped"]), the first one must fit (GeometryError). A run
    whose rescan loses its pits is left out too (parameters["runs_failed"], with why); with no
    run of an axis left the experiment fails. The model keeps as many terms as the runs hold,
    up to one per `guess` (fit_creep_terms; parameters["terms_dropped"])."""
    limits = instrument.limits
    scale = range_scale(instrument)
    step = STEP * scale if step is None else step
    lane_offset = LANE_OFFSET * scale if lane_offset is None else lane_offset
    step = checks.positive("step", step, "m", upper=min(limits.range_x, limits.range_y) * 0.9)
    duration = checks.positive("duration", duration, "s", upper=3600.0)
    pits = checks.count("pits", pits, 8, 400)
    fast_pits = checks.count("fast_pits", fast_pits, 1, pits - 4)
    repeats = checks.count("repeats", repeats, 1, 20)
    pit_spacing = checks.positive("pit_spacing", pit_spacing, "m", upper=5e-6)
    force = indent_force(instrument, force)
    runs, data, duration = _measured_runs(
        instrument,
        step,
        (duration, pits, fast_pits, pit_spacing),
        repeats,
        lane_offset,
        dict(settle=settle, pixel=pixel, force=force),
        progress,
    )
    fit, dropped = fit_creep_terms(runs, guess, duration)
    for record, model in zip(data["x"] + data["y"], fit["model"]):
        record["model"] = model
    parameters = {
        "time_constants": fit["time_constants"],
        "fractions_x": fit["fractions"][0],
        "fractions_y": fit["fractions"][1],
        "drift_velocity": fit["drift_velocity"],
        "rms_residual": fit["rms_residual"],
        "step_response_25s": fit["step_response_25s"],
        "step_response_25s_sigma": fit["step_response_25s_sigma"],
        "time_constants_sigma": fit["time_constants_sigma"],
        "fractions_x_sigma": fit["fractions_sigma"][0],
        "fractions_y_sigma": fit["fractions_sigma"][1],
        "step": step,
        "success": fit["success"],
        # what the runs could resolve: a time constant at either end is not measured
        "time_constant_range": [float(min(r["t"][0] for r in runs)), duration],
        "record_per_tau": RECORD_PER_TAU,
        # the runs whose pits were not found (why), fitted without them (fit_checks warns)
        "runs_failed": list(data.get("runs_failed", [])),
        "runs_fitted": len(runs),
        # terms no axis could tell from 0, left out of the model (fit_creep_terms)
        "terms_dropped": dropped,
    }
    return Experiment(parameters, data)


STEP = 50e-6  # m on REFERENCE_RANGE (experiment.range_scale)
LANE_OFFSET = 15e-6  # m on REFERENCE_RANGE, the lanes of pits from the centre across the step
APPROACH = 50e-6  # m on REFERENCE_RANGE, the rescans' approach (see measure_creep)

# Creep is a few % of the step (book Fig. 7.7: ~2 %); the first rescan reaches back this
# share of the step, and further as far as the runs measure (up to MAX_CREEP_FRACTION, past
# which the pits are not creep but a failed step).
INITIAL_CREEP_FRACTION = 0.05
MAX_CREEP_FRACTION = 0.25
# The rescan reaches this far past the extent of the measured lag: the next runs' early pits
# may lag more than the ones measured (a step's fast creep is caught by the first pit or not).
REACH_PER_LAG = 1.5
RESCAN_MARGIN = 0.5e-6  # m, past the pits: the pit's own width and the compensation residual
RUN_CLEARANCE = 1.0e-6  # m between one run's rescan box and the pits of the run before


# The slowest creep term must decay within a run, or the drift line fitted with it takes it
# up: a run resolves a time constant up to 1 / RECORD_PER_TAU of its length (e^-4: 2 % of the
# term left at the end); a slower one is flagged (fit_checks). Runs are not lengthened from a
# first fit: at a drift of 1 nm/s a 1200 s run's pits drift apart by 8 pit spacings along
# their lane and no longer match (issue 37's creep 3x, 150 s against 300 s runs: flagged).
RECORD_PER_TAU = 4.0


def _measured_runs(instrument, step, schedule, repeats, lane_offset, options, progress):
    """Every run of measure_creep: (runs for fit_creep, records per axis, the run length). The
    rescan reaches back along the step by `reach`; the runs of an axis lie `reach` +
    RUN_CLEARANCE apart so one run's rescan never shows the run before. Both start from a
    creep of a few % of the step and grow with the lag a run measured (issue 37: creep 3x
    lags 3 um behind a 50 um step, past the 3 um box, and the missing early pits left the
    fast time constant free)."""
    duration, pits, fast_pits, pit_spacing = schedule
    reach = INITIAL_CREEP_FRACTION * step + RESCAN_MARGIN
    plans = _planned_runs(instrument, step, pits, repeats, pit_spacing, lane_offset, reach)
    runs, data, punched = [], {"x": [], "y": []}, set()
    steps = StepProgress(progress, "creep", f"step run of {pits} pits", len(plans), instrument)
    for number in range(1, len(plans) + 1):
        if plans[number - 1] is None:  # no room for this repeat at the lag measured
            data["runs_dropped"] = data.get("runs_dropped", 0) + 1
            steps.step(number)
            continue
        axis, start, end = plans[number - 1]
        name = "xy"[axis]
        # a later run of an axis must not reach back to the run before it (measured or not:
        # a failed run's pits are on the sample all the same)
        room = np.inf if name not in punched else reach + RUN_CLEARANCE - RESCAN_MARGIN
        punched.add(name)
        try:
            run, record = _creep_run(
                instrument,
                axis,
                start,
                end,
                step=step,
                schedule=(duration, pits, fast_pits, pit_spacing),
                label=f"creep ({name}, run {(number - 1) % repeats})",
                reach=(reach, min(room, MAX_CREEP_FRACTION * step)),
                **options,
            )
        except RuntimeError as exc:
            # one run's rescan losing its pits (a strong drift carries them out of the box)
            # must not discard the minutes of runs that were measured: the fit takes the rest,
            # the report says which run failed and why (fit_checks warns)
            data.setdefault("runs_failed", []).append(str(exc))
            steps.step(number)
            continue
        runs.append(run)
        data[name].append(record)
        needed = REACH_PER_LAG * record["lag"] + RESCAN_MARGIN
        if needed > reach:
            reach = needed
            wider = _planned_runs(instrument, step, pits, repeats, pit_spacing, lane_offset, reach)
            plans = plans[:number] + wider[number:]
        steps.step(number)
    missing = [axis for axis in "xy" if not data[axis]]
    if missing:
        raise RuntimeError(
            f"creep: no run of axis {', '.join(missing)} measured: "
            + "; ".join(data.get("runs_failed", []) or ["every run left out (no room)"])
        )
    return runs, data, duration


def _planned_runs(
    instrument,
    step: float,
    pits: int,
    repeats: int,
    pit_spacing: float,
    lane_offset: float,
    reach: float,
) -> list[tuple | None]:
    """(axis, start, end) of every run, x runs first, the runs of an axis `reach` +
    RUN_CLEARANCE apart along the step (past the lag a rescan box reaches back); each run's
    lane checked against the scanner range before anything moves: a later repeat that does not
    fit in the range (a small scanner, or a plan widened for a larger lag) is None, that axis
    then has fewer runs; a first one that does not is a GeometryError."""
    centre = range_centre(instrument)
    run_spacing = reach + RUN_CLEARANCE
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
            try:
                check_box(
                    f"creep lane ({'xy'[axis]}, run {repeat})",
                    instrument,
                    np.minimum(start, last),
                    np.maximum(end, last),
                )
            except ValueError as exc:
                if not repeat:
                    raise GeometryError(
                        f"{exc}; the first run's {'xy'[axis]} lane, from "
                        f"{start[0] * 1e6:.3g}, {start[1] * 1e6:.3g} to {last[0] * 1e6:.3g}, "
                        f"{last[1] * 1e6:.3g} um; pass a smaller step "
                        f"(now {step:.3g} m), lane_offset ({lane_offset:.3g} m) or pits x "
                        f"pit_spacing ({pits} x {pit_spacing:.3g} m): afm calibrate --set "
                        "creep.step=VALUE"
                    ) from None
                plans.append(None)
                continue
            plans.append((axis, start, end))
    return plans


def _creep_run(
    instrument, axis: int, start, end, *, step, schedule, settle, pixel, force, label: str, reach
) -> tuple[dict, dict]:
    """One run: rest at `start`, step (by `step`) to `end`, punch the lane of pits on `schedule`
    (duration, pits, fast_pits, pit_spacing), rescan and find them (`reach`: (how far the
    rescan reaches back along the step, the most it may), see `_rescanned_lane`). Returns the
    run for `fit_creep` and its record for the report (with "lag": the extent of the pits
    along the step)."""
    duration, pits, fast_pits, pit_spacing = schedule
    limits = instrument.limits
    other = 1 - axis
    instrument.move_tip(float(start[0]), float(start[1]), 0.5 * limits.max_speed)
    wait(instrument, settle)
    t0 = float(instrument.time)
    instrument.move_tip(float(end[0]), float(end[1]), limits.max_speed)
    ramp_time = float(instrument.time) - t0
    # log-spaced moments from just after the step; the early ones come faster than a pit can
    # be punched, so those go back to back (fast_pits of them at least)
    moments_planned = np.geomspace(ramp_time + 0.05, duration, pits)
    moments_planned[:fast_pits] = 0.0
    moments, lane = [], []
    for k, when in enumerate(moments_planned):
        wait(instrument, t0 + when - float(instrument.time))
        target = end.copy()
        target[other] += k * pit_spacing
        moments.append(
            punch_at(instrument, float(target[0]), float(target[1]), limits.max_speed, force) - t0
        )
        lane.append(float(target[other]))
    index, detected = _rescanned_lane(instrument, axis, end, lane, pixel, reach, fast_pits)
    ok = index >= 0
    if ok.sum() < 8:
        raise RuntimeError(f"{label}: only {int(ok.sum())} of {pits} pits found in the rescan")
    positions = np.array([[detected[j].x, detected[j].y][axis] for j in index[ok]])
    times = np.asarray(moments)[ok]
    # pit k comes after k moves along the lane (the step itself is common to all: x_inf)
    run = {
        "t": times,
        "x": positions,
        "step": step,
        "ramp_time": ramp_time,
        "group": "xy"[axis],
        "moves": np.flatnonzero(ok) + 1,
    }
    record = {
        "t": times.tolist(),
        "position": positions.tolist(),
        "step": step,
        "ramp_time": ramp_time,
        "pits_punched": pits,
        "pits_found": int(ok.sum()),
        "lag": float(np.ptp(positions)),
    }
    return run, record


# Across the lane the rescan reaches this far past its first and last pit, and at most
# LANE_MARGIN_MOST when the pits crowd that side (a drift across the lane carried them).
LANE_MARGIN = 0.4e-6  # m
LANE_MARGIN_MOST = 1.6e-6  # m


def _rescanned_lane(instrument, axis, end, lane, pixel, reach, fast_pits) -> tuple:
    """The lane's pits in a rescan reaching reach[0] back along the step from `end`: (index
    into the detections per pit or -1, detections). The early pits lag most; when fewer than
    half of the first `fast_pits` are found and the earliest found lies in the outer quarter of
    the box, they fell outside it: the box is doubled (up to reach[1]) and the lane rescanned.
    Likewise where pits are missing and those found crowd another side (within half its
    margin): a drift carries them past the step's end (2 nm/s: 0.6 um in a run, past the 0.5 um
    margin, and a run found 6 of 40) or across the lane; that side's margin is doubled, past
    the end up to RUN_CLEARANCE (the next run's box starts there), across up to
    LANE_MARGIN_MOST."""
    other = 1 - axis
    extent, most = reach
    past, side = RESCAN_MARGIN, np.array([LANE_MARGIN, LANE_MARGIN])
    while True:
        lo, hi = np.array(end, float), np.array(end, float)
        lo[axis] -= extent
        hi[axis] += past
        lo[other], hi[other] = lane[0] - side[0], lane[-1] + side[1]
        scan = rescan(
            instrument, lo, hi, pixel, slow_axis=axis, approach=APPROACH * range_scale(instrument)
        )
        detected = find_pits(scan)
        found = np.array([[p.x, p.y][other] for p in detected])
        index = match_monotone(lane, found) if len(found) else np.full(len(lane), -1)
        if not np.any(index >= 0) or np.all(index >= 0):
            return index, detected
        matched = np.array([[detected[j].x, detected[j].y] for j in index[index >= 0]])
        along, across = matched[:, axis], matched[:, other]
        grown = False
        early_missing = np.sum(index[:fast_pits] >= 0) < 0.5 * fast_pits
        if early_missing and along.min() < lo[axis] + 0.25 * extent and 2 * extent <= most:
            extent, grown = 2 * extent, True
        if along.max() > hi[axis] - 0.5 * past and 2 * past <= RUN_CLEARANCE:
            past, grown = 2 * past, True
        crowded = [
            across.min() < lo[other] + 0.5 * side[0],
            across.max() > hi[other] - 0.5 * side[1],
        ]
        for k in (0, 1):
            if crowded[k] and 2 * side[k] <= LANE_MARGIN_MOST:
                side[k], grown = 2 * side[k], True
        if not grown:
            return index, detected


STEP_RESPONSE_TIME = 25.0  # s, the book's creep figure: what the motion model predicts


def _covariance(fit) -> np.ndarray:
    """The parameters' covariance at the solution, linearised: s^2 (J^T J)^-1 (J and the cost
    as least_squares leaves them, whitened where the fit was)."""
    jacobian = np.asarray(fit.jac, float)
    dof = max(1, jacobian.shape[0] - jacobian.shape[1])
    return 2.0 * float(fit.cost) / dof * np.linalg.pinv(jacobian.T @ jacobian)


def _step_response_sigmas(fit, covariance, unpack, groups: int) -> tuple[list, list]:
    """Per group the creep step response at STEP_RESPONSE_TIME and its standard error: the
    parameters' covariance propagated by the numerical gradient of the response."""
    t = np.array([STEP_RESPONSE_TIME])

    def responses(theta):
        taus, fractions, _ = unpack(theta)
        return np.array([creep_step_response(taus, fractions[g], t)[0] for g in range(groups)])

    base = responses(fit.x)
    gradient = np.zeros((groups, len(fit.x)))
    for k in range(len(fit.x)):
        step = 1e-6 * max(1.0, abs(fit.x[k]))
        shifted = fit.x.copy()
        shifted[k] += step
        gradient[:, k] = (responses(shifted) - base) / step
    variance = np.einsum("gi,ij,gj->g", gradient, covariance, gradient)
    return base.tolist(), np.sqrt(np.maximum(variance, 0.0)).tolist()


def creep_step_response(time_constants, fractions, t) -> np.ndarray:
    """Creep part of the unit step response, sum_i c_i (1 - e^{-t/tau_i}) (eq. 5.29-5.31)."""
    t = np.asarray(t, float)[:, None]
    return (-np.expm1(-t / np.asarray(time_constants, float)[None, :])) @ np.asarray(
        fractions, float
    )
