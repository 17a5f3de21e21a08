"""The localizer node in a graph with the simulated driver: it follows every command the
driver executes, publishes the estimate, and localizes through the Localize action."""

import time

import numpy as np
import pytest
from conftest import wait_for
from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped
from sim_calibration import oracle_calibration
from std_msgs.msg import Header

from afm_bringup.commander import AfmCommander, AfmError
from afm_core.imaging.landmarks import Landmark
from afm_msgs.action import Localize, MoveTip
from afm_msgs.msg import GroundTruth, LandmarkArray
from afm_ros.conversions import FRAME_TASK, landmarks_to_msg, pose_to_mean_cov
from afm_ros.qos_profiles import LATCHED

pytestmark = pytest.mark.ros

SPHERE = (55.0e-6, 55.0e-6)  # the default simulator's first sphere, r = 100 nm


def landmark(i, x, y, sigma=2e-9):
    return Landmark(
        id=i,
        kind="sphere",
        x=x,
        y=y,
        covariance=np.diag([sigma**2, sigma**2]),
        radius=100e-9,
        height=200e-9,
        length=0.0,
        orientation=0.0,
    )


def move(afm, x, y):
    target = PointStamped()
    target.header.frame_id = "afm_scanner"
    target.point.x, target.point.y = x, y
    result = afm.send("move_tip", MoveTip.Goal(target=target, speed=2e-6))
    assert result.success, result.message


def test_localize_through_the_action_with_lost_gated_and_unknown_landmarks(
    tmp_path, nodes, ros_node
):
    calibration = oracle_calibration(tmp_path / "calibration.yaml")
    nodes("driver", seed=3, real_time_factor=0.0)
    nodes("localizer", calibration_file=str(calibration))
    poses, truths = [], []
    ros_node.create_subscription(PoseWithCovarianceStamped, "/afm/tip_pose", poses.append, 10)
    ros_node.create_subscription(GroundTruth, "/afm/ground_truth", truths.append, LATCHED)
    marks = [
        landmark(0, *SPHERE),
        landmark(7, 54.0e-6, 54.0e-6),  # nothing there: lost
        landmark(8, SPHERE[0] + 80e-9, SPHERE[1] - 80e-9, sigma=0.5e-9),
    ]  # the sphere, mis-mapped: gated
    ros_node.create_publisher(LandmarkArray, "/afm/landmarks", LATCHED).publish(
        landmarks_to_msg(marks, Header(frame_id=FRAME_TASK))
    )
    with AfmCommander(server_timeout=30) as afm:
        refused = afm.localize(landmark_id=0)
        assert not refused.success and "no tip estimate yet" in refused.message
        move(afm, 54.7e-6, 54.75e-6)
        wait_for(lambda: poses, 10, what="a pose once the driver has moved")
        mean, cov = pose_to_mean_cov(poses[-1])
        assert poses[-1].header.frame_id == FRAME_TASK and mean == pytest.approx(
            (54.7e-6, 54.75e-6), abs=150e-9
        )
        sigma_before = np.sqrt(np.diag(cov))
        assert np.all(sigma_before > 10e-9)  # 50 nm initial, plus a ~0.4 um move

        result = afm.localize(landmark_id=0)
        assert result.success, result.message
        assert not result.lost and not result.gated_out and len(result.innovation) == 2
        mean, cov = pose_to_mean_cov(result.pose)
        sigma = np.sqrt(np.diag(cov))
        assert np.all(sigma < 0.5 * sigma_before) and np.all(sigma < 10e-9)
        wait_for(
            lambda: truths and truths[-1].header.stamp == result.pose.header.stamp or truths, 5
        )
        true_tip = np.array([truths[-1].tip_position.x, truths[-1].tip_position.y])
        assert np.all(np.abs(mean - true_tip) < 4 * sigma), (mean - true_tip, sigma)

        # right after the update the tip is known to a few nm: a landmark 80 nm from its map
        # position on both axes is rejected, line by line, and changes nothing
        gated = afm.localize(landmark_id=8)
        assert not gated.success and gated.gated_out and "gated" in gated.message
        assert "accepted" not in gated.message, gated.message
        lost = afm.localize(landmark_id=7)
        assert not lost.success and lost.lost and "lost" in lost.message
        unknown = afm.localize(landmark_id=42)
        assert not unknown.success and "landmark_id=42" in unknown.message
        assert "known ids: 0, 7, 8)" in unknown.message
        below = afm.localize(landmark_id=-5, position=SPHERE)  # not -1: no position meant
        assert not below.success and "landmark_id=-5: an id >= 0, or -1" in below.message
        far = afm.localize(position=(60e-6, 60e-6))
        assert not far.success and "match_radius" in far.message
        out_of_range = afm.localize(landmark_id=0, toward=(SPHERE[0], 200e-6))
        assert not out_of_range.success and "refused" in out_of_range.message
        assert "y line end.y" in out_of_range.message and "scanner range" in out_of_range.message
        not_finite = afm.localize(landmark_id=0, toward=(float("nan"), SPHERE[1]))
        assert not not_finite.success and "toward: must be finite" in not_finite.message
        # the estimate stayed consistent through the failed observations; the last line goes
        # on down to the next task point's height
        below = (SPHERE[0] + 200e-9, SPHERE[1] - 600e-9)
        final = afm.localize(position=(SPHERE[0] + 30e-9, SPHERE[1]), toward=below)
        assert final.success, final.message
        mean, cov = pose_to_mean_cov(final.pose)
        assert abs(mean[1] - below[1]) < 60e-9
        wait_for(lambda: len(truths) > 1, 5)
        true_tip = np.array([truths[-1].tip_position.x, truths[-1].tip_position.y])
        assert np.all(np.abs(mean - true_tip) < 4 * np.sqrt(np.diag(cov)))


def set_parameter(client, name, value):
    from rclpy.parameter import Parameter as RosParameter

    future = client.set_parameters([RosParameter(name, value=value)])
    wait_for(future.done, 10, what=f"an answer to setting {name}")
    return future.result().results[0]


def test_a_parameter_set_at_run_time_is_applied_or_refused_with_the_reason(
    tmp_path, nodes, ros_node
):
    from rclpy.parameter_client import AsyncParameterClient

    calibration = oracle_calibration(tmp_path / "calibration.yaml")
    nodes("driver", seed=3, real_time_factor=0.0)
    nodes("localizer", calibration_file=str(calibration))
    ros_node.create_publisher(LandmarkArray, "/afm/landmarks", LATCHED).publish(
        landmarks_to_msg([landmark(0, *SPHERE)], Header(frame_id=FRAME_TASK))
    )
    client = AsyncParameterClient(ros_node, "afm_localizer")
    assert client.wait_for_services(timeout_sec=20)
    with AfmCommander(server_timeout=30) as afm:
        move(afm, 54.7e-6, 54.75e-6)
        # a gate no innovation passes: the running filter takes it, the same line is rejected
        assert set_parameter(client, "gate", 1e-12).successful
        gated = afm.localize(landmark_id=0)
        assert not gated.success and gated.gated_out, gated.message
        restored = set_parameter(client, "gate", 10.827566170662733)
        assert restored.successful
        assert afm.localize(landmark_id=0).success

        refused = set_parameter(client, "gate", -1.0)
        assert not refused.successful and "parameter gate=-1.0: must be > 0" in refused.reason
        # what `ros2 param set /afm_localizer gate 12` sends: an integer, taken as the number
        assert set_parameter(client, "gate", 12).successful
        word = set_parameter(client, "gate", "wide")
        assert not word.successful and "parameter gate='wide': must be a number" in word.reason
        assert set_parameter(client, "gate", 10.827566170662733).successful
        read_only = set_parameter(client, "calibration_file", "other.yaml")
        assert not read_only.successful and "read-only" in read_only.reason
        assert afm.localize(landmark_id=0).success  # the refusals changed nothing


class HandFedLocalizer:
    """A localizer node fed by this test: TipCommands as a driver reports them, /clock, and the
    poses it publishes."""

    def __init__(self, nodes, ros_node):
        from rosgraph_msgs.msg import Clock

        from afm_msgs.msg import TipCommand
        from afm_ros import topics
        from afm_ros.qos_profiles import EVENTS

        nodes("localizer")
        self.poses = []
        ros_node.create_subscription(
            PoseWithCovarianceStamped, topics.TIP_POSE, self.poses.append, 100
        )
        self._commands = ros_node.create_publisher(TipCommand, topics.TIP_COMMAND, EVENTS)
        self._clock = ros_node.create_publisher(Clock, "/clock", 10)
        wait_for(
            lambda: self._clock.get_subscription_count() > 0, 30, what="the localizer listening"
        )

    def command(self, start_time, start, end, duration, kind=None):
        from afm_msgs.msg import TipCommand
        from afm_ros.conversions import seconds_to_time

        kind = TipCommand.MOVE if kind is None else kind
        msg = TipCommand(kind=kind, duration=duration, speed=1e-6)
        msg.header.stamp, msg.header.frame_id = seconds_to_time(start_time), "afm_scanner"
        msg.start.x, msg.start.y = start
        msg.end.x, msg.end.y = end
        msg.start_voltage = msg.end_voltage = [float("nan")] * 3
        self._commands.publish(msg)

    def clock(self, seconds: float) -> None:
        from rosgraph_msgs.msg import Clock

        from afm_ros.conversions import seconds_to_time

        self._clock.publish(Clock(clock=seconds_to_time(seconds)))


def test_no_pose_is_published_for_a_time_the_driver_has_not_yet_said_what_it_did(nodes, ros_node):
    """The driver publishes a command once it has run it, and its /clock runs ahead meanwhile.
    A pose for a clock time past the last command heard would put the tip where the move began,
    and the same stamp would come again with the tip where it ended once the command arrives."""
    from afm_ros.conversions import stamp_of

    feed = HandFedLocalizer(nodes, ros_node)
    poses, clock = feed.poses, feed.clock
    command = feed.command

    begin, end = (50e-6, 50e-6), (50.45e-6, 50e-6)
    command(1.0, begin, begin, 0.1)
    clock(1.1)
    wait_for(lambda: poses, 30, what="a pose after the first command")
    clock(3.0)  # a 450 nm move running, unheard
    time.sleep(1.0)  # ten ticks of the steady-rate pose
    command(1.1, begin, end, 1.9)
    wait_for(
        lambda: any(
            stamp_of(p.header) >= 3.0 - 1e-6 and p.pose.pose.position.x - begin[0] > 400e-9
            for p in list(poses)
        ),
        10,
        what="a pose at the move's end that has the move",
    )
    time.sleep(0.5)  # and the ticks after it
    at = {}
    for pose in poses:
        at.setdefault(round(stamp_of(pose.header), 6), []).append(pose.pose.pose.position.x)
    spread = {t: max(xs) - min(xs) for t, xs in at.items()}
    assert max(spread.values()) < 1e-9, spread


def test_a_tip_command_no_driver_can_have_run_is_ignored(nodes, ros_node):
    """Another program's TipCommand ending at 1 m (the scanner is 110 um), or one stamped
    1e6 s ahead of the clock, put the localizer's estimate there for good: every later
    Localize was refused as out of range until the node was restarted."""
    from afm_msgs.msg import TipCommand
    from afm_ros.conversions import stamp_of

    feed = HandFedLocalizer(nodes, ros_node)
    poses, clock = feed.poses, feed.clock

    def command(start_time, end, kind=TipCommand.MOVE):  # a stay at `end`, 0.1 s long
        feed.command(start_time, end, end, 0.1, kind)

    here = (50e-6, 50e-6)
    command(1.0, here)
    clock(1.1)
    wait_for(lambda: poses, 30, what="a pose after the first command")
    command(2.0, (1.0, 50e-6))  # 1 m: outside the scanner
    command(1e6, (60e-6, 50e-6))  # a million seconds ahead of the clock
    command(2.5, (60e-6, 50e-6), kind=42)  # no such kind
    there = (51e-6, 50e-6)
    command(3.0, there)
    clock(3.1)
    wait_for(
        lambda: any(stamp_of(p.header) >= 3.1 - 1e-6 for p in list(poses)),
        10,
        what="a pose after the good command",
    )
    time.sleep(0.3)
    last = list(poses)[-1]
    assert stamp_of(last.header) < 10.0, stamp_of(last.header)  # not moved to 1e6 s
    x = last.pose.pose.position.x
    # where the good command left the tip (the estimate follows the commands' model), not 1 m
    assert abs(x - there[0]) < 5e-6, x


def test_localize_goals_beyond_the_limit_are_rejected_and_the_rest_all_answer(
    tmp_path, nodes, ros_node
):
    """Three Localize goals at once held all three executor threads waiting on the one that
    observed, which then heard nothing from a live, idle driver and reported it gone."""
    from afm_localization.localizer_node import MAX_LOCALIZE_GOALS

    calibration = oracle_calibration(tmp_path / "calibration.yaml")
    nodes("driver", seed=3, real_time_factor=0.0)
    nodes("localizer", calibration_file=str(calibration))
    ros_node.create_publisher(LandmarkArray, "/afm/landmarks", LATCHED).publish(
        landmarks_to_msg([landmark(0, *SPHERE)], Header(frame_id=FRAME_TASK))
    )
    with AfmCommander(server_timeout=30) as afm:
        move(afm, 54.7e-6, 54.75e-6)
        jobs, rejected = [], []
        for _ in range(MAX_LOCALIZE_GOALS + 2):
            try:
                jobs.append(afm.send("localize", Localize.Goal(landmark_id=0), wait=False))
            except AfmError as exc:
                rejected.append(str(exc))
        assert len(jobs) >= MAX_LOCALIZE_GOALS  # those within the limit are all taken
        assert len(rejected) == MAX_LOCALIZE_GOALS + 2 - len(jobs)
        assert all("at most three at once" in text for text in rejected), rejected
        results = [job.result(120) for job in jobs]
        assert all(r.success for r in results), [r.message for r in results]


def test_a_cancelled_localize_ends_with_the_line_in_progress(tmp_path, nodes, ros_node):
    """A Localize on a landmark that is not there misses, then searches with up to eight
    lines. A cancel midway used to wait for every one of them (about 10 s at the simulator's
    real time); now the goal ends with the line or move in progress, says it was cancelled,
    and the next goal runs on an estimate that carries what the cancelled one moved."""
    calibration = oracle_calibration(tmp_path / "calibration.yaml")
    nodes("driver", seed=3, real_time_factor=1.0)
    nodes("localizer", calibration_file=str(calibration))
    ros_node.create_publisher(LandmarkArray, "/afm/landmarks", LATCHED).publish(
        landmarks_to_msg(
            [landmark(0, *SPHERE), landmark(7, 54.0e-6, 54.0e-6)], Header(frame_id=FRAME_TASK)
        )
    )
    with AfmCommander(server_timeout=30) as afm:
        move(afm, 54.1e-6, 54.1e-6)
        job = afm.send("localize", Localize.Goal(landmark_id=7), wait=False)
        wait_for(lambda: job.feedback is not None, 30, what="the lines under way")
        time.sleep(2.0)
        cancelled_at = time.monotonic()
        assert job.cancel()
        result = job.result(60)
        assert time.monotonic() - cancelled_at < 4.0, result.message
        assert not result.success and result.message.startswith("cancelled"), result.message
        assert "cancelled" in result.message.removeprefix("cancelled"), result.message
        after = afm.localize(landmark_id=0)
        assert after.success, after.message
