"""What `afm launch` gives the nodes by default (afm_bringup.launcher)."""

import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

from afm_bringup.launcher import (
    CALIBRATED_NODES,
    REFUSED_STATUS,
    Graph,
    latest_output,
    restart_output,
    sim_calibration_file,
    with_sim_calibration,
)
from afm_core.localization.calibration.model import load_calibration


def test_on_the_simulator_the_calibrated_nodes_get_its_calibration_unless_set():
    calibration = sim_calibration_file()
    load_calibration(calibration)  # the shipped file is there and valid
    assert Path(calibration).name == "sim_calibration.yaml"
    nodes = ["driver", "imaging", "localizer", "planner", "nano_hand", "teleop"]
    overrides = {"planner": {"calibration_file": "/lab/mine.yaml"}, "imaging": {"x": "1"}}
    given = with_sim_calibration(nodes, overrides, calibration)
    assert given == ["driver", "localizer", "nano_hand", "teleop"]
    assert all(overrides[n]["calibration_file"] == calibration for n in given)
    assert overrides["planner"]["calibration_file"] == "/lab/mine.yaml"  # the user's wins
    assert "calibration_file" not in overrides["imaging"]  # it loads none
    assert set(given) | {"planner"} == set(CALIBRATED_NODES)


def test_on_a_real_instrument_nothing_is_given():
    overrides = {"driver": {"backend": "daq"}}
    assert with_sim_calibration(["driver", "localizer"], overrides, "x.yaml") == []
    assert overrides == {"driver": {"backend": "daq"}}


def test_the_live_recording_follows_the_restarted_recorder(tmp_path):

    output = tmp_path / "session.mcap"
    assert latest_output(output) == output
    (tmp_path / "session.mcap.part").write_bytes(b"")
    assert latest_output(output) == output
    first = Path(restart_output(str(output), 1))
    first.with_name(first.name + ".part").write_bytes(b"")
    assert latest_output(output) == first
    second = Path(restart_output(str(output), 2))
    second.write_bytes(b"")  # finished under its own name
    assert latest_output(output) == second != first


def test_a_recorder_that_refused_its_configuration_is_not_restarted(tmp_path):
    """It would refuse again (a name already taken, a bad compression): the graph stops and
    says why, instead of recording to another name than the one asked for."""
    graph = Graph(environment={})
    started = []

    def start(name, overrides, alias, params_file):  # no process: only what would start
        started.append(overrides["output"])
        graph.processes[alias] = SimpleNamespace(returncode=None)
        return graph.processes[alias]

    graph.start = start
    graph.specs["recorder"] = ("recorder", {"output": str(tmp_path / "s.mcap")}, None)
    from afm_ros import node_main

    assert REFUSED_STATUS == node_main.REFUSED_STATUS  # what a refusing node exits with
    graph.processes["recorder"] = SimpleNamespace(returncode=REFUSED_STATUS)
    assert graph.restart("recorder") is None and started == []
    graph.processes["recorder"] = SimpleNamespace(returncode=-9)  # killed: restarted
    assert graph.restart("recorder") is not None
    assert started == [restart_output(str(tmp_path / "s.mcap"), 1)]


def launch_recording(tmp_path, output) -> tuple[subprocess.CompletedProcess, float]:
    started = time.monotonic()
    run = subprocess.run(
        [sys.executable, "-m", "afm_bringup.cli", "launch", "--record", str(output)]
        + ["--log-dir", str(tmp_path / "logs")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    return run, time.monotonic() - started


def test_launch_refuses_a_recording_name_in_use_before_starting_anything(tmp_path):
    taken = tmp_path / "taken.mcap"
    taken.write_bytes(b"")
    run, took = launch_recording(tmp_path, taken)
    assert run.returncode == 2 and "--record: output" in run.stderr  # bad input: status 2
    assert "already exists" in run.stderr and took < 30
    assert not any((tmp_path / "logs").iterdir())  # no node was started


def test_launch_refuses_a_name_whose_restart_file_an_earlier_session_left(tmp_path):
    """A restarted recorder would have refused that name (and the graph stopped), and
    Sim2Real took the old file for the live recording."""
    old = Path(restart_output(str(tmp_path / "b.mcap"), 2))
    old.with_name(old.name + ".part").write_bytes(b"")
    run, _ = launch_recording(tmp_path, tmp_path / "b.mcap")
    assert run.returncode == 2, run.stderr
    assert f"{old}.part exists from an earlier session" in run.stderr
    assert not any((tmp_path / "logs").iterdir())
