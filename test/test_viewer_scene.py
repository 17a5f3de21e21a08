"""The live viewer without ROS: the scene's Foxglove messages against closed forms, the checks
on what a client publishes, and the WebSocket server as a headless client sees it (channels,
schemas, a Twist taken, bad ones refused, a taken port named)."""

import json
import math
import re
from pathlib import Path
from types import SimpleNamespace as NS

import numpy as np
import pytest

from afm_core.manipulation.execute import TIP_HEIGHT
from afm_viewer import scene
from afm_viewer.inputs import ActionStates, parse_twist
from afm_viewer.probe import Probe, decode
from afm_viewer.server import CHANNELS, TELEOP_TOPIC, LiveServer, PortTaken


def header(sec=100, nanosec=250, frame="afm_task"):
    return NS(stamp=NS(sec=sec, nanosec=nanosec), frame_id=frame)


def rotated(angle, major, minor):
    r = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    return r @ np.diag([major**2, minor**2]) @ r.T


def fox(message) -> dict:
    """An SDK message as the client decodes it (by the schema the server advertises)."""
    schema = message.get_schema()
    return decode(message.encode(), schema.data, schema.name)


def v(d: dict, *path, default=0.0):
    """d[path...]; protobuf leaves zeros out."""
    for key in path:
        d = d.get(key, {}) if isinstance(d, dict) else d
    return default if d == {} else d


def yaw(q):
    return 2 * math.atan2(q.get("z", 0.0), q.get("w", 0.0))


def test_ellipse_axes_are_3_sigma_along_the_covariance():
    angle, major, minor = math.radians(-35.0), 9e-9, 3e-9
    a, b, theta = scene.ellipse_axes(rotated(angle, major, minor).ravel())
    assert a == pytest.approx(2 * 3 * major, rel=1e-9)
    assert b == pytest.approx(2 * 3 * minor, rel=1e-9)
    assert math.remainder(theta - angle, math.pi) == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(ValueError, match="must be finite"):
        scene.ellipse_axes([math.nan, 0, 0, 1e-18])


def test_landmarks_replace_the_old_map_with_spheres_and_ellipses():
    cov = rotated(math.radians(20.0), 6e-9, 2e-9)
    mark = NS(
        id=4, position=NS(x=55e-6, y=54e-6, z=0.0), radius=40e-9, covariance=list(cov.ravel())
    )
    update = fox(scene.landmark_scene(NS(header=header(), landmarks=[mark])))
    (deletion,) = update["deletions"]
    assert deletion["type"] == scene.SceneEntityDeletionType.All.value
    (entity,) = update["entities"]
    assert entity["id"] == "landmark/4" and entity["frame_id"] == "afm_task"
    assert entity["timestamp"] == {"seconds": 100, "nanos": 250}
    (ball,) = entity["spheres"]
    assert v(ball, "size", "x") == pytest.approx(80e-9)
    assert v(ball, "pose", "position", "x") == 55e-6
    (disc,) = entity["cylinders"]
    assert v(disc, "size", "x") == pytest.approx(36e-9, rel=1e-9)
    assert v(disc, "size", "y") == pytest.approx(12e-9, rel=1e-9)
    assert math.remainder(yaw(disc["pose"]["orientation"]) - math.radians(20.0), math.pi) == (
        pytest.approx(0.0, abs=1e-9)
    )


def test_tip_pose_draws_its_xy_covariance():
    covariance = np.zeros((6, 6))
    covariance[:2, :2] = rotated(0.0, 10e-9, 5e-9)
    msg = NS(
        header=header(7, 5),
        pose=NS(
            pose=NS(position=NS(x=1e-6, y=2e-6, z=0.0), orientation=NS(x=0, y=0, z=0, w=1.0)),
            covariance=list(covariance.ravel()),
        ),
    )
    (entity,) = fox(scene.tip_scene(msg))["entities"]
    (disc,) = entity["cylinders"]
    assert v(disc, "size", "x") == pytest.approx(60e-9)
    assert v(disc, "size", "y") == pytest.approx(30e-9)
    pose = fox(scene.tip_pose(msg))
    assert (v(pose, "pose", "position", "x"), pose["frame_id"]) == (1e-6, "afm_task")
    assert scene.stamp_ns(msg.header) == 7_000_000_005


def test_planned_strokes_are_coloured_by_contact():
    points = [(0.0, 0.0), (1e-6, 0.0), (1e-6, 1e-6)]
    planned = NS(
        path=NS(
            header=header(),
            poses=[NS(pose=NS(position=NS(x=x, y=y))) for x, y in points],
        ),
        waypoint_role=["lift", "lift", "push"],
        covariance_xx=[4e-18] * 3,
        covariance_xy=[0.0] * 3,
        covariance_yy=[1e-18] * 3,
    )
    (entity,) = fox(scene.path_scene(planned))["entities"]
    lifted, pushed = entity["lines"]
    assert v(lifted, "color", "g") == pytest.approx(0.6) and v(pushed, "color", "g") == (
        pytest.approx(0.2)
    )
    assert [(v(p, "x"), v(p, "y")) for p in pushed["points"]] == points[1:]
    assert v(pushed, "thickness") == pytest.approx(2 * v(lifted, "thickness"))
    (disc,) = entity["cylinders"]
    assert v(disc, "size", "x") == pytest.approx(12e-9)
    assert v(disc, "size", "y") == pytest.approx(6e-9)


def test_believed_objects_carry_their_source_and_sigma():
    obj = NS(id=2, position=NS(x=3e-6, y=4e-6, z=0.0), radius=50e-9)
    array = NS(header=header(), source=1, origin="nano_hand", objects=[obj], position_sigma=[5e-9])
    (entity,) = fox(scene.objects_scene(array))["entities"]
    assert entity["id"] == "nano_hand/2"
    assert v(entity["spheres"][0], "color", "g") == pytest.approx(0.9)  # observed: green
    assert v(entity["cylinders"][0], "size", "x") == pytest.approx(30e-9)  # 2 x 3 sigma
    unknown = NS(**{**vars(array), "source": 0, "position_sigma": [math.nan]})
    (predicted,) = fox(scene.objects_scene(unknown))["entities"]
    assert "cylinders" not in predicted
    assert v(predicted["spheres"][0], "color", "g") == pytest.approx(0.55)  # predicted: orange
    assert scene.objects_json(array)["source"] == "observed"


def trace(n, rate=1000.0):
    return NS(
        header=header(10, 0),
        times=list(np.arange(n) / rate),
        lateral_torsion=list(np.linspace(0, 1e-3, n)),
        vertical_deflection=list(np.linspace(0, 2e-9, n)),
        lateral_spring_constant=2e-9,
        normal_spring_constant=0.2,
        task="push",
        object_id=3,
    )


def test_force_samples_are_forces_in_newtons_at_their_sample_times():
    samples = scene.force_samples(trace(5))
    assert len(samples) == 5
    t, last = samples[-1]
    assert t == 10_000_000_000 + 4_000_000
    assert last["lateral_force"] == pytest.approx(1e-3 * 2e-9 / TIP_HEIGHT, rel=1e-12)
    assert last["normal_force"] == pytest.approx(2e-9 * 0.2, rel=1e-12)
    assert last["timestamp"] == {"sec": 10, "nsec": 4_000_000}


def test_a_long_trace_is_thinned_evenly_keeping_both_ends():
    samples = scene.force_samples(trace(10_001), max_samples=100)
    times = [t for t, _ in samples]
    assert len(samples) == 100 and times[0] == 10_000_000_000
    assert times[-1] == 10_000_000_000 + 10_000_000_000  # 10 s: the last sample
    gaps = np.diff(times)
    assert gaps.max() - gaps.min() <= 1_000_000  # one sample period at most
    bad = NS(**{**vars(trace(5)), "lateral_torsion": [0.0]})
    with pytest.raises(ValueError, match="must have one length"):
        scene.force_samples(bad)


def test_a_twist_is_taken_only_with_finite_numbers_and_its_own_fields():
    twist = parse_twist(b'{"linear": {"x": 1e-7, "y": -2e-7}, "angular": {"z": 0}}')
    assert twist == {
        "linear": {"x": 1e-7, "y": -2e-7, "z": 0.0},
        "angular": {"x": 0.0, "y": 0.0, "z": 0.0},
    }
    for payload, words in (
        (b'{"linear": {"x": NaN}}', "linear.x=nan: must be finite"),
        (b'{"linear": {"x": Infinity}}', "must be finite"),
        (b'{"linear": {"x": "fast"}}', "linear.x='fast': must be a number"),
        (b'{"linear": {"x": true}}', "must be a number"),
        (b'{"linear": {"w": 1}}', "linear: unknown field"),
        (b'{"speed": 1}', "unknown field(s) ['speed']"),
        (b"[1, 2]", "expected a JSON object"),
        (b"\xff\xfe", "not JSON"),
        (b"{" + b" " * 5000 + b"}", "at most"),
    ):
        with pytest.raises(ValueError, match=re.escape(words)):
            parse_twist(payload)


def test_action_state_follows_the_running_goal():
    states = ActionStates()
    status = NS(
        status_list=[
            NS(goal_info=NS(goal_id=NS(uuid=[1] * 16)), status=4),
            NS(goal_info=NS(goal_id=NS(uuid=[2] * 16)), status=2),
        ]
    )
    view = states.status("push_particle", status)
    assert (view["goal_id"], view["status"]) == ("02" * 16, "executing")
    view = states.feedback("push_particle", "02" * 16, {"phase": "pushing", "step": 3})
    assert view["feedback"] == {"phase": "pushing", "step": 3}


def test_message_dict_of_a_ros_message_is_json():
    from geometry_msgs.msg import Twist

    msg = Twist()
    msg.linear.x = 1e-7
    msg.angular.z = math.nan
    data = scene.message_dict(msg)
    assert data["linear"] == {"x": 1e-7, "y": 0.0, "z": 0.0} and data["angular"]["z"] is None
    json.dumps(data)


@pytest.fixture
def served():
    twists, logs = [], []
    server = LiveServer("127.0.0.1", 0, twists.append, logs.append)
    yield server, twists, logs
    server.stop()


def test_a_headless_client_sees_every_channel_and_its_schema(served):
    server, _, _ = served
    assert server.port > 0 and server.url == f"ws://127.0.0.1:{server.port}"
    with Probe(server.url) as client:
        client.wait(lambda: len(client.channels) == len(CHANNELS), what="every channel")
        assert client.server_info["capabilities"] == ["clientPublish"]
        assert client.server_info["supportedEncodings"] == ["json"]
        names = {t: (c["encoding"], c["schemaName"]) for t, c in client.channels.items()}
        assert names["/afm/viewer/landmarks"] == ("protobuf", "foxglove.SceneUpdate")
        assert names["/afm/map/image"] == ("protobuf", "foxglove.RawImage")
        assert names["/afm/tip_pose"] == ("protobuf", "foxglove.PoseInFrame")
        assert names["/tf"] == ("protobuf", "foxglove.FrameTransforms")
        assert names["/afm/viewer/force"] == ("json", "afm.ForceSample")
        assert names[TELEOP_TOPIC] == ("json", "geometry_msgs/Twist")
        client.subscribe(["/afm/viewer/force"])
        client.wait(lambda: server.listener.subscribers, what="the subscription")
        server.log("/afm/viewer/force", {"lateral_force": 1e-9}, log_time=123_456_789)
        (got,) = client.wait(lambda: client.messages("/afm/viewer/force"), what="a message")
        assert got.log_time == 123_456_789 and json.loads(got.payload) == {"lateral_force": 1e-9}


def test_a_client_twist_is_taken_and_bad_ones_refused(served):
    server, twists, logs = served
    good = {"linear": {"x": 1e-7, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.0}}
    with Probe(server.url) as client:
        client.advertise(1, TELEOP_TOPIC, "geometry_msgs/Twist")
        client.advertise(2, "/cmd_vel", "geometry_msgs/Twist")
        client.wait(lambda: server.listener.accepted and len(logs) >= 2, what="the advertise")
        client.publish(1, json.dumps(good).encode())
        client.publish(1, b'{"linear": {"x": NaN}}')
        client.publish(2, json.dumps(good).encode())
        client.wait(lambda: server.listener.refused >= 2 and twists, what="the messages")
    assert twists == [good]
    assert any("'/cmd_vel': clients may publish only on /afm/teleop/cmd_vel" in m for m in logs)
    assert any("linear.x=nan: must be finite" in m for m in logs)


def test_a_taken_port_is_refused_naming_the_parameter(served):
    server, _, _ = served
    with pytest.raises(
        PortTaken, match=rf"parameter port={server.port} \(host .*\): cannot serve"
    ):
        LiveServer("127.0.0.1", server.port, print, print)


LAYOUT = Path(__file__).parent.parent / "afm_viewer" / "foxglove" / "afm_live.json"


def layout_topics(config: dict) -> set[str]:
    """Every topic a panel's settings name (a message path's topic is before its first '.')."""
    found = set()
    for panel in config.values():
        found |= set(panel.get("topics", {}))
        found |= {panel[k] for k in ("topic", "topicPath") if k in panel}
        found |= {panel["imageMode"]["imageTopic"]} if "imageMode" in panel else set()
        for path in panel.get("paths", []):
            found.add("/" + path["value"].lstrip("/").split(".", 1)[0])
    return found


def test_the_live_layout_shows_only_advertised_channels_and_every_panel_is_placed(served):
    server, _, _ = served
    layout = json.loads(LAYOUT.read_text())

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])

    assert sorted(leaves(layout["layout"])) == sorted(layout["configById"])
    kinds = {panel.split("!")[0] for panel in layout["configById"]}
    assert {"3D", "Image", "Plot", "Teleop", "RawMessages"} <= kinds
    with Probe(server.url) as client:
        client.wait(lambda: len(client.channels) == len(CHANNELS), what="every channel")
        named = layout_topics(layout["configById"])
        assert named and named <= set(client.channels), named - set(client.channels)
    assert layout["configById"]["Teleop!drive"]["topic"] == TELEOP_TOPIC


def test_the_demo_takes_any_free_port_when_the_default_is_taken(tmp_path):
    import socket

    from afm_bringup.launcher import port_free, read_port, viewer_overrides

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        busy = taken.getsockname()[1]
        assert not port_free("127.0.0.1", busy)
        chosen = viewer_overrides(tmp_path / "p", port=busy)
    assert chosen == {"port": "0", "port_file": str(tmp_path / "p")}
    assert viewer_overrides(tmp_path / "p", port=busy)["port"] == str(busy)  # free again
    (tmp_path / "p").write_text("40123\n")
    assert read_port(tmp_path / "p", timeout=1.0) == 40123
    assert read_port(tmp_path / "missing", timeout=0.1) is None


def test_a_late_client_gets_the_newest_state_but_not_old_stream_samples(served):
    server, _, _ = served
    mark = NS(
        id=1, position=NS(x=1e-6, y=1e-6, z=0.0), radius=5e-8, covariance=[1e-18, 0, 0, 1e-18]
    )
    for sec in (1, 2):  # two maps: only the newer is kept
        server.log(
            "/afm/viewer/landmarks",
            scene.landmark_scene(NS(header=header(sec), landmarks=[mark])),
            sec,
        )
    server.log("/afm/viewer/force", {"lateral_force": 1.0}, 5)
    assert server.replay_pending() == 0  # nobody subscribed yet
    with Probe(server.url) as client:
        client.subscribe(["/afm/viewer/landmarks", "/afm/viewer/force"])
        client.wait(
            lambda: server.listener.new_subscriptions >= {"/afm/viewer/landmarks"}, what="sub"
        )
        assert server.replay_pending() == 1
        (got,) = client.wait(lambda: client.messages("/afm/viewer/landmarks"), what="the map")
        assert got.log_time == 2
        assert client.messages("/afm/viewer/force") == []


def test_the_viewer_forwards_client_twists_to_the_topic_the_teleop_node_takes():
    from afm_ros import topics
    from afm_viewer.server import TELEOP_TOPIC

    assert TELEOP_TOPIC == topics.TELEOP_CMD_VEL


def test_the_layouts_teleop_panel_publishes_faster_than_the_dead_man_stops_the_tip():
    """Foxglove's Teleop panel publishes at 1 Hz unless told: with the 0.5 s dead-man the tip
    would move half of each second. The layout's rate puts at least two commands in each
    timeout, so one lost message does not stop the tip."""
    from afm_core.manipulation.teleop import DEFAULT_COMMAND_TIMEOUT

    layout = json.loads(LAYOUT.read_text())
    (teleop,) = [v for k, v in layout["configById"].items() if k.startswith("Teleop")]
    assert teleop["topic"] == "/afm/teleop/cmd_vel"
    assert 1.0 / teleop["publishRate"] <= DEFAULT_COMMAND_TIMEOUT / 2
