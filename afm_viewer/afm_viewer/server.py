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

What is sent is what a client can read: on JSON channels a number that is not finite is null
(`json_ready`), and a log time is held within the protocol's unsigned 64-bit nanoseconds.
"""

from __future__ import annotations

import json
import math
import socket
import threading
import time
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
# the newest this many keys of a KEPT channel are sent to a late client (the believed objects
# are kept per set of ids, which grows with what a session pushes)
KEPT_PER_TOPIC = 256
TYPED = {
    "image": RawImageChannel,
    "scene": SceneUpdateChannel,
    "pose": PoseInFrameChannel,
    "tf": FrameTransformsChannel,
}


# s between two log lines about one client channel's refused messages
REFUSAL_LOG_PERIOD = 5.0
# the WebSocket protocol's log time is an unsigned 64-bit count of ns: a stamp outside it (a
# header before 1970, a sample time of 1e30 s) made the SDK raise, and the node die
LOG_TIME_MAX = 2**64 - 1


class CannotServe(RuntimeError):
    """The server cannot listen where the parameters say; the message names the parameter."""


class PortTaken(CannotServe):
    pass


def json_ready(value):
    """`value` with every float that is not finite as None: json.dumps (the SDK's
    Channel.log) writes NaN and Infinity, which are not JSON, and a client's parser then
    drops the whole message (a force sample, the teleop status) rather than the one number."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_ready(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_ready(v) for v in value]
    return value


def log_time_ns(log_time: int | None) -> int | None:
    return None if log_time is None else min(max(int(log_time), 0), LOG_TIME_MAX)


def check_host(host: str, parameter: str = "host") -> None:
    """CannotServe naming `parameter` when no socket can listen on `host` (not an address,
    or not one of this machine's): the SDK's error for it read as a taken port."""
    try:
        found = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (OSError, UnicodeError) as exc:
        raise CannotServe(
            f"parameter {parameter}={host!r}: not an address ({exc}); 127.0.0.1: this machine "
            "only, 0.0.0.0: every network it is on"
        ) from exc
    reasons = []
    for family, kind, proto, _, address in found:
        try:
            with socket.socket(family, kind, proto) as probe:
                probe.bind(address)
                return
        except OSError as exc:
            reasons.append(str(exc))
    raise CannotServe(
        f"parameter {parameter}={host!r}: not an address of this machine "
        f"({'; '.join(reasons)}); 127.0.0.1: this machine only, 0.0.0.0: every network it is on"
    )


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
        # (client id, channel id) -> (when its last refusal was logged, refusals not logged)
        self.refusals: dict[tuple[int, int], tuple[float, int]] = {}

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        with self.lock:
            self.subscribers.setdefault(client.id, set()).add(channel.topic)
            self.new_subscriptions.add(channel.topic)

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        with self.lock:
            topics = self.subscribers.get(client.id, set())
            topics.discard(channel.topic)
            if not topics:  # the SDK unsubscribes a client that leaves: forget it
                self.subscribers.pop(client.id, None)

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
            self.refusals.pop((client.id, client_channel_id), None)

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
        try:
            self.on_twist(twist)
        except Exception as exc:  # noqa: BLE001 - the SDK would print it without the client
            self.log(f"client {client.id} channel {client_channel_id}: not forwarded: {exc!r}")
            return
        with self.lock:
            self.forwarded += 1

    def refuse(self, client: Client, channel_id: int, reason: str) -> None:
        """Count a refused message; log it, and then at most every REFUSAL_LOG_PERIOD per
        client channel with how many since: a panel held down sends 20 a second."""
        now = time.monotonic()
        with self.lock:
            self.refused += 1
            logged, quiet = self.refusals.get((client.id, channel_id), (-math.inf, 0))
            if now - logged < REFUSAL_LOG_PERIOD:
                self.refusals[(client.id, channel_id)] = (logged, quiet + 1)
                return
            self.refusals[(client.id, channel_id)] = (now, 0)
        more = f" ({quiet} more refused since the last line)" if quiet else ""
        self.log(f"client {client.id} channel {channel_id}: message refused: {reason}{more}")


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
        check_host(host)
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
        host = f"[{self.host}]" if ":" in self.host else self.host  # an IPv6 address
        return f"ws://{host}:{self.port}"

    def log(self, topic: str, message, log_time: int | None = None, key: str = "") -> None:
        """Send `message` on `topic`'s channel (a dict or list as JSON, non-finite numbers
        null; `log_time` held in [0, 2^64) ns); on a KEPT channel also keep it, the newest per
        `key` (e.g. the static and the dynamic frame tree on /tf), for late subscribers."""
        log_time = log_time_ns(log_time)
        if isinstance(message, dict | list):
            message = json.dumps(json_ready(message), allow_nan=False).encode()
        if topic in KEPT:
            with self.kept_lock:
                kept = self.kept.setdefault(topic, {})
                # re-inserted, so a late client gets them in the order they were sent: updated
                # in place, an older belief about an object came after the newer one
                kept.pop(key, None)
                kept[key] = (message, log_time)
                if len(kept) > KEPT_PER_TOPIC:  # keys that grow with a session (object sets)
                    del kept[next(iter(kept))]
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
