"""`afm batch push|localize`: the project's benchmark sweeps as batches over seeds, one row per
seed (a trial on a fresh simulator of that seed, the same wherever it runs), so a sweep of
hundreds of seeds spreads over a cluster and a re-run does only the seeds not done.

- push: afm_core.manipulation.push_trials.push_trial (bench_pushing (b)): a strategy's plan
  run on the simulated AFM from an estimate off the truth by N(0, estimate_sigma); the error
  of the particle's true final centre to the goal, success within the tolerance.
- montecarlo: afm_core.manipulation.push_trials.monte_carlo_trial (bench_pushing (a)): the
  stochastic pushing model of one of the bench's plans with this seed's draws (500 by
  default); success probability within the tolerance, lateral / along spread, split.
- localize: afm_core.localization.trials (bench_localization): the book's Tables 7.1 / 7.2
  trial in one of its modes (the tip's error at x8, the filter's sigma, the NEES), or Table
  7.3's pit below a nanotube; with a calibration file or the simulator's oracle calibration
  (computed once per batch).

The summaries are the benches' figures over the finished rows of each strategy / mode.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from afm_core.batch.items import file_sha256

ROW_FORMAT = 1  # bump when a column's meaning changes: the rows computed before are redone
TUBE_MODES = ("table_7_3_book", "table_7_3_line_ends_at_pit")

PUSH_COLUMNS = [
    "seed",
    "strategy",
    "tolerance_m",
    "strokes",
    "completed",
    "goal_x_m",
    "goal_y_m",
    "final_x_m",
    "final_y_m",
    "error_m",
    "success",
    "along_m",
    "sideways_m",
    "sim_seconds",
]
MONTE_CARLO_COLUMNS = [
    "seed",
    "plan",
    "samples",
    "sigma_m",
    "tolerance_m",
    "strokes",
    "success_probability",
    "mean_offset_x_m",
    "mean_offset_y_m",
    "sigma_lateral_m",
    "sigma_along_m",
    "share_left",
    "share_right",
    "split_fraction",
    "bimodal",
    "bimodality_coefficient",
    "between_paths",
    "touched",
]
LOCALIZE_COLUMNS = [
    "seed",
    "mode",
    "true_error_x_m",
    "true_error_y_m",
    "estimate_error_x_m",
    "estimate_error_y_m",
    "reported_sigma_x_m",
    "reported_sigma_y_m",
    "nees",
    "nees_dof",
    "pit_distance_m",
    "lines",
    "sim_seconds",
]


def localize_modes() -> tuple[str, ...]:
    from afm_core.localization.trials import MODES_71_72

    return (*MODES_71_72, *TUBE_MODES)


def push_options(strategy="nano_hand", estimate_sigma=None, goal_distance=None, tolerance=None):
    """(what each task gets, what the configuration hash is of): every setting, defaults
    included, so a changed default is a changed configuration."""
    from afm_core.manipulation import push_trials as pt

    options = {
        "strategy": strategy,
        "estimate_sigma": pt.ESTIMATE_SIGMA if estimate_sigma is None else float(estimate_sigma),
        "goal_distance": pt.GOAL_DISTANCE if goal_distance is None else float(goal_distance),
        "tolerance": pt.TOLERANCE if tolerance is None else float(tolerance),
    }
    if strategy not in pt.STRATEGIES:
        raise ValueError(f"strategy {strategy!r}: expected one of {list(pt.STRATEGIES)}")
    for name in ("estimate_sigma", "goal_distance", "tolerance"):
        value = options[name]
        if not (math.isfinite(value) and value >= 0 and (value > 0 or name != "tolerance")):
            raise ValueError(f"{name}={value}: must be finite and >= 0 m (tolerance > 0)")
    return options, options


def monte_carlo_options(plan="nano_hand", samples=None, sigma=None, tolerance=None):
    """(task options, hashed): every setting, defaults included."""
    from afm_core.manipulation import push_trials as pt

    if plan not in pt.MC_PLANS:
        raise ValueError(f"plan {plan!r}: expected one of {list(pt.MC_PLANS)}")
    options = {
        "plan": plan,
        "samples": 500 if samples is None else samples,
        "sigma": pt.ESTIMATE_SIGMA if sigma is None else float(sigma),
        "tolerance": pt.TOLERANCE if tolerance is None else float(tolerance),
    }
    if not (isinstance(options["samples"], int) and 1 <= options["samples"] <= 100_000):
        raise ValueError(f"samples={samples}: must be an integer within [1, 100000]")
    if not (math.isfinite(options["sigma"]) and options["sigma"] >= 0):
        raise ValueError(f"sigma={sigma}: must be finite and >= 0 m")
    if not (math.isfinite(options["tolerance"]) and options["tolerance"] > 0):
        raise ValueError(f"tolerance={tolerance}: must be finite and > 0 m")
    return options, options


def localize_options(mode="via_landmark_toward_x8", calibration=None):
    """(task options, hashed): the mode and the calibration file (by its content) or the
    simulator's oracle calibration."""
    if mode not in localize_modes():
        raise ValueError(f"mode {mode!r}: expected one of {list(localize_modes())}")
    if calibration and not Path(calibration).is_file():
        raise ValueError(f"calibration {str(calibration)!r}: no such calibration file")
    path = str(Path(calibration).resolve()) if calibration else None
    hashed = {"mode": mode, "calibration": file_sha256(path) if path else "sim_oracle"}
    return {"mode": mode, "calibration": path}, hashed


def prepare_calibration(path: str | None, mode: str):
    """The calibration every trial of the batch uses (run once, as one task): the file's, or
    the oracle one (bench_localization's); for Table 7.3 with the high-resolution map's sigma
    and, for the oracle, the scan-region sigma measured across the tube."""
    from afm_core.localization import trials
    from afm_core.localization.calibration.model import load_calibration

    calibration = load_calibration(path) if path else trials.sim_oracle_calibration()
    if mode not in TUBE_MODES:
        return calibration
    sigma = trials.HIRES_MAP_SIGMA
    hires = dataclasses.replace(calibration, map_sigma=[sigma, sigma])
    if path is None:
        matrix = np.array(calibration.scanner_matrix)
        tube = trials.measure_scan_region_sigma(matrix, "tube")
        hires = dataclasses.replace(hires, scan_region_sigma=tube)
    return hires


def push_row(seed: int, options: dict) -> dict:
    from afm_core.manipulation.push_trials import push_trial

    trial = push_trial(
        seed,
        options["strategy"],
        options["estimate_sigma"],
        goal_distance=options["goal_distance"],
        tolerance=options["tolerance"],
    )
    return {
        "seed": seed,
        "strategy": trial["strategy"],
        "tolerance_m": options["tolerance"],
        "strokes": trial["strokes"],
        "completed": trial["completed"],
        "goal_x_m": float(trial["goal"][0]),
        "goal_y_m": float(trial["goal"][1]),
        "final_x_m": float(trial["final"][0]),
        "final_y_m": float(trial["final"][1]),
        "error_m": trial["error"],
        "success": trial["success"],
        "along_m": trial["along"],
        "sideways_m": trial["sideways"],
        "sim_seconds": trial["sim_seconds"],
    }


def monte_carlo_row(seed: int, options: dict) -> dict:
    from afm_core.manipulation.push_trials import monte_carlo_trial

    r = monte_carlo_trial(
        seed,
        options["plan"],
        samples=options["samples"],
        sigma=options["sigma"],
        tolerance=options["tolerance"],
    )
    offset = r.mean - r.goal
    return {
        "seed": seed,
        "plan": options["plan"],
        "samples": r.samples,
        "sigma_m": options["sigma"],
        "tolerance_m": r.tolerance,
        "strokes": r.strokes_applied,
        "success_probability": r.success_probability,
        "mean_offset_x_m": float(offset[0]),
        "mean_offset_y_m": float(offset[1]),
        "sigma_lateral_m": r.sigma_lateral,
        "sigma_along_m": r.sigma_along,
        "share_left": r.share_left,
        "share_right": r.share_right,
        "split_fraction": r.split_fraction,
        "bimodal": r.bimodal,
        "bimodality_coefficient": r.bimodality_coefficient,
        "between_paths": r.between_paths,
        "touched": r.touched,
    }


def localize_row(seed: int, options: dict, calibration) -> dict:
    from afm_core.localization import trials

    mode = options["mode"]
    if mode in TUBE_MODES:
        trial = trials.table_73_trial(seed, calibration, mode == TUBE_MODES[1])
        return {
            "seed": seed,
            "mode": mode,
            "reported_sigma_y_m": float(trial["reported_sigma"]),
            "nees": float(trial["nees"]),
            "nees_dof": 1,
            "pit_distance_m": float(trial["distance"]),
            "lines": ";".join(trial["lines"]),
        }
    trial = trials.table_71_72_trial(seed, calibration, mode)
    return {
        "seed": seed,
        "mode": mode,
        "true_error_x_m": float(trial["true_error"][0]),
        "true_error_y_m": float(trial["true_error"][1]),
        "estimate_error_x_m": float(trial["estimate_error"][0]),
        "estimate_error_y_m": float(trial["estimate_error"][1]),
        "reported_sigma_x_m": float(trial["reported_sigma"][0]),
        "reported_sigma_y_m": float(trial["reported_sigma"][1]),
        "nees": trial["nees"],
        "nees_dof": 2,
        "lines": ";".join(f"{axis}:{status}" for axis, status, _ in trial["lines"]),
        "sim_seconds": trial["sim_time_s"],
    }


# -- summaries ------------------------------------------------------------------------------------
def _groups(rows: list[dict], column: str) -> dict[str, list[dict]]:
    groups: dict[str, list[dict]] = {}
    for row in rows:
        if row.get("status") == "ok":
            groups.setdefault(row.get(column, ""), []).append(row)
    return dict(sorted(groups.items()))


def _values(rows: list[dict], column: str) -> np.ndarray:
    return np.array([float(r[column]) for r in rows if r.get(column) not in (None, "")])


def summarise_push(rows: list[dict]) -> dict:
    """Per strategy, bench_pushing's figures: success rate within the tolerance, the error's
    median and maximum, the along / sideways displacement's mean and spread."""
    out = {"failed": sum(1 for r in rows if r.get("status") == "failed"), "strategies": {}}
    for strategy, group in _groups(rows, "strategy").items():
        error, along, side = (_values(group, c) for c in ("error_m", "along_m", "sideways_m"))
        out["strategies"][strategy] = {
            "runs": len(group),
            "tolerance_m": sorted({float(r["tolerance_m"]) for r in group}),
            "success_rate": sum(r["success"] == "True" for r in group) / len(group),
            "error_median_m": float(np.median(error)),
            "error_max_m": float(error.max()),
            "along_mean_m": float(along.mean()),
            "along_sd_m": float(along.std()),
            "sideways_mean_m": float(side.mean()),
            "sideways_sd_m": float(side.std()),
            "sideways_abs_max_m": float(np.abs(side).max()),
        }
    return out


def summarise_monte_carlo(rows: list[dict]) -> dict:
    """Per plan, bench_pushing (a)'s figures averaged over the seeds, with the seed-to-seed
    spread (sample sd) of the success probability: how far one seed's estimate can be off."""
    out = {"failed": sum(1 for r in rows if r.get("status") == "failed"), "plans": {}}
    for plan, group in _groups(rows, "plan").items():
        success = _values(group, "success_probability")
        between = _values(group, "between_paths")
        out["plans"][plan] = {
            "seeds": len(group),
            "samples": sorted({int(r["samples"]) for r in group}),
            "tolerance_m": sorted({float(r["tolerance_m"]) for r in group}),
            "success_mean": float(success.mean()),
            "success_sd": float(success.std(ddof=1)) if len(group) > 1 else math.nan,
            "sigma_lateral_mean_m": float(_values(group, "sigma_lateral_m").mean()),
            "sigma_along_mean_m": float(_values(group, "sigma_along_m").mean()),
            "split_mean": float(_values(group, "split_fraction").mean()),
            "bimodal_share": sum(r["bimodal"] == "True" for r in group) / len(group),
            "between_paths_mean": float(between.mean()) if between.size else math.nan,
        }
    return out


def monte_carlo_markdown(summary: dict) -> str:
    lines = [
        "# Push Monte Carlo model over seeds (afm batch montecarlo)",
        "",
        f"{summary['failed']} seeds failed (results.csv has each one's error).",
        "",
        "| plan | seeds | draws | tolerance (nm) | success (mean +- sd over seeds) "
        "| lateral sigma (nm) | along sigma (nm) | split | bimodal seeds | between paths |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for plan, s in summary["plans"].items():
        between = "-" if math.isnan(s["between_paths_mean"]) else f"{s['between_paths_mean']:.2f}"
        lines.append(
            f"| {plan} | {s['seeds']} | {', '.join(map(str, s['samples']))} | "
            f"{', '.join(_nm(t) for t in s['tolerance_m'])} | "
            f"{s['success_mean']:.3f} +- {s['success_sd']:.3f} | "
            f"{_nm(s['sigma_lateral_mean_m'])} | {_nm(s['sigma_along_mean_m'])} | "
            f"{s['split_mean']:.3f} | {s['bimodal_share']:.2f} | {between} |"
        )
    return "\n".join(lines) + "\n"


def summarise_localize(rows: list[dict]) -> dict:
    """Per mode, bench_localization's figures: the true error's sigma (sample, ddof 1) and
    mean at x8, the filter's mean sigma, the mean NEES against the 95 % band of a consistent
    filter; for Table 7.3 the pit's distance from the tube, mean and sigma."""
    from afm_core.localization.trials import nees_band

    out = {"failed": sum(1 for r in rows if r.get("status") == "failed"), "modes": {}}
    for mode, group in _groups(rows, "mode").items():
        nees, dof = _values(group, "nees"), int(float(group[0]["nees_dof"]))
        band = nees_band(len(group), dof=dof)
        s = {
            "trials": len(group),
            "nees_dof": dof,
            "mean_nees": float(nees.mean()),
            "nees_band_95": band,
            "nees_consistent": bool(band[0] <= nees.mean() <= band[1]),
            "reported_sigma_y_mean_m": float(_values(group, "reported_sigma_y_m").mean()),
        }
        if mode in TUBE_MODES:
            distance = _values(group, "pit_distance_m")
            s["pit_distance_mean_m"] = float(distance.mean())
            s["pit_distance_sigma_m"] = float(distance.std(ddof=1)) if len(group) > 1 else math.nan
        else:
            true = np.stack([_values(group, "true_error_x_m"), _values(group, "true_error_y_m")])
            s["true_error_sigma_m"] = (
                true.std(axis=1, ddof=1).tolist() if len(group) > 1 else [math.nan] * 2
            )
            s["true_error_mean_m"] = true.mean(axis=1).tolist()
            s["true_error_rms_radial_m"] = float(np.sqrt(np.mean(np.sum(true**2, axis=0))))
            s["reported_sigma_x_mean_m"] = float(_values(group, "reported_sigma_x_m").mean())
        out["modes"][mode] = s
    return out


def _nm(value: float) -> str:
    return f"{value * 1e9:.1f}"


def push_markdown(summary: dict) -> str:
    lines = [
        "# Push trials on the simulated AFM (afm batch push)",
        "",
        f"{summary['failed']} seeds failed (results.csv has each one's error).",
        "",
        "| strategy | seeds | tolerance (nm) | success | median error (nm) | max error (nm) "
        "| along (nm) | sideways (nm) | max sideways (nm) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name, s in summary["strategies"].items():
        tolerance = ", ".join(_nm(t) for t in s["tolerance_m"])
        lines.append(
            f"| {name} | {s['runs']} | {tolerance} | {s['success_rate']:.2f} | "
            f"{_nm(s['error_median_m'])} | {_nm(s['error_max_m'])} | "
            f"{_nm(s['along_mean_m'])} +- {_nm(s['along_sd_m'])} | "
            f"{_nm(s['sideways_mean_m'])} +- {_nm(s['sideways_sd_m'])} | "
            f"{_nm(s['sideways_abs_max_m'])} |"
        )
    return "\n".join(lines) + "\n"


def localize_markdown(summary: dict) -> str:
    lines = [
        "# Tip localization trials on the simulated AFM (afm batch localize)",
        "",
        f"{summary['failed']} seeds failed (results.csv has each one's error).",
        "",
        "| mode | seeds | true error sigma x, y (nm) | mean x, y (nm) | filter sigma x, y (nm) "
        "| pit distance (nm) | mean NEES (95 % band) |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for mode, s in summary["modes"].items():
        lo, hi = s["nees_band_95"]
        flag = "" if s["nees_consistent"] else " **outside**"
        if mode in TUBE_MODES:
            cells = (
                "-",
                "-",
                f"-, {_nm(s['reported_sigma_y_mean_m'])}",
                f"{_nm(s['pit_distance_mean_m'])} +- {_nm(s['pit_distance_sigma_m'])}",
            )
        else:
            cells = (
                ", ".join(_nm(v) for v in s["true_error_sigma_m"]),
                ", ".join(_nm(v) for v in s["true_error_mean_m"]),
                f"{_nm(s['reported_sigma_x_mean_m'])}, {_nm(s['reported_sigma_y_mean_m'])}",
                "-",
            )
        lines.append(
            f"| {mode} | {s['trials']} | {' | '.join(cells)} | "
            f"{s['mean_nees']:.2f} ({s['nees_dof']} dof) [{lo:.2f}, {hi:.2f}]{flag} |"
        )
    return "\n".join(lines) + "\n"
