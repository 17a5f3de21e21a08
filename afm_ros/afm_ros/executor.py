"""The multi-threaded executor every node spins: rclpy 7.1's, minus its re-submission of
callbacks that wait in the thread pool's queue.

Why (issue 33): rclpy 7.1's `MultiThreadedExecutor` keeps every callback it has handed to
its thread pool in the executor's task list until the callback is done, and each pass of
`_wait_for_ready_callbacks` hands out again every task that is neither executing nor done.
A callback still waiting in the pool's queue (its thread busy, or not yet given the GIL) is
neither, so every wake-up of the executor (each callback's start and end triggers one)
submits it again. Measured in our teleop node during a drive: 2,227 passes in one second and
513 entries in the executor's bookkeeping at once, each pass a Python loop over that list
with the GIL held, while the callbacks it queued waited for the same GIL. Upstream rclpy
rewrote this loop (ros2/rclpy#1547, for #1452 and #1223: tasks are yielded once, when
scheduled); Jazzy's 7.1 has not got it.

Here a task leaves the executor's task list when it is handed to the pool and comes back only
if its run leaves it pending (a coroutine awaiting a future, which the executor must poll
again, as upstream 7.1 does). Everything else is rclpy's: the wait set, callback groups,
guard conditions, the thread pool, and `_futures`, which node_main's clean stop waits on.
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping

from rclpy.exceptions import InvalidHandle
from rclpy.executors import (
    ConditionReachedException,
    ExternalShutdownException,
    MultiThreadedExecutor,
    ShutdownException,
    TimeoutException,
)

# "0" leaves out the executor thread's yield of the GIL before each pass (below): only so that
# bench/bench_teleop_holds.py can measure with and without it; unset in normal use
YIELD_ENVIRONMENT = "AFM_EXECUTOR_YIELD"
# "rclpy" gives a node rclpy's own MultiThreadedExecutor instead: only so that
# bench/bench_node_stalls.py can measure the two side by side; unset in normal use
ENVIRONMENT = "AFM_EXECUTOR"
STOCK = "rclpy"

_NOTHING_READY = (
    ExternalShutdownException,
    ShutdownException,
    TimeoutException,
    ConditionReachedException,
)


class QueueAwareExecutor(MultiThreadedExecutor):
    """A MultiThreadedExecutor that submits each ready callback to its pool once, and whose
    spinning thread yields the GIL before each pass over the wait set."""

    yield_each_pass = True

    def _wait_for_ready_callbacks(self, *args, **kwargs):
        # The spinning thread drops the GIL in every wait and takes it back at once when the
        # wait returns at once (work is ready), so a pool thread that waits for the GIL to run
        # the ready callback does not get it: CPython hands the GIL over by force only to a
        # thread that waited a whole switch interval without any release in between. In the
        # teleop drive this held the operator's commands 0.3-0.7 s in about one run in six,
        # with the spinning thread running Python 83 % of the drive. sleep(0) releases the GIL
        # and lets the kernel run the waiting thread (bench/bench_teleop_holds.py).
        if self.yield_each_pass:
            time.sleep(0)
        yield from super()._wait_for_ready_callbacks(*args, **kwargs)

    def _spin_once_impl(self, timeout_sec=None, wait_condition=lambda: False) -> None:
        try:
            handler, _, _ = self.wait_for_ready_callbacks(timeout_sec, None, wait_condition)
        except _NOTHING_READY:
            return
        entry = self._withdraw(handler)
        self._executor.submit(self._run, handler, entry)
        self._futures.append(handler)
        # as rclpy's: forget what is done, and raise what a callback raised
        for future in self._futures[:]:
            if future.done():
                self._futures.remove(future)
                future.result()

    def _withdraw(self, task):
        """Take the task's entry out of the list `_wait_for_ready_callbacks` hands out from."""
        with self._tasks_lock:
            for index, entry in enumerate(self._tasks):
                if entry[0] is task:
                    return self._tasks.pop(index)
        return None

    def _run(self, task, entry) -> None:
        try:
            task()
        finally:
            if entry is not None and not task.done():
                # a coroutine waiting on a future: polled again, as rclpy polls it
                with self._tasks_lock:
                    self._tasks.append(entry)
                try:
                    self._guard.trigger()
                except InvalidHandle:
                    pass  # the executor shut down meanwhile: nothing will poll it


def collect_stopped_tasks(executor) -> list[BaseException]:
    """After a stop: take the errors of the callbacks that finished once spinning had ended,
    and return those that are not the stop itself. A callback handed to the pool just before
    the stop runs after the executor's guard condition is destroyed, and rclpy 7.1's handler
    triggers it unguarded: InvalidHandle ("cannot use Destroyable because destruction was
    requested"), which nobody reads, so rclpy printed "The following exception was never
    retrieved" at every node's stop."""
    errors = []
    for task in list(getattr(executor, "_futures", [])):
        if task.done():
            error = task.exception()  # read: the task no longer reports it when collected
            if (
                error is not None
                and not isinstance(error, InvalidHandle)
                and not guard_gone(error)
            ):
                errors.append(error)
    return errors


def guard_gone(error: BaseException) -> bool:
    """The stop itself, not a callback's failure: rclpy built this callback's handler after the
    executor had shut down, so the handler captured its guard condition as None and fails on
    it ("'NoneType' object has no attribute 'trigger'"; seen when the launcher stopped a
    nano-hand in the middle of a push)."""
    return isinstance(error, AttributeError) and error.name == "trigger" and error.obj is None


def multi_threaded(threads: int, environ: Mapping[str, str] = os.environ) -> MultiThreadedExecutor:
    """The executor a node with `threads` threads spins (node_main.run)."""
    choice = environ.get(ENVIRONMENT, "")
    if choice == STOCK:
        return MultiThreadedExecutor(num_threads=threads)
    if choice:
        raise ValueError(f"{ENVIRONMENT}={choice!r}: unset, or {STOCK!r} for rclpy's own executor")
    executor = QueueAwareExecutor(num_threads=threads)
    passes = environ.get(YIELD_ENVIRONMENT, "")
    if passes not in ("", "0", "1"):
        raise ValueError(f"{YIELD_ENVIRONMENT}={passes!r}: unset, or 0 to leave out the yield")
    executor.yield_each_pass = passes != "0"
    return executor
