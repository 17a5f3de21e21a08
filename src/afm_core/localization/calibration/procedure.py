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

import json
import time as wallclock
from datetime import datetime, timezone

from afm_core.localization.calibration.creep import measure_creep
from afm_core.localization.calibration.drift_statistics import measure_drift
from afm_core.localization.calibration.hysteresis import hysteresis_fit_of, measure_hysteresis
from afm_core.localization.calibration.line_deflection import measure_line_deflection
from afm_core.localization.calibration.map_errors import map_errors
from afm_core.localization.calibration.model import Calibration
from afm_core.localization.calibration.motion_error import measure_motion_noise
from afm_core.localization.calibration.scanner_matrix import measure_scanner_matrix


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
        source=source or f"afm_core.localization.calibration.procedure.run_calibration, {stamp}",
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
