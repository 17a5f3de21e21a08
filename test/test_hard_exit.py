"""afm_ros.hard_exit.Deadline: the process ends with the given status even while a thread
holds the GIL for good (as rclpy's C++ code does in a middleware deadlock), and not at all
once cancelled."""

import subprocess
import sys
import textwrap
import time

SCRIPT = """
    import ctypes, time
    from afm_ros.hard_exit import Deadline
    deadline = Deadline({seconds}, {status})
    if {cancel}:
        deadline.cancel()
        time.sleep({seconds} + 1.0)
        print("still here")
        raise SystemExit(0)
    ctypes.PyDLL(None).sleep(60)  # keeps the GIL: no Python code runs any more
"""


def run(seconds: float, status: int, cancel: bool) -> tuple[subprocess.CompletedProcess, float]:
    source = textwrap.dedent(SCRIPT.format(seconds=seconds, status=status, cancel=cancel))
    start = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-c", source], capture_output=True, text=True, timeout=50
    )
    return done, time.monotonic() - start


def test_the_deadline_ends_a_process_whose_gil_is_held_with_its_status_and_the_stacks():
    done, took = run(1.0, 7, cancel=False)
    assert done.returncode == 7, (done.returncode, done.stderr)
    assert took < 10.0, took  # not the 60 s the GIL is held
    assert "Thread" in done.stderr and "most recent call first" in done.stderr, done.stderr


def test_a_cancelled_deadline_leaves_the_process_alone():
    done, _ = run(0.5, 7, cancel=True)
    assert done.returncode == 0, (done.returncode, done.stderr)
    assert done.stdout.strip() == "still here"
    assert "most recent call first" not in done.stderr


def test_a_status_above_255_is_what_the_parent_would_read_of_it():
    done, _ = run(0.5, 256 + 3, cancel=False)
    assert done.returncode == 3, (done.returncode, done.stderr)
