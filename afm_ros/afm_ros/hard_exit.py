"""A deadline on the process that holds even when no Python code can run any more.

Why: leaving ROS deletes the node's DDS participant inside rclpy's C++ code, which keeps the
GIL. When the middleware deadlocks there (eProsima/Fast-DDS#6193; seen in CI on 2026-11-29, a
refused recorder printed its reason and hung until it was killed 90 s later), every Python
thread waits for the GIL, so a deadline kept by a Python thread (thread.join with a timeout)
never fires. Both pieces below run outside the interpreter:

- faulthandler's watchdog thread writes every thread's stack to stderr: the next hang says
  where it was;
- a POSIX timer (timer_create, SIGEV_THREAD) whose expiry makes glibc call `_exit(status)` in
  a thread of its own, so the process ends with the status it was going to end with.

Outside Linux/glibc the timer is not available and faulthandler ends the process instead
(status 1)."""

from __future__ import annotations

import ctypes
import faulthandler
import sys

CLOCK_MONOTONIC = 1  # linux/time.h
SIGEV_THREAD = 2  # asm-generic/siginfo.h


class _SigEvent(ctypes.Structure):
    """struct sigevent as glibc lays it out for SIGEV_THREAD (64 bytes on 64-bit Linux)."""

    _fields_ = [
        ("value", ctypes.c_void_p),  # union sigval: what the function is called with
        ("signo", ctypes.c_int),
        ("notify", ctypes.c_int),
        ("function", ctypes.c_void_p),
        ("attributes", ctypes.c_void_p),
        ("padding", ctypes.c_int * 8),
    ]


class _TimeSpec(ctypes.Structure):
    _fields_ = [("seconds", ctypes.c_long), ("nanoseconds", ctypes.c_long)]


class _ITimerSpec(ctypes.Structure):
    _fields_ = [("interval", _TimeSpec), ("value", _TimeSpec)]


class Deadline:
    """Ends the process with `status` after `seconds` unless cancelled; the threads' stacks are
    written to stderr shortly before."""

    STACKS_BEFORE_S = 0.5  # the stacks are written this long before the exit

    def __init__(self, seconds: float, status: int):
        status &= 0xFF  # what the parent would read of _exit(status) anyway
        self._libc = None
        self._timer = None
        timed = self._arm_timer(seconds, status)
        self.exits_with = status if timed else 1  # else faulthandler's own exit status
        try:
            faulthandler.dump_traceback_later(
                max(seconds - self.STACKS_BEFORE_S, 0.01) if timed else seconds,
                exit=not timed,
                file=sys.__stderr__,
            )
        except (ValueError, RuntimeError, AttributeError):  # no stderr to write the stacks to
            pass

    def _arm_timer(self, seconds: float, status: int) -> bool:
        if not sys.platform.startswith("linux"):
            return False
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            create, settime = libc.timer_create, libc.timer_settime
            exit_now = ctypes.cast(libc._exit, ctypes.c_void_p).value
        except (AttributeError, OSError):  # a libc without timers in itself (glibc < 2.34)
            return False
        event = _SigEvent(value=status, notify=SIGEV_THREAD, function=exit_now)
        timer = ctypes.c_void_p()
        if create(CLOCK_MONOTONIC, ctypes.byref(event), ctypes.byref(timer)) != 0:
            return False
        whole = int(seconds)
        spec = _ITimerSpec(value=_TimeSpec(whole, int((seconds - whole) * 1e9)))
        if settime(timer, 0, ctypes.byref(spec), None) != 0:
            libc.timer_delete(timer)
            return False
        self._libc, self._timer = libc, timer
        return True

    def cancel(self) -> None:
        faulthandler.cancel_dump_traceback_later()
        if self._timer is not None:
            self._libc.timer_delete(self._timer)
            self._timer = None
