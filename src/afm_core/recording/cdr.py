"""Encode a message (a dict, or an object with the fields as attributes) as ROS 2 CDR from its
full `ros2msg` schema text (`full_message_definition`), without a ROS runtime.

mcap_ros2 decodes CDR through a public API (`mcap_ros2.decoder.DecoderFactory`) but encodes
only inside its own MCAP writer; our recordings are written by `RecordingWriter` (rosbag2's
metadata, QoS, `.part` until closed), so the encoder is ours: plain XCDR1, little endian, as
rclpy serialises (4-byte encapsulation header 00 01 00 00; each primitive aligned to its size
counted from after the header; strings as uint32 length with the NUL, then the bytes and the
NUL (wstring is refused); sequences as uint32 count, then the elements; fixed arrays without
a count; a message without fields as one uint8, as rosidl gives it). A missing field is
written as its zero value. Tests compare its bytes with rclpy's serialize_message.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Callable

import numpy as np

from afm_core.recording.definitions import SEPARATOR

# primitive: (struct format, numpy dtype, size in bytes)
_PRIMITIVES = {
    "bool": ("<?", "u1", 1),
    "byte": ("<B", "u1", 1),
    "char": ("<B", "u1", 1),
    "int8": ("<b", "<i1", 1),
    "uint8": ("<B", "u1", 1),
    "int16": ("<h", "<i2", 2),
    "uint16": ("<H", "<u2", 2),
    "int32": ("<i", "<i4", 4),
    "uint32": ("<I", "<u4", 4),
    "int64": ("<q", "<i8", 8),
    "uint64": ("<Q", "<u8", 8),
    "float32": ("<f", "<f4", 4),
    "float64": ("<d", "<f8", 8),
}
_TIME = [("int32", "sec", None), ("uint32", "nanosec", None)]
_FIELD = re.compile(
    r"^\s*(?P<type>[A-Za-z][A-Za-z0-9_/]*(?:<=\d+)?)(?P<array>\[(?P<bound><=)?(?P<n>\d*)\])?"
    r"\s+(?P<name>[A-Za-z][A-Za-z0-9_]*)\s*(?P<rest>.*)$"
)


class CdrError(ValueError):
    """The schema cannot be parsed or a value does not fit its field (names both)."""


def parse_definitions(type_name: str, schema_text: str) -> dict[str, list]:
    """{'pkg/Type': [(field type, name, array length: None | -1 (sequence) | N)]} for the
    top type (under `type_name`, 'pkg/msg/Type' or 'pkg/Type') and every `MSG:` section."""
    package, _, short = _short(type_name).partition("/")
    sections = [(f"{package}/{short}", schema_text.split(SEPARATOR)[0])]
    for block in schema_text.split(SEPARATOR)[1:]:
        lines = block.strip("\n").split("\n")
        if not lines or not lines[0].startswith("MSG: "):
            raise CdrError(f"{type_name}: a schema section does not start with 'MSG: pkg/Type'")
        sections.append((_short(lines[0][5:].strip()), "\n".join(lines[1:])))
    types: dict[str, list] = {
        "builtin_interfaces/Time": _TIME,
        "builtin_interfaces/Duration": _TIME,
    }
    for name, text in sections:
        fields = []
        own_package = name.split("/")[0]
        for raw in text.split("\n"):
            line = raw.split("#", 1)[0].strip()
            if not line:
                continue
            match = _FIELD.match(line)
            if match is None:
                raise CdrError(f"{name}: cannot parse the field line {raw.strip()!r}")
            rest = match["rest"]
            if rest.startswith("=") or (rest == "" and "=" in match["name"]):
                continue  # a constant: not on the wire
            field_type = re.sub(r"<=\d+$", "", match["type"])  # bounded strings: as strings
            if field_type not in _PRIMITIVES and field_type not in ("string", "wstring"):
                field_type = _resolve(field_type, own_package)
            if match["array"] is None:
                length = None
            elif match["n"] and not match["bound"]:
                length = int(match["n"])
            else:
                length = -1  # unbounded or bounded sequence: both carry a count
            fields.append((field_type, match["name"], length))
        types[name] = fields
    return types


def encoder(type_name: str, schema_text: str) -> Callable[[object], bytes]:
    """A function message -> CDR bytes for `type_name` described by `schema_text`."""
    types = parse_definitions(type_name, schema_text)
    top = _short(type_name)
    for name, fields in types.items():
        for field_type, field, _ in fields:
            if field_type not in _PRIMITIVES and field_type not in ("string", "wstring"):
                if field_type not in types:
                    raise CdrError(f"{name}.{field}: type {field_type} is not in the schema")

    def encode(message) -> bytes:
        out = bytearray(b"\x00\x01\x00\x00")
        _write_struct(out, types, top, message, top)
        return bytes(out)

    return encode


def _short(type_name: str) -> str:
    parts = type_name.strip().split("/")
    if len(parts) == 3 and parts[1] == "msg":
        return f"{parts[0]}/{parts[2]}"
    if len(parts) == 2:
        return type_name.strip()
    raise CdrError(f"type {type_name!r}: expected 'pkg/Type' or 'pkg/msg/Type'")


def _resolve(field_type: str, own_package: str) -> str:
    if "/" in field_type:
        return _short(field_type)
    if field_type == "Header":
        return "std_msgs/Header"
    return f"{own_package}/{field_type}"


def _get(message, name: str):
    if isinstance(message, dict):
        return message.get(name)
    return getattr(message, name, None)


def _align(out: bytearray, size: int) -> None:
    out.extend(b"\x00" * ((-(len(out) - 4)) % size))


def _write_struct(out: bytearray, types: dict, name: str, message, where: str) -> None:
    fields = types[name]
    if not fields:
        out.append(0)  # rosidl's structure_needs_at_least_one_member
        return
    for field_type, field, length in fields:
        value = _get(message, field) if message is not None else None
        here = f"{where}.{field}"
        if length is None:
            _write_one(out, types, field_type, value, here)
            continue
        values = [] if value is None else value
        if length >= 0:  # fixed array: exactly `length` values, no count on the wire
            if value is None:
                values = [None] * length
            elif len(values) != length:
                raise CdrError(f"{here}: {len(values)} values, the field holds exactly {length}")
        else:
            _align(out, 4)
            out.extend(struct.pack("<I", len(values)))
        count = len(values)
        if field_type in _PRIMITIVES and count and field_type not in ("bool",):
            _, dtype, size = _PRIMITIVES[field_type]
            try:
                if isinstance(values, (bytes, bytearray, memoryview)):
                    array = np.frombuffer(values, dtype=np.uint8).astype(dtype)
                else:
                    array = np.asarray(values, dtype=dtype)
            except (TypeError, ValueError, OverflowError) as exc:
                raise CdrError(f"{here}: not {field_type} values ({exc})") from None
            if array.ndim != 1:
                raise CdrError(f"{here}: expected a flat sequence, got shape {array.shape}")
            _align(out, size)
            out.extend(array.tobytes())
            continue
        for number, item in enumerate(values):
            _write_one(out, types, field_type, item, f"{here}[{number}]")


def _write_one(out: bytearray, types: dict, field_type: str, value, where: str) -> None:
    if field_type == "wstring":
        raise CdrError(f"{where}: wstring fields are not supported")
    if field_type == "string":
        text = "" if value is None else value
        if not isinstance(text, str):
            raise CdrError(f"{where}: expected a string, got {type(value).__name__}")
        data = text.encode("utf-8")
        _align(out, 4)
        out.extend(struct.pack("<I", len(data) + 1))
        out.extend(data + b"\x00")
        return
    if field_type in _PRIMITIVES:
        fmt, _, size = _PRIMITIVES[field_type]
        _align(out, size)
        try:
            out.extend(struct.pack(fmt, 0 if value is None else value))
        except struct.error as exc:
            raise CdrError(f"{where}: {value!r} is not a {field_type} ({exc})") from None
        return
    _write_struct(out, types, field_type, value, where)
