"""The largest raster the instrument allows (4096 x 4096 pixels) on the simulator: how soon the
first line comes, how long one line takes, how soon a cancel lands, and the process's peak
memory over the whole scan (the dilated field is made in tiles as lines need it, issue 30).

Run: `scripts/with_env.sh python bench/bench_scan_memory.py [--lines N]`
Writes bench/results/scan_memory.md and scan_memory.json. Peak memory is this process's VmHWM
(it includes the interpreter and numpy, ~100 MiB); the scan's own image is 4096^2 float64
(128 MiB) while it is acquired, float32 (64 MiB) when returned.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from afm_core.instrument import ScannerLimits, ScanRequest
from afm_core.sim.config import load_config, merge
from afm_core.sim.instrument import SimulatedAfm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import command_line  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def peak_rss_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def largest_request() -> ScanRequest:
    """4096 x 4096 pixels over 40 um at 1 Hz (80 um/s, under the 100 um/s slew limit)."""
    pixels = ScannerLimits().max_pixels
    return ScanRequest(30e-6, 30e-6, 40e-6, 40e-6, pixels, pixels, line_rate=1.0)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lines", type=int, default=0, help="stop after N lines (0: all)")
    args = parser.parse_args()
    afm = SimulatedAfm(merge(load_config(), {"seed": 1}))
    request = largest_request()
    started = time.perf_counter()
    marks: dict[str, float] = {}

    def on_line(done: int, total: int) -> None:
        now = time.perf_counter() - started
        marks.setdefault("first_line_s", now)
        marks["last_line_s"], marks["lines"] = now, done

    def should_stop() -> bool:
        return bool(args.lines) and marks.get("lines", 0) >= args.lines

    afm.raster_scan(request, on_line=on_line, should_stop=should_stop)
    wall = time.perf_counter() - started
    lines = int(marks.get("lines", 0))
    # a cancel is checked before each chunk of lines: the longest wait is one chunk's time
    from afm_core.sim.instrument import LINES_PER_CHUNK

    per_line = (marks["last_line_s"] - marks["first_line_s"]) / max(lines - 1, 1)
    result = {
        "pixels": [request.pixels_x, request.pixels_y],
        "lines_acquired": lines,
        "first_line_s": round(marks["first_line_s"], 2),
        "wall_per_line_s": round(per_line, 4),
        "cancel_latency_bound_s": round(LINES_PER_CHUNK * per_line, 2),
        "scan_wall_s": round(wall, 1),
        "peak_rss_mib": round(peak_rss_mib(), 1),
        "command": command_line(),
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "scan_memory.json").write_text(json.dumps(result, indent=2) + "\n")
    (RESULTS / "scan_memory.md").write_text(
        "# The largest raster on the simulator (bench/bench_scan_memory.py)\n\n"
        f"`{result['command']}`\n\n"
        "| pixels | lines acquired | first line | wall per line | cancel lands within | "
        "wall | peak memory (process) |\n|---|---|---|---|---|---|---|\n"
        f"| {request.pixels_x} x {request.pixels_y} | {lines} | {result['first_line_s']} s | "
        f"{result['wall_per_line_s']} s | {result['cancel_latency_bound_s']} s | "
        f"{result['scan_wall_s']} s | {result['peak_rss_mib']} MiB |\n\n"
        'A cancel is checked before every chunk of lines; "cancel lands within" is one chunk\'s '
        "time. A chunk that enters a new band of the dilated field waits for that band first "
        "(about the first line's wait, which is the first band's), so the longest wait for a "
        "cancel is about the first line's time plus one chunk.\n"
    )
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
