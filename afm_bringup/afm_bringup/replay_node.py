"""Replay node: republish a recording with its original timing.

Publishers offer the durability the recorded publishers offered (so latched scans stay
latched), reliably and with a deep history, so that no subscriber that asks for reliability
misses a message; /clock carries the recording's time for nodes running with use_sim_time. The
recording is streamed chunk by chunk, never loaded whole.
"""

from __future__ import annotations

import sys
import threading
import time

import rclpy
from rclpy.duration import Duration
from rclpy.node import Node
from rosgraph_msgs.msg import Clock

from afm_core.parameters import Parameter, ParameterTable
from afm_core.recording import RecordingError, RecordingReader
from afm_ros import params
from afm_ros.action_client import STOPPING
from afm_ros.message_types import import_message_type, publisher_qos_for
from afm_ros.node_main import run

PARAMETERS = ParameterTable(
    Parameter("input", "", "Path of the .mcap recording to replay (required)."),
    Parameter(
        "rate",
        1.0,
        "Playback speed factor (2.0 = twice as fast).",
        minimum=0.0,
        above_minimum=True,
    ),
    Parameter("topics", [""], "Topics to replay; empty = every recorded topic."),
    Parameter("loop", False, "Start again from the beginning after the last message."),
    Parameter("publish_clock", True, "Publish the recording's time on /clock (for use_sim_time)."),
    Parameter(
        "clock_frequency",
        100.0,
        "Rate of /clock messages (recording time), when publish_clock.",
        unit="Hz",
        minimum=0.0,
        above_minimum=True,
    ),
    Parameter(
        "start_delay",
        1.0,
        "Wait before the first message so subscribers can connect.",
        unit="s",
        minimum=0.0,
    ),
    Parameter(
        "wait_for_subscribers",
        0,
        "Before playing, wait until every replayed topic has at least this many "
        "subscribers (0: do not wait); an evaluation pipeline then misses nothing.",
        minimum=0,
    ),
    Parameter(
        "wait_timeout",
        30.0,
        "Wait for those subscribers at most this long, then give up with an error.",
        unit="s",
        minimum=0.0,
    ),
    Parameter(
        "queue_depth",
        100,
        "Messages each publisher keeps for subscribers that fall behind or match late "
        "(at least the recorded depth); latched topics hold this many for late joiners.",
        minimum=1,
    ),
)
# A subscriber that has not acknowledged within this is stalled or gone; the replay goes on.
ACKNOWLEDGE_TIMEOUT_S = 10.0
# The longest playback a rate may ask for (about 32 years): beyond it the schedule's waits
# overflow the platform's time_t mid-playback (rate=1e-300), so such a rate is refused.
MAX_PLAYBACK_S = 1e9


def check_playable(reader: RecordingReader, topics: list[str], rate: float) -> None:
    """RecordingError (a refusal, exit 2) when there is nothing to replay in `topics` (a loop
    would spin for ever publishing nothing) or `rate` stretches the recording past
    MAX_PLAYBACK_S."""
    recorded = reader.topics()
    counts = {t: recorded[t].message_count for t in topics}
    if not sum(counts.values()):
        held = ", ".join(f"{t} ({n} messages)" for t, n in counts.items()) or "no topic"
        raise RecordingError(
            f"nothing to replay: {reader.path} holds {held}"
            + ("" if topics else " that can be published")
        )
    playback_s = reader.duration_s / rate if rate > 0 else float("inf")
    if not playback_s <= MAX_PLAYBACK_S:
        raise RecordingError(
            f"parameter rate={rate!r}: the recording's {reader.duration_s:.6g} s would take "
            f"{playback_s:.3g} s; the limit is {MAX_PLAYBACK_S:.0e} s of playback, so rate "
            f"must be at least {reader.duration_s / MAX_PLAYBACK_S:.3g}"
        )


class ReplayNode(Node):
    def __init__(self):
        super().__init__("afm_replay")
        self.config = params.declare(self, PARAMETERS)
        if not self.config["input"]:
            raise RecordingError("parameter input: required (path of the .mcap recording)")
        self.reader = RecordingReader(self.config["input"])
        recorded = self.reader.topics()
        selected = [t for t in self.config["topics"] if t]
        unknown = [t for t in selected if t not in recorded]
        if unknown:
            raise RecordingError(
                f"parameter topics: {unknown} not in {self.reader.path}; "
                f"recorded: {sorted(recorded)}"
            )
        self.publishers_by_topic = {}
        for topic, info in recorded.items():
            if selected and topic not in selected:
                continue
            try:
                msg_type = import_message_type(info.type)
            except ValueError as exc:
                self.get_logger().warning(f"skipping {topic}: {exc}")
                continue
            self.publishers_by_topic[topic] = self.create_publisher(
                msg_type, topic, publisher_qos_for(info.offered_qos, self.config["queue_depth"])
            )
        check_playable(self.reader, list(self.publishers_by_topic), self.config["rate"])
        self.clock_publisher = (
            self.create_publisher(Clock, "/clock", 10) if self.config["publish_clock"] else None
        )
        self.published = 0
        self.slow_topics: set[str] = set()
        self.failure: str | None = None
        threading.Thread(target=self.play_then_stop, daemon=True).start()

    def play_then_stop(self):
        try:
            self.wait_for_subscribers()
            self.play()
        except (TimeoutError, RecordingError) as exc:
            self.failure = str(exc)
            rclpy.try_shutdown()
            return
        except Exception as exc:  # noqa: BLE001 - publishing races a SIGINT shutdown
            if rclpy.ok():
                # anything else still ends the node with the reason, never a silent hang
                self.failure = f"playback failed: {type(exc).__name__}: {exc}"
                rclpy.try_shutdown()
            return
        self.wait_until_delivered(self.publishers_by_topic)
        rclpy.try_shutdown()

    def warn_of_other_publishers(self) -> None:
        """A warning naming the topics another node also publishes (a running driver, say):
        replayed into a live graph, its nodes and recorder see both sessions mixed, and two
        /clock sources."""
        mine = self.get_name()
        topics = [*self.publishers_by_topic, *(["/clock"] if self.clock_publisher else [])]
        shared = {}
        for topic in topics:
            others = {
                info.node_name
                for info in self.get_publishers_info_by_topic(topic)
                if info.node_name != mine
            }
            if others:
                shared[topic] = sorted(others)
        if shared:
            listed = "; ".join(f"{topic} ({', '.join(nodes)})" for topic, nodes in shared.items())
            self.get_logger().warning(
                f"other nodes publish what this replay publishes: {listed}. Their subscribers "
                "get both sessions mixed (replay into a graph without a driver, or in another "
                "--domain-id)"
            )

    def wait_for_subscribers(self):
        wanted = self.config["wait_for_subscribers"]
        deadline = time.monotonic() + self.config["wait_timeout"]
        while wanted > 0 and rclpy.ok():
            short = {
                t: p.get_subscription_count()
                for t, p in self.publishers_by_topic.items()
                if p.get_subscription_count() < wanted
            }
            if not short:
                return
            if time.monotonic() > deadline:
                raise TimeoutError(
                    f"parameter wait_for_subscribers={wanted}: after "
                    f"{self.config['wait_timeout']} s these topics have fewer: {short}"
                )
            time.sleep(0.05)

    def wait_until_delivered(self, topics, timeout_s: float = ACKNOWLEDGE_TIMEOUT_S):
        """Wait until every reliable subscriber of these topics has acknowledged every message
        so far. A message lost on its way (a burst overflowing a transport buffer) is resent
        only from the publisher's history, so the replay waits before that history would
        overflow, and before it exits."""
        deadline = time.monotonic() + timeout_s
        for topic in topics:
            left = max(0.0, deadline - time.monotonic())
            if (
                not self.publishers_by_topic[topic].wait_for_all_acked(Duration(seconds=left))
                and topic not in self.slow_topics
            ):
                self.slow_topics.add(topic)
                self.get_logger().warning(
                    f"{topic}: a subscriber had not acknowledged every message "
                    f"after {timeout_s} s; it may miss some"
                )

    def play(self):
        """Publish every selected message at its recorded time (scaled by rate)."""
        time.sleep(self.config["start_delay"])
        self.warn_of_other_publishers()
        topics = list(self.publishers_by_topic)
        unacknowledged = dict.fromkeys(topics, 0)
        while rclpy.ok() and not STOPPING.is_set():
            schedule = _Schedule(self.reader.start_time_ns, self.config["rate"])
            next_clock = self.reader.start_time_ns
            clock_step_ns = int(1e9 / self.config["clock_frequency"])
            published_before = self.published
            for _schema, channel, message in self.reader.raw_messages(topics):
                if schedule.start_wall is None:  # /clock starts with the first message played
                    next_clock = max(next_clock, message.log_time)
                while self.clock_publisher and next_clock < message.log_time:
                    schedule.wait_for(next_clock)  # /clock ticks until this message is due
                    self._publish_clock(next_clock)
                    next_clock += clock_step_ns
                schedule.wait_for(message.log_time)
                if not rclpy.ok() or STOPPING.is_set():
                    return
                if self.clock_publisher:
                    self._publish_clock(message.log_time)
                publisher = self.publishers_by_topic[channel.topic]
                if unacknowledged[channel.topic] >= publisher.qos_profile.depth:
                    self.wait_until_delivered([channel.topic])
                    unacknowledged[channel.topic] = 0
                publisher.publish(message.data)
                schedule.published(message.log_time)
                unacknowledged[channel.topic] += 1
                self.published += 1
            if not self.config["loop"] or self.published == published_before:
                break  # a pass that found nothing would loop for ever publishing nothing
        self.get_logger().info(f"replayed {self.published} messages from {self.reader.path}")

    def _publish_clock(self, t_ns):
        msg = Clock()
        msg.clock.sec, msg.clock.nanosec = divmod(int(t_ns), 1_000_000_000)
        self.clock_publisher.publish(msg)


class _Schedule:
    """Wall-clock times of recorded ones, anchored when the first message has gone out: the
    first publish on a new topic can take a while on a loaded machine, and a schedule anchored
    before it would then send the messages after it as a burst. A later stall is caught up
    (the messages then due go out at once), as rosbag2 does."""

    def __init__(self, start_rec_ns: int, rate: float):
        self.start_rec_ns = start_rec_ns
        self.rate = rate
        self.start_wall: float | None = None

    def wall_offset(self, rec_ns: int) -> float:
        return (rec_ns - self.start_rec_ns) * 1e-9 / self.rate

    def wait_for(self, rec_ns: int):
        if self.start_wall is not None:
            delay = self.start_wall + self.wall_offset(rec_ns) - time.monotonic()
            if delay > 0:
                time.sleep(delay)

    def published(self, rec_ns: int):
        if self.start_wall is None:
            self.start_wall = time.monotonic() - self.wall_offset(rec_ns)


def finish(node: ReplayNode):
    node.reader.close()
    if node.failure:
        raise RuntimeError(node.failure)


def main(args=None):
    return run(
        ReplayNode,
        "afm replay",
        args,
        config_errors=(RecordingError, ValueError),
        on_shutdown=finish,
    )


if __name__ == "__main__":
    sys.exit(main())
