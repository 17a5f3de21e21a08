"""Simulator speed: one 512x512 raster with a 41x41-pixel tip and drift, and the ratio of
simulated to wall time over a 10-minute push session.

Run: `make bench` (with the recording benchmark) or
`scripts/with_env.sh python bench/bench_simulator.py [--quick]`.
Writes bench/results/simulator.json and simulator.md. Wall times are medians over
repetitions, timed with perf_counter in this process; peak memory is this process's
VmHWM. Targets (issue 3): the scan in <= 2 s; the session at >= 100x real time.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from afm_core.instrument import LineRequest, ScanRequest
from afm_core.sim.config import load_config, merge
from afm_core.sim.instrument import SimulatedAfm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import command_line  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
TIP_PIXELS = 41


def peak_rss_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def scan_with_41_pixel_tip(afm: SimulatedAfm) -> tuple[ScanRequest, tuple]:
    """A 512x512 request whose pixel makes the imaging tip grid exactly 41x41."""
    depth = afm._imaging_depth()
    for pixel_nm in np.arange(2.0, 20.0, 0.05):
        grid = afm.tip.grid(pixel_nm * 1e-9, depth)
        if grid.shape[0] == TIP_PIXELS:
            size = 512 * pixel_nm * 1e-9
            return ScanRequest(
                5e-6 - size / 2, 5e-6 - size / 2, size, size, 512, 512, line_rate=1.0
            ), grid.shape
    raise RuntimeError("no pixel size gives a 41x41 tip")


def bench_scan(repetitions: int) -> dict:
    times = []
    for rep in range(repetitions):
        afm = SimulatedAfm(merge(load_config(), {"seed": rep}))
        assert afm.config.drift.enabled
        request, tip_shape = scan_with_41_pixel_tip(afm)
        start = time.perf_counter()
        scan = afm.raster_scan(request)
        times.append(time.perf_counter() - start)
        assert scan.complete and np.isfinite(scan.height).all()
    return {
        "wall_s_median": statistics.median(times),
        "wall_s_min": min(times),
        "wall_s_max": max(times),
        "tip_pixels": list(tip_shape),
        "pixel_nm": request.size_x / 512 * 1e9,
        "drift": True,
        "hysteresis_and_creep": True,
        "repetitions": repetitions,
    }


def push_session(afm: SimulatedAfm, sim_seconds: float) -> int:
    """What a push task does, repeated: a small overview scan, two localization lines, a
    13-step virtual nano-hand zigzag (Table 7.6 lengths), a rescan."""
    sphere = afm.sample.spheres[0]
    cycles = 0
    while afm.time < sim_seconds:
        x, y = sphere.x, sphere.y
        afm.raster_scan(ScanRequest(x - 0.6e-6, y - 0.6e-6, 1.2e-6, 1.2e-6, 64, 64, line_rate=4.0))
        afm.local_scan(LineRequest(x - 0.3e-6, y, x + 0.3e-6, y, 300, 1e-6))
        afm.local_scan(LineRequest(x, y - 0.3e-6, x, y + 0.3e-6, 300, 1e-6))
        direction = 1.0 if cycles % 2 == 0 else -1.0
        for step in range(13):
            side = 1.0 if step % 2 == 0 else -1.0
            lateral = y + side * 78e-9
            start_x = sphere.x - direction * (
                sphere.radius + afm.config.contact.tip_radius + 120e-9
            )
            afm.move_tip(start_x, lateral, 10e-6)
            afm.move_tip(
                start_x + direction * 156e-9 + direction * 120e-9, lateral, 1e-6, contact=True
            )
            afm.move_tip(start_x, lateral, 10e-6)
        cycles += 1
    return cycles


def bench_session(sim_seconds: float) -> dict:
    afm = SimulatedAfm(load_config())
    start = time.perf_counter()
    cycles = push_session(afm, sim_seconds)
    wall = time.perf_counter() - start
    return {"sim_s": afm.time, "wall_s": wall, "ratio": afm.time / wall, "cycles": cycles}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1 repetition and a 2-minute session")
    args = parser.parse_args()
    scan = bench_scan(1 if args.quick else 5)
    session = bench_session(120.0 if args.quick else 600.0)
    result = {
        "measured": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": {
            "cpus": __import__("os").cpu_count(),
            "python": platform.python_version(),
            "platform": platform.platform(),
        },
        "scan_512_tip41_drift": scan,
        "push_session": session,
        "peak_rss_mib": peak_rss_mib(),
        "quick": args.quick,
    }
    RESULTS.mkdir(exist_ok=True)
    name = "simulator-quick" if args.quick else "simulator"
    (RESULTS / f"{name}.json").write_text(json.dumps(result, indent=2))
    lines = [
        f"# Simulator speed{' (quick)' if args.quick else ''}",
        "",
        f"Measured {result['measured']} on {result['machine']['cpus']} CPUs, "
        f"Python {result['machine']['python']}.",
        "",
        f"Command: `{command_line()}`",
        "",
        "| figure | value | target |",
        "|---|---|---|",
        f"| 512x512 scan, {scan['tip_pixels'][0]}x{scan['tip_pixels'][1]}-pixel tip, "
        f"drift + hysteresis + creep (median of {scan['repetitions']}) "
        f"| {scan['wall_s_median']:.2f} s (min {scan['wall_s_min']:.2f}, "
        f"max {scan['wall_s_max']:.2f}) | <= 2 s |",
        f"| push session: simulated / wall time | {session['ratio']:.0f}x "
        f"({session['sim_s']:.0f} s simulated in "
        f"{session['wall_s']:.1f} s, {session['cycles']} push cycles) | >= 100x |",
        f"| peak resident memory | {result['peak_rss_mib']:.0f} MiB | |",
    ]
    (RESULTS / f"{name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
