"""Shared fixtures: an isolated DDS domain per test run and node processes that always stop."""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import tempfile
import time
from pathlib import Path

import pytest

# Isolate this run's DDS traffic from anything else on the machine (other runs, demos): a domain
# id no other process uses, held for this run (a random one collided with other runs' graphs)
from afm_ros.exposure import claim_domain, isolate_run  # noqa: E402
from afm_ros.stall_watch import ENVIRONMENT as STALL_WATCH  # noqa: E402
from afm_ros.teardown import destroy_node_fully  # noqa: E402

DOMAIN_CHOSEN_BY_USER = "ROS_DOMAIN_ID" in os.environ
isolate_run()
# Unless the user chose the domain, the graph tests take turns over this many domains claimed
# for the run: a participant a test leaves behind (a node it killed on purpose is listed, and
# its endpoints matched, for its lease, about 20 s) is in another domain than the next test's
GRAPH_DOMAINS = 3
_graph_domains: list[int] = []
_graph_tests = itertools.count()
LOG_TAIL_CHARS = 6000  # of each node's output, printed when a test fails
# s: the driver, the slowest to stop, takes about 1.1 s after a stop signal
GRACEFUL_STOP_S = 5.0
# AFM_STALL_WATCH=<folder> in the test run's environment turns the nodes' stall watch on
# (afm_ros.stall_watch), and a failure then prints what held them. It is off by default: with
# it on in every node of a full run, three nodes crashed (faulthandler reads the threads'
# frames without the GIL)
STALL_FOLDER = os.environ.get(STALL_WATCH, "")


def wait_for(predicate, timeout=10.0, interval=0.05, what="condition"):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


class NodeProcess:
    """A node in its own process. Its output goes to a file, never to a pipe: nobody reads a
    pipe while the test runs, and a node that has logged 64 KiB would block in its next log
    call and stop answering; the file is also what a failed test shows."""

    def __init__(self, name, overrides=None):
        from afm_bringup.launcher import node_command

        self.name = name
        self.log = tempfile.TemporaryFile()
        self.started = time.time()  # the epoch of the nodes' log stamps
        self.process = subprocess.Popen(
            node_command(name, None, overrides),
            stdout=self.log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            # what it printed reaches the file at once: a node killed at the test's end shows
            # how far it got, not an empty buffer
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )

    def output(self) -> str:
        self.log.seek(0)
        return self.log.read().decode(errors="replace")

    def stalls(self) -> str:
        """What this node's stall watch wrote (stacks and CPU over each stall), if anything."""
        if not STALL_FOLDER:
            return ""
        found = sorted(Path(STALL_FOLDER).glob(f"*.{self.process.pid}.stalls.txt"))
        return "".join(path.read_text(errors="replace") for path in found)

    def stop(self, sig=signal.SIGINT, timeout=15.0) -> tuple[int, str]:
        if self.process.poll() is None:
            self.process.send_signal(sig)
        try:
            self.process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        return self.process.returncode, self.output()

    def wait(self, timeout=30.0) -> tuple[int, str]:
        self.process.wait(timeout=timeout)
        return self.process.returncode, self.output()


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_makereport(item, call):
    report = yield
    setattr(item, f"report_{report.when}", report)
    return report


def stop_all(started: list[NodeProcess], grace_s: float = GRACEFUL_STOP_S) -> None:
    """Stop the test's nodes the way a user's Ctrl-C does, all at once, and kill only those
    still running after grace_s. A killed node's DDS participant says no goodbye: the other
    participants list it and match its endpoints until its lease runs out (about 20 s,
    measured), so the next test's graph held a second driver, nano-hand... of the test before."""
    running = [node for node in started if node.process.poll() is None]
    for node in running:
        node.process.send_signal(signal.SIGINT)
    deadline = time.monotonic() + grace_s
    for node in running:
        try:
            node.process.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            node.process.kill()
            node.process.wait()


@pytest.fixture(autouse=True)
def graph_domain(request, monkeypatch):
    """The domain of this test's graph (None for a test that starts no DDS participant)."""
    if request.node.get_closest_marker("ros") is None or DOMAIN_CHOSEN_BY_USER:
        yield None
        return
    if not _graph_domains:
        _graph_domains.append(int(os.environ["ROS_DOMAIN_ID"]))
        _graph_domains.extend(claim_domain() for _ in range(GRAPH_DOMAINS - 1))
    domain = _graph_domains[next(_graph_tests) % GRAPH_DOMAINS]
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    yield domain


@pytest.fixture
def nodes(request):
    started: list[NodeProcess] = []

    def start(name, **overrides):
        node = NodeProcess(name, {k: str(v) for k, v in overrides.items()})
        started.append(node)
        return node

    yield start
    stop_all(started)
    report = getattr(request.node, "report_call", None)
    if report is not None and (report.failed or hasattr(report, "wasxfail")):
        for node in started:  # what each node said, for the failure's diagnosis
            tail = node.output()[-LOG_TAIL_CHARS:]
            stalls = node.stalls()[-LOG_TAIL_CHARS:]
            print(
                f"\n----- {node.name} (started at {node.started:.3f}, pid {node.process.pid}, "
                f"domain {os.environ.get('ROS_DOMAIN_ID')}, exit {node.process.returncode}) "
                f"-----\n{tail}" + (f"\n----- its stalls -----\n{stalls}" if stalls else "")
            )
    for node in started:
        node.log.close()


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
    destroy_node_fully(node, context)  # or a later test in its domain still lists it
