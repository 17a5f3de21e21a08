"""The graph as a user meets it: driver actions, the launcher, the CLI and the Python API."""

import signal
import subprocess
import sys
import threading
import time

import pytest
from conftest import wait_for

from afm_bringup.commander import AfmCommander, AfmError
from afm_bringup.units import parse_length
from afm_core.recording import RecordingReader
from afm_ros.conversions import image_msg_to_array

pytestmark = pytest.mark.ros

AFM = [sys.executable, "-m", "afm_bringup.cli"]


def test_scan_through_the_driver_action(nodes):
    nodes("driver", seed=3)
    with AfmCommander() as afm:
        scan = afm.scan(
            origin=(54.6e-6, 54.6e-6), size=(0.8e-6, 0.8e-6), pixels=(64, 48), angle_deg=90.0
        )
        with pytest.raises(AfmError, match="scanner range"):
            afm.scan(origin=(109.9e-6, 1e-6), size=(1e-6, 1e-6))
        with pytest.raises(AfmError, match="pixels_x"):
            afm.scan(origin=(1e-6, 1e-6), size=(1e-6, 1e-6), pixels=(1, 10))
    height = image_msg_to_array(scan.height)
    assert height.shape == (48, 64) and scan.header.frame_id == "afm_scanner"
    assert height.max() == pytest.approx(200e-9, abs=3e-9)  # a 100 nm-radius sphere is in the area
    assert len(scan.line_start_times) == 64 and scan.scan_angle_deg == 90.0


def test_ctrl_c_while_waiting_for_a_scan_cancels_it(nodes, ros_node):
    """Ctrl-C on `afm scan` left its goal running: the driver scanned a 4096 x 4096 image on
    for minutes, the next scan queued behind it and the interrupted one was published."""
    from afm_msgs.msg import RasterScan
    from afm_ros.qos_profiles import SCANS

    nodes("driver", seed=3)
    published = []
    ros_node.create_subscription(RasterScan, "/afm/scan", published.append, SCANS)

    def interrupt(_signum, _frame):
        raise KeyboardInterrupt

    with AfmCommander(server_timeout=20.0) as afm:
        afm.scan(origin=(54.6e-6, 54.6e-6), size=(0.5e-6, 0.5e-6), pixels=(16, 16))
        previous = signal.signal(signal.SIGALRM, interrupt)
        signal.setitimer(signal.ITIMER_REAL, 2.0)  # a shell's Ctrl-C, in the waiting thread
        try:
            with pytest.raises(KeyboardInterrupt):  # minutes of computing: never done in 2 s
                afm.scan(origin=(50e-6, 50e-6), size=(10e-6, 10e-6), pixels=(2048, 2048))
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0.0)
            signal.signal(signal.SIGALRM, previous)
        after = afm.scan(origin=(54.6e-6, 54.6e-6), size=(0.5e-6, 0.5e-6), pixels=(16, 16))
    wait_for(lambda: any(m.scan_id == after.scan_id for m in published), 10, what="the scan")
    widths = [m.height.width for m in published]
    assert 2048 not in widths and widths[-1] == 16, widths  # the interrupted scan was stopped


def test_commander_reports_a_missing_server_by_name():
    with (
        AfmCommander(server_timeout=0.5) as afm,
        pytest.raises(AfmError, match="/afm/push_particle"),
    ):
        afm.push(goal=(1e-6, 1e-6), particle_id=1)


def test_launch_records_and_stops_cleanly(tmp_path):
    record = tmp_path / "graph.mcap"
    launch = subprocess.Popen(
        AFM + ["launch", "--record", str(record), "--log-dir", str(tmp_path / "logs")],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    lines = []
    threading.Thread(target=lambda: lines.extend(launch.stdout), daemon=True).start()
    try:
        wait_for(
            lambda: any(b"afm launch: ready" in line for line in lines), 60, what="launch ready"
        )
        with AfmCommander(server_timeout=20.0) as afm:
            afm.scan(origin=(54.5e-6, 54.5e-6), size=(1e-6, 1e-6), pixels=(32, 32))
        time.sleep(1.0)
        logs = sorted(p.name for p in (tmp_path / "logs").iterdir())
        assert logs == [
            "driver.log",
            "imaging.log",
            "localizer.log",
            "nano_hand.log",
            "planner.log",
            "recorder.log",
            "sim2real.log",
            "teleop.log",
            "viewer.log",
        ]
    finally:  # a graph left running would answer every later test's goals on this domain
        launch.send_signal(signal.SIGINT)
        launch.wait(timeout=60)
    assert launch.returncode == 0, b"".join(lines).decode()
    # every pair of a topic's publishers and subscribers can match: the teleop node offered its
    # believed objects volatile where the viewer asks for the history, and the viewer never
    # got them
    said = b"".join(lines).decode() + "".join(
        p.read_text(errors="replace") for p in (tmp_path / "logs").iterdir()
    )
    assert "incompatible QoS" not in said, [
        line for line in said.splitlines() if "incompatible QoS" in line
    ]
    with RecordingReader(record) as reader:
        topics = reader.topics()
    assert topics["/afm/scan"].message_count == 1
    # the approach from beyond the image (raster_approach), the move to its first sample,
    # where the driver waited for creep (afm launch gives it the simulator's calibration), then
    # the raster
    assert topics["/afm/tip_command"].message_count == 3
    assert topics["/afm/ground_truth"].message_count >= 1


def test_cli_help_and_info(tmp_path):
    from test_recording_files import write_session

    top = subprocess.run(AFM + ["--help"], capture_output=True, text=True)
    assert top.returncode == 0
    for command in (
        "run",
        "launch",
        "record",
        "replay",
        "info",
        "recover",
        "scan",
        "push",
        "demo",
        "calibrate",
        "sim2real",
    ):
        assert command in top.stdout
        sub = subprocess.run(AFM + [command, "--help"], capture_output=True, text=True)
        assert sub.returncode == 0 and "usage: afm " + command in sub.stdout
    path = tmp_path / "s.mcap"
    write_session(path, n=2)
    info = subprocess.run(AFM + ["info", str(path)], capture_output=True, text=True)
    assert info.returncode == 0
    assert (
        "/afm/scan" in info.stdout
        and "afm_msgs/msg/RasterScan" in info.stdout
        and "messages:  6" in info.stdout
    )
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(b"not an mcap file")
    info = subprocess.run(AFM + ["info", str(broken)], capture_output=True, text=True)
    assert info.returncode != 0 and "is not an MCAP recording" in info.stderr
    # a file given as the report folder: named as such, not "[Errno 20] Not a directory"
    taken = subprocess.run(
        AFM + ["sim2real", str(path), "--report", str(broken)], capture_output=True, text=True
    )
    assert taken.returncode == 2 and "--report" in taken.stderr and "a file" in taken.stderr


def test_a_refused_push_prints_the_reason_and_no_position(nodes):
    nodes("nano_hand")  # no map yet: it refuses every particle
    result = subprocess.run(
        AFM + ["push", "--particle", "7", "--goal", "55um", "55um"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 1, result.stdout + result.stderr
    assert "refused: particle_id=7: unknown" in result.stdout, result.stdout
    assert "particle at" not in result.stdout  # the result carries no position


def test_cli_rejects_bad_lengths_by_name():
    result = subprocess.run(
        AFM + ["push", "--particle", "1", "--goal", "12furlong", "3nm"],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 2 and "goal='12furlong'" in result.stderr


def test_calibrate_refuses_to_overwrite_and_names_a_missing_config(tmp_path):
    existing = tmp_path / "calibration.yaml"
    existing.write_text("keep me")
    result = subprocess.run(
        AFM + ["calibrate", "-o", str(existing)], capture_output=True, text=True
    )
    assert (
        result.returncode != 0 and "exists" in result.stderr and existing.read_text() == "keep me"
    )
    result = subprocess.run(
        AFM
        + [
            "calibrate",
            "-o",
            str(tmp_path / "new.yaml"),
            "--sim-config",
            str(tmp_path / "missing.yaml"),
        ],
        capture_output=True,
        text=True,
    )
    assert (
        result.returncode != 0
        and "missing.yaml" in result.stderr
        and not (tmp_path / "new.yaml").exists()
    )
    # a drift-pair count the drift experiment would refuse hours in: refused at once
    result = subprocess.run(
        AFM + ["calibrate", "-o", str(tmp_path / "new.yaml"), "--pairs", "1"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2 and "pairs=1" in result.stderr and "[2, " in result.stderr
    assert not (tmp_path / "new.yaml").exists()
    # outputs that cannot be written were found after the experiments (hours on an instrument)
    for extra, complaint in (
        (["-o", str(tmp_path / "no folder" / "cal.yaml")], "the folder"),
        (["-o", str(tmp_path)], "a folder; name a file"),
        (["-o", str(tmp_path / "new.yaml"), "--report", str(existing)], "--report"),
        (["-o", str(existing), "--overwrite", "--report", str(existing)], "the calibration file"),
    ):
        result = subprocess.run(
            AFM + ["calibrate", *extra], capture_output=True, text=True, timeout=60
        )
        assert result.returncode == 2 and complaint in result.stderr, (extra, result.stderr)
        assert "calibrating the" not in result.stdout  # refused before any experiment
    assert existing.read_text() == "keep me"


@pytest.mark.parametrize(
    "text, metres", [("500nm", 500e-9), ("1.5um", 1.5e-6), ("2e-6", 2e-6), (" 3 mm", 3e-3)]
)
def test_lengths_with_units(text, metres):
    assert parse_length(text) == pytest.approx(metres)


@pytest.mark.parametrize("text", ["", "nan", "5 parsecs", "inf nm", "1e999"])
def test_bad_lengths_are_refused(text):
    with pytest.raises(ValueError):
        parse_length(text)


def test_a_bare_number_too_long_for_metres_asks_for_its_unit():
    """'--min-height 10' meant 10 nm; read as 10 m it found no feature without a word."""
    with pytest.raises(ValueError, match=r"min-height='10': .* give the unit, e.g. 10nm"):
        parse_length("10", "min-height")
    with pytest.raises(ValueError, match="give the unit"):
        parse_length("-5", "at")
    assert parse_length("1e-3") == 1e-3 and parse_length("10nm") == pytest.approx(10e-9)
