"""Throughput of `afm batch evaluate` on Dask: recordings per minute with 1 and 2 workers of an
embedded LocalCluster, the scheduler's overhead per task, and the peak memory of the workers.

The recordings are short simulated sessions (a 64x64 raster of a particle, a push stroke
through it, the raster again; ~0.3 MB each), written once into a temporary folder. Each batch
runs on a fresh cluster and a fresh output folder (nothing skipped); its time is from the
first submit to the last row, without the cluster's start (reported apart).

Overhead: N no-op tasks through the same cluster, one worker: wall time / N is what the
scheduler, the transport and the worker add to each item. With the per-item time t (one
worker), a cluster of W workers is expected to give W / (t + overhead) items per second as
long as the scheduler keeps up (about 1 / overhead tasks per second at most).

Usage: scripts/with_env.sh python bench/bench_batch.py [--recordings 12]
Results: bench/results/batch.md
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

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
    scan = ScanRequest(x - 0.5e-6, y - 0.5e-6, 1e-6, 1e-6, 64, 64, line_rate=8.0)
    paths = []
    for seed in range(1, count + 1):
        path = folder / f"session_{seed:03d}.mcap"
        config = merge(work_config(), {"seed": seed})
        with RecordingInstrument(SimulatedAfm(config), path) as rec:
            rec.raster_scan(scan)
            rec.move_tip(x - 0.3e-6, y, 1e-6)
            rec.move_tip(x + 0.3e-6, y, 1e-7, contact=True)
            rec.raster_scan(scan)
        paths.append(path)
    return paths


def _peak_rss_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: KiB


def _noop(i: int) -> int:
    return i


def measure(folder: Path, workers: int, scratch: Path) -> dict:
    from afm_core.batch import dask_client, run_batch

    t0 = time.perf_counter()
    with dask_client(workers=workers) as client:
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
        "worker_peak_rss": max(peaks.values()),
        "overhead_s": overhead,
    }


def markdown(runs: list[dict], count: int, size: int, machine: dict, command: str) -> str:
    one = runs[0]
    per_item = 60.0 / one["per_minute"]
    overhead = one["overhead_s"]
    lines = [
        "# Batch evaluation on Dask (`afm batch evaluate`)",
        "",
        f"Date: {datetime.now(timezone.utc).strftime('%Y-%m-%d %H:%M UTC')}  ",
        f"Machine: {machine['cpu_count']} CPUs ({machine['cpu_model']}), Python "
        f"{machine['python']}, load average at start {machine['load_average_at_start']}  ",
        f"Command: `{command}`",
        "",
        f"{count} simulated sessions of {size / 1e6:.2f} MB each (two 64x64 rasters, a push), "
        "evaluated against their ground truth; a fresh embedded LocalCluster per row.",
        "",
        "| workers | recordings/min | s per recording | ok | failed | cluster start s "
        "| worker peak RSS MiB |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for run in runs:
        lines.append(
            f"| {run['workers']} | {run['per_minute']:.1f} | {60 / run['per_minute']:.3f} | "
            f"{run['ok']} | {run['failed']} | {run['cluster_start_s']:.1f} | "
            f"{run['worker_peak_rss'] / 2**20:.0f} |"
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
        "Expected on a cluster of W workers (W / (t + overhead), t the one-worker time per "
        "recording; the scheduler saturates near 1 / overhead tasks per second):",
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
    parser.add_argument("--recordings", type=int, default=12)
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
