"""The time a message is about, read from its CDR bytes without decoding it: the recordings'
log time (one time base: the instrument's clock, as the messages' header stamps are).

A message carries its stamp in one of three places this module knows from the type's schema:
its first field is a `std_msgs/Header` (whose first field is the stamp) or a
`builtin_interfaces/Time` (`rosgraph_msgs/Clock`): the stamp is the first 8 bytes after the
encapsulation header; or its first field is a sequence of messages that start with a Header
(`tf2_msgs/TFMessage`, `visualization_msgs/MarkerArray`): the first element's stamp, after the
sequence's count. Any other layout has no stamp here, and the recorder uses its clock.
"""

from __future__ import annotations

import struct

from afm_core.recording.cdr import parse_definitions

HEADER = "std_msgs/Header"
TIME = "builtin_interfaces/Time"
DIRECT = "direct"  # the stamp is the message's first field (or its Header's)
FIRST_ELEMENT = "first_element"  # the first element of the leading sequence holds it
_ENCAPSULATION = 4  # bytes before the CDR body
_LITTLE_ENDIAN = 0x01  # second encapsulation byte: CDR_LE (rclpy's), 0x00 is CDR_BE


def stamp_layout(type_name: str, schema_text: str) -> str | None:
    """DIRECT, FIRST_ELEMENT or None for a type ('pkg/msg/Type') and its full schema text.
    First fields are followed into nested messages (`afm_msgs/PlannedPath` starts with a
    `nav_msgs/Path`, which starts with a Header): a nested message's first field sits where the
    message starts, so the stamp's place is the same."""
    types = parse_definitions(type_name, schema_text)
    package, _, name = type_name.split("/")
    current, layout = f"{package}/{name}", DIRECT
    for _ in range(len(types)):  # a chain of first fields visits each type at most once
        fields = types.get(current, [])
        if not fields:
            return None
        field_type, _, length = fields[0]
        if field_type in (HEADER, TIME):
            return layout if length is None else None
        if field_type not in types:
            return None  # a primitive or a string: no stamp at the start
        if length == -1 and layout == DIRECT:
            layout = FIRST_ELEMENT  # one leading sequence: its count comes first
        elif length is not None:
            return None  # a fixed array, or a sequence inside the sequence
        current = field_type
    return None


def stamp_ns(data: bytes, layout: str | None) -> int | None:
    """The stamp in nanoseconds, or None when the layout has none, the sequence is empty, the
    stamp is zero (never set) or the bytes are too short to hold it."""
    if layout is None or len(data) < _ENCAPSULATION:
        return None
    order = "<" if data[1] == _LITTLE_ENDIAN else ">"
    offset = _ENCAPSULATION
    if layout == FIRST_ELEMENT:
        if len(data) < offset + 4 or struct.unpack_from(order + "I", data, offset)[0] == 0:
            return None
        offset += 4
    elif layout != DIRECT:
        raise ValueError(f"layout={layout!r}: expected {DIRECT!r}, {FIRST_ELEMENT!r} or None")
    if len(data) < offset + 8:
        return None
    sec, nanosec = struct.unpack_from(order + "iI", data, offset)
    stamp = sec * 1_000_000_000 + nanosec
    return stamp if stamp > 0 else None
