"""The viewer's Foxglove WebSocket server and its channels, without ROS.

`LiveServer` starts the SDK's embedded server (foxglove.start_server) on its own logging
context, advertises every channel of the live scene at once (a client sees the whole list
before any data, and a layout can name them), and takes what clients publish: a client may
advertise only TELEOP_TOPIC with JSON encoding; each of its messages is checked
(afm_viewer.inputs.parse_twist) and handed to `on_twist`, or refused with a log line.

The server keeps no history, so a client that subscribes late would see no map until the next
one: the newest message of each state-like channel (KEPT: the images, landmarks, plan, tip,
believed objects, frame tree, action states) is kept, and sent again when a client subscribes
to its channel (`replay_pending`, called by the node's timer: not from the server's callback).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import foxglove
from foxglove import Channel, Context
from foxglove.channels import (
    FrameTransformsChannel,
    PoseInFrameChannel,
    RawImageChannel,
    SceneUpdateChannel,
)
from foxglove.websocket import Capability, ChannelView, Client, ClientChannel, ServerListener

from afm_viewer.inputs import CLIENT_ENCODING, TWIST_SCHEMAS, parse_twist

# what a client may publish (geometry_msgs/Twist, JSON); afm_ros.topics.TELEOP_CMD_VEL, named
# here as this module is ROS-free (test_viewer_scene checks the two agree)
TELEOP_TOPIC = "/afm/teleop/cmd_vel"
ACTIONS = ("push_particle", "assemble", "localize", "scan_image", "local_scan", "move_tip")

VECTOR = {"type": "object", "properties": {a: {"type": "number"} for a in ("x", "y", "z")}}
TIME = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
FORCE_SCHEMA = {
    "title": "afm.ForceSample",
    "type": "object",
    "properties": {
        "timestamp": TIME,
        "lateral_force": {"type": "number", "description": "N"},
        "normal_force": {"type": "number", "description": "N"},
        "task": {"type": "string"},
        "object_id": {"type": "integer"},
    },
}
TWIST_SCHEMA = {
    "title": "geometry_msgs/Twist",
    "type": "object",
    "properties": {"linear": VECTOR, "angular": VECTOR},
}
WRENCH_SCHEMA = {
    "title": "geometry_msgs/WrenchStamped",
    "type": "object",
    "properties": {
        "header": {
            "type": "object",
            "properties": {"stamp": TIME, "frame_id": {"type": "string"}},
        },
        "wrench": {"type": "object", "properties": {"force": VECTOR, "torque": VECTOR}},
    },
}
ANY = {"type": "object", "additionalProperties": True}

# Foxglove topic -> (channel kind, JSON schema for "json")
CHANNELS = {
    "/afm/map/image": ("image", None),
    "/afm/scan/image": ("image", None),
    "/afm/viewer/landmarks": ("scene", None),
    "/afm/viewer/tip": ("scene", None),
    "/afm/viewer/planned_path": ("scene", None),
    "/afm/viewer/objects": ("scene", None),
    "/afm/tip_pose": ("pose", None),
    "/tf": ("tf", None),
    "/afm/objects/believed": ("json", {**ANY, "title": "afm.ObjectsBelieved"}),
    "/afm/viewer/force": ("json", FORCE_SCHEMA),
    "/afm/teleop/wrench": ("json", WRENCH_SCHEMA),
    "/afm/teleop/status": ("json", {**ANY, "title": "afm.TeleopStatus"}),
    TELEOP_TOPIC: ("json", TWIST_SCHEMA),
    **{f"/afm/viewer/actions/{a}": ("json", {**ANY, "title": "afm.ActionState"}) for a in ACTIONS},
}
# channels whose newest message is a state a late client needs (not a stream like the forces)
KEPT = {
    "/afm/map/image",
    "/afm/scan/image",
    "/afm/viewer/landmarks",
    "/afm/viewer/tip",
    "/afm/tip_pose",
    "/afm/viewer/planned_path",
    "/afm/viewer/objects",
    "/afm/objects/believed",
    "/tf",
    "/afm/teleop/status",
    *(f"/afm/viewer/actions/{a}" for a in ACTIONS),
}
TYPED = {
    "image": RawImageChannel,
    "scene": SceneUpdateChannel,
    "pose": PoseInFrameChannel,
    "tf": FrameTransformsChannel,
}


class PortTaken(RuntimeError):
    pass


class TeleopListener(ServerListener):
    """Client channels on TELEOP_TOPIC in JSON are taken; their messages go to `on_twist` when
    they are Twists with finite numbers. Everything else is refused with a log line."""

    def __init__(
        self,
        on_twist: Callable[[dict], None],
        log: Callable[[str], None],
        info: Callable[[str], None] | None = None,
    ):
        self.on_twist, self.log, self.info = on_twist, log, info or log
        self.lock = threading.Lock()
        self.new_subscriptions: set[str] = set()  # topics to send their kept messages again
        self.accepted: set[tuple[int, int]] = set()  # (client id, client channel id)
        self.forwarded = 0
        self.refused = 0
        self.subscribers: dict[int, set[str]] = {}

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        with self.lock:
            self.subscribers.setdefault(client.id, set()).add(channel.topic)
            self.new_subscriptions.add(channel.topic)

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        with self.lock:
            self.subscribers.get(client.id, set()).discard(channel.topic)

    def on_client_advertise(self, client: Client, channel: ClientChannel) -> None:
        reason = None
        if channel.topic != TELEOP_TOPIC:
            reason = f"topic {channel.topic!r}: clients may publish only on {TELEOP_TOPIC}"
        elif channel.encoding != CLIENT_ENCODING:
            reason = f"encoding {channel.encoding!r}: expected {CLIENT_ENCODING!r}"
        elif channel.schema_name not in TWIST_SCHEMAS:
            reason = f"schema {channel.schema_name!r}: expected geometry_msgs/Twist"
        if reason:
            self.log(f"client {client.id} channel {channel.id} refused: {reason}")
            return
        with self.lock:
            self.accepted.add((client.id, channel.id))
        self.info(f"client {client.id} publishes Twists on {TELEOP_TOPIC} (channel {channel.id})")

    def on_client_unadvertise(self, client: Client, client_channel_id: int) -> None:
        with self.lock:
            self.accepted.discard((client.id, client_channel_id))

    def on_message_data(self, client: Client, client_channel_id: int, data: bytes) -> None:
        with self.lock:
            taken = (client.id, client_channel_id) in self.accepted
        if not taken:
            self.refuse(client, client_channel_id, "its channel was not accepted")
            return
        try:
            twist = parse_twist(bytes(data))
        except ValueError as exc:
            self.refuse(client, client_channel_id, str(exc))
            return
        self.on_twist(twist)
        with self.lock:
            self.forwarded += 1

    def refuse(self, client: Client, channel_id: int, reason: str) -> None:
        with self.lock:
            self.refused += 1
        self.log(f"client {client.id} channel {channel_id}: message refused: {reason}")


class LiveServer:
    """The WebSocket server on host:port (port 0: any free port, see `port`) and the live
    scene's channels (CHANNELS); log(topic, message, log_time_ns) sends on one."""

    def __init__(
        self,
        host: str,
        port: int,
        on_twist: Callable[[dict], None],
        log: Callable[[str], None],
        name: str = "afm live viewer",
        port_parameter: str = "port",
        info: Callable[[str], None] | None = None,
    ):
        self.context = Context()
        self.listener = TeleopListener(on_twist, log, info)
        self.kept: dict[str, dict[str, tuple[object, int | None]]] = {}
        self.kept_lock = threading.Lock()
        self.channels = {}
        for topic, (kind, schema) in CHANNELS.items():
            if kind == "json":
                self.channels[topic] = Channel(topic, schema=schema, context=self.context)
            else:
                self.channels[topic] = TYPED[kind](topic, context=self.context)
        try:
            self.server = foxglove.start_server(
                name=name,
                host=host,
                port=port,
                capabilities=[Capability.ClientPublish],
                server_listener=self.listener,
                supported_encodings=[CLIENT_ENCODING],
                context=self.context,
            )
        except RuntimeError as exc:
            raise PortTaken(
                f"parameter {port_parameter}={port} (host {host!r}): cannot serve on "
                f"{host}:{port} ({exc}); give another port, or {port_parameter}:=0 for any "
                "free one"
            ) from exc
        self.host = host

    @property
    def port(self) -> int:
        return self.server.port

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def log(self, topic: str, message, log_time: int | None = None, key: str = "") -> None:
        """Send `message` on `topic`'s channel; on a KEPT channel also keep it, the newest per
        `key` (e.g. the static and the dynamic frame tree on /tf), for late subscribers."""
        if topic in KEPT:
            with self.kept_lock:
                self.kept.setdefault(topic, {})[key] = (message, log_time)
        self.channels[topic].log(message, log_time=log_time)

    def replay_pending(self) -> int:
        """Send the kept messages of every channel a client subscribed to since the last call
        (every subscriber of it gets them again: each replaces what it shows). Returns how
        many were sent."""
        with self.listener.lock:
            topics, self.listener.new_subscriptions = self.listener.new_subscriptions, set()
        sent = 0
        for topic in sorted(topics & KEPT):
            with self.kept_lock:
                kept = list(self.kept.get(topic, {}).values())
            for message, log_time in kept:
                self.channels[topic].log(message, log_time=log_time)
                sent += 1
        return sent

    def stop(self) -> None:
        self.server.stop()
        for channel in self.channels.values():
            channel.close()
