"""What the benchmarks record about the machine they ran on."""

import platform
import subprocess
from contextlib import contextmanager
from pathlib import Path


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def machine_record(load_average_at_start) -> dict:
    """The machine block of a benchmark's results: CPUs, their model, Python, and the load
    when the run started (timings on a loaded machine are not comparable)."""
    import os

    return {
        "cpu_count": os.cpu_count(),
        "cpu_model": cpu_model(),
        "python": platform.python_version(),
        "load_average_at_start": load_average_at_start,
    }


def command_line() -> str:
    """The command that ran this benchmark, as a user types it from the repository root."""
    import shlex
    import sys

    script = Path(sys.argv[0])
    try:
        script = script.resolve().relative_to(Path(__file__).resolve().parents[1])
    except ValueError:
        pass
    return shlex.join(["scripts/with_env.sh", "python", str(script), *sys.argv[1:]])


@contextmanager
def busy_loops(count: int):
    """`count` shell loops that only spin on a CPU while the block runs (the other nodes of a
    graph and other jobs on the machine), killed when it ends."""
    loops = [subprocess.Popen(["sh", "-c", "while :; do :; done"]) for _ in range(count)]
    try:
        yield
    finally:
        for loop in loops:
            loop.kill()
            loop.wait()
