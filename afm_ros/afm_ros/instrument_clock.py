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


class InstrumentClock:
    def __init__(self, node, callback_group=None):
        self.node = node
        self.latest = None
        node.create_subscription(Clock, "/clock", self._take, 10, callback_group=callback_group)

    def _take(self, msg: Clock) -> None:
        self.latest = msg.clock

    def now(self):
        """The latest instrument time heard (builtin_interfaces/Time), else wall time."""
        latest = self.latest
        return latest if latest is not None else self.node.get_clock().now().to_msg()
