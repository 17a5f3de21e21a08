"""The one main loop every node uses: init, build, spin, clean shutdown on SIGINT/SIGTERM."""

from __future__ import annotations

import ctypes
import gc
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

import rclpy
from rclpy.executors import (
    ExternalShutdownException,
    SingleThreadedExecutor,
    TimeoutException,
)
from rclpy.signals import SignalHandlerOptions

from afm_ros import exposure, links, stall_watch
from afm_ros.action_client import STOPPING
from afm_ros.executor import collect_stopped_tasks, multi_threaded
from afm_ros.hard_exit import Deadline
from afm_ros.teardown import destroy_node_fully

_LOADED = time.monotonic()
DRAIN_IDLE = 0.01  # s without a ready callback: what had arrived is taken
# After SIGINT/SIGTERM a callback in progress gets this long to end (waits for other servers
# end at once through STOPPING); one that does not (a long computation) is abandoned and the
# process exits anyway, so a stop takes at most about 2 s with the drain's share.
STOP_GRACE_S = 1.0
LEAVE_ROS_S = 5.0  # s a node gets to delete itself and shut ROS down before it exits anyway
# then, if the GIL is still held by the middleware (no Python thread runs), the C-level
# deadline ends the process with its status
HARD_EXIT_AFTER_S = LEAVE_ROS_S + 1.0
SPIN_SLICE_S = 0.1  # the main thread looks at the stop flag this often
PARENT_PID_ENV = "AFM_LAUNCHER_PID"  # set by afm_bringup.launcher.Graph for its children
# exit status of a node that refuses its configuration or command line: afm_bringup.launcher
# does not restart it (it would refuse again)
REFUSED_STATUS = 2
PR_SET_PDEATHSIG = 1  # linux/prctl.h


def die_with_parent() -> None:
    """A node the launcher started gets SIGTERM (a clean stop) when the launcher dies, however
    it dies. Set here, in the child, rather than in a preexec_fn (not safe in a launcher with
    threads); a launcher already gone before this point is caught by its pid."""
    expected = os.environ.get(PARENT_PID_ENV)
    if not expected or not sys.platform.startswith("linux"):
        return
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0) != 0:
        print(
            f"warning: prctl(PR_SET_PDEATHSIG) failed: errno {ctypes.get_errno()}", file=sys.stderr
        )
    if os.getppid() != int(expected):
        os.kill(os.getpid(), signal.SIGTERM)


def watch_stop_signals(on_stop: Callable[[], None]) -> None:
    """Call on_stop from a thread of its own at every SIGINT/SIGTERM.

    Why not in the Python signal handler: the handler runs in the main thread between two
    bytecodes, possibly while that thread holds the very lock on_stop needs (threading.Event's
    condition), and a second signal runs a nested handler on top of the first. Both deadlock
    the process for good, and a node that ignores SIGTERM outlives its launcher; seen when the
    launcher died while a restarted recorder was starting (it got its parent-death SIGTERM
    twice). The C-level handler only writes the signal's number to a pipe (set_wakeup_fd,
    async-signal-safe); the Python handler does nothing."""
    reader, writer = os.pipe()  # raw descriptors: nothing closes them behind our back
    os.set_blocking(writer, False)
    signal.set_wakeup_fd(writer, warn_on_full_buffer=False)
    stop_numbers = {int(signal.SIGINT), int(signal.SIGTERM)}
    for sig in stop_numbers:
        signal.signal(sig, lambda *_: None)

    def relay():
        while received := os.read(reader, 64):
            if stop_numbers.intersection(received):
                on_stop()

    threading.Thread(target=relay, name="afm-stop-signals", daemon=True).start()


def seconds_since_start() -> float:
    """Seconds since this process started (Linux: /proc; elsewhere since this module loaded)."""
    try:
        ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return uptime - ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return time.monotonic() - _LOADED


def freeze_startup_heap() -> None:
    """Collect once, then move every object the start created (modules, message classes, the
    node and what it built, e.g. the simulator) to the permanent generation: later collections
    scan only what came after.

    Why (issue 33, measured with gc.callbacks in the driver and the teleop node): a full
    collection over that heap takes ~55 ms of CPU holding the GIL, so no callback or thread of
    the process runs meanwhile, and the allocations of the first work trigger one a few seconds
    after the start, i.e. on the operator's first commands; on a loaded machine it stretched
    to 0.09-0.43 s, during which teleop segments and commands stood still."""
    gc.collect()
    gc.freeze()


def run(
    node_factory,
    program: str,
    args=None,
    *,
    config_errors=(ValueError,),
    threads: int | Callable[[object], int] = 1,
    on_shutdown=None,
    drain_seconds: float = 0.0,
) -> int:
    """threads: executor threads, or a function of the built node giving them.

    Exit status: 0 after a clean stop, 2 when the node refused its configuration
    (the message names the parameter), a callback's SystemExit code as Python reads it (1 for
    a message), and 1 when deleting the node or shutting ROS down failed after a clean stop.

    drain_seconds > 0: SIGINT/SIGTERM stop the spinning but not ROS, and the callbacks already
    waiting (messages a reliable publisher counts as delivered) run until none is ready within
    DRAIN_IDLE, for at most drain_seconds (a publisher faster than that keeps it going to the
    end), before on_shutdown. Only for nodes whose callbacks are short.

    SIGINT and SIGTERM set STOPPING (every wait for another server gives up), stop the
    spinning, and the process exits within about STOP_GRACE_S even when a callback is still
    busy (an action mid-way: its goal is abandoned with the process)."""
    stop = threading.Event()

    def on_stop_signal():
        stop.set()
        STOPPING.set()

    exposure.apply_node_default(os.environ)  # before ROS reads it: localhost unless told
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except RuntimeError as exc:  # rcl's RCLError: a --params-file missing or not parameters
        print(f"{program}: ROS refused the command line: {rcl_reason(exc)}", file=sys.stderr)
        _exit_now(REFUSED_STATUS)
    watch_stop_signals(on_stop_signal)
    die_with_parent()
    refusal = []
    try:
        node = node_factory()
    except config_errors as exc:
        print(f"{program}: {exc}", file=sys.stderr)
        refusal.append(exc)  # its traceback holds the half-built node; exit_refused frees it
    if refusal:
        exit_refused(refusal)
    if callable(threads):  # from the node's configuration (e.g. its queue length)
        threads = threads(node)
    links.LinkReporter(node)
    freeze_startup_heap()
    watch = stall_watch.start_from_environment(program)  # AFM_STALL_WATCH: a diagnosis, off
    executor = multi_threaded(threads) if threads > 1 else SingleThreadedExecutor()
    executor.add_node(node)
    # one line per node when it starts to serve: a client that finds no server can then tell a
    # node that never got here (its import or construction) from one the graph did not discover
    node.get_logger().info(
        f"spinning ({threads} threads), {seconds_since_start():.2f} s after its process started"
    )
    status = 0
    try:
        # spin in slices: a Python signal handler runs only between them
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=SPIN_SLICE_S)
        if drain_seconds > 0 and rclpy.ok():
            _drain(executor, drain_seconds)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except SystemExit as exc:
        status = _exit_status(exc.code)
    except Exception:  # noqa: BLE001 - a signal may shut the context down mid-wait (RCLError)
        if rclpy.ok():
            raise
    finally:
        STOPPING.set()
        if on_shutdown is not None:
            try:
                on_shutdown(node)
            except Exception as exc:  # noqa: BLE001 - report, still shut down
                print(f"{program}: {exc}", file=sys.stderr)
                status = status or 1
        executor.shutdown(timeout_sec=0)
        if not _callbacks_finish(executor, STOP_GRACE_S):
            # a callback is still busy; its thread would keep the interpreter from exiting
            print(f"{program}: stopped with a callback still running", file=sys.stderr)
            _exit_now(status)
        for error in collect_stopped_tasks(executor):
            print(f"{program}: a callback failed while stopping: {error!r}", file=sys.stderr)
        left, error = _leave_ros(lambda: (destroy_node_fully(node), rclpy.try_shutdown()), status)
        if watch is not None:
            watch.stop()
        if error is not None:
            print(f"{program}: leaving ROS failed: {error!r}", file=sys.stderr)
            status = status or 1
        if not left:
            print(f"{program}: leaving ROS took over {LEAVE_ROS_S:g} s; exiting", file=sys.stderr)
            _exit_now(status)
    return status


def exit_refused(refusal: list) -> NoReturn:
    """Leave ROS and end the process with status 2, within about LEAVE_ROS_S whatever the
    middleware does. `refusal` holds the only reference to the exception whose traceback holds
    the half-built node, so the node is deleted in _leave_ros's thread; it is the context's last
    node, so its participant is deleted and announces that it leaves, and the graph forgets the
    node at once rather than after its ~20 s lease. The process then exits without the
    interpreter's own clean-up, which would delete what is left with no bound."""

    def leave():
        refusal.clear()
        gc.collect()  # in case reference cycles still hold the half-built node
        rclpy.try_shutdown()

    _leave_ros(leave, REFUSED_STATUS)
    _exit_now(REFUSED_STATUS)


def _leave_ros(release: Callable[[], object], status: int) -> tuple[bool, Exception | None]:
    """Run `release` (deleting the node, shutting ROS down) in a thread of its own: (True if
    it ended within LEAVE_ROS_S, the exception it raised or None).

    Why a thread: in `make test` (2026-11-28) a node refused while 17 others started beside it
    printed its reason and then never exited (not reproduced in 288 later runs under load).
    Fast DDS is known to deadlock now and then when a participant is deleted while others are
    being discovered (eProsima/Fast-DDS#6193); a stop must not wait on that for ever.
    Why also a Deadline: a deadlock inside rclpy's C++ code keeps the GIL, and then the join's
    timeout never returns (CI, 2026-11-29: a refused recorder hung 90 s); the deadline ends
    the process with `status` from outside the interpreter, after writing the threads' stacks."""
    deadline = Deadline(HARD_EXIT_AFTER_S, status)
    failed = []

    def guarded():
        try:
            release()
        except Exception as exc:  # noqa: BLE001 - reported by the caller, the exit goes on
            failed.append(exc)

    thread = threading.Thread(target=guarded, name="afm-leave-ros", daemon=True)
    thread.start()
    thread.join(LEAVE_ROS_S)
    left = not thread.is_alive()
    if left:
        deadline.cancel()  # else it stays armed over the exit that follows
    return left, (failed[0] if failed else None)


def rcl_reason(exc: Exception) -> str:
    """rcl's message without its source locations ("..., at /project/src/...")."""
    return str(exc).split(", at /")[0].strip()


def _exit_status(code) -> int:
    """SystemExit's code as Python itself reads it: None is 0, a number is itself, anything
    else (a message) is printed and 1."""
    if code is None:
        return 0
    if isinstance(code, int):
        return code
    print(code, file=sys.stderr)
    return 1


def _exit_now(status: int) -> NoReturn:
    """End the process at once (threads still running would keep the interpreter alive)."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


def _callbacks_finish(executor, timeout_s: float) -> bool:
    """True once no callback runs. rclpy 7.1's Executor.shutdown(timeout_sec) does not wait
    (it tests its shutdown flag after setting it) and its work tracker does not count tasks
    (an action's execute callback), so wait on what the thread pool still runs."""
    deadline = time.monotonic() + timeout_s
    while any(not task.done() for task in list(getattr(executor, "_futures", []))):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def _drain(executor, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            handler, _, _ = executor.wait_for_ready_callbacks(timeout_sec=DRAIN_IDLE)
        except TimeoutException:
            return
        handler()
        if handler.exception() is not None:
            raise handler.exception()
