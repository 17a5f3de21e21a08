"""The instrument's clock for nodes that stamp what they publish but do not drive the instrument
(the planner): every stamp in the graph, and so every log time of a recording, is then on one
time base.

The driver stamps with the instrument's time (wall time at its start + instrument time) and
publishes it on /clock for the simulated and replayed instruments, whose time runs ahead of
wall time when they run faster than real time (minutes in a session). Without /clock (the DAQ
backend, whose instrument time is wall time) wall time is the instrument's time.
"""

from __future__ import annotations

from rosgraph_msgs.msg import Clock

from afm_ros.conversions import seconds_to_time


class InstrumentClock:
    def __init__(self, node, callback_group=None):
        self.node = node
        self.latest = None
        node.create_subscription(Clock, "/clock", self._take, 10, callback_group=callback_group)

    def _take(self, msg: Clock) -> None:
        self.latest = msg.clock

    def now(self, not_before: float | None = None):
        """The latest instrument time heard (builtin_interfaces/Time), else wall time; never
        before `not_before` (s), the stamp of the newest input what is stamped was made from.

        Why: /clock and the inputs come on topics of their own, taken by separate callbacks. A
        node whose /clock callbacks had not run since a scan began stamped a plan made from that
        scan's map 32 s (the scan's length) before the map itself, so a recording showed the plan
        before what it was made from (the Foxglove recording test, 2026-11-28)."""
        latest = self.latest
        if latest is None:
            latest = self.node.get_clock().now().to_msg()
        if not_before is not None and latest.sec + latest.nanosec * 1e-9 < not_before:
            return seconds_to_time(not_before)
        return latest
