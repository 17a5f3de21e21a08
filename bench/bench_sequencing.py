"""Particle sequencing: the book's ant colony against our solver, on random instances.

What is measured
----------------
Instances: n particles uniform in a 4 um x 4 um square (seeded), Euclidean distances in metres;
the cost of an order is the sum of the distances between consecutive particles (open path,
free start and end), as for the book's Table 6.5 / 6.6 (afm_core.planning.sequencing).
Sizes 16 (3 instances), 50 (2) and 200 (1); --quick: one of each and shorter reference runs.

Solvers, each timed with perf_counter around the call, in this process, one after the other:
- aco: ant_colony_order with its defaults (Ant System: 200 iterations, one ant per particle,
  alpha 1, beta 2, rho 0.5; the book prints no parameter values), seed 0;
- ours: best_order (exact Held-Karp for n <= 16, else multi-start nearest neighbour with
  2-opt + Or-opt);
- best known: for n = 16 the exact optimum (ours, proved); for n > 16 the best of an iterated
  local search (heuristic_order with random double-bridge kicks, a few seeds) and of the two
  solvers above. Gaps are cost / best known - 1.
Peak memory: this process's VmHWM at the end (all solvers), as bench_simulator records it.
BLAS threads are pinned to 1 (the solvers are numpy loops, not BLAS-bound).

Run: `scripts/with_env.sh python bench/bench_sequencing.py [--quick]` (~2.5 min on 2 shared cores;
--quick ~45 s).
Results: bench/results/sequencing.json (sequencing-quick.json for --quick).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from datetime import datetime, timezone  # noqa: E402
from importlib.metadata import version  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from machine import cpu_model  # noqa: E402

from afm_core.planning.sequencing import (  # noqa: E402
    EXACT_LIMIT,
    AntColonyParameters,
    ant_colony_order,
    best_order,
    exact_order,
    heuristic_order,
)

RESULTS = Path(__file__).resolve().parent / "results"
SQUARE = 4e-6  # m


def peak_rss_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def instance(n: int, seed: int) -> np.ndarray:
    points = np.random.default_rng(seed).uniform(0.0, SQUARE, (n, 2))
    return np.linalg.norm(points[:, None, :] - points[None, :, :], axis=-1)


def timed(solver, *args, **kwargs):
    start = time.perf_counter()
    result = solver(*args, **kwargs)
    return result, time.perf_counter() - start


def reference(d: np.ndarray, seeds: int, kicks: int):
    """Best known order: exact when small enough, else iterated local search over a few seeds."""
    if d.shape[0] <= EXACT_LIMIT:
        result, seconds = timed(exact_order, d)
        return result, seconds, "exact (Held-Karp)"
    best, total = None, 0.0
    for seed in range(seeds):
        result, seconds = timed(heuristic_order, d, starts=16, kicks=kicks, seed=seed)
        total += seconds
        if best is None or result.cost < best.cost:
            best = result
    return best, total, f"iterated local search, {seeds} seeds x {kicks} kicks"


def run_case(n: int, seed: int, quick: bool) -> dict:
    d = instance(n, seed)
    aco, aco_s = timed(ant_colony_order, d, seed=0)
    ours, ours_s = timed(best_order, d)
    kicks = {50: 150, 200: 100}.get(n, 0) // (4 if quick else 1)
    ref, ref_s, how = reference(d, 2 if quick or n > 50 else 3, kicks)
    best = min(aco.cost, ours.cost, ref.cost)
    row = {
        "n": n,
        "instance_seed": seed,
        "aco": {"cost_m": aco.cost, "seconds": aco_s, "gap": aco.cost / best - 1},
        "ours": {
            "method": ours.method,
            "optimal": ours.optimal,
            "cost_m": ours.cost,
            "seconds": ours_s,
            "gap": ours.cost / best - 1,
        },
        "best_known": {
            "cost_m": best,
            "how": how,
            "seconds": ref_s,
            "proved_optimal": n <= EXACT_LIMIT,
        },
    }
    print(
        f"n={n:4d} seed={seed}: aco {aco.cost * 1e6:8.4f} um ({aco_s:6.2f} s, gap "
        f"{row['aco']['gap']:6.2%}) | "
        f"ours[{ours.method}] {ours.cost * 1e6:8.4f} um ({ours_s:6.2f} s, gap "
        f"{row['ours']['gap']:6.2%}) | "
        f"best {best * 1e6:8.4f} um ({how}, {ref_s:.1f} s)",
        flush=True,
    )
    return row


def markdown_report(result: dict, command: str) -> str:
    """bench/results/sequencing*.md: per size and per instance, headed with date, machine and
    command."""
    m, aco = result["machine"], result["settings"]["aco"]

    def span(values, unit="") -> str:
        low, high = min(values), max(values)
        return f"{low:.2f}{unit}" if low == high else f"{low:.2f}-{high:.2f}{unit}"

    lines = [
        "# Particle sequencing: the book's ant colony against our solver",
        "",
        f"Measured {result['measured']} on {m['cpus']} CPUs ({m['cpu']}), Python {m['python']}, "
        f"load {m['loadavg_start'][0]:.2f} at start; peak memory {result['peak_rss_mib']:.0f} "
        "MiB, "
        f"{result['wall_seconds']:.0f} s in all.",
        "",
        f"Command: `{command}`",
        "",
        f"Points uniform in a {result['settings']['square_m'] * 1e6:.0f} um square, Euclidean "
        f"distances, open path. ACO: Ant System, {aco['iterations']} iterations, one ant per "
        f"particle, alpha {aco['alpha']:g}, beta {aco['beta']:g}, rho {aco['evaporation']:g}. "
        f"Ours: exact up to {result['settings']['exact_limit']} particles, heuristic above. "
        "Gap = cost / best known - 1.",
        "",
        "| n | instances | ACO gap | ACO time (s) | ours | ours gap | ours time (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for n in sorted({c["n"] for c in result["cases"]}):
        cs = [c for c in result["cases"] if c["n"] == n]
        lines.append(
            f"| {n} | {len(cs)} | {span([c['aco']['gap'] * 100 for c in cs], ' %')} | "
            f"{span([c['aco']['seconds'] for c in cs])} | {cs[0]['ours']['method']} | "
            f"{span([c['ours']['gap'] * 100 for c in cs], ' %')} | "
            f"{span([c['ours']['seconds'] for c in cs])} |"
        )
    lines += [
        "",
        "| n | instance | ACO cost (um) | ACO time (s) | ours cost (um) | ours time (s) "
        "| best known (um) | how |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for c in result["cases"]:
        lines.append(
            f"| {c['n']} | {c['instance_seed']} | {c['aco']['cost_m'] * 1e6:.4f} | "
            f"{c['aco']['seconds']:.2f} | {c['ours']['cost_m'] * 1e6:.4f} | "
            f"{c['ours']['seconds']:.2f} | {c['best_known']['cost_m'] * 1e6:.4f} | "
            f"{c['best_known']['how']} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick", action="store_true", help="one instance per size, shorter reference runs"
    )
    args = parser.parse_args()
    cases = (
        [(16, 1), (50, 1), (200, 1)]
        if args.quick
        else [(16, 1), (16, 2), (16, 3), (50, 1), (50, 2), (200, 1)]
    )
    wall = time.perf_counter()
    result = {
        "measured": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": {
            "cpus": os.cpu_count(),
            "cpus_usable": len(os.sched_getaffinity(0)),
            "cpu": cpu_model(),
            "python": platform.python_version(),
            "platform": platform.platform(),
            "loadavg_start": list(os.getloadavg()),
            "packages": {name: version(name) for name in ("numpy", "scipy")},
        },
        "settings": {
            "square_m": SQUARE,
            "aco": AntColonyParameters().__dict__,
            "exact_limit": EXACT_LIMIT,
            "quick": args.quick,
        },
        "cases": [run_case(n, seed, args.quick) for n, seed in cases],
    }
    result["machine"]["loadavg_end"] = list(os.getloadavg())
    result["peak_rss_mib"] = peak_rss_mib()
    result["wall_seconds"] = time.perf_counter() - wall
    RESULTS.mkdir(exist_ok=True)
    name = "sequencing-quick" if args.quick else "sequencing"
    (RESULTS / f"{name}.json").write_text(json.dumps(result, indent=2))
    (RESULTS / f"{name}.md").write_text(
        markdown_report(
            result,
            "scripts/with_env.sh python bench/bench_sequencing.py"
            + (" --quick" if args.quick else ""),
        )
    )
    lines = [
        "",
        f"Sequencing, measured {result['measured']} on {result['machine']['cpus']} CPUs "
        f"({result['machine']['cpu']}), Python {result['machine']['python']}, "
        f"load {result['machine']['loadavg_start'][0]:.2f}; peak memory "
        f"{result['peak_rss_mib']:.0f} MiB; "
        f"{result['wall_seconds']:.0f} s in all.",
        "",
        "| n | instance | ACO cost (um) | ACO gap | ACO time (s) | ours | ours cost (um) | ours "
        "gap | "
        "ours time (s) | best known (um) | how |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in result["cases"]:
        lines.append(
            f"| {c['n']} | {c['instance_seed']} | {c['aco']['cost_m'] * 1e6:.4f} | "
            f"{c['aco']['gap']:.2%} | "
            f"{c['aco']['seconds']:.2f} | {c['ours']['method']} | {c['ours']['cost_m'] * 1e6:.4f} "
            "| "
            f"{c['ours']['gap']:.2%} | {c['ours']['seconds']:.2f} | "
            f"{c['best_known']['cost_m'] * 1e6:.4f} | "
            f"{c['best_known']['how']} |"
        )
    print("\n".join(lines))


if __name__ == "__main__":
    main()
