"""A watch on one process's Python threads: when none of them could run for longer than a
threshold, write what every thread was doing and how each used the CPU meanwhile.

Why: a node stands still as a whole when one thread holds Python's GIL while it waits, and
from outside that looks like a slow network or a slow peer. rclpy's publish, for one, holds the
GIL through Fast DDS's write, so a write that waits (issue 33: on another process's
shared-memory port) stops every callback, timer and thread of the node. The stacks name the
call that held it; the CPU figures tell that case (no thread ran, none queued) from a process
starved of CPU (threads queued) or one busy in Python (one thread ran throughout).

Off unless the environment variable AFM_STALL_WATCH names a directory; `afm_ros.node_main.run`
starts it for every node then. The stacks come from the standard library's faulthandler, whose
watchdog thread needs no GIL; it is process-wide, so nothing else in the process may use
faulthandler.dump_traceback_later meanwhile. It is a diagnosis, not something to leave on: the
watchdog reads the other threads' frames without the GIL, and re-arming it each tick joins and
starts a thread with the GIL held. With it on in every node of a full graph test run, three
nodes crashed (SIGSEGV) after their executor thread had run Python for 0.4-0.8 s, and the same
files passed with it off (2026-11-28).
"""

from __future__ import annotations

import faulthandler
import os
import threading
import time
from datetime import datetime, timezone
from pathlib import Path

ENVIRONMENT = "AFM_STALL_WATCH"
THRESHOLD_S = 0.15  # a tenth of a second and more: what a 20 Hz teleop stream notices
TICK_S = 0.05
# the threads' CPU figures are read every this many ticks, not every tick (a node has 20-40
# threads: reading all of them 50 times a second cost 5 % of a core), so a stall's figures
# also cover up to SNAPSHOT_TICKS * TICK_S before it
SNAPSHOT_TICKS = 2


def _thread_times() -> dict[str, tuple[int, int]]:
    """Per thread of this process: (ns on a CPU, ns queued for one), from the kernel's
    schedstat; empty where /proc has none."""
    times = {}
    try:
        tids = os.listdir("/proc/self/task")
    except OSError:
        return times
    for tid in tids:
        try:
            with open(f"/proc/self/task/{tid}/schedstat") as file:
                ran, queued, _ = file.read().split()
        except (OSError, ValueError):
            continue
        times[tid] = (int(ran), int(queued))
    return times


class StallWatch:
    """Reports to `path` every time this process's threads stood still for more than
    `threshold_s`: first the stacks (written while the stall lasts), then a line with its length
    and each thread's CPU and queue time over it (and up to 0.1 s before it)."""

    def __init__(self, path: Path, threshold_s: float = THRESHOLD_S):
        if not threshold_s > TICK_S:
            raise ValueError(f"threshold_s must exceed the watch's tick {TICK_S} s: {threshold_s}")
        self.path = Path(path)
        self.threshold_s = threshold_s
        self.stalls: list[float] = []  # s, each stall's length
        self._stop = threading.Event()
        self._file = open(self.path, "a", buffering=1)  # noqa: SIM115 - open while watching
        self._thread = threading.Thread(target=self._run, name="afm_stall_watch", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        faulthandler.cancel_dump_traceback_later()
        self._file.close()

    def _run(self) -> None:
        last = time.monotonic()
        before = _thread_times()
        ticks = 0
        while not self._stop.is_set():
            faulthandler.dump_traceback_later(self.threshold_s, file=self._file)
            self._stop.wait(TICK_S)
            now = time.monotonic()
            ticks += 1
            if now - last - TICK_S > self.threshold_s and not self._stop.is_set():
                self.stalls.append(now - last)
                after = _thread_times()
                self._file.write(self._summary(now - last, before, after) + "\n")
                before = after
            elif ticks % SNAPSHOT_TICKS == 0:
                before = _thread_times()
            last = now
        faulthandler.cancel_dump_traceback_later()

    def _summary(self, seconds: float, before: dict, after: dict) -> str:
        names = {str(t.native_id): t.name for t in threading.enumerate()}
        rows = []
        for tid, (ran, queued) in sorted(after.items()):
            ran0, queued0 = before.get(tid, (ran, queued))
            if ran - ran0 > 1e6 or queued - queued0 > 1e6:
                rows.append(
                    f"{names.get(tid, tid)} ran {(ran - ran0) / 1e6:.0f} ms, "
                    f"queued {(queued - queued0) / 1e6:.0f} ms"
                )
        ended = datetime.now(timezone.utc).isoformat(timespec="milliseconds")
        threads = "; ".join(rows) or "no thread ran or queued (all waited)"
        clock = f"monotonic {time.monotonic():.3f}"
        return f"STALL {seconds:.3f} s, ended {ended} ({clock}): {threads}"


def start_from_environment(program: str, environ=os.environ) -> StallWatch | None:
    """A watch writing to $AFM_STALL_WATCH/<program>.<pid>.stalls.txt, or None when unset."""
    folder = environ.get(ENVIRONMENT, "")
    if not folder:
        return None
    Path(folder).mkdir(parents=True, exist_ok=True)
    return StallWatch(Path(folder) / f"{program}.{os.getpid()}.stalls.txt")
