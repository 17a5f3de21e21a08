"""The structure of a Gwyddion serialized object (the body of a .gwy file after "GWYP"),
checked before gwyfile parses it.

gwyfile trusts every size and count in the file: a damaged one can make it loop for ever (a
string array "of 4 billion items" with no NULs, a component whose size walks backwards), which
a fuzz test of damaged files found. This walk follows the format (Gwyddion's "GWY file format"
page: an object is its name, NUL, a 32-bit little-endian size and that many bytes of
components; a component is its name, NUL, a type character and its data) with every size and
count bounded by the bytes that are left, so it ends on any input, and raises ValueError
naming the byte where the file stops making sense.
"""

from __future__ import annotations

import struct

SCALAR_BYTES = {"b": 1, "c": 1, "i": 4, "q": 8, "d": 8}
ARRAY_ITEM_BYTES = {"C": 1, "I": 4, "Q": 8, "D": 8}
# objects nested deeper than this are not a height map (a data field is 2 deep in its
# container, its units 3)
MAX_DEPTH = 32


def check_gwy_structure(data: bytes) -> None:
    """ValueError unless `data` is exactly one well-formed serialized object."""
    end = _object(data, 0, len(data), 0)
    if end != len(data):
        raise ValueError(f"byte {end}: {len(data) - end} bytes follow the top object")


def _name(data: bytes, pos: int, limit: int) -> int:
    nul = data.find(b"\0", pos, limit)
    if nul < 0:
        raise ValueError(f"byte {pos}: a name or string without its terminating NUL")
    try:
        data[pos:nul].decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"byte {pos}: a name or string that is not UTF-8") from exc
    return nul + 1


def _count(data: bytes, pos: int, limit: int, what: str) -> int:
    if pos + 4 > limit:
        raise ValueError(f"byte {pos}: the {what} is cut off")
    return struct.unpack_from("<I", data, pos)[0]


def _object(data: bytes, pos: int, limit: int, depth: int) -> int:
    if depth > MAX_DEPTH:
        raise ValueError(f"byte {pos}: objects nested more than {MAX_DEPTH} deep")
    pos = _name(data, pos, limit)
    size = _count(data, pos, limit, "object size")
    pos += 4
    end = pos + size
    if end > limit:
        raise ValueError(
            f"byte {pos}: an object of {size} bytes where {limit - pos} are left in its container"
        )
    while pos < end:
        pos = _component(data, pos, end, depth)
    return end


def _component(data: bytes, pos: int, limit: int, depth: int) -> int:
    pos = _name(data, pos, limit)
    if pos >= limit:
        raise ValueError(f"byte {pos}: a component without its type")
    typecode = chr(data[pos])
    pos += 1
    if typecode in SCALAR_BYTES:
        end = pos + SCALAR_BYTES[typecode]
    elif typecode == "s":
        return _name(data, pos, limit)
    elif typecode == "o":
        return _object(data, pos, limit, depth + 1)
    elif typecode in ARRAY_ITEM_BYTES or typecode in "SO":
        count = _count(data, pos, limit, "array length")
        pos += 4
        if typecode in ARRAY_ITEM_BYTES:
            end = pos + count * ARRAY_ITEM_BYTES[typecode]
        else:
            if count > limit - pos:  # every item takes at least one byte
                raise ValueError(f"byte {pos}: {count} items where {limit - pos} bytes are left")
            for _ in range(count):
                pos = (
                    _name(data, pos, limit)
                    if typecode == "S"
                    else _object(data, pos, limit, depth + 1)
                )
            return pos
    else:
        raise ValueError(f"byte {pos - 1}: unknown component type {typecode!r}")
    if end > limit:
        raise ValueError(f"byte {pos}: a {typecode!r} component runs past its object")
    return end
