"""Full `ros2msg` schema text for a message type, assembled the way rosbag2 does it.

rosbag2 (and so Foxglove and `ros2 bag play`) expect a schema to be the type's own .msg
text followed by the text of every type it depends on, each once, depth first, each after
a line of 80 '=' and a `MSG: pkg/Type` line. The .msg files come from the ament index
(`<prefix>/share/<pkg>/msg/<Type>.msg` for every prefix on AMENT_PREFIX_PATH).
"""

from __future__ import annotations

import os
import re
from functools import cache
from pathlib import Path

PRIMITIVE_TYPES = frozenset(
    {
        "bool",
        "byte",
        "char",
        "float32",
        "float64",
        "int8",
        "uint8",
        "int16",
        "uint16",
        "int32",
        "uint32",
        "int64",
        "uint64",
        "string",
        "wstring",
    }
)
# A field line starts with its type, e.g. "geometry_msgs/Point[] goals" or "float64[4] c".
FIELD_TYPE = re.compile(r"^\s*([A-Za-z][A-Za-z0-9_/]*)(?:\[[^\]]*\])?(?:<=\d+)?\s+", re.MULTILINE)
SEPARATOR = "=" * 80


class DefinitionNotFound(LookupError):
    """No .msg file for a type on any ament prefix (e.g. action-internal types)."""


def ament_prefixes() -> tuple[str, ...]:
    return tuple(p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p)


def split_type_name(type_name: str) -> tuple[str, str]:
    """'pkg/msg/Type' or 'pkg/Type' -> ('pkg', 'Type')."""
    parts = type_name.split("/")
    if len(parts) == 3 and parts[1] == "msg":
        return parts[0], parts[2]
    if len(parts) == 2:
        return parts[0], parts[1]
    raise DefinitionNotFound(
        f"type name {type_name!r} is not of the form 'package/msg/Type' (only message types"
        " with a .msg file can be recorded)"
    )


@cache
def _read_msg_file(package: str, type_name: str, prefixes: tuple[str, ...]) -> str:
    for prefix in prefixes:
        candidate = Path(prefix) / "share" / package / "msg" / f"{type_name}.msg"
        if candidate.is_file():
            return candidate.read_text()
    raise DefinitionNotFound(
        f"no {package}/msg/{type_name}.msg under any AMENT_PREFIX_PATH entry "
        f"({len(prefixes)} searched); is the workspace sourced?"
    )


def dependencies(msg_text: str, package: str) -> list[str]:
    """Non-primitive field types named in a .msg text, as 'pkg/Type', sorted and unique."""
    found = set()
    for match in FIELD_TYPE.finditer(msg_text):
        field_type = match.group(1)
        if field_type in PRIMITIVE_TYPES:
            continue
        if "/" not in field_type:
            field_type = f"{package}/{field_type}"
        elif field_type.count("/") == 2:
            pkg, _, name = field_type.split("/")
            field_type = f"{pkg}/{name}"
        found.add(field_type)
    return sorted(found)


def full_message_definition(type_name: str, prefixes: tuple[str, ...] | None = None) -> str:
    """The complete ros2msg schema text for `type_name` ('pkg/msg/Type')."""
    prefixes = ament_prefixes() if prefixes is None else tuple(prefixes)
    seen: set[str] = set()

    def expand(package: str, name: str, depth: int) -> str:
        if depth > 50:
            raise DefinitionNotFound(f"{type_name}: definitions nest deeper than 50 levels")
        text = _read_msg_file(package, name, prefixes)
        for dep in dependencies(text, package):
            if dep in seen:
                continue
            seen.add(dep)
            dep_pkg, dep_name = dep.split("/")
            text += f"\n{SEPARATOR}\nMSG: {dep}\n" + expand(dep_pkg, dep_name, depth + 1)
        return text

    package, name = split_type_name(type_name)
    return expand(package, name, 0)
