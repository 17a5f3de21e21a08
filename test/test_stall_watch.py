"""afm_ros.stall_watch: a thread that holds the GIL while it waits stops every other thread
of its process (rclpy's publish inside a blocked Fast DDS write did, issue 33); the watch
reports such a stall with the stack that held it, and stays silent while threads wait without
the GIL."""

import ctypes
import time

import pytest

from afm_ros.stall_watch import ENVIRONMENT, StallWatch, start_from_environment

HELD_S = 0.4
THRESHOLD_S = 0.1


def hold_the_gil(seconds: float) -> None:
    # PyDLL keeps the GIL through the C call (CDLL would release it): a blocked write inside a
    # C extension that does not release it looks exactly like this
    ctypes.PyDLL(None).usleep(int(seconds * 1e6))


def wait_without_the_gil(seconds: float) -> None:
    time.sleep(seconds)


def watched(tmp_path, work) -> tuple[StallWatch, str]:
    watch = StallWatch(tmp_path / "stalls.txt", threshold_s=THRESHOLD_S)
    time.sleep(0.1)  # the watch has armed its first tick
    work(HELD_S)
    time.sleep(0.1)  # it has woken after the stall and written its line
    watch.stop()
    return watch, (tmp_path / "stalls.txt").read_text()


def test_a_thread_holding_the_gil_while_it_waits_is_reported_with_its_stack(tmp_path):
    watch, report = watched(tmp_path, hold_the_gil)
    assert len(watch.stalls) == 1, report
    # the watch's own tick (50 ms) can add to the held time, never remove from it
    assert HELD_S - 0.02 <= watch.stalls[0] < HELD_S + 0.2, watch.stalls
    assert "STALL" in report
    assert "hold_the_gil" in report  # faulthandler's stacks, written while it was held


def test_threads_waiting_without_the_gil_are_not_a_stall(tmp_path):
    watch, report = watched(tmp_path, wait_without_the_gil)
    assert watch.stalls == [], report
    assert "STALL" not in report


def test_the_watch_is_off_unless_the_environment_names_a_folder(tmp_path):
    assert start_from_environment("node", {}) is None
    watch = start_from_environment("node", {ENVIRONMENT: str(tmp_path / "stalls")})
    try:
        assert watch.path.parent == tmp_path / "stalls" and watch.path.name.startswith("node.")
    finally:
        watch.stop()


def test_a_threshold_within_the_watch_tick_is_refused(tmp_path):
    with pytest.raises(ValueError, match="threshold_s must exceed"):
        StallWatch(tmp_path / "stalls.txt", threshold_s=0.01)
