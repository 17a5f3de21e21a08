"""The whole calibration of book 7.2.2, run on an instrument, fitted, and returned as one
`Calibration` (model.py) for the localizer, with a report of every experiment.

ROS-free: every experiment takes an `afm_core.instrument.Instrument` (the simulated AFM, or
the DAQ driver on the real one) and uses only its public calls (move_tip, indent,
raster_scan, local_scan, commanded_position, time), plus two the experiments need:
`hold(seconds)` (falls back to waiting on the wall clock) and, for the hysteresis
experiment alone, a `feed_forward_enabled` switch (the controller's inverse-PI feed-forward
off = the raw drive the book applies). Each experiment returns an `Experiment`: the fitted
parameters and the raw data for a plot (plain lists, JSON-ready).

Experiments (`run_calibration` runs the drift pairs first, then the others in this order):
- `measure_creep` (creep.py): a large step, then pits along the other axis over `duration`
  s; creep time constants (shared) and fractions (per axis) by nonlinear least squares
  (eq. 5.29-5.31, Fig. 7.7).
- `measure_hysteresis` (hysteresis.py): feed-forward off, a full-range voltage cycle with a
  pit every 4th step on the descending and the ascending sweep, feed-forward on, rescan; PI
  weights for fixed thresholds by non-negative least squares, the input asymmetry by a 1-D
  search (eq. 5.22-5.23, Fig. 7.6a). The measured creep is part of the model.
- `measure_scanner_matrix` (scanner_matrix.py): a grid of pits at commanded offsets; the
  affine map commanded -> imaged displacement.
- `measure_motion_noise` (motion_error.py): repeated moves of several lengths, a pit before
  and after each; variance of the separations about their mean vs distance:
  sigma^2 = a d + b (Fig. 7.6e, Fig. 7.20b).
- `measure_line_deflection` (line_deflection.py): pits at both ends of local scan lines
  (Fig. 7.12).
- `measure_drift` (drift_statistics.py): frame-up / frame-down image pairs of a particle
  area, apart in time (eq. 5.32-5.36, Fig. 7.9); the same frames give the map error
  (Fig. 7.10) and the scan-region error (Fig. 7.11), `map_errors` (map_errors.py).
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import time as wallclock
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from afm_core.localization.calibration.creep import measure_creep
from afm_core.localization.calibration.drift_statistics import measure_drift
from afm_core.localization.calibration.fit_checks import calibration_checks
from afm_core.localization.calibration.hysteresis import (
    hysteresis_fit_of,
    measure_hysteresis,
    measure_hysteresis_once,
)
from afm_core.localization.calibration.line_deflection import measure_line_deflection
from afm_core.localization.calibration.map_errors import map_errors
from afm_core.localization.calibration.model import Calibration
from afm_core.localization.calibration.motion_error import calibrated_slopes, measure_motion_noise
from afm_core.localization.calibration.scanner_matrix import measure_scanner_matrix

# What an experiment that cannot measure raises (too few pits found, a fit that does not
# converge, an instrument refusing a move); anything else is a bug and propagates.
EXPERIMENT_FAILURES = (ValueError, RuntimeError, ArithmeticError, np.linalg.LinAlgError)


# The experiments in the order run_calibration runs them (for progress: "k of n").
EXPERIMENTS = (
    "drift",
    "map_errors",
    "creep",
    "hysteresis_x",
    "hysteresis_y",
    "scanner_matrix",
    "motion_noise",
    "line_deflection",
)


# Which experiment measures which Calibration field (for `measured`, `--only` and merging).
# what no experiment here can measure, by design not a fallback to the book: the images' own
# branch is the identity in the images' frame, and their scale needs a grating (model.Calibration)
FRAME_FIELDS = ("image_matrix", "lateral_scale")
FIELDS = {
    "drift": ("drift_mean_velocity", "drift_sigma_velocity"),
    "map_errors": ("map_sigma", "scan_region_sigma"),
    "creep": ("creep_time_constants", "creep_fractions_x", "creep_fractions_y"),
    "hysteresis_x": ("hysteresis_x",),
    "hysteresis_y": ("hysteresis_y",),
    "scanner_matrix": ("scanner_matrix", "scanner_matrix_span"),
    "motion_noise": (
        "motion_noise_slope_x",
        "motion_noise_slope_y",
        "motion_noise_cross_slope",
        "motion_noise_offset",
    ),
    "line_deflection": ("line_deflection_mean_deg", "line_deflection_sigma_deg"),
}


# `afm calibrate --set EXPERIMENT.OPTION=VALUE`: which run_calibration keyword and measuring
# function take an experiment's options; the arguments run_calibration supplies itself are not
# options.
OPTION_FUNCTIONS = {
    "drift": measure_drift,
    "creep": measure_creep,
    "hysteresis": measure_hysteresis_once,
    "scanner_matrix": measure_scanner_matrix,
    "motion_noise": measure_motion_noise,
    "line_deflection": measure_line_deflection,
}
NOT_OPTIONS = {"instrument", "axis", "creep", "ignore", "progress"}


def experiment_options(settings) -> dict:
    """{keyword: {option: value}} for run_calibration from "EXPERIMENT.OPTION=VALUE" texts
    (VALUE a number, or numbers separated by commas for a list); ValueError naming the first
    bad one and the valid choices, before any experiment runs (e.g. a smaller geometry for a
    small scanner: "creep.step=4e-6")."""
    options: dict = {}
    for text in settings or ():
        name, _, value = str(text).partition("=")
        experiment, _, option = name.strip().partition(".")
        if experiment not in OPTION_FUNCTIONS or not value.strip():
            raise ValueError(
                f"--set {text!r}: need EXPERIMENT.OPTION=VALUE, EXPERIMENT one of "
                f"{', '.join(OPTION_FUNCTIONS)}"
            )
        valid = [
            p
            for p in inspect.signature(OPTION_FUNCTIONS[experiment]).parameters
            if p not in NOT_OPTIONS
        ]
        if option not in valid:
            raise ValueError(
                f"--set {text!r}: {experiment} has no option {option!r}; choose from "
                f"{', '.join(valid)}"
            )
        try:
            numbers = [_number(part) for part in value.split(",")]
        except ValueError:
            raise ValueError(
                f"--set {text!r}: {value!r} is not a number or a list of numbers"
            ) from None
        options.setdefault(experiment, {})[option] = numbers[0] if len(numbers) == 1 else numbers
    return options


def _number(text: str):
    text = text.strip()
    try:
        return int(text)
    except ValueError:
        return float(text)


def checked_experiments(only) -> tuple[str, ...]:
    """The experiments of `only` (names of EXPERIMENTS) in run order; ValueError naming the
    bad choice and the valid ones. map_errors comes from the drift frames, so it needs drift."""
    if only is None:
        return EXPERIMENTS
    chosen = [str(name) for name in only]
    unknown = sorted(set(chosen) - set(EXPERIMENTS))
    if unknown or not chosen:
        raise ValueError(
            f"only={chosen}: unknown experiment(s) {unknown}; choose from {', '.join(EXPERIMENTS)}"
        )
    if "map_errors" in chosen and "drift" not in chosen:
        raise ValueError("only: map_errors is measured on the drift frames; add drift")
    return tuple(name for name in EXPERIMENTS if name in chosen)


def merge_calibration(previous: Calibration, new: Calibration, experiments) -> Calibration:
    """`previous` with the fields the `experiments` of a rerun measured taken from `new`
    (a field the rerun could not measure keeps the previous value and mark); `measured` and
    `defaults` follow each field."""
    values = {f.name: getattr(previous, f.name) for f in dataclasses.fields(Calibration)}
    measured, defaults = dict(previous.measured), set(previous.defaults)
    for experiment in experiments:
        for name in FIELDS.get(experiment, ()):
            if name in new.measured:
                values[name] = getattr(new, name)
                measured[name] = new.measured[name]
                defaults.discard(name)
    values.update(
        source=f"{previous.source}; merged with {new.source} ({', '.join(experiments)})",
        measured=measured,
        defaults=sorted(defaults),
    )
    return Calibration(**values)


def _attempt(report: dict, name: str, measure, progress=None, instrument=None):
    """Run one experiment; a failure is recorded with its reason and the run goes on.
    `progress(text)`, if given, hears when it starts and how it ended (wall and instrument
    seconds: on the real instrument the experiments take hours)."""
    chosen = report.get("_chosen", EXPERIMENTS)
    number, total = chosen.index(name) + 1, len(chosen)
    if report.get("_interrupted"):  # Ctrl-C: what was measured is kept, nothing more is run
        report[name] = None
        report.setdefault("_failed", {})[name] = "not run (interrupted)"
        return None
    wall0 = wallclock.perf_counter()
    clock0 = float(instrument.time) if instrument is not None else 0.0
    if progress is not None:
        progress(f"experiment {number} of {total}: {name} ...")
    try:
        report[name] = measure()
        outcome = "done"
    except EXPERIMENT_FAILURES as exc:
        report[name] = None
        report.setdefault("_failed", {})[name] = f"{type(exc).__name__}: {exc}"
        outcome = f"failed ({type(exc).__name__}: {exc})"
    except KeyboardInterrupt:
        # hours of experiments done before this one are worth a file: the run ends here and
        # returns them, this one and the rest listed as not measured
        report[name] = None
        report.setdefault("_failed", {})[name] = "interrupted (Ctrl-C)"
        report["_interrupted"] = True
        outcome = "interrupted"
    if progress is not None:
        spent = float(instrument.time) - clock0 if instrument is not None else 0.0
        progress(
            f"experiment {number} of {total}: {name} {outcome} in "
            f"{wallclock.perf_counter() - wall0:.0f} s ({spent:.0f} s of instrument time)"
        )
    return report[name]


def _calibration_fields(report: dict) -> dict:
    """The Calibration fields the successful experiments measured."""
    fields: dict = {}
    if report.get("drift") is not None:
        drift = report["drift"].parameters
        fields["drift_mean_velocity"] = list(drift["mean_velocity"])
        fields["drift_sigma_velocity"] = list(drift["sigma_velocity"])
    if report.get("map_errors") is not None:
        errors = report["map_errors"].parameters
        fields["map_sigma"] = list(errors["map_sigma"])
        fields["scan_region_sigma"] = float(errors["scan_region_sigma"])
    if report.get("creep") is not None:
        creep = report["creep"].parameters
        fields["creep_time_constants"] = list(creep["time_constants"])
        fields["creep_fractions_x"] = list(creep["fractions_x"])
        fields["creep_fractions_y"] = list(creep["fractions_y"])
    for axis in ("x", "y"):
        if report.get(f"hysteresis_{axis}") is not None:
            fields[f"hysteresis_{axis}"] = hysteresis_fit_of(report[f"hysteresis_{axis}"])
    if report.get("scanner_matrix") is not None:
        fields["scanner_matrix"] = report["scanner_matrix"].parameters["scanner_matrix"]
        if "span" in report["scanner_matrix"].parameters:
            fields["scanner_matrix_span"] = report["scanner_matrix"].parameters["span"]
    if report.get("motion_noise") is not None:
        noise = report["motion_noise"].parameters
        slopes = calibrated_slopes(noise) if "pooled_slope_sigma" in noise else noise
        fields["motion_noise_slope_x"] = max(0.0, slopes["slope_x"])
        fields["motion_noise_slope_y"] = max(0.0, slopes["slope_y"])
        fields["motion_noise_cross_slope"] = max(0.0, slopes["cross_slope"])
        fields["motion_noise_offset"] = max(0.0, 0.5 * (noise["offset_x"] + noise["offset_y"]))
    if report.get("line_deflection") is not None:
        deflection = report["line_deflection"].parameters
        fields["line_deflection_mean_deg"] = float(deflection["mean_deg"])
        fields["line_deflection_sigma_deg"] = float(deflection["sigma_deg"])
    return fields


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
    progress=None,
    only=None,
    previous: Calibration | None = None,
) -> tuple[Calibration, dict]:
    """All experiments, in an order where each can use what the previous measured (creep
    before hysteresis: the hysteresis fit includes it; drift, map and scan-region errors
    first, before there are pits). Each keyword is that experiment's options
    (see its function). Returns the Calibration and a report {experiment: {"parameters",
    "data"}} (the drift frames are left out of the report; `map_errors` has used them) with
    the fit checks under "checks" (fit_checks.calibration_checks).

    An experiment that cannot measure (EXPERIMENT_FAILURES) does not stop the others: its
    report entry is {"failed": reason}, its Calibration fields keep the book's defaults and
    are listed in `Calibration.defaults`, so the file still carries every result measured
    (a hysteresis fit then goes without the creep term, the y sweep without the x sweep's pit
    list). `progress(text)`, if given, hears each experiment's start and end.

    only: run just these experiments (names of EXPERIMENTS; `checked_experiments`), e.g. to
    repeat one a check flagged; `previous` (a Calibration) then supplies what they use from
    the others (the creep model of the hysteresis fit); merge the result into it with
    `merge_calibration`."""
    chosen = checked_experiments(only)
    report: dict = {"_chosen": chosen}

    def attempt(name, measure):
        return _attempt(report, name, measure, progress, instrument) if name in chosen else None

    started = wallclock.perf_counter()
    clock0 = float(instrument.time)
    # Drift first: it needs no pits, and on the simulator every image gets slower with every
    # pit on the sample (hundreds by the end), which matters for ~100 hours of frame pairs.
    drift_result = attempt(
        "drift", lambda: measure_drift(instrument, progress=progress, **(drift or {}))
    )
    if drift_result is not None:
        frames = drift_result.data.pop("frames")
        attempt("map_errors", lambda: map_errors(frames))
        del frames
    elif "map_errors" in chosen:
        report["map_errors"] = None
        report["_failed"]["map_errors"] = "no drift frames (the drift experiment failed)"
    result = attempt(
        "creep", lambda: measure_creep(instrument, progress=progress, **(creep or {}))
    )
    creep_axes = _creep_axes(result, previous)
    options = dict(hysteresis or {})
    first = attempt(
        "hysteresis_x",
        lambda: measure_hysteresis(
            instrument, 0, creep=creep_axes[0], progress=progress, **options
        ),
    )
    ignore = first.data["all_detected"] if first is not None else None
    attempt(
        "hysteresis_y",
        lambda: measure_hysteresis(
            instrument, 1, creep=creep_axes[1], ignore=ignore, progress=progress, **options
        ),
    )
    attempt(
        "scanner_matrix",
        lambda: measure_scanner_matrix(instrument, **(scanner_matrix or {})),
    )
    attempt(
        "motion_noise",
        lambda: measure_motion_noise(instrument, progress=progress, **(motion_noise or {})),
    )
    attempt(
        "line_deflection",
        lambda: measure_line_deflection(instrument, **(line_deflection or {})),
    )
    report.pop("_chosen")
    interrupted = report.pop("_interrupted", False)
    failed = report.pop("_failed", {})
    fields = _accepted_fields(_calibration_fields(report), failed)
    stamp = datetime.now(timezone.utc).isoformat(timespec="seconds")
    calibration = Calibration(
        source=source or f"afm_core.localization.calibration.procedure.run_calibration, {stamp}",
        **fields,
    )
    calibration.measured = {
        name: f"{experiment}, {stamp}"
        for experiment, names in FIELDS.items()
        for name in names
        if name in fields
    }
    calibration.defaults = sorted(
        f.name
        for f in dataclasses.fields(Calibration)
        if f.name not in fields and f.name not in ("source", "defaults", "measured", *FRAME_FIELDS)
    )
    summary = {
        name: {"failed": failed[name]}
        if value is None
        else {"parameters": value.parameters, "data": value.data}
        for name, value in report.items()
    }
    for name, reason in failed.items():  # measured, but refused by the Calibration's checks
        if report.get(name) is not None:
            summary[name]["failed"] = reason
    summary["checks"] = calibration_checks(summary)
    summary["interrupted"] = interrupted
    summary["instrument_seconds"] = float(instrument.time) - clock0
    summary["wall_seconds"] = wallclock.perf_counter() - started
    return calibration, summary


def _accepted_fields(fields: dict, failed: dict) -> dict:
    """`fields` less each experiment's whose values the Calibration refuses (a fit outside its
    limits, e.g. a time constant of 0 s): those keep the defaults and the experiment is
    marked failed with the reason, so the file is still written with the rest."""
    accepted = dict(fields)
    for experiment, names in FIELDS.items():
        own = {name: fields[name] for name in names if name in fields}
        if not own:
            continue
        try:
            Calibration(**own)
        except ValueError as exc:
            failed[experiment] = f"fit refused by the calibration's checks: {exc}"
            for name in own:
                accepted.pop(name)
    return accepted


def _creep_axes(result, previous: Calibration | None) -> list:
    """The creep model (time constants, fractions) per axis for the hysteresis fit: this run's
    creep experiment, else a previous calibration's measured creep, else none."""
    if result is not None:
        taus = result.parameters["time_constants"]
        return [(taus, result.parameters["fractions_x"]), (taus, result.parameters["fractions_y"])]
    if previous is not None and previous.creep_time_constants:
        taus = previous.creep_time_constants
        return [(taus, previous.creep_fractions_x), (taus, previous.creep_fractions_y)]
    return [None, None]


def report_json(summary: dict) -> str:
    """The report of `run_calibration` as JSON: every experiment's fitted parameters and raw
    data (SI; arrays as lists), and the instrument and wall seconds. A person or a script can
    check each fit against its data."""

    def plain(value):
        if hasattr(value, "tolist"):
            return value.tolist()
        if hasattr(value, "__dict__"):
            return vars(value)
        return str(value)

    return json.dumps(summary, indent=2, default=plain)


# The fitted numbers a person reads first, per experiment (the rest is in the JSON report).
HEADLINE = {
    "drift": (
        "mean_velocity",
        "mean_velocity_interval95",
        "sigma_velocity",
        "sigma_velocity_interval95",
        "pairs",
    ),
    "map_errors": ("map_sigma", "scan_region_sigma"),
    "creep": (
        "time_constants",
        "time_constants_sigma",
        "fractions_x",
        "fractions_y",
        "step_response_25s",
        "rms_residual",
    ),
    "hysteresis_x": ("loop_fraction", "loop_fraction_sigma", "asymmetry", "gain", "rms_residual"),
    "hysteresis_y": ("loop_fraction", "loop_fraction_sigma", "asymmetry", "gain", "rms_residual"),
    "scanner_matrix": ("scanner_matrix", "span", "rms_residual"),
    "motion_noise": ("pooled_slope", "pooled_slope_sigma", "slope_x", "slope_y", "cross_slope"),
    "line_deflection": ("mean_deg", "sigma_deg"),
}


def report_markdown(summary: dict, figures: dict | None = None) -> str:
    """The report of `run_calibration` for a person: per experiment measured or failed (why),
    its headline parameters (SI), then every check with its level, warnings first, then the
    `figures` ({experiment: path relative to the report}, figures.calibration_figures) of the
    raw data and the fits."""

    def shown(value):
        if isinstance(value, (list, tuple)):
            return "[" + ", ".join(shown(v) for v in value) + "]"
        return f"{value:.4g}" if isinstance(value, float) else str(value)

    lines = [
        "# Calibration report",
        "",
        "| experiment | outcome | parameters (SI) |",
        "|---|---|---|",
    ]
    for name in EXPERIMENTS:
        entry = summary.get(name)
        if not isinstance(entry, dict):
            continue
        if "failed" in entry:
            lines.append(f"| {name} | failed | {entry['failed'].replace('|', '/')} |")
            continue
        parameters = entry["parameters"]
        text = "; ".join(
            f"{key} {shown(parameters[key])}" for key in HEADLINE[name] if key in parameters
        )
        lines.append(f"| {name} | measured | {text} |")
    checks = sorted(
        summary.get("checks", []), key=lambda c: ("error", "warning", "ok").index(c["level"])
    )
    lines += ["", "## Checks", ""]
    lines += [f"- **{c['level']}** {c['experiment']}: {c['message']}" for c in checks]
    if figures:
        lines += ["", "## Raw data and fits", ""]
        lines += [f"![{name}]({Path(path).as_posix()})" for name, path in figures.items()]
    lines += [
        "",
        f"Instrument time {summary.get('instrument_seconds', 0.0) / 3600:.2f} h, wall "
        f"{summary.get('wall_seconds', 0.0):.0f} s. Raw data: the JSON report.",
    ]
    return "\n".join(lines) + "\n"
