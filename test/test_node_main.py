"""afm_ros.node_main: the heap a node's start built is frozen before it spins, so a full
garbage collection later (which holds the GIL: no callback of the process runs meanwhile) scans
only what came after (issue 33: such a collection stalled teleop segments)."""

import json
import os
import subprocess
import sys
import textwrap

import pytest

START_OBJECTS = 100_000  # containers the start builds in the scripts below


def run_python(source: str, timeout: float = 60) -> subprocess.CompletedProcess:
    """`source` (dedented) in a Python process of its own, its output captured."""
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(source)],
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


def run_script(source: str) -> dict:
    done = run_python(source, timeout=120)
    lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
    assert lines, f"exit {done.returncode}: {done.stdout[-2000:]} {done.stderr[-2000:]}"
    return json.loads(lines[-1])


def test_a_collection_after_the_frozen_start_scans_only_what_came_after():
    seen = run_script(
        f"""
        import gc, json
        from afm_ros.node_main import freeze_startup_heap
        start = [[i] for i in range({START_OBJECTS})]  # long-lived, as a node's start builds
        freeze_startup_heap()
        later = [[i] for i in range(10)]
        scanned = {{id(o) for o in gc.get_objects()}}  # what a full collection would visit
        print(json.dumps({{
            "frozen": gc.get_freeze_count(),
            "start_scanned": sum(id(o) in scanned for o in [start, *start]),
            "later_scanned": sum(id(o) in scanned for o in [later, *later]),
            "scanned": len(scanned),
        }}))
        """
    )
    assert seen["frozen"] > START_OBJECTS
    assert seen["start_scanned"] == 0, seen
    assert seen["later_scanned"] == 11, seen  # new objects are still collected
    assert seen["scanned"] < START_OBJECTS / 10, seen


@pytest.mark.ros
def test_a_node_run_by_node_main_spins_with_its_start_frozen():
    seen = run_script(
        f"""
        import gc, json
        from rclpy.node import Node
        from afm_ros.node_main import run

        class Probe(Node):
            def __init__(self):
                super().__init__("afm_freeze_probe")
                self.start = [[i] for i in range({START_OBJECTS})]
                self.create_timer(0.01, self.tick)

            def tick(self):
                scanned = {{id(o) for o in gc.get_objects()}}
                print(json.dumps({{
                    "frozen": gc.get_freeze_count(),
                    "start_scanned": sum(id(o) in scanned for o in self.start),
                }}), flush=True)
                raise SystemExit(0)

        run(Probe, "freeze probe")
        """
    )
    assert seen["frozen"] > START_OBJECTS and seen["start_scanned"] == 0, seen


STOP_SIGNALS_SCRIPT = """
    import json, os, signal, threading, time
    from afm_ros.node_main import watch_stop_signals
    stopped = threading.Event()
    calls = []
    def on_stop():
        calls.append(1)
        stopped.set()
    {install}
    # the main thread holds the lock on_stop needs when the signals come, twice (a launcher's
    # parent-death signal and a second stop): a handler that took the lock itself would wait
    # for its own thread for ever
    with stopped._cond:
        os.kill(os.getpid(), signal.SIGTERM)
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.3)
    print(json.dumps({{"stopped": stopped.wait(5.0), "calls": len(calls)}}))
"""


@pytest.mark.parametrize(
    "install, deadlocks",
    [
        ("watch_stop_signals(on_stop)", False),
        (
            "[signal.signal(s, lambda *_: on_stop()) for s in (signal.SIGINT, signal.SIGTERM)]",
            True,
        ),
    ],
    ids=["watch_stop_signals", "handler_sets_the_event"],
)
def test_stop_signals_arriving_while_the_main_thread_holds_the_lock_still_stop(install, deadlocks):
    """A node that got SIGTERM while its main thread held the stop event's lock ignored every
    later signal (a restarted recorder outlived its killed launcher). The second case is the
    old handler, kept to show the script can catch the deadlock."""
    script = textwrap.dedent(STOP_SIGNALS_SCRIPT.format(install=install))
    try:
        done = subprocess.run(
            [sys.executable, "-c", script], capture_output=True, text=True, timeout=20
        )
    except subprocess.TimeoutExpired:
        assert deadlocks, "the process hung after its stop signals"
        return
    assert not deadlocks, f"the old handler did not deadlock: {done.stdout} {done.stderr}"
    seen = json.loads(done.stdout.splitlines()[-1])
    assert seen["stopped"] and seen["calls"] >= 1, (seen, done.stderr)


REFUSING_NODE_SCRIPT = """
    import ctypes
    import threading
    import rclpy
    from afm_ros.node_main import run
    GIL_HELD = False
    {patch}

    class HalfBuilt:
        def __del__(self):  # deleting what the start had built: where a middleware may block
            if DELETION_HANGS and GIL_HELD:  # a deadlock inside C++ code that keeps the GIL
                ctypes.PyDLL(None).sleep(600)
            if DELETION_HANGS:
                threading.Event().wait()

    def refuse():
        half_built = HalfBuilt()  # held by the traceback's frame, as a node's __init__ is
        raise ValueError("parameter model='x.yaml': is not valid YAML")

    raise SystemExit(run(refuse, "refusing probe"))  # as every node's main
"""


@pytest.mark.ros
@pytest.mark.parametrize(
    "patch",
    [
        "DELETION_HANGS = False",
        "DELETION_HANGS = False; rclpy.try_shutdown = lambda *a, **k: threading.Event().wait()",
        "DELETION_HANGS = True",
        "DELETION_HANGS = GIL_HELD = True",
    ],
    ids=["clean", "shutdown_hangs", "deletion_hangs", "deletion_hangs_holding_the_gil"],
)
def test_a_node_that_refuses_its_configuration_exits_with_status_2_even_if_ros_hangs(patch):
    """A refused node once printed its reason and never exited (make test, 2026-11-28; CI,
    2026-11-29); the other cases make leaving ROS hang for ever, as a middleware deadlock would,
    the last one while holding the GIL as rclpy's C++ code does."""
    done = run_python(REFUSING_NODE_SCRIPT.format(patch=patch))
    assert done.returncode == 2, (done.returncode, done.stdout, done.stderr)
    assert "refusing probe: parameter model='x.yaml': is not valid YAML" in done.stderr


STOPPING_NODE_SCRIPT = """
    import ctypes
    import threading
    from rclpy.node import Node
    from afm_ros.node_main import run

    class StopsItself(Node):
        def __init__(self):
            super().__init__("afm_stop_probe")
            self.create_timer(0.05, self.stop)

        def stop(self):
            raise SystemExit({status})

        def destroy_node(self):
            if "{deletion}" == "hangs":  # as a middleware deadlock while its participant goes
                threading.Event().wait()
            if "{deletion}" == "hangs_holding_the_gil":  # the same inside rclpy's C++ code
                ctypes.PyDLL(None).sleep(600)
            if "{deletion}" == "fails":
                raise RuntimeError("rcl_node_fini failed")
            return super().destroy_node()

    raise SystemExit(run(StopsItself, "stop probe"))
"""


@pytest.mark.ros
@pytest.mark.parametrize(
    "deletion, status, says",
    [
        ("works", 3, None),
        ("hangs", 3, "leaving ROS took over 5 s"),
        ("hangs_holding_the_gil", 3, "Thread "),  # no Python runs: the stacks, then status 3
        ("fails", 3, "leaving ROS failed: RuntimeError('rcl_node_fini failed')"),
        ("fails", 0, "leaving ROS failed"),  # a clean stop whose clean-up failed: status 1
    ],
)
def test_a_stopping_node_exits_with_its_status_even_if_deleting_it_hangs(deletion, status, says):
    done = run_python(STOPPING_NODE_SCRIPT.format(status=status, deletion=deletion))
    expected = 1 if (deletion == "fails" and status == 0) else status
    assert done.returncode == expected, (done.returncode, done.stdout, done.stderr)
    assert (says is None and "leaving ROS" not in done.stderr) or says in done.stderr, done.stderr


GRAPH_WATCH_SCRIPT = """
    import json, subprocess, sys, textwrap, time
    import rclpy
    refuser = textwrap.dedent('''
        import time
        from rclpy.node import Node
        from afm_ros.node_main import run
        class Late(Node):
            def __init__(self):
                super().__init__("afm_late_refuser")
                time.sleep(3.0)  # long enough to be discovered first
                raise ValueError("parameter x: bad")
        raise SystemExit(run(Late, "late refuser"))
    ''')
    rclpy.init()
    watcher = rclpy.create_node("afm_graph_watch")
    process = subprocess.Popen([sys.executable, "-c", refuser])
    start, exited, last_seen = time.monotonic(), None, None
    while time.monotonic() - start < 15.0:
        rclpy.spin_once(watcher, timeout_sec=0.1)
        now = time.monotonic() - start
        if "afm_late_refuser" in watcher.get_node_names():
            last_seen = now
        if exited is None and process.poll() is not None:
            exited = now
    print(json.dumps({"status": process.returncode, "exited": exited, "last_seen": last_seen}))
"""


@pytest.mark.ros
def test_a_refused_node_leaves_the_graph_when_its_process_ends():
    """Not a ghost for the middleware's lease (about 20 s): the half-built node and the
    context are destroyed before the process ends, so its participant says it leaves."""
    seen = run_script(GRAPH_WATCH_SCRIPT)
    assert seen["status"] == 2, seen
    assert seen["last_seen"] is not None, f"the node was never discovered: {seen}"
    assert seen["last_seen"] < seen["exited"] + 2.0, seen
