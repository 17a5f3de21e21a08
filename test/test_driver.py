"""The driver node through its actions: results, feedback, cancel, queueing, bad input."""

import time
from pathlib import Path

import numpy as np
import pytest
from conftest import wait_for
from geometry_msgs.msg import PointStamped
from rosgraph_msgs.msg import Clock

from afm_bringup.commander import AfmCommander, AfmError
from afm_msgs.action import Indent, LocalScan, MoveTip, ScanImage
from afm_msgs.msg import GroundTruth
from afm_ros.conversions import image_msg_to_array
from afm_ros.qos_profiles import LATCHED

pytestmark = pytest.mark.ros


def scan_goal(
    origin=(54.6e-6, 54.6e-6), size=(0.8e-6, 0.8e-6), pixels=(64, 64), angle=0.0, line_rate=2.0
):
    goal = ScanImage.Goal(
        size_x=size[0],
        size_y=size[1],
        pixels_x=pixels[0],
        pixels_y=pixels[1],
        scan_angle_deg=angle,
        slow_scan_up=True,
        line_rate=line_rate,
    )
    goal.origin.x, goal.origin.y = origin
    return goal


def move_goal(x, y, speed=1e-6, contact=False, frame="afm_scanner"):
    target = PointStamped()
    target.header.frame_id = frame
    target.point.x, target.point.y = x, y
    return MoveTip.Goal(target=target, speed=speed, contact=contact)


def line_goal(speed, start=(54.7e-6, 55e-6), end=(55.3e-6, 55e-6)):
    goal = LocalScan.Goal(samples=200, speed=speed, landmark_id=-1)
    goal.start.x, goal.start.y = start
    goal.end.x, goal.end.y = end
    return goal


@pytest.fixture
def driver(nodes):
    return nodes("driver", seed=2, real_time_factor=0.0)


def test_scan_line_move_push_and_indent_through_actions(driver, ros_node):
    truths = []
    # latched: the goals may all finish before DDS has matched this subscription
    ros_node.create_subscription(GroundTruth, "/afm/ground_truth", truths.append, LATCHED)
    with AfmCommander(server_timeout=30) as afm:
        feedback = []
        result = afm.send(
            "scan_image", scan_goal(), feedback=lambda f: feedback.append(f.lines_done)
        )
        assert result.success and image_msg_to_array(result.scan.height).shape == (64, 64)
        # one feedback per line, counting up; in a burst the client may drop some, and it
        # ignores any that arrive after the result
        assert feedback and feedback == sorted(set(feedback)) and feedback[-1] <= 64
        line_goal = LocalScan.Goal(samples=200, speed=1e-6, landmark_id=7)
        line_goal.start.x, line_goal.start.y, line_goal.end.x, line_goal.end.y = (
            54.7e-6,
            55e-6,
            55.3e-6,
            55e-6,
        )
        line = afm.send("local_scan", line_goal)
        assert line.success and len(line.line.height) == 200 and line.line.landmark_id == 7
        assert max(line.line.height) == pytest.approx(
            200e-9, abs=3e-9
        )  # crosses the sphere at (55, 55) um
        assert afm.send("move_tip", move_goal(54.75e-6, 55.0e-6, speed=10e-6)).success
        push = afm.send("move_tip", move_goal(55.15e-6, 55.0e-6, contact=True))
        assert push.success and push.trace.task == "push" and len(push.trace.times) > 10
        indent = afm.send("indent", Indent.Goal(force=0.5e-6, dwell=0.2, position=line_goal.start))
        assert indent.success and max(indent.trace.vertical_deflection) > 1e-6
    wait_for(
        lambda: truths and any(o.position.x > 55.05e-6 for o in truths[-1].objects if o.id == 0),
        10,
        what="ground truth showing the pushed sphere",
    )


@pytest.mark.parametrize(
    "action, goal, complaint",
    [
        ("scan_image", scan_goal(origin=(float("nan"), 1e-6)), "origin_x=nan"),
        ("scan_image", scan_goal(size=(0.0, 1e-6)), "size_x=0.0: must be > 0"),
        (
            "scan_image",
            scan_goal(pixels=(100_000, 64)),
            "pixels_x=100000: need a whole number [2, 4096]",
        ),
        ("scan_image", scan_goal(origin=(109.5e-6, 1e-6)), "outside the scanner range"),
        ("scan_image", scan_goal(size=(50e-6, 50e-6), line_rate=20.0), "slew limit"),
        (
            "move_tip",
            move_goal(120e-6, 1e-6),
            "target.x=1.2000e-04 m: outside the scanner range [0, 1.1000e-04] m",
        ),
        ("move_tip", move_goal(1e-6, float("inf")), "target.y=inf"),
        ("move_tip", move_goal(1e-6, 1e-6, speed=1.0), "slew limit"),
        ("move_tip", move_goal(1e-6, 1e-6, frame="map"), "frame_id='map'"),
        # a negative or NaN speed was run at the default speed (issue 30); 0 is the default
        ("move_tip", move_goal(1e-6, 1e-6, speed=-1.0), "speed=-1.0000e+00 m/s: must be > 0"),
        ("move_tip", move_goal(1e-6, 1e-6, speed=float("nan")), "speed=nan: must be finite"),
        ("local_scan", line_goal(-1.0), "speed=-1.0000e+00 m/s: must be > 0"),
        ("local_scan", line_goal(0.0), "speed=0.0000e+00 m/s: must be > 0"),
        ("local_scan", line_goal(float("nan")), "speed=nan: must be finite"),
        ("indent", Indent.Goal(force=-1.0, dwell=0.1), "force=-1.000e+00 N"),
    ],
)
def test_bad_goals_are_refused_naming_the_field_and_the_tip_stays(driver, action, goal, complaint):
    with AfmCommander(server_timeout=30) as afm:
        before = afm.send("move_tip", move_goal(10e-6, 10e-6, speed=10e-6)).commanded_position
        result = afm.send(action, goal)
        assert not result.success and complaint in result.message, result.message
        after = afm.send("move_tip", move_goal(10e-6, 10e-6, speed=10e-6)).commanded_position
        assert (before.x, before.y) == (after.x, after.y)


def test_cancel_stops_a_scan_and_a_queued_goal_waits_its_turn(nodes):
    # a 512-line scan at 1 Hz paced to ~100 s of wall time: time enough to cancel it even when a
    # loaded machine has spent its whole pacing budget computing the image
    nodes("driver", seed=2, real_time_factor=5.0)
    with AfmCommander(server_timeout=30) as afm:
        first = afm.send("scan_image", scan_goal(pixels=(64, 512), line_rate=1.0), wait=False)
        second = afm.send("move_tip", move_goal(20e-6, 20e-6, speed=10e-6), wait=False)
        wait_for(
            lambda: first.feedback is not None and first.feedback.lines_done >= 5,
            90,
            what="scan started",
        )
        assert not second.done()  # queued behind the scan
        assert second.cancel()
        assert first.cancel()
        cancelled = first.result(30)
        assert not cancelled.success and "scan cancelled; tip held at" in cancelled.message
        waiting = second.result(30)
        assert not waiting.success and "while waiting" in waiting.message
        done = afm.send("move_tip", move_goal(20e-6, 20e-6, speed=10e-6))
        assert done.success


def test_the_queue_limit_holds_when_goals_arrive_at_once_and_cancel_still_answers(nodes):
    # 8 accepted 12 (issue 30): goals accepted but not yet executing did not count, and each
    # waiting goal held one of four threads, so a cancel went unanswered behind a full queue
    nodes("driver", seed=2, real_time_factor=5.0, max_queued_goals=4)
    with AfmCommander(server_timeout=30) as afm:
        scan = afm.send("scan_image", scan_goal(pixels=(64, 512), line_rate=1.0), wait=False)
        wait_for(lambda: scan.feedback is not None, 90, what="scan started")
        waiting, refused = [], 0
        for k in range(7):
            try:
                waiting.append(
                    afm.send("move_tip", move_goal(20e-6 + k * 1e-6, 20e-6), wait=False)
                )
            except AfmError as exc:
                assert "rejected" in str(exc), exc
                refused += 1
        assert (len(waiting), refused) == (4, 3)
        assert scan.cancel()
        assert not scan.result(30).success
        assert all(job.result(60).success for job in waiting)
        assert afm.send("move_tip", move_goal(10e-6, 10e-6)).success  # places freed


def test_a_clients_readiness_probe_leaves_running_goals_alone(nodes):
    # the probe is a cancel request: it must name no goal that exists, never "all goals"
    nodes("driver", seed=2, real_time_factor=5.0)
    with (
        AfmCommander(server_timeout=30) as afm,
        AfmCommander("second_commander", server_timeout=30) as other,
    ):
        scan = afm.send("scan_image", scan_goal(pixels=(32, 64), line_rate=4.0), wait=False)
        wait_for(lambda: scan.feedback is not None, 60, what="scan started")
        assert other.clients["scan_image"].wait_until_answering(30)
        result = scan.result(120)
        assert result.success, result.message
        assert image_msg_to_array(result.scan.height).shape == (64, 32)


def test_a_server_nobody_runs_is_reported_with_the_nodes_the_graph_lists(ros_node):
    with AfmCommander("lonely_commander", server_timeout=1) as afm:
        client = afm.clients["scan_image"]
        assert not client.wait_until_answering(1.0)
        assert "the graph does not list its server" in client.not_answering
        assert "none now" in client.not_answering
        assert "/lonely_commander" in client.not_answering, client.not_answering


def test_sim_clock_runs_ahead_of_wall_time(nodes, ros_node):
    clocks = []
    ros_node.create_subscription(
        Clock, "/clock", lambda m: clocks.append(m.clock.sec + m.clock.nanosec * 1e-9), 50
    )
    nodes("driver", seed=2, real_time_factor=0.0)
    # the clock before the scan is the baseline: under load DDS may match us only later
    wait_for(lambda: clocks, 30, what="/clock before the scan")
    with AfmCommander(server_timeout=30) as afm:
        wall = time.monotonic()
        afm.send(
            "scan_image", scan_goal(pixels=(32, 200), line_rate=1.0)
        )  # 200 s of instrument time
        wall = time.monotonic() - wall
    wait_for(lambda: len(clocks) > 2, 10, what="/clock")
    assert max(clocks) - min(clocks) >= 199.0 and wall < 20.0


def test_daq_backend_without_hardware_fails_at_start_with_a_clear_message(nodes):
    code, output = nodes("driver", backend="daq").wait(60)
    assert code == 2 and "nidaqmx" in output.lower(), output


def test_unknown_backend_is_refused(nodes):
    code, output = nodes("driver", backend="telepathy").wait(60)
    assert code == 2 and "backend='telepathy'" in output, output


def test_replay_backend_serves_a_recorded_session(tmp_path, nodes):
    recording = tmp_path / "session.mcap"
    recorder = nodes("recorder", output=recording, discovery_period=0.1)
    live = nodes("driver", seed=5)
    with AfmCommander(server_timeout=30) as afm:
        afm.clients["scan_image"].wait_for_server(timeout_sec=30)
        afm.wait_until_subscribed(["/afm/scan", "/afm/scan_line", "/afm/force_trace"])
        recorded_scan = afm.send("scan_image", scan_goal())
        line_goal = LocalScan.Goal(samples=100, speed=1e-6)
        line_goal.start.x, line_goal.start.y, line_goal.end.x, line_goal.end.y = (
            54.7e-6,
            55e-6,
            55.3e-6,
            55e-6,
        )
        recorded_line = afm.send("local_scan", line_goal)
        time.sleep(1.0)
    live.stop()
    assert recorder.stop()[0] == 0
    nodes("driver", backend="replay", replay_input=recording)
    with AfmCommander(server_timeout=30) as afm:
        replayed_scan = afm.send("scan_image", scan_goal())
        np.testing.assert_array_equal(
            image_msg_to_array(replayed_scan.scan.height),
            image_msg_to_array(recorded_scan.scan.height),
        )
        wrong_line = LocalScan.Goal(samples=100, speed=1e-6)
        wrong_line.start.x, wrong_line.start.y, wrong_line.end.x, wrong_line.end.y = (
            1e-6,
            1e-6,
            2e-6,
            1e-6,
        )
        refused = afm.send("local_scan", wrong_line)
        assert not refused.success and "does not match the next recorded line" in refused.message
        replayed_line = afm.send("local_scan", line_goal)
        assert list(replayed_line.line.height) == list(recorded_line.line.height)


def test_the_driver_as_a_core_instrument_through_its_actions(driver, ros_node):
    """ActionInstrument: what the localizer and nano-hand call; results carry the executed
    command, so the instrument clock and the commanded position follow the driver."""
    from afm_core.instrument import LineRequest, ScanRequest
    from afm_ros.action_instrument import ActionInstrument

    instrument = ActionInstrument(ros_node, server_timeout=30)
    move = instrument.move_tip(54.7e-6, 55.0e-6, 10e-6)
    assert move.completed and instrument.commanded_position() == pytest.approx((54.7e-6, 55.0e-6))
    after_move = instrument.time
    assert after_move > 0 and instrument.last_command.kind == instrument.last_command.MOVE
    line = instrument.local_scan(LineRequest(54.7e-6, 55e-6, 55.3e-6, 55e-6, 200, 1e-6))
    assert (
        line.complete
        and len(line.height) == 200
        and line.height.max() == pytest.approx(200e-9, abs=3e-9)
    )
    assert line.start_time >= after_move and instrument.time == pytest.approx(
        line.start_time + line.times[-1], abs=0.05
    )
    assert instrument.commanded_position() == pytest.approx((55.3e-6, 55e-6))
    scan = instrument.raster_scan(
        ScanRequest(54.8e-6, 54.8e-6, 0.4e-6, 0.4e-6, 32, 32, line_rate=4.0)
    )
    assert scan.complete and scan.height.shape == (32, 32) and np.nanmax(scan.height) > 150e-9
    with pytest.raises(ValueError, match="x="):
        instrument.move_tip(200e-6, 55e-6, 1e-6)  # refused before sending: beyond the range
    with pytest.raises(ValueError, match="force"):
        instrument.indent(55e-6, 55e-6, 5e-6, 0.1)


def test_with_a_calibration_a_scan_after_a_long_move_waits_for_creep_and_says_so(nodes):
    """The shipped calibration's creep: after a 30 um move the scan waits (minutes of
    instrument time, none of wall time at real_time_factor 0) and its result says how long
    and why; the next scan, right after, does not."""
    calibration = (
        Path(__file__).resolve().parents[1]
        / "afm_localization"
        / "config"
        / "sim_calibration.yaml"
    )
    nodes("driver", seed=2, real_time_factor=0.0, calibration_file=str(calibration))
    with AfmCommander(server_timeout=30) as afm:
        moved = afm.send("move_tip", move_goal(25e-6, 55e-6, speed=1e-5))
        assert moved.success
        origin = (25e-6, 55e-6)
        first = afm.send("scan_image", scan_goal(origin=origin, pixels=(16, 16)))
        assert first.success and "waited" in first.message and "creep" in first.message
        seconds = float(first.message.split("waited ")[1].split(" s")[0])
        assert 60 < seconds < 600  # the 50 s creep of a 30 um step, down to 5 nm
        again = afm.send("scan_image", scan_goal(origin=origin, pixels=(16, 16)))
        waited = (
            float(again.message.split("waited ")[1].split(" s")[0])
            if "waited" in again.message
            else 0.0
        )
        assert again.success and waited < 0.25 * seconds  # only the 0.8 um approach's creep
