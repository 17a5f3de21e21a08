"""The Foxglove layout shipped with the repository (afm_bringup/foxglove/afm_session.json):
a well-formed layout whose panels name topics the graph publishes and message fields that
exist, and that shows what a session is about."""

import json
import re
from pathlib import Path

import pytest
from geometry_msgs.msg import PoseWithCovarianceStamped
from sensor_msgs.msg import Image
from visualization_msgs.msg import MarkerArray

from afm_msgs.msg import ForceTrace
from afm_ros import topics

LAYOUT = Path(__file__).parent.parent / "afm_bringup" / "foxglove" / "afm_session.json"
TYPES = {
    topics.FORCE_TRACE: ForceTrace,
    topics.TIP_POSE: PoseWithCovarianceStamped,
    topics.MAP_IMAGE: Image,
    topics.SCAN_IMAGE: Image,
    topics.MARKERS: MarkerArray,
    topics.LANDMARK_MARKERS: MarkerArray,
}
FRAMES = {"afm_task", "afm_scanner", "afm_image"}


@pytest.fixture(scope="module")
def layout():
    return json.loads(LAYOUT.read_text())


def leaves(node):
    if isinstance(node, str):
        return [node]
    assert node["direction"] in ("row", "column"), node
    return leaves(node["first"]) + leaves(node["second"])


def message_paths(config):
    paths = [p["value"] for p in config.get("paths", [])]
    return paths + ([config["xAxisPath"]["value"]] if "xAxisPath" in config else [])


def field_exists(msg_type, fields: str) -> bool:
    """'pose.pose.position.x' or 'commanded_x' (array element selectors removed) in the type."""
    for name in re.sub(r"\[[^\]]*\]", "", fields).split("."):
        slots = msg_type.get_fields_and_field_types()
        if name not in slots:
            return False
        kind = slots[name]
        inner = re.sub(r"^sequence<(.*)>$", r"\1", kind)
        if "/" in inner:
            package, short = inner.split("/")
            module = __import__(f"{package}.msg", fromlist=[short])
            msg_type = getattr(module, short)
    return True


def test_every_panel_is_placed_once_and_configured(layout):
    placed = leaves(layout["layout"])
    assert sorted(placed) == sorted(layout["configById"]) and len(set(placed)) == len(placed)


def test_panels_name_published_topics_and_existing_fields(layout):
    published = {v for k, v in vars(topics).items() if k.isupper() and isinstance(v, str)}
    for panel, config in layout["configById"].items():
        named = list(config.get("topics", {}))
        if "imageMode" in config:
            named.append(config["imageMode"]["imageTopic"])
        for path in message_paths(config):
            topic, _, fields = path.partition(".")
            assert field_exists(TYPES[topic], fields), f"{panel}: {path} names no field"
            named.append(topic)
        assert named, f"{panel} shows nothing"
        for topic in named:
            assert topic in published and topic in topics.RECORDED_BY_DEFAULT, (panel, topic)
        if "followTf" in config:
            assert config["followTf"] in FRAMES


def test_the_layout_shows_the_session(layout):
    configs = layout["configById"].values()
    images = {c["imageMode"]["imageTopic"] for c in configs if "imageMode" in c}
    assert images == {topics.MAP_IMAGE, topics.SCAN_IMAGE}
    scene = [c for c in configs if "followTf" in c]
    assert len(scene) == 1
    assert {topics.MARKERS, topics.LANDMARK_MARKERS, topics.TIP_POSE} <= set(scene[0]["topics"])
    plotted = {p for c in configs for p in message_paths(c)}
    for needed in (
        "/afm/force_trace.vertical_deflection",  # force plots
        "/afm/force_trace.lateral_torsion",
        "/afm/force_trace.commanded_x",  # strokes
        "/afm/tip_pose.pose.pose.position.x",  # tip path
    ):
        assert needed in plotted, needed
