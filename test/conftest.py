"""Shared fixtures: an isolated DDS domain per test run and node processes that always stop."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import time

import pytest

# Isolate this run's DDS traffic from anything else on the machine (other runs, demos).
os.environ.setdefault("ROS_DOMAIN_ID", str(random.Random(os.getpid()).randint(110, 200)))
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


def wait_for(predicate, timeout=10.0, interval=0.05, what="condition"):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


class NodeProcess:
    def __init__(self, name, overrides=None):
        from afm_bringup.launcher import node_command

        self.name = name
        self.process = subprocess.Popen(
            node_command(name, None, overrides),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )

    def stop(self, sig=signal.SIGINT, timeout=15.0) -> tuple[int, str]:
        if self.process.poll() is None:
            self.process.send_signal(sig)
        try:
            output, _ = self.process.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.process.kill()
            output, _ = self.process.communicate()
        return self.process.returncode, output.decode(errors="replace")

    def wait(self, timeout=30.0) -> tuple[int, str]:
        output, _ = self.process.communicate(timeout=timeout)
        return self.process.returncode, output.decode(errors="replace")


@pytest.fixture
def nodes():
    started: list[NodeProcess] = []

    def start(name, **overrides):
        node = NodeProcess(name, {k: str(v) for k, v in overrides.items()})
        started.append(node)
        return node

    yield start
    for node in started:
        if node.process.poll() is None:
            node.stop(signal.SIGKILL)


@pytest.fixture
def ros_node():
    """An rclpy node in this test process (own context), spun in a background thread."""
    import threading

    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    context = Context()
    rclpy.init(context=context)
    node = rclpy.create_node("afm_test_peer", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    yield node
    executor.shutdown()
    thread.join(timeout=5)
    node.destroy_node()
    rclpy.try_shutdown(context=context)
