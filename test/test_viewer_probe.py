"""The viewer as a lab user meets it, with inputs the other tests never send: a landmark map or
tip estimate whose covariance is not finite, a force trace with a sample at an infinite or
negative time, numbers JSON has no words for, a client's Twist whose number no float holds,
clients that come and go, an address that is not this machine's, a map of thousands of
particles. The viewer shows what it can of each, says what it cannot, and keeps serving."""

import json
import math
from types import SimpleNamespace as NS

import numpy as np
import pytest
from conftest import wait_for

from afm_core.manipulation.teleop import TeleopController, TeleopSettings
from afm_core.manipulation.teleop_model import PushPredictor
from afm_core.physics.contact import ContactParams
from afm_viewer import scene
from afm_viewer.inputs import parse_twist
from afm_viewer.probe import Probe, decode
from afm_viewer.server import CHANNELS, TELEOP_TOPIC, LiveServer


def header(sec=100, nanosec=250, frame="afm_task"):
    return NS(stamp=NS(sec=sec, nanosec=nanosec), frame_id=frame)


def mark(i, covariance, x=1e-6):
    return NS(id=i, position=NS(x=x, y=1e-6, z=0.0), radius=5e-8, covariance=covariance)


def fox(message) -> dict:
    schema = message.get_schema()
    return decode(message.encode(), schema.data, schema.name)


def test_a_landmark_or_tip_without_a_finite_covariance_is_drawn_without_its_ellipse():
    marks = [
        mark(1, [1e-18, 0, 0, 1e-18]),
        mark(2, [math.nan, 0, 0, 1e-18]),
        mark(3, [math.inf] * 4),
    ]
    update = fox(scene.landmark_scene(NS(header=header(), landmarks=marks)))
    entities = {e["id"]: e for e in update["entities"]}
    assert set(entities) == {"landmark/1", "landmark/2", "landmark/3"}  # every sphere drawn
    assert len(entities["landmark/1"]["cylinders"]) == 1
    assert "cylinders" not in entities["landmark/2"] and "cylinders" not in entities["landmark/3"]
    covariance = np.full(36, math.nan)
    tip = NS(
        header=header(),
        pose=NS(
            pose=NS(position=NS(x=1e-6, y=2e-6, z=0.0), orientation=NS(x=0, y=0, z=0, w=1.0)),
            covariance=list(covariance),
        ),
    )
    (entity,) = fox(scene.tip_scene(tip))["entities"]
    assert len(entity["spheres"]) == 1 and "cylinders" not in entity


def test_a_degenerate_covariance_draws_a_flat_or_empty_ellipse():
    assert scene.ellipse_axes([0.0, 0.0, 0.0, 0.0])[:2] == (0.0, 0.0)
    major, minor, _ = scene.ellipse_axes([1e-18, 1e-18, 1e-18, 1e-18])  # a line
    assert major == pytest.approx(6 * math.sqrt(2e-18)) and minor == pytest.approx(0.0, abs=1e-15)


def test_an_empty_map_clears_the_old_one_and_thousands_of_particles_are_drawn():
    empty = fox(scene.landmark_scene(NS(header=header(), landmarks=[])))
    assert len(empty["deletions"]) == 1 and "entities" not in empty
    many = [mark(i, [1e-18, 0, 0, 1e-18], x=i * 1e-8) for i in range(3000)]
    update = fox(scene.landmark_scene(NS(header=header(), landmarks=many)))
    assert len(update["entities"]) == 3000


def trace(times, torsion=None):
    n = len(times)
    return NS(
        header=header(10, 0),
        times=times,
        lateral_torsion=torsion if torsion is not None else [1e-3] * n,
        vertical_deflection=[2e-9] * n,
        lateral_spring_constant=2e-9,
        normal_spring_constant=0.2,
        task="push",
        object_id=3,
    )


def test_force_samples_at_times_that_are_no_times_are_left_out():
    samples = scene.force_samples(trace([0.0, math.inf, math.nan, 0.002]))
    assert [t for t, _ in samples] == [10_000_000_000, 10_002_000_000]


@pytest.fixture
def served():
    twists, logs = [], []
    server = LiveServer("127.0.0.1", 0, twists.append, logs.append)
    yield server, twists, logs
    server.stop()


def test_json_channels_carry_null_for_non_finite_numbers_and_times_before_zero(served):
    server, _, _ = served
    with Probe(server.url) as client:
        client.subscribe(["/afm/viewer/force", "/afm/teleop/status"])
        client.wait(
            lambda: [len(t) for t in server.listener.subscribers.values()] == [2], what="subs"
        )
        force = dict(scene.force_samples(trace([0.0], torsion=[math.nan]))[0][1])
        server.log("/afm/viewer/force", force, log_time=-5)  # a stamp before 1970
        server.log("/afm/teleop/status", {"gap": math.inf, "list": [1.0, -math.inf]}, 2**70)
        client.wait(lambda: len(client.received) == 2, what="both messages")
        (got,) = client.messages("/afm/viewer/force")
        assert got.log_time == 0
        assert json.loads(got.payload, parse_constant=pytest.fail)["lateral_force"] is None
        (status,) = client.messages("/afm/teleop/status")
        assert status.log_time == 2**64 - 1
        assert json.loads(status.payload, parse_constant=pytest.fail) == {
            "gap": None,
            "list": [1.0, None],
        }


def test_a_twist_whose_number_no_float_holds_or_nested_deep_is_refused_with_its_reason(served):
    for payload, words in (
        (b'{"linear": {"x": 1' + b"0" * 400 + b"}}", "linear.x=1000"),
        (b"[" * 2000 + b"]" * 2000, "nests too deep"),
    ):
        with pytest.raises(ValueError, match=words):
            parse_twist(payload)
    server, twists, logs = served
    with Probe(server.url) as client:
        client.advertise(1, TELEOP_TOPIC, "geometry_msgs/Twist")
        client.wait(lambda: server.listener.accepted, what="the advertise")
        client.publish(1, b'{"linear": {"x": 1' + b"0" * 400 + b"}}")
        client.wait(lambda: server.listener.refused, what="the refusal")
    assert twists == [] and any("must be finite" in m for m in logs)


def test_clients_that_come_and_go_leave_nothing_behind_and_get_the_state_again(served):
    server, _, _ = served
    server.log("/afm/viewer/landmarks", scene.landmark_scene(NS(header=header(), landmarks=[])))
    for _ in range(3):
        with Probe(server.url) as client:
            client.subscribe(["/afm/viewer/landmarks"])
            wait_for(lambda: server.replay_pending() or client.messages("/afm/viewer/landmarks"))
            client.wait(lambda: client.messages("/afm/viewer/landmarks"), what="the map")
        wait_for(lambda: not server.listener.subscribers, what="the client forgotten")
    assert not server.listener.accepted


def test_an_address_that_is_not_this_machines_names_the_host_parameter():
    from afm_viewer.server import CannotServe

    for host in ("256.1.1.1", "192.0.2.1"):  # not an address; TEST-NET-1, on no interface
        with pytest.raises(CannotServe, match=rf"parameter host='{host}'") as error:
            LiveServer(host, 0, print, print)
        assert "port" not in str(error.value).split("(")[0]
    ipv6 = LiveServer("::1", 0, print, print)
    try:
        assert ipv6.url == f"ws://[::1]:{ipv6.port}"
    finally:
        ipv6.stop()


def test_a_command_too_large_for_its_speed_keeps_its_direction():
    controller = TeleopController(TeleopSettings(max_speed=1e-6))
    clip = controller.command(1.7e308, -1.7e308, 0.0)  # finite, but their norm is not
    assert controller.wanted == pytest.approx([1e-6 / math.sqrt(2), -1e-6 / math.sqrt(2)])
    assert "limited to 1000 nm/s" in clip
    # a position that is no position stops the tip, said in the step, not raised
    step = controller.step(0.0, (math.nan, 1e-6))
    assert step.segment is None and "not finite: tip stopped" in step.stop
    assert not controller.wanted.any() and controller.last_command is None


class Mark:
    def __init__(self, id, radius=50e-9, covariance=None, orientation=0.0):
        self.id, self.x, self.y, self.radius, self.kind = id, 1e-6, 1e-6, radius, "sphere"
        self.covariance = np.diag([1e-16, 1e-16]) if covariance is None else covariance
        self.length, self.orientation = 0.0, orientation


def test_the_push_model_leaves_out_what_it_cannot_push_and_says_unknown_for_no_sigma():
    predictor = PushPredictor(ContactParams(tip_radius=10e-9))
    # a 1 fm sphere: the model's step is a tenth of the smallest radius, 10^8 steps for
    # this 50 nm segment (the process ran out of memory before)
    predictor.load([Mark(1, radius=1e-15), Mark(2, covariance=np.diag([math.nan, 1e-16]))])
    assert predictor.push((0.95e-6, 1e-6), (1.0e-6, 1e-6), 0.05) == []
    (kept,) = predictor.objects(only_pushed=False)
    assert kept.id == 2 and math.isnan(kept.sigma)


# -- the viewer node in ROS ------------------------------------------------------------------


@pytest.mark.ros
def test_the_viewer_node_survives_messages_it_cannot_show(nodes, ros_node, tmp_path):
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from std_msgs.msg import Header

    from afm_bringup.launcher import read_port
    from afm_msgs.msg import ForceTrace, Landmark, LandmarkArray
    from afm_ros import topics
    from afm_ros.qos_profiles import LATCHED, STREAM

    viewer = nodes("viewer", port=0, port_file=str(tmp_path / "viewer.port"))
    port = read_port(tmp_path / "viewer.port", timeout=60.0)
    assert port, f"the viewer wrote no port: {viewer.output()[-2000:]}"
    url = f"ws://127.0.0.1:{port}"
    pose_pub = ros_node.create_publisher(PoseWithCovarianceStamped, topics.TIP_POSE, 10)
    trace_pub = ros_node.create_publisher(ForceTrace, topics.FORCE_TRACE, STREAM)
    map_pub = ros_node.create_publisher(LandmarkArray, topics.LANDMARKS, LATCHED)
    with Probe(url, timeout=30.0) as client:
        client.wait(lambda: len(client.channels) == len(CHANNELS), what="every channel")
        client.subscribe(["/afm/viewer/landmarks", "/afm/viewer/tip", "/afm/viewer/force"])
        pose = PoseWithCovarianceStamped()
        pose.header = Header(frame_id="afm_task")
        pose.header.stamp.sec = 5
        pose.pose.covariance = [math.nan] * 36
        bad_trace = ForceTrace(times=[0.0, math.inf], task="push", object_id=1)
        bad_trace.lateral_torsion, bad_trace.vertical_deflection = [0.0, 1e-3], [0.0, 1e-9]
        bad_trace.header.stamp.sec = 5

        def landmarks(covariance, x):
            msg = LandmarkArray(header=Header(frame_id="afm_task"))
            msg.header.stamp.sec = 6
            msg.landmarks = [Landmark(id=1, radius=5e-8, covariance=covariance)]
            msg.landmarks[0].position.x = x
            return msg

        def sent_and_shown():
            pose_pub.publish(pose)
            trace_pub.publish(bad_trace)
            map_pub.publish(landmarks([math.nan, 0.0, 0.0, 1e-18], 1e-6))
            return client.messages("/afm/viewer/tip") and client.messages("/afm/viewer/landmarks")

        wait_for(sent_and_shown, 30, interval=0.5, what="the tip and the map shown")
        map_pub.publish(landmarks([1e-18, 0.0, 0.0, 1e-18], 2e-6))  # a good map after them

        def good_map_shown():
            updates = [fox_json(client, m) for m in client.messages("/afm/viewer/landmarks")]
            return any(e.get("cylinders") for u in updates for e in u.get("entities", []))

        wait_for(good_map_shown, 30, what="the good map with its ellipse")
        assert viewer.process.poll() is None, viewer.output()[-3000:]


def fox_json(client, message):
    import base64

    channel = client.channels[message.topic]
    schema = base64.b64decode(channel["schema"])
    return decode(message.payload, schema, channel["schemaName"])


def test_force_feedback_is_finite_when_the_trace_has_glitches_and_full_when_it_is_large():
    from afm_core.manipulation.teleop import segment_wrench

    k_lat, k_n, height = 1e-9, 0.2, 10e-6
    force = segment_wrench(
        (1.0, 0.0), [math.nan, 2e-3, math.inf], [5e-8, math.nan], k_lat, k_n, height
    )
    assert force == pytest.approx([-2e-3 * k_lat / height, 0.0, 5e-8 * k_n], rel=1e-12)
    assert segment_wrench((1.0, 0.0), [math.nan], [math.nan], k_lat, k_n, height).tolist() == [
        0.0,
        0.0,
        0.0,
    ]
    assert segment_wrench((math.nan, 0.0), [2e-3], [5e-8], k_lat, k_n, height).tolist() == [
        0.0,
        0.0,
        0.0,
    ]
    # far above any set-point the feedback is the force as measured, not clipped: the
    # operator must feel it (a haptic device saturates at its own limit)
    huge = segment_wrench((0.0, 2.0), [1.0], [1e-5], k_lat, k_n, height)
    assert huge == pytest.approx([0.0, -1.0 * k_lat / height, 1e-5 * k_n], rel=1e-12)


def test_a_message_the_viewer_cannot_show_is_logged_by_topic_not_raised():
    from afm_viewer.viewer_node import ViewerNode

    said = []
    logger = NS(error=said.append)
    node = NS(get_logger=lambda: logger)

    def cannot(msg):
        raise RuntimeError(f"no scene of {msg}")

    call = ViewerNode.guarded(node, "/afm/landmarks", cannot)
    for k in range(3):  # a latched bad map, then the same at 20 Hz: one line, not three
        call(k)
    assert said == ["/afm/landmarks: message not shown (1 so far): RuntimeError('no scene of 0')"]


def test_a_late_client_gets_the_kept_beliefs_in_the_order_they_were_sent(served, monkeypatch):
    from afm_viewer import server as server_module

    server, _, _ = served
    topic = "/afm/objects/believed"
    server.log(topic, {"belief": "3 at A"}, 1, key="teleop/3")
    server.log(topic, {"belief": "3 at B, 5"}, 2, key="teleop/3,5")
    server.log(topic, {"belief": "3 at C"}, 3, key="teleop/3")  # after a new map: newest
    monkeypatch.setattr(server_module, "KEPT_PER_TOPIC", 2)
    server.log(topic, {"belief": "8"}, 4, key="teleop/8")  # the oldest key goes
    with Probe(server.url) as client:
        client.subscribe([topic])
        client.wait(lambda: server.listener.new_subscriptions, what="the subscription")
        assert server.replay_pending() == 2
        client.wait(lambda: len(client.messages(topic)) == 2, what="the replay")
        beliefs = [json.loads(m.payload)["belief"] for m in client.messages(topic)]
    assert beliefs == ["3 at C", "8"]


def test_a_client_sending_bad_twists_at_the_panel_rate_does_not_flood_the_log(served):
    server, twists, logs = served
    with Probe(server.url) as client:
        client.advertise(1, TELEOP_TOPIC, "geometry_msgs/Twist")
        client.wait(lambda: server.listener.accepted, what="the advertise")
        for _ in range(100):
            client.publish(1, b'{"linear": {"x": NaN}}')
        client.wait(lambda: server.listener.refused == 100, what="the refusals")
    (refusal,) = [m for m in logs if "message refused" in m]
    assert refusal.endswith("channel 1: message refused: linear.x=nan: must be finite")
    assert twists == []
