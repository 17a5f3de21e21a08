"""The one main loop every node uses: init, build, spin, clean shutdown on SIGINT/SIGTERM."""
from __future__ import annotations

import sys

import rclpy
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor


def run(node_factory, program: str, args=None, *, config_errors=(ValueError,), threads: int = 1,
        on_shutdown=None) -> int:
    """Exit status: 0 after a clean stop, 2 when the node refused its configuration
    (the message names the parameter), 1 when a callback asked to stop with an error."""
    rclpy.init(args=args)
    try:
        node = node_factory()
    except config_errors as exc:
        print(f"{program}: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    executor = MultiThreadedExecutor(num_threads=threads) if threads > 1 else SingleThreadedExecutor()
    executor.add_node(node)
    status = 0
    try:
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
