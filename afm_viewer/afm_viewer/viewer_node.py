"""Viewer node: the live scene in Foxglove, served by the Foxglove SDK's embedded WebSocket
server (book 2.2.2, 7.1.2: the operator's augmented-reality view).

The node is an adapter: it subscribes to the graph's topics, turns each message into Foxglove
messages (afm_viewer.scene, ROS-free) and logs them on the server's channels
(afm_viewer.server) with the message's header stamp, the instrument's time, as log time; a
message without a header gets the newest instrument time on /clock. What a client publishes on
/afm/teleop/cmd_vel (Foxglove's Teleop panel: geometry_msgs/Twist in JSON) is checked
(finite numbers, the Twist's fields only) and published on the ROS topic of that name, where
the teleop node takes it; anything else is refused with a log line. A message the node cannot
show (a covariance that is no covariance is drawn without its ellipse; worse is logged per
topic) never stops it: a viewer only watches.

The server listens on host:port, 127.0.0.1:8765 by default (Foxglove's default port,
localhost only); port 0 takes any free port. The port served is logged, published on
/afm/viewer/status (std_msgs/String, JSON, latched) and, if port_file is set, written there.
A port already taken, or a host that is not an address of this machine, stops the node (exit
2) with the parameter's name.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from pathlib import Path

from action_msgs.msg import GoalStatusArray
from geometry_msgs.msg import PoseWithCovarianceStamped, Twist, WrenchStamped
from rclpy.node import Node
from rclpy.qos import qos_profile_action_status_default
from sensor_msgs.msg import Image
from std_msgs.msg import String
from tf2_msgs.msg import TFMessage

from afm_core.parameters import Parameter, ParameterTable
from afm_msgs.action import Assemble, Localize, LocalScan, MoveTip, PushParticle, ScanImage
from afm_msgs.msg import ForceTrace, LandmarkArray, ObjectArray, PlannedPath
from afm_ros import frames, params, topics
from afm_ros.instrument_clock import InstrumentClock
from afm_ros.node_main import run
from afm_ros.qos_profiles import EVENTS, FEEDBACK, LATCHED, STREAM
from afm_viewer import scene
from afm_viewer.inputs import ActionStates, goal_id
from afm_viewer.server import ACTIONS, TELEOP_TOPIC, CannotServe, LiveServer

VIEWER_STATUS = "/afm/viewer/status"  # std_msgs/String (JSON), latched: where it serves
ACTION_TYPES = {
    "push_particle": PushParticle,
    "assemble": Assemble,
    "localize": Localize,
    "scan_image": ScanImage,
    "local_scan": LocalScan,
    "move_tip": MoveTip,
}
LOOPBACK = ("127.0.0.1", "localhost", "::1")
# s: a client that subscribes gets the newest map, plan, tip... this long after, at most
REPLAY_PERIOD = 0.2
# s between two log lines about the messages of one topic the viewer cannot show (a publisher
# at 20 Hz would otherwise fill the log)
UNSHOWN_LOG_PERIOD = 5.0


def _host(value: str) -> str:
    if not value.strip():
        raise ValueError("must name an address (127.0.0.1: this machine only)")
    return value


PARAMETERS = ParameterTable(
    Parameter(
        "host",
        "127.0.0.1",
        "Address the WebSocket server listens on; 127.0.0.1: this machine only, 0.0.0.0: every "
        "network the machine is on (anyone there can watch and send teleop commands).",
        check=_host,
    ),
    Parameter(
        "port",
        8765,
        "WebSocket port (8765: Foxglove's default); 0: any free port, reported in the log, "
        "on /afm/viewer/status and in port_file.",
        minimum=0,
        maximum=65535,
    ),
    Parameter("port_file", "", "If set, the port served is written to this file at start."),
    Parameter(
        "max_force_samples",
        scene.MAX_FORCE_SAMPLES,
        "Force samples per force trace sent to the plot (evenly spread).",
        minimum=2,
        maximum=100000,
        runtime=True,
    ),
)


class ViewerNode(Node):
    def __init__(self):
        super().__init__("afm_viewer")
        self.config = params.declare(self, PARAMETERS)
        self.clock = InstrumentClock(self)
        self.actions = ActionStates()
        self.twist_pub = self.create_publisher(Twist, TELEOP_TOPIC, 10)
        self.status_pub = self.create_publisher(String, VIEWER_STATUS, LATCHED)
        host, port = self.config["host"], self.config["port"]
        # a bad host or port is a configuration error (node_main: exit 2 with this message)
        try:
            self.server = LiveServer(
                host,
                port,
                self.forward_twist,
                self.get_logger().warning,
                info=self.get_logger().info,
            )
        except CannotServe as exc:
            raise ValueError(str(exc)) from exc
        self.subscribe()
        self.create_timer(REPLAY_PERIOD, self.server.replay_pending)
        try:
            self.announce()
        except OSError as exc:
            self.server.stop()
            raise ValueError(
                f"parameter port_file={self.config['port_file']!r}: cannot write it ({exc})"
            ) from exc
        if host not in LOOPBACK:
            self.get_logger().warning(
                f"host={host}: the viewer is reachable from the network, and anyone who reaches "
                "it can send teleop commands"
            )

    def announce(self) -> None:
        status = {"url": self.server.url, "host": self.server.host, "port": self.server.port}
        self.status_pub.publish(String(data=json.dumps(status)))
        if self.config["port_file"]:
            path = Path(self.config["port_file"])
            partial = path.with_name(path.name + ".part")
            partial.write_text(f"{self.server.port}\n")
            os.replace(partial, path)  # a reader never sees half a number
        self.get_logger().info(
            f"serving the live scene on {self.server.url} (Foxglove: Open connection > "
            "Foxglove WebSocket; layout afm_viewer/foxglove/afm_live.json)"
        )

    def guarded(self, topic: str, callback):
        """`callback` that logs a message it cannot show (at most every UNSHOWN_LOG_PERIOD per
        topic, with how many) instead of raising: a raise in a callback ends the node (one
        landmark with a NaN covariance did), and a latched message would end it again at
        each restart. A viewer only watches, so nothing it drops stops the session."""
        unshown = {"count": 0, "logged": -math.inf}

        def call(msg):
            try:
                callback(msg)
            except Exception as exc:  # noqa: BLE001 - any message a scene cannot be made of
                unshown["count"] += 1
                now = time.monotonic()
                if now - unshown["logged"] >= UNSHOWN_LOG_PERIOD:
                    self.get_logger().error(
                        f"{topic}: message not shown ({unshown['count']} so far): {exc!r}"
                    )
                    unshown["logged"] = now

        return call

    def subscribe(self) -> None:
        def sub(msg_type, topic, callback, qos):
            self.create_subscription(msg_type, topic, self.guarded(topic, callback), qos)

        sub(Image, topics.MAP_IMAGE, self.image_to("/afm/map/image"), LATCHED)
        sub(Image, topics.SCAN_IMAGE, self.image_to("/afm/scan/image"), LATCHED)
        sub(LandmarkArray, topics.LANDMARKS, self.on_landmarks, LATCHED)
        sub(PoseWithCovarianceStamped, topics.TIP_POSE, self.on_tip_pose, 10)
        sub(PlannedPath, topics.PLANNED_PATH, self.on_path, EVENTS)
        sub(ObjectArray, topics.OBJECTS_BELIEVED, self.on_objects, EVENTS)
        sub(ForceTrace, topics.FORCE_TRACE, self.on_force, STREAM)
        sub(TFMessage, topics.TF, lambda m: self.on_tf(m, "dynamic"), frames.DYNAMIC_QOS)
        sub(TFMessage, topics.TF_STATIC, lambda m: self.on_tf(m, "static"), frames.STATIC_QOS)
        sub(WrenchStamped, topics.TELEOP_WRENCH, self.on_wrench, 10)
        sub(String, topics.TELEOP_STATUS, self.on_teleop_status, 10)
        sub(Twist, TELEOP_TOPIC, self.on_twist_echo, 10)
        for name in ACTIONS:
            action_type, base = ACTION_TYPES[name], f"/afm/{name}/_action"
            sub(
                GoalStatusArray,
                f"{base}/status",
                lambda msg, name=name: self.on_action_status(name, msg),
                qos_profile_action_status_default,
            )
            sub(
                action_type.Impl.FeedbackMessage,
                f"{base}/feedback",
                lambda msg, name=name: self.on_action_feedback(name, msg),
                FEEDBACK,
            )

    # -- ROS -> the viewer -----------------------------------------------------------------
    def now_ns(self) -> int:
        t = self.clock.now()
        return int(t.sec) * 1_000_000_000 + int(t.nanosec)

    def image_to(self, channel: str):
        return lambda msg: self.server.log(
            channel, scene.image(msg), log_time=scene.stamp_ns(msg.header)
        )

    def on_landmarks(self, msg) -> None:
        self.server.log(
            "/afm/viewer/landmarks", scene.landmark_scene(msg), scene.stamp_ns(msg.header)
        )

    def on_tip_pose(self, msg) -> None:
        t = scene.stamp_ns(msg.header)
        self.server.log("/afm/tip_pose", scene.tip_pose(msg), t)
        self.server.log("/afm/viewer/tip", scene.tip_scene(msg), t)

    def on_path(self, msg) -> None:
        t = scene.stamp_ns(msg.path.header)
        self.server.log("/afm/viewer/planned_path", scene.path_scene(msg), t)

    def on_objects(self, msg) -> None:
        t = scene.stamp_ns(msg.header)
        key = f"{msg.origin}/" + ",".join(str(o.id) for o in msg.objects)  # newest per object
        self.server.log("/afm/viewer/objects", scene.objects_scene(msg), t, key=key)
        self.server.log("/afm/objects/believed", scene.objects_json(msg), t, key=key)

    def on_force(self, msg) -> None:
        try:
            samples = scene.force_samples(msg, self.config["max_force_samples"])
        except ValueError as exc:
            self.get_logger().error(f"force trace not shown: {exc}")
            return
        for t, sample in samples:
            self.server.log("/afm/viewer/force", sample, t)

    def on_tf(self, msg, kind: str) -> None:
        if msg.transforms:
            t = scene.stamp_ns(msg.transforms[0].header)
            self.server.log("/tf", scene.transforms(msg), t, key=kind)

    def on_wrench(self, msg) -> None:
        self.server.log(topics.TELEOP_WRENCH, scene.message_dict(msg), scene.stamp_ns(msg.header))

    def on_teleop_status(self, msg) -> None:
        try:
            status = json.loads(msg.data)
        except json.JSONDecodeError:
            status = None
        if not isinstance(status, dict):
            status = {"data": msg.data}
        self.server.log(topics.TELEOP_STATUS, status, self.now_ns())

    def on_twist_echo(self, msg) -> None:
        self.server.log(TELEOP_TOPIC, scene.message_dict(msg), self.now_ns())

    def on_action_status(self, name: str, msg) -> None:
        state = self.actions.status(name, msg)
        self.server.log(f"/afm/viewer/actions/{name}", state, self.now_ns())

    def on_action_feedback(self, name: str, msg) -> None:
        state = self.actions.feedback(name, goal_id(msg.goal_id), scene.message_dict(msg.feedback))
        self.server.log(f"/afm/viewer/actions/{name}", state, self.now_ns())

    # -- the viewer -> ROS -----------------------------------------------------------------
    def forward_twist(self, twist: dict) -> None:
        """A client's checked Twist (afm_viewer.inputs.parse_twist) on the ROS topic."""
        msg = Twist()
        for part in ("linear", "angular"):
            vector = getattr(msg, part)
            vector.x, vector.y, vector.z = (twist[part][a] for a in ("x", "y", "z"))
        self.twist_pub.publish(msg)

    def stop(self) -> None:
        self.server.stop()


def main(args=None):
    return run(ViewerNode, "afm_viewer", args, on_shutdown=lambda node: node.stop())


if __name__ == "__main__":
    sys.exit(main())
