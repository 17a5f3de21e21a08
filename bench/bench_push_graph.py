"""Pushes through the whole graph on the simulated instrument: virtual nano-hand vs centre
pushing over seeded runs, and the book's 13-step Table 7.6 push (book 7.3.1).

What is measured
----------------
Per seed, the graph runs as separate processes (driver with the default physics and that
seed, imaging, localizer, planner, nano_hand; the localization calibration of the simulated
instrument). A sample with three spheres (r = 100 nm) 0.8 um apart in a row is scanned as a
0/90 deg pair; the imaging node maps them; then, through the PushParticle action:
- one sphere with the virtual nano-hand ("nano_hand": localize on it, zigzag chosen from the
  uncertainties, aimed at the goal, open loop), 500 nm along -y;
- one with the closed loop ("closed_loop": the same zigzag in legs, observed between them by
  local scan lines across a static neighbour and the particle, re-planned), 500 nm along -y;
- one with centre pushing ("center"), 500 nm along -y;
- with --table-7-6, instead of centre pushing, the book's 13-step push: Table 7.6 parameters
  (156/120 nm pushes and backs, paths 120 nm apart, 36 nm steps), 13 steps along -y.
The order of the strategies rotates with the seed. Success: the true displacement (ground
truth, brought into the map's own frame, the frame the goal is given in:
afm_core.evaluation.maps_frame_matrix of the same 0/90 pair on a drift-free copy of the
simulator, about 4 % smaller than the sample on the default scanner where a creep-free step
is 6 %: creep shortens the fast axis by 2 %, which the pair's drift correction puts on both
axes) within 20 nm of the planned one; the same error in the creep-free step's frame
(image_frame_matrix, the figure before 2026-11-28) beside it. Also the action's own verdict
(the rescan) and the run time per push.

Run: `scripts/with_env.sh python bench/bench_push_graph.py [--seeds 20]` (~10 min).
Results: bench/results/push_graph.json.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import platform
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import command_line, cpu_model  # noqa: E402

from afm_bringup.commander import AfmCommander  # noqa: E402
from afm_bringup.demo import peak_rss_bytes  # noqa: E402
from afm_bringup.launcher import Graph  # noqa: E402
from afm_bringup.units import length_type  # noqa: E402
from afm_core.evaluation import image_frame_matrix, maps_frame_matrix  # noqa: E402
from afm_core.imaging.raster_approach import RASTER_APPROACH_OVERSHOOT  # noqa: E402
from afm_core.instrument import ScanRequest  # noqa: E402
from afm_core.manipulation.verdict import verdict_shares  # noqa: E402
from afm_core.sim.config import load_config, merge  # noqa: E402
from afm_msgs.action import PushParticle  # noqa: E402
from afm_msgs.msg import GroundTruth, LandmarkArray  # noqa: E402
from afm_ros.exposure import isolate_run  # noqa: E402
from afm_ros.qos_profiles import LATCHED  # noqa: E402

RESULTS_DIR = Path(__file__).resolve().parent / "results"
NM = 1e-9
SPHERES = [(54.2e-6, 55.0e-6), (55.0e-6, 55.0e-6), (55.8e-6, 55.0e-6)]
SCAN_ORIGIN, SCAN_SIZE, SCAN_PIXELS = (53.8e-6, 53.9e-6), 2.4e-6, 256
PUSH = 500 * NM
TOLERANCE = 20 * NM
# true per map displacement of a creep-free step (evaluation only): the frame of the figures
# before 2026-11-28, kept beside them
IMAGE_FRAME = image_frame_matrix()
MAP_SCANS = [
    ScanRequest(*SCAN_ORIGIN, SCAN_SIZE, SCAN_SIZE, SCAN_PIXELS, SCAN_PIXELS, angle, True, 4.0)
    for angle in (0.0, 90.0)
]


@functools.cache
def maps_frame() -> np.ndarray:
    """True per map displacement of the map's own frame (evaluation only): the bench's 0/90
    pair, approached as the driver does, on a drift-free copy of the default simulator (the
    pair's correction takes the drift out; about 20 s)."""
    quiet = merge(load_config(), {"drift": {"enabled": False}})
    return maps_frame_matrix(quiet, MAP_SCANS, float(RASTER_APPROACH_OVERSHOOT.default))


CALIBRATION = (
    Path(__file__).resolve().parents[1] / "afm_localization" / "config" / "sim_calibration.yaml"
)


def run_seed(
    seed: int, workdir: Path, log, table: bool = False, tolerance: float = TOLERANCE
) -> list[dict]:
    config = workdir / f"sim-{seed}.yaml"
    config.write_text(
        yaml.safe_dump(
            {"sample": {"spheres": [{"x": x, "y": y, "radius": 100e-9} for x, y in SPHERES]}}
        )
    )
    graph = Graph(workdir / f"logs-{seed}")
    calibrated = {"calibration_file": str(CALIBRATION)}
    graph.start(
        "driver", {"seed": str(seed), "real_time_factor": "0.0", "sim_config": str(config)}
    )
    graph.start("imaging")
    for name in ("localizer", "planner", "nano_hand"):
        graph.start(name, calibrated)
    rows = []
    try:
        with AfmCommander(server_timeout=60.0) as afm:
            maps, truths = [], []
            afm.node.create_subscription(LandmarkArray, "/afm/landmarks", maps.append, LATCHED)
            afm.node.create_subscription(GroundTruth, "/afm/ground_truth", truths.append, LATCHED)
            afm.wait_until_subscribed(["/afm/scan"], "afm_imaging", timeout=60.0)
            for angle in (0.0, 90.0):
                afm.scan(
                    SCAN_ORIGIN,
                    (SCAN_SIZE, SCAN_SIZE),
                    (SCAN_PIXELS, SCAN_PIXELS),
                    angle_deg=angle,
                    line_rate=4.0,
                    pair_id=f"bench-{seed}",
                )
            deadline = time.monotonic() + 60
            while not (maps and len(maps[-1].landmarks) >= 3) and time.monotonic() < deadline:
                time.sleep(0.1)
            if not (maps and len(maps[-1].landmarks) >= 3):
                raise RuntimeError(
                    f"seed {seed}: the imaging node mapped "
                    f"{len(maps[-1].landmarks) if maps else 0} "
                    f"of the 3 spheres (logs in {graph.log_dir})"
                )
            marks = sorted(maps[-1].landmarks, key=lambda lm: lm.position.x)
            jobs = [
                ("nano_hand", {}),
                ("closed_loop", {}),
                ("center", {}),
                (
                    "table_7_6",
                    {
                        "push_length": 156 * NM,
                        "back_length": 120 * NM,
                        "lateral_offset": 60 * NM,
                        "step_length": 36 * NM,
                        "max_steps": 13,
                    },
                ),
            ]
            jobs = jobs[:2] + [jobs[3] if table else jobs[2]]
            shift = seed % len(jobs)
            jobs = jobs[shift:] + jobs[:shift]
            for mark, (name, overrides) in zip(marks, jobs):
                start = np.array([mark.position.x, mark.position.y])
                distance = PUSH if name != "table_7_6" else 530 * NM  # the book's measured reach
                goal = start + np.array([0.0, -distance])
                truth_before = true_position(truths[-1], start)
                request = PushParticle.Goal(
                    particle_id=int(mark.id),
                    strategy="nano_hand" if name == "table_7_6" else name,
                    tolerance=tolerance,
                    **overrides,
                )
                request.goal.x, request.goal.y = map(float, goal)
                began = time.monotonic()
                result = afm.send("push_particle", request, timeout=900)
                seconds = time.monotonic() - began
                time.sleep(0.3)  # the last ground truth arrives
                shift = true_position(truths[-1], truth_before) - truth_before
                moved = np.linalg.solve(maps_frame(), shift)
                wanted = goal - start
                error = float(np.linalg.norm(moved - wanted))
                creep_free = float(np.linalg.norm(np.linalg.solve(IMAGE_FRAME, shift) - wanted))
                rows.append(
                    {
                        "seed": seed,
                        "strategy": name,
                        "ran": result.steps > 0,
                        "message": result.message,
                        "along": float(-moved[1]),
                        "sideways": float(moved[0]),
                        "true_error": error,
                        "true_error_creep_free": creep_free,
                        # the yardstick, whatever the push was asked for
                        "success": bool(result.steps > 0 and error <= TOLERANCE),
                        "verified_error": float(result.error),
                        "verified_success": bool(result.success),
                        "verified_sigma": float(result.error_sigma),
                        "verdict": result.verdict,
                        "asked_tolerance": float(tolerance),
                        "steps": int(result.steps),
                        "seconds": seconds,
                        "push_seconds": float(result.duration),
                        "lines": int(result.lines),
                        "observations": int(result.observations),
                        "slid": float(result.slid),
                    }
                )
                log(
                    f"seed {seed} {name:9s}: along {rows[-1]['along'] / NM:6.1f} nm, sideways "
                    f"{rows[-1]['sideways'] / NM:6.1f} nm, true error {error / NM:5.1f} nm, "
                    "verified "
                    f"{result.error / NM:5.1f} nm ({seconds:.1f} s)"
                )
        memory = sum(peak_rss_bytes(p.pid) for p in graph.processes.values())
        for row in rows:
            row["graph_peak_bytes"] = memory
    finally:
        graph.stop_all()
    return rows


def true_position(truth: GroundTruth, near) -> np.ndarray:
    spheres = [np.array([o.position.x, o.position.y]) for o in truth.objects if o.kind == 0]
    return min(spheres, key=lambda p: math.hypot(*(p - near)))


def summarise(rows: list[dict]) -> dict:
    out = {}
    for name in ("nano_hand", "closed_loop", "center", "table_7_6"):
        mine = [r for r in rows if r["strategy"] == name and r["ran"]]
        if not mine:
            continue
        out[name] = {
            "runs": len([r for r in rows if r["strategy"] == name]),
            "ran": len(mine),
            "success_rate": float(np.mean([r["success"] for r in mine])),
            "within_10nm": float(np.mean([r["true_error"] <= 10 * NM for r in mine])),
            "true_error_p95_nm": float(np.percentile([r["true_error"] for r in mine], 95) / NM),
            "instrument_seconds_median": float(np.median([r["push_seconds"] for r in mine])),
            "lines_median": float(np.median([r["lines"] for r in mine])),
            "observations_mean": float(np.mean([r["observations"] for r in mine])),
            "verified_success_rate": float(np.mean([r["verified_success"] for r in mine])),
            "true_error_median_nm": float(np.median([r["true_error"] for r in mine]) / NM),
            **creep_free_figures(mine),
            "along_mean_nm": float(np.mean([r["along"] for r in mine]) / NM),
            "along_sd_nm": float(np.std([r["along"] for r in mine]) / NM),
            "sideways_mean_nm": float(np.mean([r["sideways"] for r in mine]) / NM),
            "sideways_abs_max_nm": float(np.max(np.abs([r["sideways"] for r in mine])) / NM),
            "seconds_median": float(np.median([r["seconds"] for r in mine])),
            **verdict_agreement(mine),
        }
    return out


def creep_free_figures(mine: list[dict]) -> dict:
    """The figures in the creep-free step's frame (before 2026-11-28), where the rows have it."""
    errors = np.array([r["true_error_creep_free"] for r in mine if "true_error_creep_free" in r])
    if not len(errors):
        return {}
    return {
        "creep_free_within_20nm": float(np.mean(errors <= TOLERANCE)),
        "creep_free_within_10nm": float(np.mean(errors <= 10 * NM)),
        "creep_free_median_nm": float(np.median(errors) / NM),
    }


def verdict_agreement(mine: list[dict]) -> dict:
    """The action's own verdict against the truth at the tolerance each push was asked for:
    success (verdict "within tolerance") as a yes/no, and the stated verdict (within / outside
    / cannot tell at this tolerance) over the definite ones."""
    truly = np.array([r["true_error"] <= r["asked_tolerance"] for r in mine])
    success = np.array([r["verified_success"] for r in mine])
    verdicts = [r.get("verdict", "") for r in mine]
    return {
        "verdict_agreement": float(np.mean(success == truly)),
        **verdict_shares(verdicts, truly),
        "verified_sigma_median_nm": float(np.median([r["verified_sigma"] for r in mine]) / NM),
    }


def markdown_report(result: dict, command: str) -> str:
    """bench/results/push_graph.md: the summary table, headed with date, machine, command."""
    m = result["machine"]
    names = {
        "nano_hand": "virtual nano-hand (chosen parameters, aimed), open loop",
        "closed_loop": "closed loop (nano-hand legs, local scans between them)",
        "center": "centre pushing",
        "table_7_6": "Table 7.6, 13 steps (book: 530 nm along, 20 nm sideways; simulated 507)",
    }
    lines = [
        "# Pushes through the whole graph on the simulated AFM",
        "",
        f"Measured {result['date']} on {m['cpu_count']} CPUs ({m['cpu_model']}), Python "
        f"{m['python']}, load {m['load_average_at_start'][0]:.2f} at start; "
        f"{result['wall_seconds']:.0f} s wall for {result['seeds']} seeds.",
        "",
        f"Command: `{command}`",
        "",
        f"Per seed: three spheres (r = 100 nm) mapped from a 0/90 pair, one pushed by each "
        f"strategy through PushParticle, {result['push_nm']:.0f} nm along -y (Table 7.6: its own "
        f"13 steps, goal 530 nm). Success: the true displacement, in the map's own frame "
        f"(maps_frame_matrix of the pair), within "
        f"{result['tolerance_nm']:.0f} nm of the planned one; verified: the action's own verdict "
        f"from its rescans. Each push was asked for "
        f"{result.get('asked_tolerance_nm', result['tolerance_nm']):.0f} nm.",
        "",
        "| strategy | pushes run | success (true) | within 10 nm | success (verified) | median "
        "true error | p95 | along | max sideways | s per push (median) | instrument s | lines |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, s in result["summary"].items():
        lines.append(
            f"| {names.get(name, name)} | {s['ran']} / {s['runs']} | {s['success_rate']:.2f} | "
            f"{s['within_10nm']:.2f} | "
            f"{s['verified_success_rate']:.2f} | {s['true_error_median_nm']:.1f} nm | "
            f"{s['true_error_p95_nm']:.1f} nm | "
            f"{s['along_mean_nm']:.1f} +- {s['along_sd_nm']:.1f} nm | "
            f"{s['sideways_abs_max_nm']:.1f} nm | {s['seconds_median']:.1f} | "
            f"{s['instrument_seconds_median']:.1f} | {s['lines_median']:.0f} |"
        )
    old = {k: s for k, s in result["summary"].items() if "creep_free_median_nm" in s}
    if old:
        lines += [
            "",
            "The same pushes judged in the creep-free step's frame (image_frame_matrix, the "
            "figures before 2026-11-28; within 20 nm / within 10 nm / median): "
            + "; ".join(
                f"{k} {s['creep_free_within_20nm']:.2f} / {s['creep_free_within_10nm']:.2f} / "
                f"{s['creep_free_median_nm']:.1f} nm"
                for k, s in old.items()
            ),
        ]
    lines += [
        "",
        "The action's own verdict against the truth at the tolerance asked (issue 32): "
        "success (verdict within) agreeing with the truth, and the stated verdict's shares "
        "with the agreement of its definite ones (within / outside).",
        "",
        "| strategy | success agrees | within / outside / cannot tell | agreement (definite) | "
        "sigma (median) |",
        "|---|---|---|---|---|",
    ]
    for name, s in result["summary"].items():
        lines.append(
            f"| {names.get(name, name)} | {s['verdict_agreement']:.2f} | "
            f"{s['share_within']:.2f} / {s['share_outside']:.2f} / {s['share_cannot_tell']:.2f} "
            f"| {s['agreement_definite']:.2f} | {s['verified_sigma_median_nm']:.1f} nm |"
        )
    lines += [
        "",
        f"Graph peak memory (sum of the node peaks, worst seed): "
        f"{result['graph_peak_bytes'] / 2**20:.0f} MiB.",
    ]
    missed = [r for r in result["runs"] if not r["ran"]]
    if missed:
        lines += ["", "Pushes that did not run (counted as not run above):", ""]
        lines += [f"- seed {r['seed']}, {r['strategy']}: {r['message']}" for r in missed]
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument(
        "--table-7-6", action="store_true", help="the book's 13-step push instead of centre"
    )
    parser.add_argument(
        "--tolerance",
        type=length_type("--tolerance"),
        default=TOLERANCE,
        help="what each push is asked for (default 20nm); success stays within 20 nm",
    )
    parser.add_argument("--name", default="push_graph", help="results file name in results/")
    args = parser.parse_args()
    # a domain no other process uses: another graph on the machine would answer this one's
    # goals and publish its truth on the same topics
    isolate_run()
    started = time.monotonic()

    def log(text):
        print(f"[{time.monotonic() - started:7.1f} s] {text}", flush=True)

    rows = []
    workdir = Path(tempfile.mkdtemp(prefix="bench_push_graph-"))
    log(f"node logs in {workdir}")
    # before any graph runs: the map's frame takes a simulated 0/90 pair (tens of seconds)
    log(f"map's frame, true per map displacement: {maps_frame().round(4).tolist()}")
    for seed in range(args.seeds):
        rows += run_seed(seed, workdir, log, args.table_7_6, args.tolerance)
    summary = summarise(rows)
    print(
        "\nstrategy   runs  success(true) success(verified)  median error  along (mean+-sd)  "
        "|sideways| max  s/push"
    )
    for name, s in summary.items():
        print(
            f"{name:10s} {s['ran']:4d}  {s['success_rate']:12.2f}  "
            f"{s['verified_success_rate']:16.2f}  "
            f"{s['true_error_median_nm']:9.1f} nm  {s['along_mean_nm']:6.1f} +- "
            f"{s['along_sd_nm']:4.1f} nm  "
            f"{s['sideways_abs_max_nm']:9.1f} nm  {s['seconds_median']:6.1f}"
        )
    peak = max((r["graph_peak_bytes"] for r in rows), default=0)
    print(
        f"graph peak memory (sum of node peaks, worst seed): {peak / 2**20:.0f} MiB; total "
        f"{time.monotonic() - started:.0f} s"
    )
    RESULTS_DIR.mkdir(exist_ok=True)
    result = {
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": {
            "cpu_count": os.cpu_count(),
            "cpu_model": cpu_model(),
            "python": platform.python_version(),
            "load_average_at_start": os.getloadavg(),
        },
        "seeds": args.seeds,
        "push_nm": PUSH / NM,
        "tolerance_nm": TOLERANCE / NM,
        "asked_tolerance_nm": args.tolerance / NM,
        "summary": summary,
        "graph_peak_bytes": peak,
        "runs": rows,
        "wall_seconds": time.monotonic() - started,
    }
    (RESULTS_DIR / f"{args.name}.json").write_text(json.dumps(result, indent=2))
    (RESULTS_DIR / f"{args.name}.md").write_text(markdown_report(result, command_line()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
