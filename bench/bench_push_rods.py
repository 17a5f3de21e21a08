"""Tubes pushed to a goal pose (position and axis angle) in the core (no ROS): PushProcedure on
the simulator over seeds, each seed in its own process.

Per seed (numpy's default_rng(seed) draws the case): the simulator with its default physics and
that seed; a carbon-nanotube-like tube (r = 10 nm, 600-1000 nm long, any orientation) at the
scanner's (55, 55) um and two spheres (r = 100 nm) about 1.2 um away as static landmarks; the
map from a raster image; the tip localized by the core Localizer with the simulated
instrument's calibration (afm_localization/config/sim_calibration.yaml). The goal: the map's
pose moved 150-400 nm in any direction and turned by up to 25 deg either way. The push: the
default strategy (closed_loop: the rod hand in legs, local scan lines between them) or the
open-loop rod hand (--strategies). Error: the tube's true displacement and turn (simulator
truth) against the goal's displacement and turn from the map's pose (the map's own error is
common to the start and the goal), in the map's own frame, the frame the goal is given in:
true displacements and directions through the inverse of that seed's map frame
(`evaluation.maps_frame_matrix` of the same map scan and seed: creep's 2 % on the fast axis and
the map's drift included); beside them the same in the creep-free step's frame
(`image_frame_matrix`, the figures before 2026-11-28).
The same errors in metres of the simulator (the calibrated scanner matrix's frame, ~6 % apart
in scale) are reported beside them ("metric"). Time:
instrument time of the whole push (scans, localization, strokes, observations, rescan), and
the wall time of the process.

Run: `scripts/with_env.sh python bench/bench_push_rods.py --seeds 30`
Results: bench/results/push_rods.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import command_line, machine_record  # noqa: E402

NM = 1e-9
DEG = math.pi / 180
CENTRE = (55e-6, 55e-6)
SPHERES = ((54.1e-6, 54.2e-6), (56.0e-6, 55.9e-6))
TOLERANCE = 20 * NM
ANGLE_TOLERANCE = 3 * DEG
ROOT = Path(__file__).resolve().parents[1]
CALIBRATION = ROOT / "afm_localization" / "config" / "sim_calibration.yaml"
RESULTS = ROOT / "bench" / "results"


def case(seed: int) -> dict:
    """The tube and the goal of a seed (module docstring)."""
    rng = np.random.default_rng(seed)
    angle = float(rng.uniform(-0.5 * math.pi, 0.5 * math.pi))
    length = float(rng.uniform(600, 1000)) * NM
    distance = float(rng.uniform(150, 400)) * NM
    heading = float(rng.uniform(0, 2 * math.pi))
    turn = float(rng.uniform(-25, 25)) * DEG
    return {
        "tube": {"x": CENTRE[0], "y": CENTRE[1], "angle": angle, "length": length},
        "move": [distance * math.cos(heading), distance * math.sin(heading)],
        "turn": turn,
    }


def push_once(seed: int, strategy: str) -> dict:
    from afm_core.evaluation import image_frame_matrix, maps_frame_matrix, rod_pose_against_truth
    from afm_core.imaging.landmarks import extract_landmarks
    from afm_core.instrument import ScanRequest
    from afm_core.localization import Localizer
    from afm_core.localization.calibration.model import load_calibration
    from afm_core.manipulation import PushProcedure, localize_with
    from afm_core.manipulation.rod_loop import wrap_angle
    from afm_core.sim.config import load_config, merge
    from afm_core.sim.instrument import SimulatedAfm

    c = case(seed)
    tube = {**c["tube"], "radius": 10 * NM, "kind": "tube"}
    spheres = [{"x": x, "y": y, "radius": 100 * NM} for x, y in SPHERES]
    sim = SimulatedAfm(
        merge(load_config(), {"seed": seed, "sample": {"spheres": spheres, "rods": [tube]}})
    )
    calibration = load_calibration(CALIBRATION)
    map_scan = ScanRequest(53.8e-6, 53.9e-6, 2.4e-6, 2.4e-6, 256, 256, line_rate=4.0)
    scan = sim.raster_scan(map_scan)
    marks = extract_landmarks(
        scan.height, scan.pixel_size_x, scan.pixel_size_y, scan.origin_x, scan.origin_y
    )
    landmarks = {m.id: m for m in marks}
    tubes = [m for m in marks if m.kind == "tube"]
    base = {"seed": seed, "strategy": strategy, **c}
    if len(tubes) != 1:
        return {**base, "ran": False, "message": f"the map has {len(tubes)} tubes, not 1"}
    mark = tubes[0]
    localizer = Localizer(
        sim, calibration, np.array(sim.commanded_position()), np.diag([(50 * NM) ** 2] * 2)
    )
    procedure = PushProcedure(
        sim,
        localize_with(localizer),
        lambda: landmarks,
        calibration=calibration,
        on_moved=lambda m: landmarks.__setitem__(m.id, m),
    )

    def true_tube():
        rod = next(o for o in sim.truth()["objects"] if o.kind == "tube")
        return np.array([rod.x, rod.y]), float(rod.angle)

    start = np.array([mark.x, mark.y])
    goal = start + np.array(c["move"])
    goal_angle = mark.orientation + c["turn"]
    xy0, angle0 = true_tube()
    began = time.monotonic()
    try:
        result = procedure.push(
            mark.id,
            goal,
            strategy=strategy,
            tolerance=TOLERANCE,
            goal_angle=goal_angle,
            angle_tolerance=ANGLE_TOLERANCE,
        )
    except Exception as exc:  # a failed push is a row, not the end of the run
        return {**base, "ran": False, "message": f"{type(exc).__name__}: {exc}"}
    xy1, angle1 = true_tube()
    error = float(np.hypot(*((xy1 - xy0) - (goal - start))))
    angle_error = abs(wrap_angle((angle1 - angle0) - c["turn"]))

    # true displacements and directions in a frame (true per map displacement)
    def in_frame(frame):
        score = rod_pose_against_truth(
            (*xy0, angle0), (*xy1, angle1), goal - start, c["turn"], frame
        )
        return score["error"], score["angle_error"]

    # the map's own: its scan on the same seed (drift, creep and noise do not depend on the
    # sample)
    map_error, map_angle_error = in_frame(
        maps_frame_matrix(merge(load_config(), {"seed": seed}), [map_scan])
    )
    image_error, image_angle_error = in_frame(image_frame_matrix())
    return {
        **base,
        "ran": True,
        "map_angle": float(mark.orientation),
        "true_error": error,
        "true_angle_error": float(angle_error),
        "map_error": map_error,
        "map_angle_error": map_angle_error,
        # the creep-free step's frame, the figures before 2026-11-28
        "image_frame_error": image_error,
        "image_frame_angle_error": image_angle_error,
        "verified_error": float(result.error),
        "verified_angle_error": float(result.angle_error),
        "push_seconds": float(result.cost.duration),
        "lines": int(result.cost.lines),
        "observations": int(result.cost.observations),
        "legs": int(result.cost.legs),
        "slid": float(result.cost.slid),
        "wall_seconds": time.monotonic() - began,
        "peak_memory_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "message": result.message,
    }


def summarise(rows: list[dict], strategies) -> dict:
    out = {}
    for name in strategies:
        mine = [r for r in rows if r["strategy"] == name and r["ran"]]
        if not mine:
            continue
        errors = np.array([r["map_error"] for r in mine]) / NM
        angles = np.array([r["map_angle_error"] for r in mine]) / DEG
        old = np.array([r["image_frame_error"] for r in mine]) / NM
        old_angles = np.array([r["image_frame_angle_error"] for r in mine]) / DEG
        metric = np.array([r["true_error"] for r in mine]) / NM
        metric_angles = np.array([r["true_angle_error"] for r in mine]) / DEG
        both = (errors <= TOLERANCE / NM) & (angles <= ANGLE_TOLERANCE / DEG)
        out[name] = {
            "runs": len([r for r in rows if r["strategy"] == name]),
            "ran": len(mine),
            # failed pushes count as misses
            "success_rate": float(np.sum(both) / len([r for r in rows if r["strategy"] == name])),
            "within_20nm": float(np.mean(errors <= 20)),
            "within_3deg": float(np.mean(angles <= 3)),
            "true_error_median_nm": float(np.median(errors)),
            "true_error_p95_nm": float(np.percentile(errors, 95)),
            "true_angle_error_median_deg": float(np.median(angles)),
            "true_angle_error_p95_deg": float(np.percentile(angles, 95)),
            "metric_success_rate": float(
                np.sum((metric <= TOLERANCE / NM) & (metric_angles <= ANGLE_TOLERANCE / DEG))
                / len([r for r in rows if r["strategy"] == name])
            ),
            "metric_error_median_nm": float(np.median(metric)),
            "metric_error_p95_nm": float(np.percentile(metric, 95)),
            "push_seconds_median": float(np.median([r["push_seconds"] for r in mine])),
            "wall_seconds_median": float(np.median([r["wall_seconds"] for r in mine])),
            "observations_mean": float(np.mean([r["observations"] for r in mine])),
            "lines_median": float(np.median([r["lines"] for r in mine])),
            # the creep-free step's frame, the figures before 2026-11-28
            "creep_free_success_rate": float(
                np.sum((old <= TOLERANCE / NM) & (old_angles <= ANGLE_TOLERANCE / DEG))
                / len([r for r in rows if r["strategy"] == name])
            ),
            "creep_free_error_median_nm": float(np.median(old)),
        }
    return out


def markdown(result: dict) -> str:
    m = result["machine"]
    lines = [
        "# Tubes pushed to a goal pose, in the core (PushProcedure on the simulator)",
        "",
        f"Measured {result['date']} on {m['cpu_count']} CPUs ({m['cpu_model']}), Python "
        f"{m['python']}, load {m['load_average_at_start'][0]:.2f} at start; "
        f"{result['wall_seconds']:.0f} s wall for {result['seeds']} seeds (seeds "
        f"{result['first_seed']}-{result['first_seed'] + result['seeds'] - 1}, one process "
        f"each); peak memory of a seed's process {result['peak_memory_mb']:.0f} MB.",
        "",
        f"Command: `{result['command']}`",
        "",
        "Per seed: a tube (r = 10 nm, 600-1000 nm long, any orientation) moved 150-400 nm in any "
        "direction and turned by up to 25 deg, default physics. Success: within "
        f"{TOLERANCE / NM:g} nm and {ANGLE_TOLERANCE / DEG:g} deg of the goal pose by the "
        "simulator's truth in the seed's own map frame (maps_frame_matrix; a failed push is a "
        "miss); metric: the same in the simulator's metres (~4 % apart in scale); creep-free: "
        "in the creep-free step's frame (image_frame_matrix, the figures before 2026-11-28). "
        "Time: instrument time of the whole push (before scan, localization, strokes, "
        "observations, rescan) and the process's wall time.",
        "",
        "| strategy | pushes | within 20 nm and 3 deg | within 20 nm | within 3 deg | "
        "median / p95 error | median / p95 angle error | metric: both / median / p95 | "
        "creep-free: both / median | push time (median) | wall (median) | observations | "
        "lines |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, s in result["summary"].items():
        lines.append(
            f"| {name} | {s['ran']}/{s['runs']} | {s['success_rate']:.0%} | "
            f"{s['within_20nm']:.0%} | {s['within_3deg']:.0%} | "
            f"{s['true_error_median_nm']:.1f} / {s['true_error_p95_nm']:.1f} nm | "
            f"{s['true_angle_error_median_deg']:.2f} / {s['true_angle_error_p95_deg']:.2f} deg | "
            f"{s['metric_success_rate']:.0%} / {s['metric_error_median_nm']:.1f} / "
            f"{s['metric_error_p95_nm']:.1f} nm | "
            f"{s['creep_free_success_rate']:.0%} / {s['creep_free_error_median_nm']:.1f} nm | "
            f"{s['push_seconds_median']:.0f} s | {s['wall_seconds_median']:.0f} s | "
            f"{s['observations_mean']:.1f} | {s['lines_median']:.0f} |"
        )
    lines += [
        "",
        "| seed | strategy | error | angle error | metric | verified | observations |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in result["rows"]:
        if r["ran"]:
            lines.append(
                f"| {r['seed']} | {r['strategy']} | {r['map_error'] / NM:.1f} nm | "
                f"{r['map_angle_error'] / DEG:.2f} deg | {r['true_error'] / NM:.1f} nm, "
                f"{r['true_angle_error'] / DEG:.2f} deg | {r['verified_error'] / NM:.1f} nm, "
                f"{r['verified_angle_error'] / DEG:.2f} deg | {r['observations']} |"
            )
        else:
            lines.append(f"| {r['seed']} | {r['strategy']} | - | - | - | - | {r['message']} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=30)
    parser.add_argument("--first-seed", type=int, default=1)
    parser.add_argument("--strategies", default="closed_loop", help="comma-separated")
    parser.add_argument("--out", default=str(RESULTS / "push_rods"))
    parser.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    strategies = [s for s in args.strategies.split(",") if s]
    if args.one is not None:  # a child: one seed, one strategy, its row on stdout
        print(json.dumps(push_once(args.one, strategies[0])))
        return
    load = os.getloadavg()
    began = time.monotonic()
    rows = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        for name in strategies:
            child = [sys.executable, __file__, "--one", str(seed), "--strategies", name]
            done = subprocess.run(child, capture_output=True, text=True)
            try:
                r = json.loads(done.stdout.strip().splitlines()[-1])
            except (IndexError, json.JSONDecodeError):
                r = {"seed": seed, "strategy": name, "ran": False, "message": done.stderr[-500:]}
            rows.append(r)
            print(
                f"seed {seed} {name:11s} "
                + (
                    f"error {r['map_error'] / NM:5.1f} nm "
                    f"{r['map_angle_error'] / DEG:5.2f} deg (metric "
                    f"{r['true_error'] / NM:5.1f} nm {r['true_angle_error'] / DEG:5.2f} deg),"
                    f" verified {r['verified_error'] / NM:5.1f} nm "
                    f"{r['verified_angle_error'] / DEG:5.2f} deg, {r['push_seconds']:.0f} s, "
                    f"{r['observations']} obs"
                    if r["ran"]
                    else f"failed: {r['message']}"
                ),
                flush=True,
            )
    result = {
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": machine_record(list(load)),
        "command": command_line(),
        "seeds": args.seeds,
        "first_seed": args.first_seed,
        "tolerance_nm": TOLERANCE / NM,
        "angle_tolerance_deg": ANGLE_TOLERANCE / DEG,
        "wall_seconds": time.monotonic() - began,
        "peak_memory_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024,
        "summary": summarise(rows, strategies),
        "rows": rows,
    }
    Path(args.out + ".json").write_text(json.dumps(result, indent=1))
    Path(args.out + ".md").write_text(markdown(result))
    print(markdown(result))


if __name__ == "__main__":
    main()
