"""The one main loop every node uses: init, build, spin, clean shutdown on SIGINT/SIGTERM."""

from __future__ import annotations

import signal
import sys
import threading
import time
from collections.abc import Callable

import rclpy
from rclpy.executors import (
    ExternalShutdownException,
    MultiThreadedExecutor,
    SingleThreadedExecutor,
    TimeoutException,
)
from rclpy.signals import SignalHandlerOptions

DRAIN_IDLE = 0.01  # s without a ready callback: what had arrived is taken


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
    """Exit status: 0 after a clean stop, 2 when the node refused its configuration
    (the message names the parameter), 1 when a callback asked to stop with an error.

    drain_seconds > 0: SIGINT/SIGTERM stop the spinning but not ROS, and the callbacks already
    waiting (messages a reliable publisher counts as delivered) run until none is ready within
    DRAIN_IDLE, for at most drain_seconds (a publisher faster than that keeps it going to the
    end), before on_shutdown. Only for nodes whose callbacks are short: a stop waits for the
    callback in progress."""
    stop = threading.Event()
    if drain_seconds > 0:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
    else:
        rclpy.init(args=args)
    try:
        node = node_factory()
    except config_errors as exc:
        print(f"{program}: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    if callable(threads):  # a count that depends on the node's parameters
        threads = threads(node)
    executor = (
        MultiThreadedExecutor(num_threads=threads) if threads > 1 else SingleThreadedExecutor()
    )
    executor.add_node(node)
    status = 0
    try:
        if drain_seconds > 0:
            while not stop.is_set():
                executor.spin_once(timeout_sec=0.2)
            _drain(executor, drain_seconds)
        else:
            executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except SystemExit as exc:
        status = int(exc.code or 1)
    except Exception:  # noqa: BLE001 - a signal may shut the context down mid-wait (RCLError)
        if rclpy.ok():
            raise
    finally:
        if on_shutdown is not None:
            try:
                on_shutdown(node)
            except Exception as exc:  # noqa: BLE001 - report, still shut down
                print(f"{program}: {exc}", file=sys.stderr)
                status = status or 1
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return status


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
