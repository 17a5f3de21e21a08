"""Calibration results against the configuration of a simulated instrument (tests, bench):
what each experiment recovered next to the value the simulator was configured with.
"""

from __future__ import annotations

import math

import numpy as np

from afm_core.localization.calibration.creep import creep_step_response
from afm_core.localization.calibration.hysteresis import major_loop
from afm_core.localization.calibration.model import Calibration, HysteresisFit
from afm_core.pzt import PrandtlIshlinskii


def simulator_calibration(config, scanner_matrix, source: str, **fields) -> Calibration:
    """What a perfect calibration of a simulated instrument (afm_core.sim.config SimConfig)
    finds: its configured creep, positioning noise and drift statistics, with `scanner_matrix`
    (measured on a quiet copy: afm_core.evaluation.image_frame_matrix); `fields` set the rest
    (scan_region_sigma, ...). An instrument whose creep is off has no creep terms."""
    s, d = config.scanner, config.drift
    # the matrix is the images' own (a metric calibration: the images' scale), unless given
    fields.setdefault("image_matrix", np.asarray(scanner_matrix, float).tolist())
    fractions = list(s.creep_fractions) if s.creep_enabled else []
    return Calibration(
        source=source,
        scanner_matrix=np.asarray(scanner_matrix, float).tolist(),
        creep_time_constants=list(s.creep_time_constants) if fractions else [],
        creep_fractions_x=fractions,
        creep_fractions_y=list(fractions),
        motion_noise_slope_x=s.positioning_noise_slope,
        motion_noise_slope_y=s.positioning_noise_slope,
        motion_noise_cross_slope=s.positioning_noise_slope,
        motion_noise_offset=s.positioning_noise_offset,
        drift_mean_velocity=[d.mean_velocity_x, d.mean_velocity_y],
        drift_sigma_velocity=[d.sigma_velocity_x, d.sigma_velocity_y],
        **fields,
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


def compare_with_simulator(
    calibration: Calibration, report: dict, config, motion_noise_pits=None
) -> list[dict]:
    """Recovered against configured values of a simulated instrument (afm_core.sim.config
    SimConfig), one row per quantity: name, recovered, true, relative error (None where the
    true value is 0 or there is none to compare with), and what is compared.
    motion_noise_pits: the simulator's true pits (afm_core.sim Pit, in the order punched)
    from the motion-noise experiment's first on; with them the motion-noise slopes are
    compared in the images' frame, where they are measured and used (`lane_image_scales`),
    and the configured true-metre value is shown beside."""
    scales = None
    noise = report.get("motion_noise")
    if motion_noise_pits is not None and isinstance(noise, dict) and "data" in noise:
        scales = lane_image_scales(noise["data"], motion_noise_pits)
    rows = (
        _hysteresis_rows(calibration, report, config.scanner)
        + _creep_rows(calibration, config.scanner)
        + _drift_and_noise_rows(calibration, report, config, scales)
        + _image_frame_rows(calibration, config.scanner)
    )
    for row in rows:  # an experiment that failed measured nothing: say so, compare nothing
        experiment = report.get(row["name"].split(".")[0].split("[")[0], {})
        if isinstance(experiment, dict) and "failed" in experiment:
            reason = experiment["failed"]
            row.update(recovered=None, relative_error=None, note=f"not measured: {reason}")
    return rows


def _row(name: str, recovered, true, note: str = "") -> dict:
    relative = None if true in (None, 0) else (recovered - true) / abs(true)
    return {
        "name": name,
        "recovered": recovered,
        "true": true,
        "relative_error": relative,
        "note": note,
    }


def _measure_row(name: str, value, note: str) -> dict:
    """A row with nothing configured to compare with: the value is its own relative error (a
    misfit already relative to the true value)."""
    row = _row(name, value, None, note)
    row["relative_error"] = row["recovered"]
    return row


def _hysteresis_rows(calibration: Calibration, report: dict, scanner) -> list[dict]:
    rows = []
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
        rows.append(
            _row(
                f"hysteresis_{axis}.loop_fraction",
                fit.loop_fraction,
                scanner.hysteresis_fraction,
                "loop width / tip-to-tip span of the full-range major loop",
            )
        )
        rows.append(
            _row(
                f"hysteresis_{axis}.asymmetry",
                fit.asymmetry,
                scanner.hysteresis_asymmetry,
                "alpha of from_fraction",
            )
        )
        # a default fit (the experiment failed) has no operators to compare
        misfit = branch_error(fit, true_model, span / 2) if fit.thresholds else math.nan
        rows.append(
            _measure_row(
                f"hysteresis_{axis}.branch_error",
                misfit,
                "max branch misfit / true loop width (relative_error = the value)",
            )
        )
        gain = (report.get(f"hysteresis_{axis}") or {}).get("parameters", {}).get("gain", math.nan)
        rows.append(_row(f"hysteresis_{axis}.gain", gain, 1.0, "tip-to-tip output / input span"))
    return rows


def _creep_rows(calibration: Calibration, scanner) -> list[dict]:
    rows = []
    taus, true_taus = calibration.creep_time_constants, list(scanner.creep_time_constants)
    order = np.argsort(true_taus)
    true_fractions = np.asarray(scanner.creep_fractions)[order]
    sorted_taus = np.sort(true_taus)
    # a fit may keep fewer terms than the simulator has (creep.fit_creep_terms): then each
    # fitted term is compared with the nearest true one in log time, not the i-th
    nearest = list(range(len(taus)))
    if len(taus) != len(sorted_taus):
        nearest = [
            int(np.argmin(np.abs(np.log(sorted_taus) - np.log(tau)))) if len(sorted_taus) else -1
            for tau in taus
        ]
    for i, (tau, j) in enumerate(zip(taus, nearest)):
        if j >= 0:
            rows.append(_row(f"creep.time_constant[{i}]", tau, float(sorted_taus[j]), "s"))
    t = np.linspace(0.0, 25.0, 501)
    true_curve = creep_step_response(sorted_taus, true_fractions, t)
    for axis, fractions in (
        ("x", calibration.creep_fractions_x),
        ("y", calibration.creep_fractions_y),
    ):
        for i, (c, j) in enumerate(zip(fractions, nearest)):
            if j >= 0:
                rows.append(_row(f"creep.fractions_{axis}[{i}]", c, float(true_fractions[j])))
        curve = creep_step_response(taus, fractions, t)
        rows.append(
            _measure_row(
                f"creep.step_response_{axis}",
                float(np.max(np.abs(curve - true_curve)) / true_curve[-1]),
                "max |fitted - true| creep over 0-25 s / true creep at 25 s "
                "(relative_error = the value)",
            )
        )
    return rows


def lane_image_scales(data: dict, pits) -> list[tuple[int, float, float]]:
    """Per motion-noise lane (measure_motion_noise's data), (axis, distance, s): the images'
    length scale there, the lane's mean separation in the images over the mean of the same
    trials' true separations; the images see the noise's variance about s^2 times the true
    one (within a few %: the compensated scanner's gain also varies along a stroke).
    `pits`: the simulator's pits in the order punched, from the experiment's first on; the
    lanes punched them round by round, the x lanes and then the y lanes of each
    (motion_error._round), `punched` trials of two pits each."""
    scales = []
    for axis, lane, block in lane_pits(data, pits):
        measured, rows = matched_rows(axis, lane, block)
        along = np.array([[p.x, p.y][axis] for p in block])
        true = along[2 * rows + 1] - along[2 * rows]
        image = np.asarray(lane["separations"], float)[measured]
        scales.append((axis, lane["distance"], float(np.mean(image) / np.mean(true))))
    return scales


def matched_rows(axis: int, lane: dict, block) -> tuple[np.ndarray, np.ndarray]:
    """Which of the lane's measured trials (index into lane["rows"]) are which punched trial:
    the experiment numbers rows from the lowest pit it found, so a stray pit below the lane
    (another experiment's) shifts every number by one; the shift whose true separations
    follow the measured ones best (correlation) is taken."""
    along = np.array([[p.x, p.y][axis] for p in block])
    rows = np.asarray(lane["rows"], int)
    image = np.asarray(lane["separations"], float)
    best = None
    for shift in range(-3, 4):
        shifted = rows + shift
        inside = (shifted >= 0) & (shifted < lane["punched"])
        if inside.sum() < 3:
            continue
        true = along[2 * shifted[inside] + 1] - along[2 * shifted[inside]]
        score = float(np.corrcoef(true, image[inside])[0, 1])
        if best is None or score > best[0]:
            best = (score, np.flatnonzero(inside), shifted[inside])
    if best is None:
        raise ValueError(f"motion-noise lane {lane.get('distance')}: no trials to match")
    return best[1], best[2]


def lane_pits(data: dict, pits) -> list[tuple[int, dict, list]]:
    """(axis, lane data, the lane's pits in the order punched: A, B of trial 0, ...) of every
    motion-noise lane (see lane_image_scales)."""
    lanes = [(axis, lane) for axis in (0, 1) for lane in data["xy"[axis]]]
    ordered = sorted(lanes, key=lambda item: (item[1].get("round", 0), item[0]))
    if any("punched" not in lane or "rows" not in lane for _, lane in ordered):
        raise ValueError("motion-noise data without 'punched'/'rows' per lane: cannot match pits")
    out, first = [], 0
    for axis, lane in ordered:
        block = pits[first : first + 2 * lane["punched"]]
        first += 2 * lane["punched"]
        if len(block) < 2 * lane["punched"]:
            raise ValueError(
                f"motion_noise_pits: {len(pits)} pits, fewer than the lanes punched ({first})"
            )
        out.append((axis, lane, block))
    return out


def _drift_and_noise_rows(calibration: Calibration, report: dict, config, scales) -> list[dict]:
    scanner, drift = config.scanner, config.drift
    measured = (report.get("drift") or {}).get("parameters") or {}
    intervals = measured.get("mean_velocity_interval95", [math.nan, math.nan])
    rows = [
        _row(
            f"drift.mean_velocity_{axis}",
            calibration.drift_mean_velocity[k],
            configured,
            # the claim to check: the configured mean inside the run's own 95 % interval
            f"m/s; the run's 95 % interval +- {intervals[k]:.3g} "
            f"({abs(calibration.drift_mean_velocity[k] - configured) / intervals[k]:.2f} of it)"
            if math.isfinite(intervals[k]) and intervals[k] > 0
            else "m/s",
        )
        for k, (axis, configured) in enumerate(
            (("x", drift.mean_velocity_x), ("y", drift.mean_velocity_y))
        )
    ]
    spreads = measured.get("sigma_velocity_interval95", [[math.nan, math.nan]] * 2)
    for k, (axis, configured) in enumerate(
        (("x", drift.sigma_velocity_x), ("y", drift.sigma_velocity_y))
    ):
        low, high = spreads[k]
        inside = "inside" if low <= configured <= high else "outside"
        rows.append(
            _row(
                f"drift.sigma_velocity_{axis}",
                calibration.drift_sigma_velocity[k],
                configured,
                f"m/s; the run's 95 % interval {low:.3g}-{high:.3g} (configured {inside})"
                if math.isfinite(low) and math.isfinite(high)
                else "m/s",
            )
        )
    noise = (report.get("motion_noise") or {}).get("parameters") or dict.fromkeys(
        ("pooled_slope", "slope_x", "slope_y", "cross_slope"), math.nan
    )
    true_slope = scanner.positioning_noise_slope
    # the per-axis slopes as the calibration keeps them (motion_error.calibrated_slopes: the
    # pooled one where a component agrees with it)
    kept = {
        "pooled_slope": noise["pooled_slope"],
        "slope_x": calibration.motion_noise_slope_x,
        "slope_y": calibration.motion_noise_slope_y,
        "cross_slope": calibration.motion_noise_cross_slope,
    }
    for name, axes in (
        ("pooled_slope", (0, 1)),
        ("slope_x", (0,)),
        ("slope_y", (1,)),
        ("cross_slope", (0, 1)),
    ):
        note = "m^2/m (the simulator's noise is isotropic: every slope is the configured one)"
        truth = true_slope
        if scales:
            # the noise is configured in true metres per metre commanded; the images see it
            # times s^2 at the lanes (lane_image_scales, motion_error's module doc)
            squared = float(np.mean([s**2 for axis, _, s in scales if axis in axes]))
            truth = true_slope * squared
            physical = _row("", kept[name], true_slope)["relative_error"]
            note = (
                f"m^2/m in the images' frame: configured {true_slope:.4g} x (the lanes' image "
                f"/ true length)^2 {squared:.4f}; against the configured true-metre "
                f"value {physical:+.1%}"
                if physical is not None and math.isfinite(physical)
                else f"m^2/m in the images' frame (x {squared:.4f})"
            )
        if name != "pooled_slope":
            note += f"; fitted on its own {noise[name]:.4g}"
        rows.append(_row(f"motion_noise.{name}", kept[name], truth, note))
    rows.append(
        _row(
            "motion_noise.offset",
            calibration.motion_noise_offset,
            scanner.positioning_noise_offset,
            "m^2 (includes the pit-position noise of two pits)",
        )
    )
    return rows


def _image_frame_rows(calibration: Calibration, scanner) -> list[dict]:
    """What is measured against the image frame, with no configured value to compare with."""
    matrix = np.asarray(calibration.scanner_matrix)
    return [
        _row(
            "scanner_matrix - I (max abs)",
            float(np.max(np.abs(matrix - np.eye(2)))),
            None,
            "against the image frame: coupling and rotation cancel; configured coupling "
            f"{scanner.coupling_x_to_y}, rotation {scanner.deflection_deg} deg (absolute)",
        ),
        _row(
            "line_deflection_mean_deg",
            calibration.line_deflection_mean_deg,
            None,
            "against the image frame; configured absolute rotation "
            f"{scanner.deflection_deg} deg cancels",
        ),
        _row("line_deflection_sigma_deg", calibration.line_deflection_sigma_deg, None, ""),
        _row("map_sigma_x", calibration.map_sigma[0], None, "book Fig. 7.10: 5.0 nm"),
        _row("map_sigma_y", calibration.map_sigma[1], None, "book Fig. 7.10: 4.5 nm"),
        _row("scan_region_sigma", calibration.scan_region_sigma, None, "book Fig. 7.11: 4.7 nm"),
    ]
