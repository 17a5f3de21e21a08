"""Tip localization experiments of the book (7.2.3-7.2.4) on the simulated AFM.

What is measured
----------------
1. Tables 7.1 / 7.2 (Fig. 5.14, 7.13): the tip goes from x0 to x8 (book geometry, positions in
   um relative to the image centre, which is the scanner's centre here):
     direct:        x0 (-1.245, 1.316) -> xd_1 (-1.245, -1.381) -> x8 (1.101, -1.471)
     via landmark:  x0 -> x1 (-1.245, -0.645) -> horizontal line through the particle at
                    (0.801, -0.684) (r = 100 nm) -> vertical line through it (scanning down)
                    -> x7 (estimate's x, -1.471) -> x8
     via landmark, straight: the same two lines, then one straight free move x6 -> x8, as
                    our graph does it (the Localize action's two lines, then the nano-hand's or
                    the planner's move to the task point): the positioning noise of a free move
                    grows with its length (sigma^2 = a d + b), so one diagonal move after the
                    last update leaves less than the book's two axis-aligned ones
     via landmark, toward x8: the Localize action with `toward` = x8 (Localizer.observe_landmark
                    toward=x8): the book's lines, but the vertical line is continued down to
                    x7 = (particle x, x8 y), so x6 -> x7 is scan-line motion, not a free move;
                    then x7 -> x8
   The book's free moves are axis-aligned. Per trial: a fresh simulator (own seed:
   positioning noise, drift velocity, sensor noise), the tip moved to x0 and left 250 s to
   settle (creep), then the localizer starts there with the book's assumed initial
   distribution, sigma (13, 16) nm (Table 7.1 x0), its mean drawn from N(truth, P0).
   Reported at x8: the spread (sample sigma over the trials) of the true error
   (true tip - x8), its mean (bias), the filter's mean reported sigma, and the mean NEES
   (estimate - truth)^T P^-1 (estimate - truth) with its two-sided 95 % band for a
   consistent filter: [chi2.ppf(0.025, 2 N) / N, chi2.ppf(0.975, 2 N) / N].
2. Table 7.3 / Fig. 7.21-7.22: a carbon-nanotube-like tube (radius 10 nm, 3 um long,
   horizontal) mapped with a high-resolution map (sigma 0.8 nm, "< 1 nm"); the tip starts
   250 nm below it (sigma 10 nm, Table 7.4), scans up across it (update), scans back down
   across it (update) and punches a pit 130 nm below the tube's centre. Reported: distance of
   the pit (where the tip truly was) from the tube's true axis, mean and sigma over trials.
   Two variants: "book" (the down line ends clear of the tube, then a free move of ~40 nm to
   the pit, as in Fig. 7.21) and "line_ends_at_pit" (the down line is planned to end at the
   pit position, so only a ~1 nm correction move, by what the line's own update changed,
   comes after the last update: scan-line motion carries no positioning noise in the
   simulator and in the motion model, a free move does).

Landmark positions in the task frame: the particle's / tube's true position plus a draw from
the map error model (map sigma of the calibration: 5.0 / 4.5 nm, Fig. 7.10; 0.8 nm for the
high-resolution map), and that map covariance as the landmark's covariance. A map from a
raster scan + extract_landmarks would carry the scanner's own errors the same way, but then
every trial would need a raster scan (~1 s of compute each) and the hysteresis state after
a raster scan differs from the one the calibration describes; not done here.

Calibration: `--calibration FILE` (e.g. the one afm_core.localization.calibration.procedure
produced); without it, a SIM-DERIVED ORACLE calibration (`sim_oracle_calibration`): scanner
matrix measured on a noise-free, drift-free, creep-free copy of the simulator (residual hysteresis
gain, coupling and rotation in the +-2 um band around the centre where all moves here stay),
creep, positioning-noise and drift parameters copied from the simulator's config
(cross-axis slope = slope: the simulator's noise is isotropic), line-deflection sigma 0 (the
simulated deflection is a fixed angle, in the matrix) and scan-region sigma measured from
lines across a known particle / tube on that noise-free copy. It is what a perfect
calibration would find; it is not a calibration experiment. A third block runs the book's
default calibration (identity scanner matrix, no creep) to show what an uncalibrated model
does on this instrument.

Run: `scripts/with_env.sh python bench/bench_localization.py [--trials 50] [--calibration FILE]`
(`--quick`: 10 trials; `--only 7.1|7.3`; `--tag T`). ~1 min on 2 cores for 50 trials.
Results: bench/results/localization[-quick][-T].json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import resource
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from afm_core.localization import Localizer, MapLandmark
from afm_core.localization.calibration.model import Calibration, load_calibration
from afm_core.localization.calibration.simulator_comparison import simulator_calibration
from afm_core.sim.config import load_config, merge
from afm_core.sim.instrument import SimulatedAfm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import cpu_model  # noqa: E402

RESULTS_DIR = Path(__file__).resolve().parent / "results"
UM = 1e-6
NM = 1e-9
CENTRE = np.array([55e-6, 55e-6])  # scanner centre = image centre of the book's geometry
BOOK = {
    k: np.array(v) * UM
    for k, v in {
        "x0": (-1.245, 1.316),
        "xd_1": (-1.245, -1.381),
        "x1": (-1.245, -0.645),
        "x8": (1.101, -1.471),
        "landmark": (0.801, -0.684),
    }.items()
}
PARTICLE_RADIUS = 100e-9
P0_TABLE_71 = np.diag([(13e-9) ** 2, (16e-9) ** 2])  # Table 7.1 x0 (experiment sigma 14 / 18 nm)
SETTLE_TIME = 250.0  # s at x0 before the localizer starts
TUBE_RADIUS = 10e-9
TUBE_LENGTH = 3e-6
HIRES_MAP_SIGMA = 0.8e-9
PIT_BELOW = 130e-9
P0_TABLE_74 = np.diag([(10e-9) ** 2, (10e-9) ** 2])  # Table 7.4 x0 sigma 10 nm
LINE_SAMPLE_SPACING = 2e-9  # m, spheres (the sim's dilation cost grows as 1/spacing^3)
TUBE_SAMPLE_SPACING = 1e-9


# -- configurations and calibrations ------------------------------------------------------------
def sim_config(seed: int, spheres=(), rods=(), **overrides):
    config = merge(
        load_config(),
        {
            "seed": int(seed),
            "sample": {
                "spheres": [
                    {"x": float(x), "y": float(y), "radius": float(r)} for x, y, r in spheres
                ],
                "rods": [dict(r) for r in rods],
                "random_spheres": 0,
            },
        },
    )
    return merge(config, overrides) if overrides else config


def _quiet(config_overrides: dict) -> dict:
    quiet = {
        "drift": {"enabled": False},
        "scanner": {"creep_enabled": False, "positioning_noise_enabled": False},
    }
    for key, value in config_overrides.items():
        quiet.setdefault(key, {}).update(value)
    return quiet


def measure_scanner_matrix(step: float = 1e-6) -> np.ndarray:
    """True displacement per commanded displacement about the centre, on a noise-, drift- and
    creep-free simulator (compensated hysteresis residual, coupling, rotation)."""
    columns = []
    for d in (np.array([step, 0.0]), np.array([0.0, step])):
        sim = SimulatedAfm(sim_config(0, **_quiet({})))
        before = np.array(sim.truth()["tip_position"])
        x, y = np.array(sim.commanded_position()) + d
        sim.move_tip(x, y, 1e-5)
        columns.append((np.array(sim.truth()["tip_position"]) - before) / step)
    return np.array(columns).T


def measure_scan_region_sigma(
    matrix: np.ndarray, kind: str, lines: int = 24, seed: int = 7
) -> float:
    """Spread of the centre found by lines across a known sphere / tube at random offsets,
    on the noise-free-positioning simulator (sensor noise on): the true tip position at the
    crossing time is known exactly from the command (linear scanner, no creep, no drift)."""
    from afm_core.instrument import LineRequest
    from afm_core.localization.landmark_observation import observe_line

    rng = np.random.default_rng(seed)
    centre = CENTRE + np.array([0.3e-6, 0.2e-6])
    if kind == "sphere":
        landmark = MapLandmark(*centre, np.zeros((2, 2)), PARTICLE_RADIUS)
        config = sim_config(seed, spheres=[(*centre, PARTICLE_RADIUS)], **_quiet({}))
        spacing, half, offset_range, vertical = (
            LINE_SAMPLE_SPACING,
            250e-9,
            0.8 * PARTICLE_RADIUS,
            False,
        )
    else:
        landmark = MapLandmark(*centre, np.zeros((2, 2)), TUBE_RADIUS, kind="tube")
        config = sim_config(
            seed,
            rods=[
                {
                    "x": float(centre[0]),
                    "y": float(centre[1]),
                    "angle": 0.0,
                    "length": TUBE_LENGTH,
                    "radius": TUBE_RADIUS,
                    "kind": "tube",
                }
            ],
            **_quiet({}),
        )
        spacing, half, offset_range, vertical = TUBE_SAMPLE_SPACING, 120e-9, 500e-9, True
    sim = SimulatedAfm(config)
    inverse = np.linalg.inv(matrix)
    c0 = np.array(sim.commanded_position())
    p0 = np.array(sim.truth()["tip_position"])
    errors = []
    calibration = Calibration(scan_region_sigma=0.0, line_deflection_sigma_deg=0.0)
    for _ in range(lines):
        offset = rng.uniform(-offset_range, offset_range)
        if vertical:
            d = np.array([0.0, 1.0])
            start_true = centre + np.array([offset, -half])
        else:
            d = np.array([1.0, 0.0])
            start_true = centre + np.array([-half, offset])
        start = c0 + inverse @ (start_true - p0)
        end = start + inverse @ (2 * half * d)
        request = LineRequest(*start, *end, int(2 * half / spacing) + 1, 1e-6)
        data = sim.local_scan(request)
        direction = matrix @ (end - start)
        obs = observe_line(data, landmark, calibration, direction)
        if not obs.ok:
            continue
        tip = p0 + matrix @ (np.array(obs.command) - c0)
        errors.append(float(obs.direction @ (centre - tip)))
    return float(np.std(errors, ddof=1)) if len(errors) > 2 else math.nan


def sim_oracle_calibration() -> Calibration:
    """See the module docstring: what a perfect calibration of the default simulator finds."""
    config = load_config()
    matrix = measure_scanner_matrix()
    return simulator_calibration(
        config,
        matrix,
        f"sim-derived oracle (bench_localization.py, {datetime.now(timezone.utc).date()}): "
        "matrix measured on a noise-free simulator, other parameters from the simulator's default "
        "config; not a calibration experiment",
        map_sigma=[5.0e-9, 4.5e-9],
        scan_region_sigma=measure_scan_region_sigma(matrix, "sphere"),
        line_deflection_mean_deg=config.scanner.deflection_deg,
        line_deflection_sigma_deg=0.0,
    )


# -- experiment 1: Tables 7.1 / 7.2 --------------------------------------------------------------
def _start_at(
    sim: SimulatedAfm,
    point: np.ndarray,
    calibration: Calibration,
    p0: np.ndarray,
    rng: np.random.Generator,
) -> Localizer:
    """Tip moved to the command of `point` (open loop), settled; localizer started there."""
    command = np.array(sim.commanded_position()) + np.linalg.solve(
        np.array(calibration.scanner_matrix), point - np.array(sim.truth()["tip_position"])
    )
    sim.move_tip(*command, 2e-6)
    sim.hold(SETTLE_TIME)
    truth = np.array(sim.truth()["tip_position"])
    return Localizer(
        sim,
        calibration,
        rng.multivariate_normal(truth, p0),
        p0,
        sample_spacing=LINE_SAMPLE_SPACING,
    )


MODES_71_72 = ("direct", "via_landmark", "via_landmark_straight", "via_landmark_toward_x8")


def table_71_72_trial(seed: int, calibration: Calibration, mode: str) -> dict:
    """mode: "direct" (x0 -> xd_1 -> x8), "via_landmark" (book path: horizontal and vertical
    line through the particle, each ending clear of it, then free moves x6 -> x7 -> x8) or
    "via_landmark_straight" (the same lines, then one straight move x6 -> x8) or
    "via_landmark_toward_x8" (observe_landmark toward x8, as the Localize action's `toward`:
    the vertical line is continued down to x7 = (particle x, x8 y), so x6 -> x7 is scan-line
    motion, not a free move; then x7 -> x8)."""
    rng = np.random.default_rng(10_000 + seed)
    particle = CENTRE + BOOK["landmark"]
    sim = SimulatedAfm(sim_config(seed, spheres=[(*particle, PARTICLE_RADIUS)]))
    loc = _start_at(sim, CENTRE + BOOK["x0"], calibration, P0_TABLE_71, rng)
    target = CENTRE + BOOK["x8"]
    lines = []
    if mode not in MODES_71_72:
        raise ValueError(f"mode={mode!r}: must be one of {MODES_71_72}")
    if mode != "direct":
        map_cov = np.diag(np.square(calibration.map_sigma))
        landmark = MapLandmark(
            *rng.multivariate_normal(particle, map_cov), map_cov, PARTICLE_RADIUS
        )
        loc.move_to(*(CENTRE + BOOK["x1"]))
        result = loc.observe_landmark(
            landmark, toward=target if mode == "via_landmark_toward_x8" else None
        ).lines
        lines = [(line.axis, line.status, line.mahalanobis) for line in result]
        if mode == "via_landmark":
            loc.move_to(loc.mean[0], target[1])
    else:
        loc.move_to(*(CENTRE + BOOK["xd_1"]))
        loc.move_to(target[0], loc.mean[1])
    loc.move_to(*target)
    truth = np.array(sim.truth()["tip_position"])
    error = loc.mean - truth
    return {
        "seed": seed,
        "true_error_nm": ((truth - target) / NM).tolist(),
        "estimate_error_nm": (error / NM).tolist(),
        "reported_sigma_nm": (np.sqrt(np.diag(loc.covariance)) / NM).tolist(),
        "nees": float(error @ np.linalg.solve(loc.covariance, error)),
        "lines": lines,
        "sim_time_s": sim.time,
    }


def nees_band(trials: int, dof: int = 2, confidence: float = 0.95) -> tuple[float, float]:
    a = (1 - confidence) / 2
    return float(chi2.ppf(a, dof * trials) / trials), float(chi2.ppf(1 - a, dof * trials) / trials)


BLOCK = 50  # the issue's trial count: longer runs are also summarised in disjoint blocks of it


def blocks_of(runs: list[dict], summarize) -> list[dict]:
    """Summaries of consecutive blocks of BLOCK trials (seeds 0-49, 50-99, ...) when there are
    at least two: how a 50-trial result scatters (a 95 % band holds one block in 20 outside)."""
    count = len(runs) // BLOCK
    return (
        [summarize(runs[k * BLOCK : (k + 1) * BLOCK], blocks=False) for k in range(count)]
        if count >= 2
        else []
    )


def summarize_71_72(runs: list[dict], blocks: bool = True) -> dict:
    true_error = np.array([r["true_error_nm"] for r in runs])
    nees = np.array([r["nees"] for r in runs])
    band = nees_band(len(runs))
    statuses = {}
    for r in runs:
        for axis, status, _ in r["lines"]:
            statuses[f"{axis}:{status}"] = statuses.get(f"{axis}:{status}", 0) + 1
    return {
        "trials": len(runs),
        "true_error_sigma_nm": true_error.std(axis=0, ddof=1).tolist(),
        "true_error_mean_nm": true_error.mean(axis=0).tolist(),
        "true_error_rms_radial_nm": float(np.sqrt(np.mean(np.sum(true_error**2, axis=1)))),
        "reported_sigma_mean_nm": np.mean([r["reported_sigma_nm"] for r in runs], axis=0).tolist(),
        "mean_nees": float(nees.mean()),
        "nees_band_95": list(band),
        "nees_consistent": bool(band[0] <= nees.mean() <= band[1]),
        "line_statuses": statuses,
        "blocks": blocks_of(runs, summarize_71_72) if blocks else [],
    }


def run_71_72(calibration: Calibration, trials: int, seed0: int = 0) -> dict:
    out = {}
    for mode in MODES_71_72:
        runs = [table_71_72_trial(seed0 + k, calibration, mode) for k in range(trials)]
        out[mode] = {"summary": summarize_71_72(runs), "runs": runs}
    return out


# -- experiment 2: Table 7.3 ----------------------------------------------------------------------
def table_73_trial(seed: int, calibration: Calibration, line_ends_at_pit: bool) -> dict:
    """`calibration` already holds the high-resolution map's sigma (see run_73)."""
    rng = np.random.default_rng(20_000 + seed)
    tube = CENTRE + np.array([0.0, 0.25e-6])
    rod = {
        "x": float(tube[0]),
        "y": float(tube[1]),
        "angle": 0.0,
        "length": TUBE_LENGTH,
        "radius": TUBE_RADIUS,
        "kind": "tube",
    }
    sim = SimulatedAfm(sim_config(seed, rods=[rod]))
    loc = _start_at(sim, CENTRE.copy(), calibration, P0_TABLE_74, rng)
    loc.sample_spacing = TUBE_SAMPLE_SPACING
    map_cov = np.diag([HIRES_MAP_SIGMA**2] * 2)
    landmark = MapLandmark(
        *rng.multivariate_normal(tube, map_cov), map_cov, TUBE_RADIUS, kind="tube", orientation=0.0
    )
    up = loc.observe_line(landmark, "y", +1.0)  # x0 -> x1 across the tube
    if line_ends_at_pit:
        down = loc.observe_line(landmark, "y", -1.0, after=PIT_BELOW)  # x1 -> pit, across the tube
        # the line's end was planned before its update: correct by the (~1 nm) difference
        loc.move_to(loc.mean[0], landmark.y - PIT_BELOW)
    else:
        down = loc.observe_line(landmark, "y", -1.0)  # x1 -> x2 (clear of the tube)
        loc.move_to(loc.mean[0], landmark.y - PIT_BELOW)  # x2 -> x3
    sigma_y = math.sqrt(loc.covariance[1, 1])
    estimate_error = loc.mean[1] - sim.truth()["tip_position"][1]
    loc.indent_here(0.5e-6, 0.1)
    pit = sim.sample.pits[-1]
    return {
        "seed": seed,
        "distance_nm": (tube[1] - pit.y) / NM,
        "lines": [up.status, down.status],
        "reported_sigma_nm": sigma_y / NM,
        "nees": estimate_error**2 / sigma_y**2,
    }


def run_73(
    calibration: Calibration, trials: int, seed0: int = 0, scan_region_sigma: float | None = None
) -> dict:
    """scan_region_sigma: the tube's (default: the calibration's)."""
    hires = dataclasses.replace(calibration, map_sigma=[HIRES_MAP_SIGMA, HIRES_MAP_SIGMA])
    if scan_region_sigma is not None:
        hires = dataclasses.replace(hires, scan_region_sigma=scan_region_sigma)
    out = {"scan_region_sigma_nm": hires.scan_region_sigma / NM}
    for variant in ("book", "line_ends_at_pit"):
        runs = [
            table_73_trial(seed0 + k, hires, variant == "line_ends_at_pit") for k in range(trials)
        ]
        out[variant] = {"summary": summarize_73(runs), "runs": runs}
    return out


def summarize_73(runs: list[dict], blocks: bool = True) -> dict:
    d = np.array([r["distance_nm"] for r in runs])
    nees = np.array([r["nees"] for r in runs])
    band = nees_band(len(runs), dof=1)
    return {
        "trials": len(runs),
        "target_nm": PIT_BELOW / NM,
        "distance_mean_nm": float(d.mean()),
        "distance_sigma_nm": float(d.std(ddof=1)),
        "reported_sigma_mean_nm": float(np.mean([r["reported_sigma_nm"] for r in runs])),
        "mean_nees_1dof": float(nees.mean()),
        "nees_band_95": list(band),
        "nees_consistent": bool(band[0] <= nees.mean() <= band[1]),
        "all_lines_accepted": all(s == "accepted" for r in runs for s in r["lines"]),
        "blocks": blocks_of(runs, summarize_73) if blocks else [],
    }


# -- report ---------------------------------------------------------------------------------------
def machine_info() -> dict:
    return {
        "cpu_count": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)),
        "cpu_model": cpu_model(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "load_average_at_start": os.getloadavg(),
    }


def _fmt(v) -> str:
    return "(" + ", ".join(f"{x:.1f}" for x in v) + ")"


def print_71_72(title: str, block: dict) -> None:
    print(f"\n{title}")
    print(
        "  mode                     trials  true-error sigma x,y nm  mean x,y nm     "
        "filter sigma x,y nm  mean NEES (95% band)"
    )
    for mode, data in block.items():
        s = data["summary"]
        lo, hi = s["nees_band_95"]
        print(
            f"  {mode:24s} {s['trials']:6d}  {_fmt(s['true_error_sigma_nm']):23s}  "
            f"{_fmt(s['true_error_mean_nm']):14s} "
            f"{_fmt(s['reported_sigma_mean_nm']):20s} {s['mean_nees']:.2f} [{lo:.2f}, {hi:.2f}]"
            f"{'' if s['nees_consistent'] else '  OUTSIDE'}  {s['line_statuses'] or ''}"
        )
        for k, b in enumerate(s["blocks"]):
            print(
                f"    trials {k * BLOCK}-{(k + 1) * BLOCK - 1}: "
                f"{_fmt(b['true_error_sigma_nm'])} nm, NEES "
                f"{b['mean_nees']:.2f} [{b['nees_band_95'][0]:.2f}, {b['nees_band_95'][1]:.2f}]"
                f"{'' if b['nees_consistent'] else '  OUTSIDE'}"
            )


def markdown_report(report: dict, command: str) -> str:
    """bench/results/localization*.md: the results' tables, headed with date, machine, command."""
    m = report["machine"]

    def pair(values) -> str:
        return ", ".join(f"{x:.1f}" for x in values)

    lines = [
        "# Tip localization experiments (book 7.2.3-7.2.4) on the simulated AFM",
        "",
        f"Measured {report['date']} on {m['cpu_count']} CPUs ({m['cpu_model']}; "
        f"{m.get('cpus_usable', m['cpu_count'])} usable), Python {m['python']}, load "
        f"{m['load_average_at_start'][0]:.2f} at start; {report['wall_seconds']:.0f} s wall, "
        f"peak memory {report['peak_rss_kib'] / 1024:.0f} MiB.",
        "",
        f"Command: `{command}`",
        "",
        f"Calibration: {report['calibration']}",
    ]
    blocks_7_1 = [
        (
            "tables_7_1_7_2",
            "Tables 7.1 / 7.2: x0 -> x8 (book: direct ~20 nm, via landmark ~10 nm)",
        ),
        (
            "tables_7_1_7_2_book_default_calibration",
            "Tables 7.1 / 7.2 with the book-default calibration (identity matrix, no creep)",
        ),
    ]
    for key, title in blocks_7_1:
        if key not in report:
            continue
        lines += [
            "",
            f"## {title}",
            "",
            "| route | trials | true error sigma x, y (nm) | true error mean x, y (nm) "
            "| filter sigma x, y (nm) | mean NEES [95 % band] | lines |",
            "|---|---|---|---|---|---|---|",
        ]
        for mode, data in report[key].items():
            s = data["summary"]
            lo, hi = s["nees_band_95"]
            flag = "" if s["nees_consistent"] else " **outside**"
            statuses = ", ".join(f"{k} {v}" for k, v in s["line_statuses"].items()) or "-"
            lines.append(
                f"| {mode} | {s['trials']} | {pair(s['true_error_sigma_nm'])} | "
                f"{pair(s['true_error_mean_nm'])} | {pair(s['reported_sigma_mean_nm'])} | "
                f"{s['mean_nees']:.2f} [{lo:.2f}, {hi:.2f}]{flag} | {statuses} |"
            )
        block_rows = [
            f"| {mode} | {k * BLOCK}-{(k + 1) * BLOCK - 1} | {pair(b['true_error_sigma_nm'])} | "
            f"{b['mean_nees']:.2f} [{b['nees_band_95'][0]:.2f}, {b['nees_band_95'][1]:.2f}]"
            f"{'' if b['nees_consistent'] else ' **outside**'} |"
            for mode, data in report[key].items()
            for k, b in enumerate(data["summary"].get("blocks", []))
        ]
        if block_rows:
            lines += [
                "",
                f"Blocks of {BLOCK} trials (seeds):",
                "",
                "| route | seeds | true error sigma x, y (nm) | mean NEES [95 % band] |",
                "|---|---|---|---|",
                *block_rows,
            ]
    if "table_7_3" in report:
        t = report["table_7_3"]
        lines += [
            "",
            "## Table 7.3: a pit 130 nm below a nanotube (book: 129.6 nm, sigma 1.5 nm)",
            "",
            f"Map sigma {HIRES_MAP_SIGMA / NM:.1f} nm, scan-region sigma "
            f"{t['scan_region_sigma_nm']:.2f} nm.",
            "",
            "| flow | trials | distance mean (nm) | distance sigma (nm) | filter sigma (nm) "
            "| mean NEES, 1 dof [95 % band] | every line accepted |",
            "|---|---|---|---|---|---|---|",
        ]
        block_rows = []
        for variant in ("book", "line_ends_at_pit"):
            s = t[variant]["summary"]
            lo, hi = s["nees_band_95"]
            lines.append(
                f"| {variant} | {s['trials']} | {s['distance_mean_nm']:.2f} | "
                f"{s['distance_sigma_nm']:.2f} | {s['reported_sigma_mean_nm']:.2f} | "
                f"{s['mean_nees_1dof']:.2f} [{lo:.2f}, {hi:.2f}]"
                f"{'' if s['nees_consistent'] else ' **outside**'} | "
                f"{'yes' if s['all_lines_accepted'] else 'no'} |"
            )
            block_rows += [
                f"| {variant} | {k * BLOCK}-{(k + 1) * BLOCK - 1} | {b['distance_sigma_nm']:.2f} "
                "| "
                f"{b['mean_nees_1dof']:.2f} [{b['nees_band_95'][0]:.2f}, "
                f"{b['nees_band_95'][1]:.2f}]{'' if b['nees_consistent'] else ' **outside**'} |"
                for k, b in enumerate(s.get("blocks", []))
            ]
        if block_rows:
            lines += [
                "",
                f"Blocks of {BLOCK} trials (seeds):",
                "",
                "| flow | seeds | distance sigma (nm) | mean NEES, 1 dof [95 % band] |",
                "|---|---|---|---|",
                *block_rows,
            ]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--trials", type=int, default=None, help="trials per case (default 50; --quick 10)"
    )
    parser.add_argument(
        "--calibration", type=Path, default=None, help="calibration YAML (default: sim oracle)"
    )
    parser.add_argument("--quick", action="store_true")
    parser.add_argument(
        "--no-book-defaults",
        action="store_true",
        help="skip the uncalibrated (book defaults) block",
    )
    parser.add_argument(
        "--only", choices=("all", "7.1", "7.3"), default="all", help="run one experiment only"
    )
    parser.add_argument("--tag", default="", help="results file localization[-quick][-TAG].json")
    args = parser.parse_args(argv)
    trials = args.trials or (10 if args.quick else 50)
    started, t0 = datetime.now(timezone.utc), time.perf_counter()
    if args.calibration is not None:
        calibration = load_calibration(args.calibration)
        calibration_label = f"file {args.calibration}: {calibration.source}"
    else:
        calibration = sim_oracle_calibration()
        calibration_label = calibration.source
    print(f"calibration: {calibration_label}")
    print(
        f"  scanner matrix {np.array(calibration.scanner_matrix).round(5).tolist()}, "
        f"scan-region sigma {calibration.scan_region_sigma / NM:.2f} nm"
    )
    report = {
        "date": started.isoformat(timespec="seconds"),
        "machine": machine_info(),
        "settings": {"trials": trials, "quick": args.quick},
        "calibration": calibration_label,
        "calibration_values": dataclasses.asdict(calibration),
    }
    if args.only in ("all", "7.1"):
        report["tables_7_1_7_2"] = run_71_72(calibration, trials)
        print_71_72(
            "Tables 7.1/7.2: x0 -> x8 (book: direct ~20 nm, via landmark ~10 nm sigma)",
            report["tables_7_1_7_2"],
        )
    if args.only in ("all", "7.3"):
        run_table_73(report, calibration, trials, args.calibration is None)
    if not args.no_book_defaults and args.only == "all":
        book_trials = min(trials, 10)
        report["tables_7_1_7_2_book_default_calibration"] = run_71_72(
            Calibration(), book_trials, seed0=500
        )
        print_71_72(
            "Same with the book-default calibration (identity matrix, no creep; "
            f"{book_trials} trials)",
            report["tables_7_1_7_2_book_default_calibration"],
        )
    report["peak_rss_kib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    report["wall_seconds"] = time.perf_counter() - t0
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    stem = "localization" + ("-quick" if args.quick else "") + (f"-{args.tag}" if args.tag else "")
    path = RESULTS_DIR / f"{stem}.json"
    path.write_text(json.dumps(report, indent=2, default=float) + "\n")
    path.with_suffix(".md").write_text(
        markdown_report(
            report,
            " ".join(
                ["scripts/with_env.sh python bench/bench_localization.py"]
                + (sys.argv[1:] if argv is None else list(argv))
            ),
        )
    )
    print(
        f"\npeak RSS {report['peak_rss_kib'] / 1024:.0f} MiB; "
        f"wall {report['wall_seconds']:.0f} s; wrote {path}"
    )
    return 0


def run_table_73(report: dict, calibration: Calibration, trials: int, oracle: bool) -> None:
    tube_region = None
    if oracle:
        tube_region = measure_scan_region_sigma(np.array(calibration.scanner_matrix), "tube")
    report["table_7_3"] = run_73(calibration, trials, scan_region_sigma=tube_region)
    print(
        f"\nTable 7.3: pit 130 nm below a nanotube (book: 129.6 nm, sigma 1.5 nm); map sigma "
        f"{HIRES_MAP_SIGMA / NM:.1f} nm, scan-region sigma "
        f"{report['table_7_3']['scan_region_sigma_nm']:.2f} nm"
    )
    for variant, data in report["table_7_3"].items():
        if variant == "scan_region_sigma_nm":
            continue
        s = data["summary"]
        print(
            f"  {variant:17s} trials {s['trials']}: distance {s['distance_mean_nm']:.2f} nm, "
            f"sigma {s['distance_sigma_nm']:.2f} nm; filter sigma "
            f"{s['reported_sigma_mean_nm']:.2f} nm; mean NEES(1 dof) "
            f"{s['mean_nees_1dof']:.2f} [{s['nees_band_95'][0]:.2f}, {s['nees_band_95'][1]:.2f}]; "
            f"all lines accepted: {s['all_lines_accepted']}"
        )
        for k, b in enumerate(s["blocks"]):
            print(
                f"    trials {k * BLOCK}-{(k + 1) * BLOCK - 1}: "
                f"sigma {b['distance_sigma_nm']:.2f} nm, NEES {b['mean_nees_1dof']:.2f} "
                f"[{b['nees_band_95'][0]:.2f}, {b['nees_band_95'][1]:.2f}]"
                f"{'' if b['nees_consistent'] else '  OUTSIDE'}"
            )


if __name__ == "__main__":
    sys.exit(main())
