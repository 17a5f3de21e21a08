"""The planner's size limits (afm_core.planning.limits): how long its requests take with size.

What is measured
----------------
In this process, one call after the other, timed with perf_counter (BLAS pinned to 1 thread):
- chain: plan_landmark_chain (what PlanPath runs) on the probe-57 map, n particles
  (R_P 50 nm, map sigma 3.2 nm) on a square grid 300 nm apart from (50, 50) um, tip at
  (49, 49) um with sigma 10 nm, the calibration's default motion noise, R_T 50 nm; a short
  route to (52, 52) um for n = 100 ... 20000, and a long one to (62, 62) um across the grid
  for n = 2000 (it runs into MAX_CHAIN_EDGES: the time to that refusal is the limit's cost);
  the short route again with radii 40-60 nm (each landmark's localization planned apart).
  Recorded: seconds, observation edges computed, chain.
- sequence_landmarks: observation_distance_matrix (PlanSequence by landmark_ids) for n
  landmarks of the same grid.
- aco / heuristic: ant_colony_order / heuristic_order on n points uniform in 10 um x 10 um.
Peak memory: this process's VmHWM at the end.

Run: `scripts/with_env.sh python bench/bench_planner_limits.py [--quick]` (~1.5 min; --quick
~20 s). Results: bench/results/planner_limits.json and planner_limits.md.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402
from datetime import datetime, timezone  # noqa: E402
from pathlib import Path  # noqa: E402
from types import SimpleNamespace  # noqa: E402

import numpy as np  # noqa: E402
from machine import command_line, machine_record  # noqa: E402

from afm_core.localization.calibration.model import Calibration  # noqa: E402
from afm_core.planning import (  # noqa: E402
    MAX_ACO_POINTS,
    MAX_CHAIN_EDGES,
    MAX_HEURISTIC_POINTS,
    MAX_SEQUENCE_LANDMARKS,
    ant_colony_order,
    heuristic_order,
    observation_distance_matrix,
    plan_landmark_chain,
)

RESULTS = Path(__file__).resolve().parent / "results"


def grid(n: int, pitch: float = 300e-9, varied: bool = False) -> list:
    """varied: radii uniform in 40-60 nm (seeded), as a real map's; else all 50 nm (a
    localization route is then planned once for all)."""
    side = int(math.ceil(math.sqrt(n)))
    cov = np.diag([3.2e-9**2] * 2)
    radii = np.random.default_rng(1).uniform(40e-9, 60e-9, n) if varied else np.full(n, 50e-9)
    return [
        SimpleNamespace(
            id=1000 + i,
            x=50e-6 + (i % side) * pitch,
            y=50e-6 + (i // side) * pitch,
            radius=float(radii[i]),
            covariance=cov,
        )
        for i in range(n)
    ]


def timed(function, *args, **kwargs):
    started = time.perf_counter()
    try:
        result, error = function(*args, **kwargs), None
    except ValueError as exc:
        result, error = None, str(exc)
    return time.perf_counter() - started, result, error


def chain_rows(sizes) -> list[dict]:
    noise = Calibration().motion_noise()
    start, cov = np.array([49e-6, 49e-6]), np.eye(2) * (10e-9) ** 2
    rows = []
    cases = [(n, 52e-6, varied) for varied in (False, True) for n in sizes]
    for n, target, varied in cases + [(2000, 62e-6, False)]:
        seconds, chain, error = timed(
            plan_landmark_chain, start, cov, grid(n, varied=varied), (target, target), 50e-9, noise
        )
        rows.append(
            {
                "landmarks": n,
                "radii": "40-60 nm" if varied else "50 nm",
                "target_um": target * 1e6,
                "seconds": round(seconds, 3),
                "edges": chain.edges_computed if chain else None,
                "chain": list(chain.landmark_ids) if chain else None,
                "refused": error,
            }
        )
        print(rows[-1], flush=True)
    return rows


def sequence_rows(quick: bool) -> list[dict]:
    rng = np.random.default_rng(0)
    rows = []
    noise = Calibration().motion_noise()
    for n in (40,) if quick else (40, 80, MAX_SEQUENCE_LANDMARKS):
        seconds, _, _ = timed(observation_distance_matrix, grid(n, 500e-9), 50e-9, noise)
        rows.append({"what": "sequence_landmarks", "n": n, "seconds": round(seconds, 3)})
        print(rows[-1], flush=True)
    for what, solver, sizes in (
        ("aco", ant_colony_order, (50,) if quick else (50, 100, MAX_ACO_POINTS, 200)),
        ("heuristic", heuristic_order, (200,) if quick else (200, MAX_HEURISTIC_POINTS, 1000)),
    ):
        for n in sizes:
            p = rng.uniform(0, 10e-6, (n, 2))
            d = np.hypot(*(p[:, None, :] - p[None, :, :]).transpose(2, 0, 1))
            seconds, _, _ = timed(solver, d)
            rows.append({"what": what, "n": n, "seconds": round(seconds, 3)})
            print(rows[-1], flush=True)
    return rows


def peak_rss_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    load = os.getloadavg()[0]
    sizes = (100, 500) if args.quick else (100, 500, 2000, 20000)
    result = {
        "when": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": machine_record(load),
        "limits": {
            "MAX_CHAIN_EDGES": MAX_CHAIN_EDGES,
            "MAX_SEQUENCE_LANDMARKS": MAX_SEQUENCE_LANDMARKS,
            "MAX_ACO_POINTS": MAX_ACO_POINTS,
            "MAX_HEURISTIC_POINTS": MAX_HEURISTIC_POINTS,
        },
        "chain": chain_rows(sizes),
        "sequencing": sequence_rows(args.quick),
    }
    result["peak_rss_mib"] = round(peak_rss_mib(), 1)
    name = "planner_limits-quick" if args.quick else "planner_limits"
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{name}.json").write_text(json.dumps(result, indent=1) + "\n")
    lines = [
        f"# Planner limits ({result['when']}, load {load:.2f}, {result['machine']['cpu_model']})",
        "",
        f"Command: `{command_line()}`",
        "",
        "| landmarks | radii | target (um) | s | edges | chain / refused |",
        "|---|---|---|---|---|---|",
    ]
    for row in result["chain"]:
        what = row["refused"][:60] + "..." if row["refused"] else row["chain"]
        lines.append(
            f"| {row['landmarks']} | {row['radii']} | {row['target_um']:.0f} | {row['seconds']} | "
            f"{row['edges']} | {what} |"
        )
    lines += ["", "| request | n | s |", "|---|---|---|"]
    lines += [f"| {r['what']} | {r['n']} | {r['seconds']} |" for r in result["sequencing"]]
    lines += ["", f"Peak RSS {result['peak_rss_mib']} MiB.", ""]
    (RESULTS / f"{name}.md").write_text("\n".join(lines))


if __name__ == "__main__":
    main()
