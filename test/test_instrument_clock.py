"""afm_ros.instrument_clock: a node that does not drive the instrument stamps on the time heard
on /clock, and never before the inputs what it stamps was made from (a /clock not yet taken put
a plan 32 s before its own map in a recording)."""

from builtin_interfaces.msg import Time
from rosgraph_msgs.msg import Clock

from afm_ros.instrument_clock import InstrumentClock


class WallClock:
    def __init__(self, seconds: float):
        self.seconds = seconds

    def now(self):
        return self

    def to_msg(self):
        return Time(sec=int(self.seconds), nanosec=round(self.seconds % 1 * 1e9))


class FakeNode:
    """What InstrumentClock asks of a node: a subscription and the node's (wall) clock."""

    def __init__(self, wall: float):
        self.callbacks = {}
        self.wall = WallClock(wall)

    def create_subscription(self, msg_type, topic, callback, depth, callback_group=None):
        self.callbacks[topic] = callback

    def get_clock(self):
        return self.wall


def seconds(stamp: Time) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


def test_the_time_heard_last_is_the_stamp_unless_an_input_is_newer():
    node = FakeNode(wall=5000.0)
    clock = InstrumentClock(node)
    assert seconds(clock.now()) == 5000.0  # nothing heard: wall time (the DAQ backend)
    node.callbacks["/clock"](Clock(clock=Time(sec=1000, nanosec=250_000_000)))
    assert seconds(clock.now()) == 1000.25
    assert seconds(clock.now(not_before=900.0)) == 1000.25
    # a map stamped at the end of a scan whose /clock messages were not taken yet
    assert seconds(clock.now(not_before=1032.5)) == 1032.5
    assert seconds(clock.now(not_before=None)) == 1000.25
