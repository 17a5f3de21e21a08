"""Throughput of `afm batch` on Dask: items per minute with 1 and 2 workers of an embedded
LocalCluster for `evaluate` and the sweeps (`push`, `montecarlo`, `localize`), the scheduler's
overhead per task, the peak memory of the workers, and the scaling a cluster would give.

The recordings are short simulated sessions of the work sample (a 0/90 deg pair of 128x128
rasters over 3 um, a push stroke through a particle, the pair again), written once into a
temporary folder. Each batch
runs on a fresh cluster and a fresh output folder (nothing skipped); its time is from the
first submit to the last row, without the cluster's start (reported apart).

Overhead: N no-op tasks through the same cluster, one worker: wall time / N is what the
scheduler, the transport and the worker add to each task. The scaling model is scaling()'s.

Usage: scripts/with_env.sh python bench/bench_batch.py [--recordings 24] [--seeds 0-11]
Results: bench/results/batch.md
"""

from __future__ import annotations

import argparse
import importlib
import os
import resource
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import command_line, machine_record  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "batch.md"
NOOP_TASKS = 200


def write_sessions(folder: Path, count: int) -> list[Path]:
    from afm_core.instrument import ScanRequest
    from afm_core.sim.config import merge
    from afm_core.sim.instrument import SimulatedAfm
    from afm_core.sim2real.session_writer import RecordingInstrument
    from afm_core.sim2real.work_session import WORK_SPHERES, work_config

    x, y = WORK_SPHERES[0]
    cx, cy = np.mean(WORK_SPHERES, axis=0)
    pair = [
        ScanRequest(cx - 1.5e-6, cy - 1.5e-6, 3e-6, 3e-6, 128, 128, angle, line_rate=8.0)
        for angle in (0.0, 90.0)
    ]
    paths = []
    for seed in range(1, count + 1):
        path = folder / f"session_{seed:03d}.mcap"
        config = merge(work_config(), {"seed": seed})
        with RecordingInstrument(SimulatedAfm(config), path) as rec:
            for scan in pair:
                rec.raster_scan(scan)
            rec.move_tip(x - 0.3e-6, y, 1e-6)
            rec.move_tip(x + 0.3e-6, y, 1e-7, contact=True)
            for scan in pair:
                rec.raster_scan(scan)
        paths.append(path)
    return paths


def _peak_rss_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: KiB


def _noop(i: int) -> int:
    return i


WARM = {  # what each kind's worker imports once before the clock starts (the cluster's start)
    "evaluate": ["afm_core.batch.evaluate"],
    "push": ["afm_core.manipulation.push_trials", "afm_core.sim.instrument"],
    "montecarlo": ["afm_core.manipulation.push_trials", "afm_core.physics.pushing"],
    "localize": ["afm_core.localization.trials"],
}
# the sweeps as `afm batch` runs them by default (push: the aimed nano-hand, 500 nm; Monte
# Carlo: 500 draws of the nano-hand plan; localize: the Localize action's path, oracle
# calibration, computed once per batch on a worker and inside the batch's time)
SWEEPS = ("push", "montecarlo", "localize")


def measure(kind: str, items, workers: int, scratch: Path) -> dict:
    from afm_core.batch import dask_client, read_rows, run_batch

    t0 = time.perf_counter()
    with dask_client(workers=workers) as client:
        # each worker imports the kind's code once before the clock starts (~1 s of imports
        # per worker process is the cluster's start, not the items')
        for module in WARM[kind]:
            client.run(importlib.import_module, module)
        started = time.perf_counter() - t0
        result = run_batch(kind, items, scratch / f"{kind}-w{workers}", client=client)
        peaks = client.run(_peak_rss_bytes)
        overhead = None
        if workers == 1 and kind == "evaluate":
            t1 = time.perf_counter()
            client.gather(client.map(_noop, range(NOOP_TASKS), pure=False))
            overhead = (time.perf_counter() - t1) / NOOP_TASKS
    return {
        "kind": kind,
        "items": result.total,
        "workers": workers,
        "cluster_start_s": started,
        "seconds": result.seconds,
        "ok": result.ok,
        "failed": result.failed,
        "per_minute": 60.0 * result.computed / result.seconds,
        # the time inside the tasks (reading and evaluating), without scheduling and waiting
        "task_s": float(np.mean([float(r["seconds"]) for r in read_rows(result.table)])),
        "worker_peak_rss": max(peaks.values()),
        "overhead_s": overhead,
    }


def _row(run: dict) -> str:
    return (
        f"| {run['kind']} | {run['items']} | {run['workers']} | {run['per_minute']:.1f} | "
        f"{60 / run['per_minute']:.3f} | {run['task_s']:.3f} | {run['ok']} | {run['failed']} | "
        f"{run['cluster_start_s']:.1f} | {run['worker_peak_rss'] / 2**20:.0f} |"
    )


def markdown(runs: list[dict], count: int, size: int, machine: dict, command: str) -> str:
    one = next(r for r in runs if r["kind"] == "evaluate" and r["workers"] == 1)
    two = next(r for r in runs if r["kind"] == "evaluate" and r["workers"] == 2)
    overhead = one["overhead_s"]
    lines = [
        "# Batches on Dask (`afm batch`): throughput and scaling",
        "",
        f"Date: {datetime.now(timezone.utc).strftime('%Y-%m-%d %H:%M UTC')}  ",
        f"Machine: {machine['cpu_count']} CPUs ({machine['cpu_model']}), Python "
        f"{machine['python']}, load average at start {machine['load_average_at_start']}, "
        f"at the end {[round(x, 2) for x in os.getloadavg()]}  ",
        f"Command: `{command}`",
        "",
        f"`evaluate`: {count} simulated sessions of {size / 1e6:.2f} MB each (four 128x128 "
        "rasters, a push), evaluated against their ground truth. The sweeps (`push`, "
        "`montecarlo`, `localize`) with their defaults over a few seeds. A fresh embedded "
        "LocalCluster per row (its start, with each worker's imports, apart); items/min is "
        "from the first submit to the last row.",
        "",
        "| kind | items | workers | items/min | wall s per item | s in the task | ok | failed "
        "| cluster start s | worker peak RSS MiB |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        *(_row(run) for run in runs),
        "",
        f"`evaluate` speed-up from 1 to 2 workers: {two['per_minute'] / one['per_minute']:.2f}x.",
        "",
        f"Scheduler overhead per task: {overhead * 1e3:.2f} ms ({NOOP_TASKS} no-op tasks, "
        "one worker).",
        "",
        *scaling(runs, overhead),
    ]
    return "\n".join(lines) + "\n"


def scaling(runs: list[dict], overhead: float) -> list[str]:
    """A cluster of W workers from the one-worker rows: each worker does an item per t + c
    (t in the task, c the rest of the one-worker wall time per item: its scheduling, the hash
    task of a recording, the row written), until the scheduler, which handles every task in
    turn, saturates at 1 / (k overhead) items per second (k tasks per item: 2 for a
    recording, its hash and its work, 1 for a seed)."""
    lines = [
        "Expected on a cluster of W workers: min(W / (t + c), 1 / (k o)) items per second, with "
        "t the time in the task and c the rest of the wall time per item on one worker "
        "(scheduling, a recording's hash task, writing its row), o the scheduler's overhead "
        "per task and k the tasks per item (2 for a recording: hash and work; 1 for a seed). "
        "Per-item work parallelises; the scheduler and the one client that writes the table "
        "are the serial part. c also holds what a batch pays once (the first task's latency; "
        "for localize the oracle calibration, ~3 s on one worker) spread over its items, so "
        "it shrinks with longer batches and the W columns are on the low side. A sim2real "
        "diagnosis (t ~ 60 s) is far from the ceiling: W "
        "workers diagnose about W recordings per minute.",
        "",
        "| kind | t s | c s | k | W = 4 | W = 16 | W = 64 | W = 256 | ceiling (items/min) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for run in (r for r in runs if r["workers"] == 1):
        t = run["task_s"]
        c = max(60.0 / run["per_minute"] - t, 0.0)
        k = 2 if run["kind"] == "evaluate" else 1
        ceiling = 60.0 / (k * overhead)
        rates = [f"{min(60.0 * w / (t + c), ceiling):.0f}" for w in (4, 16, 64, 256)]
        lines.append(
            f"| {run['kind']} | {t:.3f} | {c:.3f} | {k} | {' | '.join(rates)} | {ceiling:.0f} |"
        )
    lines.append(
        "| sim2real (not measured here) | ~60 | - | 2 | 4 | 16 | 64 | 256 | "
        f"{60.0 / (2 * overhead):.0f} |"
    )
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--recordings", type=int, default=24)
    parser.add_argument("--seeds", default="0-11", help="the sweeps' seeds (default 0-11)")
    parser.add_argument("--output", default=str(RESULTS))
    args = parser.parse_args()
    load = [round(x, 2) for x in os.getloadavg()]
    with tempfile.TemporaryDirectory(prefix="afm-bench-batch-") as tmp:
        folder = Path(tmp) / "sessions"
        folder.mkdir()
        paths = write_sessions(folder, args.recordings)
        size = sum(p.stat().st_size for p in paths) / len(paths)
        runs = [measure("evaluate", [folder], w, Path(tmp)) for w in (1, 2)]
        for kind in SWEEPS:
            runs += [measure(kind, args.seeds, w, Path(tmp)) for w in (1, 2)]
    text = markdown(runs, args.recordings, size, machine_record(load), command_line())
    Path(args.output).write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
