"""What `afm launch` gives the nodes by default (afm_bringup.launcher)."""

from pathlib import Path

from afm_bringup.launcher import (
    CALIBRATED_NODES,
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
