"""Throughput of `afm batch evaluate` on Dask: recordings per minute with 1 and 2 workers of an
embedded LocalCluster, the scheduler's overhead per task, and the peak memory of the workers.

The recordings are short simulated sessions of the work sample (a 0/90 deg pair of 128x128
rasters over 3 um, a push stroke through a particle, the pair again), written once into a
temporary folder. Each batch
runs on a fresh cluster and a fresh output folder (nothing skipped); its time is from the
first submit to the last row, without the cluster's start (reported apart).

Overhead: N no-op tasks through the same cluster, one worker: wall time / N is what the
scheduler, the transport and the worker add to each item. With the per-item time t (one
worker), a cluster of W workers is expected to give W / (t + overhead) items per second as
long as the scheduler keeps up (about 1 / overhead tasks per second at most).

Usage: scripts/with_env.sh python bench/bench_batch.py [--recordings 24]
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


def measure(folder: Path, workers: int, scratch: Path) -> dict:
    from afm_core.batch import dask_client, read_rows, run_batch

    t0 = time.perf_counter()
    with dask_client(workers=workers) as client:
        # each worker imports the evaluation once before the clock starts (~1 s of imports
        # per worker process is the cluster's start, not the items')
        client.run(importlib.import_module, "afm_core.batch.evaluate")
        started = time.perf_counter() - t0
        result = run_batch("evaluate", [folder], scratch / f"w{workers}", client=client)
        peaks = client.run(_peak_rss_bytes)
        overhead = None
        if workers == 1:
            t1 = time.perf_counter()
            client.gather(client.map(_noop, range(NOOP_TASKS), pure=False))
            overhead = (time.perf_counter() - t1) / NOOP_TASKS
    return {
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


def markdown(runs: list[dict], count: int, size: int, machine: dict, command: str) -> str:
    one = runs[0]
    per_item = one["task_s"]
    overhead = one["overhead_s"]
    lines = [
        "# Batch evaluation on Dask (`afm batch evaluate`)",
        "",
        f"Date: {datetime.now(timezone.utc).strftime('%Y-%m-%d %H:%M UTC')}  ",
        f"Machine: {machine['cpu_count']} CPUs ({machine['cpu_model']}), Python "
        f"{machine['python']}, load average at start {machine['load_average_at_start']}  ",
        f"Command: `{command}`",
        "",
        f"{count} simulated sessions of {size / 1e6:.2f} MB each (four 128x128 rasters, a "
        "push), evaluated against their ground truth; a fresh embedded LocalCluster per row "
        "(its start, with each worker's imports, apart).",
        "",
        "| workers | recordings/min | wall s per recording | s in the task | ok | failed "
        "| cluster start s | worker peak RSS MiB |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for run in runs:
        lines.append(
            f"| {run['workers']} | {run['per_minute']:.1f} | {60 / run['per_minute']:.3f} | "
            f"{run['task_s']:.3f} | {run['ok']} | {run['failed']} | "
            f"{run['cluster_start_s']:.1f} | {run['worker_peak_rss'] / 2**20:.0f} |"
        )
    speedup = runs[-1]["per_minute"] / one["per_minute"] if len(runs) > 1 else float("nan")
    lines += [
        "",
        f"Speed-up from 1 to 2 workers: {speedup:.2f}x (the machine's other load shares its "
        "cores).",
        "",
        f"Scheduler overhead per task: {overhead * 1e3:.2f} ms ({NOOP_TASKS} no-op tasks, "
        "one worker).",
        "",
        "Expected on a cluster of W workers: W / (t + overhead), t the time in the task per "
        "recording (one worker); the scheduler saturates near 1 / overhead tasks per second. "
        "A sim2real diagnosis takes about a minute per recording (t = 60 s), so W workers "
        f"diagnose about W recordings per minute up to W ~ {60 / overhead:.0f}.",
        "",
        "| workers | recordings/min |",
        "| --- | --- |",
    ]
    ceiling = 60.0 / overhead
    for w in (4, 16, 64, 256):
        lines.append(f"| {w} | {min(60.0 * w / (per_item + overhead), ceiling):.0f} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--recordings", type=int, default=24)
    parser.add_argument("--output", default=str(RESULTS))
    args = parser.parse_args()
    load = [round(x, 2) for x in os.getloadavg()]
    with tempfile.TemporaryDirectory(prefix="afm-bench-batch-") as tmp:
        folder = Path(tmp) / "sessions"
        folder.mkdir()
        paths = write_sessions(folder, args.recordings)
        size = sum(p.stat().st_size for p in paths) / len(paths)
        runs = [measure(folder, w, Path(tmp)) for w in (1, 2)]
    text = markdown(runs, args.recordings, size, machine_record(load), command_line())
    Path(args.output).write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
