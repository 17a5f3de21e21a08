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
import os
import platform
import resource
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from afm_core.localization import trials as core
from afm_core.localization.calibration.model import Calibration, load_calibration
from afm_core.localization.trials import (  # noqa: F401 - the tests use them through the bench
    BOOK,
    CENTRE,
    HIRES_MAP_SIGMA,
    MODES_71_72,
    NM,
    PIT_BELOW,
    UM,
    load_config,
    measure_scan_region_sigma,
    measure_scanner_matrix,
    nees_band,
    sim_config,
    sim_oracle_calibration,
)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import cpu_model  # noqa: E402

RESULTS_DIR = Path(__file__).resolve().parent / "results"


# -- experiment 1: Tables 7.1 / 7.2 (the trial itself: afm_core.localization.trials) -------------
def table_71_72_trial(seed: int, calibration: Calibration, mode: str) -> dict:
    """afm_core.localization.trials.table_71_72_trial, in the nm of this bench's report."""
    trial = core.table_71_72_trial(seed, calibration, mode)
    return {
        "seed": seed,
        "true_error_nm": (trial["true_error"] / NM).tolist(),
        "estimate_error_nm": (trial["estimate_error"] / NM).tolist(),
        "reported_sigma_nm": (trial["reported_sigma"] / NM).tolist(),
        "nees": trial["nees"],
        "lines": trial["lines"],
        "sim_time_s": trial["sim_time_s"],
    }


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
    """afm_core.localization.trials.table_73_trial, in the nm of this bench's report."""
    trial = core.table_73_trial(seed, calibration, line_ends_at_pit)
    return {
        "seed": seed,
        "distance_nm": trial["distance"] / NM,
        "lines": trial["lines"],
        "reported_sigma_nm": trial["reported_sigma"] / NM,
        "nees": trial["nees"],
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
