"""A headless Foxglove WebSocket client: what the tests and the latency bench use to watch the
viewer as the Foxglove app does (its WebSocket protocol: serverInfo, advertise, subscribe, binary
message data; a client's own advertise and message data for publishing).

Built on tornado's WebSocket client (tornado comes with dask, already pinned), run on an
asyncio loop in a thread of its own so callers stay synchronous.
"""

from __future__ import annotations

import asyncio
import json
import struct
import threading
import time
from dataclasses import dataclass

SUBPROTOCOL = "foxglove.sdk.v1"  # what the SDK's server accepts (the app asks for it too)
MESSAGE_DATA = 0x01  # binary opcode, both directions


@dataclass
class Received:
    topic: str
    log_time: int  # ns, as the server sent it
    wall: float  # time.time() when it arrived here
    payload: bytes


class Probe:
    """Connect to `url`; `channels` (by topic) fill as the server advertises them; every
    message of a subscribed topic lands in `received`."""

    def __init__(self, url: str, timeout: float = 10.0):
        self.url, self.timeout = url, timeout
        self.lock = threading.RLock()  # wait() holds it while a predicate reads messages()
        self.server_info: dict | None = None
        self.channels: dict[str, dict] = {}
        self.received: list[Received] = []
        self.texts: list[dict] = []
        self.subscriptions: dict[int, str] = {}
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.connection = self._run(self._connect())
        self.reader = asyncio.run_coroutine_threadsafe(self._read(), self.loop)

    def _run(self, coroutine):
        return asyncio.run_coroutine_threadsafe(coroutine, self.loop).result(self.timeout)

    async def _connect(self):
        from tornado.websocket import websocket_connect

        return await websocket_connect(
            self.url, subprotocols=[SUBPROTOCOL], connect_timeout=self.timeout
        )

    async def _read(self) -> None:
        while True:
            message = await self.connection.read_message()
            if message is None:
                return
            if isinstance(message, bytes):
                self._take_binary(message)
            else:
                self._take_text(json.loads(message))

    def _take_text(self, data: dict) -> None:
        with self.lock:
            self.texts.append(data)
            if data.get("op") == "serverInfo":
                self.server_info = data
            elif data.get("op") == "advertise":
                for channel in data["channels"]:
                    self.channels[channel["topic"]] = channel

    def _take_binary(self, message: bytes) -> None:
        if message[0] != MESSAGE_DATA:
            return
        subscription, log_time = struct.unpack_from("<IQ", message, 1)
        arrived = time.time()
        with self.lock:
            topic = self.subscriptions.get(subscription, "")
            self.received.append(Received(topic, log_time, arrived, message[13:]))

    # -- what a test does ------------------------------------------------------------------
    def wait(self, predicate, timeout: float | None = None, what: str = "the viewer"):
        deadline = time.monotonic() + (timeout or self.timeout)
        while time.monotonic() < deadline:
            with self.lock:
                value = predicate()
            if value:
                return value
            time.sleep(0.02)
        raise TimeoutError(f"timed out waiting for {what}")

    def subscribe(self, topics) -> None:
        """Subscribe to each of `topics` (waiting for them to be advertised)."""
        self.wait(lambda: all(t in self.channels for t in topics), what=f"channels {topics}")
        subscriptions = []
        with self.lock:
            for topic in topics:
                sub_id = len(self.subscriptions) + 1
                self.subscriptions[sub_id] = topic
                subscriptions.append({"id": sub_id, "channelId": self.channels[topic]["id"]})
        self._send_text({"op": "subscribe", "subscriptions": subscriptions})

    def advertise(self, channel_id: int, topic: str, schema_name: str, encoding: str = "json"):
        channel = {"id": channel_id, "topic": topic, "encoding": encoding}
        channel["schemaName"] = schema_name
        self._send_text({"op": "advertise", "channels": [channel]})

    def publish(self, channel_id: int, payload: bytes) -> None:
        data = struct.pack("<BI", MESSAGE_DATA, channel_id) + payload
        self._run(self._write(data, True))

    def messages(self, topic: str) -> list[Received]:
        with self.lock:
            return [r for r in self.received if r.topic == topic]

    def _send_text(self, data: dict) -> None:
        self._run(self._write(json.dumps(data), False))

    async def _write(self, data, binary: bool) -> None:
        await self.connection.write_message(data, binary=binary)

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.connection.close)
        time.sleep(0.05)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(timeout=5)

    def __enter__(self):
        return self

    def __exit__(self, *_):
        self.close()


# -- decoding what the SDK's schemas send (protobuf), by the schema the server advertises -----
# google/protobuf/descriptor.proto field numbers, all this decoder needs of it
FILE, MESSAGE_TYPE, NESTED_TYPE, FIELD = 1, 4, 3, 2
PACKAGE, NAME, NUMBER, LABEL, TYPE, TYPE_NAME = 2, 1, 3, 4, 5, 6
REPEATED, MESSAGE, DOUBLE, FLOAT, STRING, BYTES, BOOL = 3, 11, 1, 2, 9, 12, 8


def _varint(data: bytes, i: int) -> tuple[int, int]:
    shift = value = 0
    while True:
        byte = data[i]
        i += 1
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return value, i
        shift += 7


def _fields(data: bytes) -> list[tuple[int, int, object]]:
    """(field number, wire type, raw value) of one protobuf message's bytes."""
    out, i = [], 0
    while i < len(data):
        key, i = _varint(data, i)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, i = _varint(data, i)
        elif wire == 1:
            value, i = data[i : i + 8], i + 8
        elif wire == 5:
            value, i = data[i : i + 4], i + 4
        elif wire == 2:
            size, i = _varint(data, i)
            value, i = data[i : i + size], i + size
        else:
            raise ValueError(f"protobuf wire type {wire} not supported")
        out.append((number, wire, value))
    return out


def _descriptors(schema: bytes) -> dict[str, dict[int, tuple[str, int, int, str]]]:
    """A FileDescriptorSet -> {".pkg.Message": {number: (name, label, type, type name)}}."""
    messages = {}

    def take(message: bytes, prefix: str) -> None:
        parts = _fields(message)
        name = next(v.decode() for n, _, v in parts if n == NAME)
        full = f"{prefix}.{name}"
        table = messages.setdefault(full, {})
        for n, _, v in parts:
            if n == FIELD:
                f = {k: val for k, _, val in _fields(v)}
                type_name = f.get(TYPE_NAME, b"").decode()
                table[f[NUMBER]] = (f[NAME].decode(), f.get(LABEL, 1), f[TYPE], type_name)
            elif n == NESTED_TYPE:
                take(v, full)

    for n, _, file in _fields(schema):
        if n != FILE:
            continue
        parts = _fields(file)
        package = next((v.decode() for k, _, v in parts if k == PACKAGE), "")
        for k, _, v in parts:
            if k == MESSAGE_TYPE:
                take(v, f".{package}" if package else "")
    return messages


def _scalar(kind: int, wire: int, raw):
    if kind == DOUBLE:
        return struct.unpack("<d", raw)[0]
    if kind == FLOAT:
        return struct.unpack("<f", raw)[0]
    if kind == STRING:
        return raw.decode()
    if kind == BYTES:
        return bytes(raw)
    if kind == BOOL:
        return bool(raw)
    return raw if wire == 0 else int.from_bytes(raw, "little")


def decode(payload: bytes, schema: bytes, schema_name: str) -> dict:
    """A protobuf message (`schema_name`, e.g. foxglove.SceneUpdate) as a dict by field name,
    repeated fields as lists; fields not sent are absent (protobuf's defaults)."""
    types = _descriptors(schema)

    def message(data: bytes, name: str) -> dict:
        table, out = types[name], {}
        for number, wire, raw in _fields(data):
            if number not in table:
                continue
            field, label, kind, type_name = table[number]
            if kind == MESSAGE:
                values = [message(raw, type_name)]
            elif wire == 2 and kind not in (STRING, BYTES):  # packed numbers
                values = _packed(kind, raw)
            else:
                values = [_scalar(kind, wire, raw)]
            if label == REPEATED:
                out.setdefault(field, []).extend(values)
            else:
                out[field] = values[-1]
        return out

    return message(payload, "." + schema_name)


def _packed(kind: int, raw: bytes) -> list:
    if kind in (DOUBLE, FLOAT):
        code = "d" if kind == DOUBLE else "f"
        return list(struct.unpack(f"<{len(raw) // struct.calcsize(code)}{code}", raw))
    values, i = [], 0
    while i < len(raw):
        value, i = _varint(raw, i)
        values.append(value)
    return values
