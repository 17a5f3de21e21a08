"""Virtual nano-hand vs centre pushing: the Monte Carlo model and the simulated AFM.

What is measured
----------------
(a) Monte Carlo stochastic pushing model (book 6.4.3, Fig. 6.18): 500 draws of the particle
    centre, sigma 10 nm, pushed by 6 strokes of the same rhythm (156 nm push, 120 nm back):
    - centre: straight pushes through the estimated centre
      (afm_core.manipulation.centre_push_plan);
    - nano-hand: the Table 7.6 zigzag (nano_hand_plan, aim=False), goal = where it takes a
      particle that sits exactly at the estimate;
    - nano-hand aimed: the planner's aimed zigzag to a goal 300 nm away (last push and last path
      adjusted in the model);
    lateral / along sigma, split fraction (share > 3 sigma off the goal line, each side),
    bimodality, share between the paths, success = within 20 nm of the goal. Also the 13-step
    Table 7.6 push (book 7.3.1) through the same model.
(b) The simulated AFM with its default physics (positioning noise, hysteresis residual, creep,
    drift; R_T 50 nm, R_P 100 nm), 20 seeds. Per seed the particle's estimated centre is its
    true centre plus a N(0, 10 nm) error per axis (the uncertainty the book assumes; the
    localization itself is another module's job), the goal is 500 nm from the estimate along +y,
    and each strategy runs on a fresh simulator of that seed through the Instrument calls
    (afm_core.manipulation.execute_plan). Success: the true final centre within 20 nm of the goal.
    Strategies: nano-hand (aimed), centre pushing in the same rhythm, one single centre push.
    Plus the book's experiment: Table 7.6, 13 steps, estimate = truth: along / sideways
    displacement (book: 530 / 20 nm measured, 507 nm simulated); its "success" and "error" are
    against the model's prediction for that plan (503 nm along, 14 nm right).
(c) The whole push of book 7.3 (afm_core.manipulation.PushProcedure, what the nano-hand node
    runs) on the same 20 simulators, ROS-free: the sample is mapped from a raster image
    (extract_landmarks), the core Localizer localizes the tip on the particle; the procedure gets
    the whole calibration of the simulated instrument, the graph's
    (afm_localization/config/sim_calibration.yaml), as the node does; control pits, before
    image, the procedure's default strategy (the closed loop: nano-hand legs, local scan lines
    between them), after image, verification. The particle of (b), 500 nm along +y from its
    mapped position. Success: the true displacement within 20 nm of the planned one, compared in
    the frame of the images (as bench_push_graph does: afm_core.evaluation.image_frame_matrix);
    also the procedure's own verdict (its verified error).

Run: `scripts/with_env.sh python bench/bench_pushing.py` (~1 min on one core).
Results: bench/results/pushing.json.
"""

from __future__ import annotations

import json
import os
import platform
import resource
import statistics
import sys
import time
from datetime import datetime, timezone
from importlib.metadata import version
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import cpu_model  # noqa: E402

from afm_core.evaluation import image_frame_matrix  # noqa: E402
from afm_core.imaging.landmarks import extract_landmarks  # noqa: E402
from afm_core.instrument import ScanRequest  # noqa: E402
from afm_core.localization import Localizer  # noqa: E402
from afm_core.localization.calibration.model import load_calibration  # noqa: E402
from afm_core.manipulation import (  # noqa: E402
    PushFailed,
    PushProcedure,
    PushRefused,
    localize_with,
    monte_carlo_push,
)
from afm_core.manipulation.push_trials import (  # noqa: E402
    MC_CENTRE,
    monte_carlo_plans,
    push_trial,
)
from afm_core.sim.config import load_config, merge  # noqa: E402
from afm_core.sim.instrument import SimulatedAfm  # noqa: E402

RESULTS_DIR = Path(__file__).resolve().parent / "results"
NM = 1e-9
TOL = 20 * NM
CALIBRATION = (
    Path(__file__).resolve().parents[1] / "afm_localization" / "config" / "sim_calibration.yaml"
)
MAP_SCAN = ScanRequest(54.2e-6, 54.5e-6, 2.0e-6, 2.0e-6, 256, 256, line_rate=4.0)  # (c)


def machine_info() -> dict:
    return {
        "cpu_count": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)),
        "cpu_model": cpu_model(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "load_average_at_start": os.getloadavg(),
        "packages": {p: version(p) for p in ("numpy", "scipy")},
    }


def monte_carlo_part() -> dict:
    c0 = np.array(MC_CENTRE)
    plans = monte_carlo_plans(c0)  # the plans: afm_core.manipulation.push_trials
    book = plans.pop("table_7_6_13_steps")
    out = {}
    for name, plan in plans.items():
        t0 = time.perf_counter()
        r = monte_carlo_push(plan, samples=500, sigma=10 * NM, seed=1, tolerance=TOL)
        out[name] = {
            **r.summary(),
            "wall_seconds": time.perf_counter() - t0,
            "goal_along_nm": float(plan.along(plan.goal) / NM),
        }
    t0 = time.perf_counter()
    r = monte_carlo_push(book, samples=500, sigma=10 * NM, seed=1, tolerance=TOL)
    disp = r.final - c0
    out["table_7_6_13_steps"] = {
        "model_nominal_along_nm": float(book.along(book.predicted) / NM),
        "model_nominal_sideways_nm": float(
            -book.lateral(book.predicted) / NM
        ),  # + = right of the axis
        "mc_along_mean_nm": float(np.mean(disp @ book.axis) / NM),
        "mc_sigma_along_nm": r.sigma_along / NM,
        "mc_sigma_lateral_nm": r.sigma_lateral / NM,
        "between_paths": r.between_paths,
        "seconds": r.seconds,
        "wall_seconds": time.perf_counter() - t0,
    }
    return out


def sim_run(seed: int, strategy: str, estimate_sigma: float) -> dict:
    """(b): afm_core.manipulation.push_trials.push_trial, in the nm of this bench's report."""
    trial = push_trial(seed, strategy, estimate_sigma, goal_distance=500 * NM, tolerance=TOL)
    return {
        "seed": seed,
        "strategy": strategy,
        "strokes": trial["strokes"],
        "completed": trial["completed"],
        "error_nm": trial["error"] / NM,
        "success": trial["success"],
        "along_nm": trial["along"] / NM,
        "sideways_nm": trial["sideways"] / NM,
        "estimate_error_nm": [float(v) for v in trial["estimate_error"] / NM],
        "sim_seconds": trial["sim_seconds"],
        "wall_seconds": trial["wall_seconds"],
    }


def procedure_run(seed: int, calibration, image_frame: np.ndarray) -> dict:
    """(c): the whole push on a fresh simulator of this seed (module docstring)."""
    sim = SimulatedAfm(merge(load_config(), {"seed": seed}))
    sphere = sim.sample.spheres[0]
    truth0 = np.array([sphere.x, sphere.y])
    scan = sim.raster_scan(MAP_SCAN)
    marks = {
        m.id: m
        for m in extract_landmarks(
            scan.height, scan.pixel_size_x, scan.pixel_size_y, scan.origin_x, scan.origin_y
        )
    }
    mark = min(marks.values(), key=lambda m: np.hypot(m.x - sphere.x, m.y - sphere.y))
    start = np.array([mark.x, mark.y])
    goal = start + [0.0, 500 * NM]
    localizer = Localizer(
        sim, calibration, np.array(sim.commanded_position()), np.diag([(50 * NM) ** 2] * 2)
    )
    procedure = PushProcedure(
        sim,
        localize_with(localizer),
        lambda: marks,
        # the whole calibration, as the node and the other benches pass it, not its scanner
        # matrix alone
        calibration=calibration,
        on_moved=lambda moved: marks.__setitem__(moved.id, moved),
    )
    t0, sim_t0 = time.perf_counter(), sim.time
    try:
        result, failure = procedure.push(mark.id, goal), ""
    except (PushFailed, PushRefused) as exc:
        result, failure = None, str(exc)
    wall = time.perf_counter() - t0
    moved = np.linalg.solve(image_frame, np.array([sphere.x, sphere.y]) - truth0)
    error = float(np.hypot(*(moved - (goal - start))))
    return {
        "seed": seed,
        "ran": result is not None,
        "message": result.message if result is not None else failure,
        "error_nm": error / NM,
        "success": bool(result is not None and error <= TOL),
        "verified_error_nm": result.error / NM if result is not None else None,
        "verified_success": bool(result is not None and result.success),
        "steps": result.steps if result is not None else 0,
        "along_nm": float(moved[1] / NM),
        "sideways_nm": float(moved[0] / NM),  # + = right of the +y axis
        "sim_seconds": sim.time - sim_t0,
        "wall_seconds": wall,
    }


def summarize_procedure(runs: list[dict]) -> dict:
    ran = [r for r in runs if r["ran"]]
    errs = [r["error_nm"] for r in ran]
    return {
        "runs": len(runs),
        "ran": len(ran),
        "success_rate": sum(r["success"] for r in runs) / len(runs),
        "verified_success_rate": sum(r["verified_success"] for r in runs) / len(runs),
        "error_nm_median": statistics.median(errs) if errs else None,
        "error_nm_max": max(errs, default=None),
        "verified_error_nm_median": (
            statistics.median(r["verified_error_nm"] for r in ran) if ran else None
        ),
        "along_nm_mean": statistics.fmean(r["along_nm"] for r in ran) if ran else None,
        "along_nm_sd": statistics.pstdev(r["along_nm"] for r in ran) if ran else None,
        "sideways_nm_mean": statistics.fmean(r["sideways_nm"] for r in ran) if ran else None,
        "sideways_abs_nm_max": max((abs(r["sideways_nm"]) for r in ran), default=None),
        "wall_seconds_per_run": statistics.fmean(r["wall_seconds"] for r in runs),
        "sim_seconds_per_run": statistics.fmean(r["sim_seconds"] for r in runs),
    }


def summarize_runs(runs: list[dict]) -> dict:
    errs = [r["error_nm"] for r in runs]
    along = [r["along_nm"] for r in runs]
    side = [r["sideways_nm"] for r in runs]
    return {
        "runs": len(runs),
        "success_rate": sum(r["success"] for r in runs) / len(runs),
        "success_rate_40nm": sum(r["error_nm"] <= 40 for r in runs) / len(runs),
        "error_nm_median": statistics.median(errs),
        "error_nm_max": max(errs),
        "along_nm_mean": statistics.fmean(along),
        "along_nm_sd": statistics.pstdev(along),
        "along_nm_min": min(along),
        "along_nm_max": max(along),
        "sideways_nm_mean": statistics.fmean(side),
        "sideways_nm_sd": statistics.pstdev(side),
        "sideways_abs_nm_max": max(abs(s) for s in side),
        "wall_seconds_per_run": statistics.fmean(r["wall_seconds"] for r in runs),
        "sim_seconds_per_run": statistics.fmean(r["sim_seconds"] for r in runs),
    }


def markdown_report(report: dict, command: str) -> str:
    """bench/results/pushing.md: the Monte Carlo and simulated-AFM tables, headed with date,
    machine and command."""
    m, st = report["machine"], report["settings"]
    lines = [
        "# Virtual nano-hand vs centre pushing: the Monte Carlo model and the simulated AFM",
        "",
        f"Measured {report['date']} on {m['cpu_count']} CPUs ({m['cpu_model']}; "
        f"{m['cpus_usable']} usable), Python {m['python']}, load "
        f"{m['load_average_at_start'][0]:.2f} at start; {report['wall_seconds']:.0f} s wall, "
        f"peak memory {report['process_peak_rss_kib'] / 1024:.0f} MiB.",
        "",
        f"Command: `{command}`",
        "",
        f"## Monte Carlo model: {st['mc_samples']} draws, sigma {st['mc_sigma_nm']} nm, "
        f"{st['mc_pushes']} pushes (156/120 nm rhythm), success within {st['tolerance_nm']} nm",
        "",
        "| strategy | goal along (nm) | lateral sigma (nm) | along sigma (nm) | split (left / "
        "right) "
        "| bimodal | between paths | success | s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, s in report["monte_carlo"].items():
        if name == "table_7_6_13_steps":
            continue
        between = "-" if s["between_paths"] is None else f"{s['between_paths']:.2f}"
        lines.append(
            f"| {name} | {s['goal_along_nm']:.0f} | {s['sigma_lateral_nm']:.1f} | "
            f"{s['sigma_along_nm']:.1f} | {s['split_fraction']:.2f} ({s['share_left']:.2f} / "
            f"{s['share_right']:.2f}) | {'yes' if s['bimodal'] else 'no'} | {between} | "
            f"{s['success_probability']:.2f} | {s['seconds']:.1f} |"
        )
    b = report["monte_carlo"]["table_7_6_13_steps"]
    lines += [
        "",
        f"Table 7.6, 13 steps, in the model: {b['model_nominal_along_nm']:.1f} nm along, "
        f"{b['model_nominal_sideways_nm']:.1f} nm sideways (book: 507 nm simulated, 530 / 20 nm "
        f"measured); Monte Carlo sigma along {b['mc_sigma_along_nm']:.1f} nm, lateral "
        f"{b['mc_sigma_lateral_nm']:.1f} nm, between paths {b['between_paths']:.2f}, "
        f"{b['seconds']:.1f} s for 500 x 13 strokes.",
        "",
        f"## SimulatedAfm, default physics, {st['sim_seeds']} seeds, estimate = truth + "
        f"N(0, {st['sim_estimate_sigma_nm']} nm), goal {st['sim_goal_nm']} nm",
        "",
        "Table 7.6 runs with the estimate exact; its error is against the model's prediction for "
        "that plan.",
        "",
        "| strategy | success <= 20 nm | <= 40 nm | median error (nm) | along (nm) "
        "| sideways (nm) | max sideways (nm) | simulated s per run |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, data in report["simulated_afm"].items():
        s = data["summary"]
        lines.append(
            f"| {name} | {s['success_rate']:.2f} | {s['success_rate_40nm']:.2f} | "
            f"{s['error_nm_median']:.0f} | {s['along_nm_mean']:.0f} +- {s['along_nm_sd']:.0f} | "
            f"{s['sideways_nm_mean']:.0f} +- {s['sideways_nm_sd']:.0f} | "
            f"{s['sideways_abs_nm_max']:.0f} | {s['sim_seconds_per_run']:.1f} |"
        )
    s = report["procedure"]["summary"]
    lines += [
        "",
        f"## PushProcedure (the node's whole push, its default closed loop), no ROS, the same "
        f"{st['sim_seeds']} "
        f"simulators, calibration {st['procedure_calibration']}",
        "",
        "Success: the true displacement, in the maps' frame (image_frame_matrix), within 20 nm "
        "of the planned one; verified: the procedure's own verdict from its rescans.",
        "",
        "| ran | success (true) | success (verified) | median / max error (nm) | along (nm) | "
        "max sideways (nm) | simulated s per run |",
        "|---|---|---|---|---|---|---|",
        f"| {s['ran']} / {s['runs']} | {s['success_rate']:.2f} | "
        f"{s['verified_success_rate']:.2f} | {s['error_nm_median']:.1f} / "
        f"{s['error_nm_max']:.1f} | {s['along_nm_mean']:.0f} +- {s['along_nm_sd']:.0f} | "
        f"{s['sideways_abs_nm_max']:.0f} | {s['sim_seconds_per_run']:.1f} |",
    ]
    return "\n".join(lines) + "\n"


def main() -> int:
    started, t0 = datetime.now(timezone.utc), time.perf_counter()
    print("(a) Monte Carlo, 500 draws, sigma 10 nm, after 6 pushes", flush=True)
    mc = monte_carlo_part()
    for name, s in mc.items():
        if name == "table_7_6_13_steps":
            continue
        print(
            f"  {name:22s} lateral sigma {s['sigma_lateral_nm']:6.1f} nm  along sigma "
            f"{s['sigma_along_nm']:5.1f} nm  split {s['split_fraction']:.3f} "
            f"(L {s['share_left']:.3f} / R {s['share_right']:.3f})  "
            f"between paths {s['between_paths'] if s['between_paths'] is not None else '-'}  "
            f"success(20 nm) {s['success_probability']:.3f}  {s['seconds']:.1f} s",
            flush=True,
        )
    b = mc["table_7_6_13_steps"]
    print(
        f"  Table 7.6, 13 steps in the model: along {b['model_nominal_along_nm']:.1f} nm, "
        f"sideways {b['model_nominal_sideways_nm']:.1f} nm (MC sigma along "
        f"{b['mc_sigma_along_nm']:.1f}, lateral "
        f"{b['mc_sigma_lateral_nm']:.1f} nm, {b['seconds']:.1f} s for 500 x 13 strokes)",
        flush=True,
    )

    print(
        "(b) SimulatedAfm, default physics, 20 seeds, estimate error N(0, 10 nm), goal 500 nm",
        flush=True,
    )
    sims = {}
    for strategy, sigma in (
        ("nano_hand", 10 * NM),
        ("centre", 10 * NM),
        ("centre_single", 10 * NM),
        ("table_7_6", 0.0),
    ):
        runs = [sim_run(seed, strategy, sigma) for seed in range(20)]
        sims[strategy] = {"summary": summarize_runs(runs), "runs": runs}
        s = sims[strategy]["summary"]
        print(
            f"  {strategy:14s} success {s['success_rate']:.2f} (40 nm: "
            f"{s['success_rate_40nm']:.2f})  median error {s['error_nm_median']:6.1f} nm  "
            f"along {s['along_nm_mean']:6.1f} +- {s['along_nm_sd']:4.1f} nm  sideways "
            f"{s['sideways_nm_mean']:6.1f} "
            f"+- {s['sideways_nm_sd']:4.1f} nm (max |.| {s['sideways_abs_nm_max']:.1f})  "
            f"{s['wall_seconds_per_run']:.2f} s/run",
            flush=True,
        )
    print(
        "(c) PushProcedure (the node's whole push, its default strategy) on the same 20 "
        "simulators, no ROS: map, core "
        "Localizer, pits, zigzag, rescan, verification; 500 nm",
        flush=True,
    )
    calibration, image_frame = load_calibration(CALIBRATION), image_frame_matrix()
    runs = [procedure_run(seed, calibration, image_frame) for seed in range(20)]
    procedure = {"summary": summarize_procedure(runs), "runs": runs}
    s = procedure["summary"]
    print(
        f"  closed_loop    success {s['success_rate']:.2f} (verified "
        f"{s['verified_success_rate']:.2f}, "
        f"{s['ran']}/{s['runs']} ran)  median error {s['error_nm_median']:6.1f} nm (verified "
        f"{s['verified_error_nm_median']:5.1f})  along {s['along_nm_mean']:6.1f} +- "
        f"{s['along_nm_sd']:4.1f} nm  sideways {s['sideways_nm_mean']:6.1f} nm (max |.| "
        f"{s['sideways_abs_nm_max']:.1f})  {s['wall_seconds_per_run']:.2f} s/run",
        flush=True,
    )
    wall = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    report = {
        "date": started.isoformat(timespec="seconds"),
        "machine": machine_info(),
        "settings": {
            "mc_samples": 500,
            "mc_sigma_nm": 10,
            "mc_pushes": 6,
            "tolerance_nm": 20,
            "sim_seeds": 20,
            "sim_estimate_sigma_nm": 10,
            "sim_goal_nm": 500,
            "push_speed_m_per_s": 0.5e-6,
            "procedure_calibration": str(CALIBRATION.relative_to(CALIBRATION.parents[2])),
        },
        "monte_carlo": mc,
        "simulated_afm": sims,
        "procedure": procedure,
        "process_peak_rss_kib": peak,
        "wall_seconds": wall,
    }
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    path = RESULTS_DIR / "pushing.json"
    path.write_text(json.dumps(report, indent=2) + "\n")
    path.with_suffix(".md").write_text(
        markdown_report(report, "scripts/with_env.sh python bench/bench_pushing.py")
    )
    print(f"peak RSS {peak / 1024:.0f} MiB; wall time {wall:.0f} s; wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
