"""The nano-hand node's localization: the strokes are mapped from the commanded position after
the localizer's lines, which reaches the node on /afm/tip_command on a path of its own."""

import threading
from types import SimpleNamespace

import numpy as np
import pytest
from std_msgs.msg import Header

from afm_msgs.action import Localize
from afm_msgs.msg import TipCommand
from afm_ros.conversions import FRAME_TASK, mean_cov_to_pose, seconds_to_time
from afm_ros.teardown import destroy_node_fully

pytestmark = pytest.mark.ros

LINES_END = 1000.0  # s, instrument time at the end of the localizer's last line


@pytest.fixture
def nano_hand(monkeypatch):
    import rclpy

    import afm_manipulation.nano_hand_node as module

    def localize_action(*_args, **_kwargs):
        result = Localize.Result(success=True, message="accepted")
        header = Header(stamp=seconds_to_time(LINES_END), frame_id=FRAME_TASK)
        result.pose = mean_cov_to_pose(np.array([55e-6, 55e-6]), np.eye(2) * 1e-18, header)
        return result

    monkeypatch.setattr(module, "call_action", localize_action)
    rclpy.init()
    node = module.NanoHandNode()
    node.instrument.rest_at((54e-6, 54e-6), 900.0)  # before the lines
    yield node
    destroy_node_fully(node)  # its action servers too: a later graph test in its domain
    rclpy.try_shutdown()  # listed this nano-hand beside its own and found no server


def line_command(end_xy, end_time) -> TipCommand:
    command = TipCommand(kind=TipCommand.SCAN_LINE, duration=1.0)
    command.header.stamp = seconds_to_time(end_time - 1.0)
    command.end.x, command.end.y = end_xy
    return command


def test_localization_waits_for_the_lines_to_be_heard(nano_hand):
    late = threading.Timer(
        0.3, nano_hand.instrument.observe_command, [line_command((55.2e-6, 55e-6), LINES_END)]
    )
    late.start()
    localization = nano_hand.localize(SimpleNamespace(id=0), lambda: False)
    late.join()
    assert localization.success, localization.message
    # what the strokes are mapped from: where the lines left the scanner, not where it was before
    assert nano_hand.instrument.commanded_position() == (55.2e-6, 55e-6)


def test_localization_fails_when_the_lines_never_arrive(nano_hand):
    localization = nano_hand.localize(SimpleNamespace(id=0), lambda: False)
    assert not localization.success and "/afm/tip_command" in localization.message


def test_one_manipulation_is_claimed_at_acceptance_and_given_back_however_it_ends(nano_hand):
    """Two goals arriving at once at an idle nano-hand were both accepted, the second waiting
    for the first: now the second is rejected at once, and the claim returns when the first
    ends, also by an exception."""
    from rclpy.action import GoalResponse

    assert nano_hand.accept(None) == GoalResponse.ACCEPT
    assert nano_hand.accept(None) == GoalResponse.REJECT

    def fails(_goal_handle):
        raise RuntimeError("the push broke")

    with pytest.raises(RuntimeError):
        nano_hand.releasing(fails)(None)
    assert nano_hand.accept(None) == GoalResponse.ACCEPT
    assert nano_hand.releasing(lambda _goal_handle: "result")(None) == "result"
    assert nano_hand.accept(None) == GoalResponse.ACCEPT


def test_a_one_image_map_s_timing_reaches_the_verdict_and_a_pair_s_does_not(nano_hand):
    """A map that is one image is stretched by its own drift: its pixel times go to the
    procedure's verdict (map_time); a drift-corrected pair's map is taken as drift-free."""
    from sample_messages import raster_scan

    assert nano_hand.procedure.map_time() is None  # no map yet
    single = raster_scan(0)
    single.pair_id = ""
    nano_hand.on_map(single)
    map_time = nano_hand.procedure.map_time()
    # row 10's centre (0 deg scan, lines along +y from the origin): its line's start time
    xy = (
        single.origin.x + 0.5 * single.pixel_size_x,
        single.origin.y + 10.5 * single.pixel_size_y,
    )
    assert map_time(np.array(xy)) == pytest.approx(100.0 + 10 * 0.5, abs=0.5)
    nano_hand.on_map(raster_scan(2))  # pair_id "pair-1": drift-corrected
    assert nano_hand.procedure.map_time() is None
