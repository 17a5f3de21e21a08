"""afm_msgs: every interface imports, serializes and documents its fields."""

import re
from pathlib import Path

import pytest
from rclpy.serialization import deserialize_message, serialize_message

import afm_msgs.action as actions
import afm_msgs.msg as messages
import afm_msgs.srv as services

MSGS_DIR = Path(__file__).resolve().parents[1] / "afm_msgs"
ALL_FILES = sorted(p for sub in ("msg", "srv", "action") for p in (MSGS_DIR / sub).iterdir())


@pytest.mark.parametrize("path", ALL_FILES, ids=lambda p: p.name)
def test_interface_imports_and_round_trips(path):
    module = {"msg": messages, "srv": services, "action": actions}[path.parent.name]
    interface = getattr(module, path.stem)
    if path.parent.name == "msg":
        parts = [interface]
    elif path.parent.name == "srv":
        parts = [interface.Request, interface.Response]
    else:
        parts = [interface.Goal, interface.Result, interface.Feedback]
    for part in parts:
        instance = part()
        assert deserialize_message(serialize_message(instance), part) == instance


@pytest.mark.parametrize("path", ALL_FILES, ids=lambda p: p.name)
def test_every_numeric_field_is_documented(path):
    """A float field without a comment is a field without a unit."""
    undocumented = []
    for line in path.read_text().splitlines():
        stripped = line.strip()
        if (
            not stripped
            or stripped.startswith("#")
            or stripped == "---"
            or "=" in stripped.split("#")[0]
        ):
            continue
        if re.match(r"float(32|64)", stripped) and "#" not in stripped:
            undocumented.append(stripped)
    assert not undocumented, f"{path.name}: numeric fields without unit comments: {undocumented}"


def test_values_survive_serialization():
    from sample_messages import force_trace, landmarks, raster_scan

    for msg in (raster_scan(3), force_trace(2), landmarks(1)):
        assert deserialize_message(serialize_message(msg), type(msg)) == msg


def test_landmark_kinds_are_distinct_constants():
    kinds = {
        messages.Landmark.SPHERE,
        messages.Landmark.TUBE,
        messages.Landmark.ROD,
        messages.Landmark.PIT,
    }
    assert len(kinds) == 4
