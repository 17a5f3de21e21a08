"""Recorder node: raw (serialized) subscriptions written to MCAP by afm_core's writer.

Topics are subscribed as their publishers appear (checked every `discovery_period`), with a
QoS that matches all of them; each channel stores the publishers' offered QoS. SIGINT and
SIGTERM close the file properly (summary, indexes, final name).

One time base: with `log_time` "header" (the default) a message's log time is the stamp it
carries (afm_core.recording.stamps), which every node takes from the instrument's clock, so a
viewer's timeline, its plots and `ros2 bag play` all run on the instrument's time; a message
without a stamp gets the instrument's latest /clock (wall time when no driver publishes one).
The wall time a message arrived is kept as its publish time. "receive" logs arrival times.
"""

from __future__ import annotations

import sys

from rclpy.node import Node
from rosgraph_msgs.msg import Clock

from afm_core.parameters import Parameter, ParameterTable
from afm_core.recording import (
    DefinitionNotFound,
    RecordingError,
    RecordingWriter,
    full_message_definition,
)
from afm_core.recording.stamps import stamp_layout, stamp_ns
from afm_ros import params, topics
from afm_ros.message_types import describe_qos, import_message_type, subscription_qos_for
from afm_ros.node_main import rcl_reason, run

PARAMETERS = ParameterTable(
    Parameter("output", "", "Path of the new .mcap file (required; never overwritten)."),
    Parameter(
        "topics",
        topics.RECORDED_BY_DEFAULT,
        "Topics to record; subscribed when a publisher appears.",
    ),
    Parameter(
        "all_topics",
        False,
        "Record every topic that appears (except /rosout and /parameter_events).",
    ),
    Parameter(
        "log_time",
        "header",
        "Log time of each message: 'header' (its stamp, the instrument's clock; unstamped "
        "messages: the latest /clock) or 'receive' (wall time of arrival).",
        choices=("header", "receive"),
    ),
    Parameter(
        "discovery_period",
        0.5,
        "Time between checks of the ROS graph for new publishers.",
        unit="s",
        minimum=0.0,
        above_minimum=True,
    ),
    Parameter(
        "compression",
        "zstd",
        "Chunk compression: zstd, lz4 or none.",
        choices=("zstd", "lz4", "none"),
    ),
    Parameter(
        "chunk_size",
        4 * 1024 * 1024,
        "Bytes of messages per MCAP chunk before it is compressed and written.",
        unit="B",
        minimum=1,
    ),
    Parameter(
        "flush_interval",
        1.0,
        "Longest time a received message waits in memory before its chunk is compressed and "
        "written: what a killed recorder can lose (shorter: smaller chunks, less compression).",
        unit="s",
        minimum=0.0,
        above_minimum=True,
    ),
    Parameter(
        "min_free_bytes",
        64 * 1024 * 1024,
        "Stop and close the recording when the disk has less free space.",
        unit="B",
        minimum=0,
    ),
)
IGNORED_WITH_ALL = {"/rosout", "/parameter_events"}
DRAIN_SECONDS = 1.0  # at most, after SIGINT/SIGTERM, writing what had already arrived (with
# node_main.STOP_GRACE_S for a callback in progress, the stop stays within 2 s)


class RecorderNode(Node):
    def __init__(self):
        super().__init__("afm_recorder")
        self.config = params.declare(self, PARAMETERS)
        if not self.config["output"]:
            raise RecordingError("parameter output: required (path of the new .mcap file)")
        # before the file exists: a refusal after it would leave a .part blocking the name
        wanted = {self._full_name(topic) for topic in self.config["topics"]}
        self.writer = RecordingWriter(
            self.config["output"],
            compression=self.config["compression"],
            chunk_size=self.config["chunk_size"],
            min_free_bytes=self.config["min_free_bytes"],
            flush_interval=self.config["flush_interval"],
        )
        self.wanted = wanted
        self.latest_clock_ns: int | None = None
        if self.config["log_time"] == "header":
            self.create_subscription(Clock, "/clock", self._take_clock, 10)
        self.recorded_topics = {}
        self._skipped = set()
        self.failure: str | None = None
        self.create_timer(self.config["discovery_period"], self.discover)
        self.create_timer(self.writer.poll_period, self.flush_if_due)
        self.discover()
        self.get_logger().info(
            f"recording {sorted(self.wanted) if not self.config['all_topics'] else 'all topics'}"
            f" to {self.writer.part} (final name {self.writer.path})"
        )

    def _full_name(self, topic: str) -> str:
        """The topic as the graph names it ('afm/scan' -> '/afm/scan'): a relative name would
        never equal a graph's name and record nothing without a word."""
        try:
            return self.resolve_topic_name(topic)
        except RuntimeError as exc:  # rcl's RCLError
            reason = rcl_reason(exc).removeprefix("failed to resolve name: ")
            raise RecordingError(
                f"parameter topics: {topic!r} is not a topic name: {reason}"
            ) from None

    def discover(self):
        if self.config["all_topics"]:
            self.wanted |= {
                name for name, _ in self.get_topic_names_and_types()
            } - IGNORED_WITH_ALL
        for topic in sorted(self.wanted - set(self.recorded_topics) - self._skipped):
            publishers = self.get_publishers_info_by_topic(topic)
            publishers = [p for p in publishers if p.node_name != self.get_name()]
            if not publishers:
                continue
            type_names = {p.topic_type for p in publishers}
            if len(type_names) > 1:
                self._skip(topic, f"publishers disagree on its type: {sorted(type_names)}")
                continue
            type_name = type_names.pop()
            try:
                offers = [describe_qos(p.qos_profile) for p in publishers]
                msg_type = import_message_type(type_name)
                channel = self.writer.add_channel(topic, type_name, offers)
                layout = stamp_layout(type_name, full_message_definition(type_name))
            except (DefinitionNotFound, ValueError) as exc:
                self._skip(topic, str(exc))
                continue
            qos = subscription_qos_for(offers)
            self.recorded_topics[topic] = self.create_subscription(
                msg_type, topic, self._writer_callback(channel, layout), qos, raw=True
            )
            self.get_logger().info(
                f"recording {topic} ({type_name}, {qos.reliability.name.lower()}, "
                f"{qos.durability.name.lower()})"
            )

    def _skip(self, topic, reason):
        self._skipped.add(topic)
        self.get_logger().error(f"not recording {topic}: {reason}")

    def _take_clock(self, msg: Clock) -> None:
        self.latest_clock_ns = msg.clock.sec * 1_000_000_000 + msg.clock.nanosec

    def log_time_ns(self, data: bytes, layout: str | None, received_ns: int) -> int:
        if self.config["log_time"] == "receive":
            return received_ns
        stamp = stamp_ns(data, layout)
        if stamp is not None:
            return stamp
        return received_ns if self.latest_clock_ns is None else self.latest_clock_ns

    def _writer_callback(self, channel, layout: str | None):
        def write(data: bytes):
            if self.writer.closed:
                return
            received = self.get_clock().now().nanoseconds
            try:
                self.writer.write(
                    channel, self.log_time_ns(data, layout, received), data, received
                )
            except RecordingError as exc:
                self.failure = str(exc)
                self.get_logger().error(self.failure)
                raise SystemExit(1) from exc

        return write

    def flush_if_due(self):
        if self.writer.closed:
            return
        try:
            self.writer.flush_if_due()
        except RecordingError as exc:
            self.failure = str(exc)
            self.get_logger().error(self.failure)
            raise SystemExit(1) from exc

    def close(self):
        path = self.writer.close()
        # The ROS context may already be down (SIGINT), so not through the node's logger.
        print(
            f"afm recorder: closed {path}: {self.writer.message_count} messages on "
            f"{len(self.writer.topics)} topics",
            file=sys.stderr,
        )


def close_recording(node: RecorderNode):
    if not node.writer.closed:
        node.close()


def main(args=None):
    # what a reliable publisher already counts as delivered is written before the file closes
    return run(
        RecorderNode,
        "afm recorder",
        args,
        config_errors=(RecordingError, ValueError),
        on_shutdown=close_recording,
        drain_seconds=DRAIN_SECONDS,
    )


if __name__ == "__main__":
    sys.exit(main())
