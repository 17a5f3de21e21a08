"""The viewer node in the graph, watched by a headless Foxglove client: the live scene during a
push on the simulated instrument (the particle predicted stroke by stroke, then observed; the
forces; the tip; the plan; the map; the action's state), and a client's Twist reaching ROS
/afm/teleop/cmd_vel while a bad one does not."""

import json
import math
import time

import numpy as np
import pytest
from conftest import wait_for
from test_push_graph import map_the_sample, start_push_graph

from afm_bringup.commander import AfmCommander
from afm_bringup.launcher import read_port
from afm_viewer.probe import Probe, decode
from afm_viewer.server import CHANNELS, TELEOP_TOPIC

pytestmark = pytest.mark.ros

SCENE = [
    "/afm/map/image",
    "/afm/viewer/landmarks",
    "/afm/viewer/tip",
    "/afm/tip_pose",
    "/afm/viewer/planned_path",
    "/afm/viewer/objects",
    "/afm/objects/believed",
    "/afm/viewer/force",
    "/tf",
    "/afm/viewer/actions/push_particle",
]


def start_viewer(nodes, tmp_path):
    port_file = tmp_path / "viewer.port"
    viewer = nodes("viewer", port=0, port_file=str(port_file))
    port = read_port(port_file, timeout=60.0)
    assert port, f"the viewer wrote no port: {viewer.output()[-2000:]}"
    return f"ws://127.0.0.1:{port}"


def decoded(client, topic):
    channel = client.channels[topic]
    if channel["encoding"] == "json":
        return [json.loads(m.payload) for m in client.messages(topic)]
    import base64

    schema = base64.b64decode(channel["schema"])
    return [decode(m.payload, schema, channel["schemaName"]) for m in client.messages(topic)]


def test_a_client_twist_reaches_ros_and_a_bad_one_does_not(nodes, ros_node, tmp_path):
    from geometry_msgs.msg import Twist

    heard = []
    ros_node.create_subscription(Twist, TELEOP_TOPIC, heard.append, 10)
    with Probe(start_viewer(nodes, tmp_path), timeout=30.0) as client:
        client.wait(lambda: len(client.channels) == len(CHANNELS), what="every channel")
        client.subscribe([TELEOP_TOPIC])
        client.advertise(1, TELEOP_TOPIC, "geometry_msgs/Twist")
        good = {"linear": {"x": 2e-7, "y": -1e-7, "z": 0.0}, "angular": {"z": 0.1}}

        def sent_and_heard():
            client.publish(1, json.dumps(good).encode())
            end = time.monotonic() + 0.5
            while not heard and time.monotonic() < end:
                time.sleep(0.02)
            return heard

        # the viewer takes the client's channel a moment after the advertise: send until heard
        wait_for(sent_and_heard, 30, interval=0.0, what="the Twist on ROS")
        twist = heard[-1]
        assert (twist.linear.x, twist.linear.y, twist.angular.z) == (2e-7, -1e-7, 0.1)
        count = len(heard)
        for bad in (b'{"linear": {"x": NaN}}', b'{"linear": {"x": "1"}}', b"not json"):
            client.publish(1, bad)
        client.publish(1, json.dumps({"linear": {"x": 3e-7}}).encode())  # a marker after them
        wait_for(lambda: any(t.linear.x == 3e-7 for t in heard), 10, what="the marker")
        assert [t.linear.x for t in heard[count:] if t.linear.x != 2e-7] == [3e-7]
        # what ROS carries on the topic comes back to clients as the channel's messages
        client.wait(lambda: decoded(client, TELEOP_TOPIC), what="the echo")
        assert decoded(client, TELEOP_TOPIC)[-1]["linear"]["x"] in (2e-7, 3e-7)


@pytest.fixture
def graph(tmp_path, nodes):
    start_push_graph(tmp_path, nodes)
    return start_viewer(nodes, tmp_path)


def test_the_viewer_shows_a_push_live(graph, ros_node):
    with Probe(graph, timeout=30.0) as client, AfmCommander(server_timeout=60) as afm:
        client.wait(lambda: len(client.channels) == len(CHANNELS), what="every channel")
        client.subscribe(SCENE)
        maps, _ = map_the_sample(afm, ros_node, "pair-viewer")
        particle = min(
            maps[-1].landmarks,
            key=lambda lm: math.hypot(lm.position.x - 55e-6, lm.position.y - 55e-6),
        )
        start = np.array([particle.position.x, particle.position.y])
        goal = start + np.array([0.0, -300e-9])
        result = afm.push(goal, particle_id=particle.id, tolerance=40e-9, timeout=600)
        assert result.steps >= 3, result.message

        achieved = (result.achieved.x, result.achieved.y)

        # the rescan's observation is published as the action ends: it may arrive after it. The
        # closed loop (the default) also publishes what its local lines observe between legs:
        # the rescan's is the observed particle where the action says it is
        def rescan_observed_last():
            beliefs = [b for b in decoded(client, "/afm/objects/believed") if b["origin"]]
            if not beliefs or beliefs[-1]["source"] != "observed":
                return False
            last = beliefs[-1]["objects"][0]
            return math.hypot(last["x"] - achieved[0], last["y"] - achieved[1]) <= 1e-12

        client.wait(rescan_observed_last, what="the particle observed by the rescan")
        beliefs = [b for b in decoded(client, "/afm/objects/believed") if b["origin"]]
        sources = [b["source"] for b in beliefs]
        # predicted stroke by stroke while pushing, then observed by the rescan
        assert sources.count("predicted") >= result.steps and sources[-1] == "observed"
        predicted = [b["objects"][0] for b in beliefs if b["source"] == "predicted"]
        assert all(o["id"] == particle.id for o in predicted)
        # the prediction moves the particle towards the goal, not elsewhere
        last = np.array([predicted[-1]["x"], predicted[-1]["y"]])
        assert np.linalg.norm(last - goal) < np.linalg.norm(start - goal), (last, start, goal)
        observed = beliefs[-1]["objects"][0]
        assert (observed["x"], observed["y"]) == pytest.approx(achieved, abs=1e-12)
        scene = decoded(client, "/afm/viewer/objects")
        ids = {e["id"] for update in scene for e in update.get("entities", [])}
        assert f"nano_hand/{particle.id}" in ids
        forces = decoded(client, "/afm/viewer/force")
        assert max(abs(f.get("lateral_force", 0.0)) for f in forces) > 0  # pushing forces
        pushes = [e for u in decoded(client, "/afm/viewer/planned_path") for e in u["entities"]]
        assert pushes and any(line.get("thickness", 0) > 0 for line in pushes[-1]["lines"])
        for topic in ("/afm/map/image", "/afm/viewer/landmarks", "/afm/viewer/tip", "/tf"):
            assert client.messages(topic), topic
        image = decoded(client, "/afm/map/image")[-1]
        assert (
            image["encoding"] == "rgb8" and len(image["data"]) == image["height"] * (image["step"])
        )

        # the action's feedback reaches the viewer after its status and after the rescan's
        # observation (a fresh clone's check ran with the last 4 of 16 states still to come)
        def phases_and_end():
            states = decoded(client, "/afm/viewer/actions/push_particle")
            phases = {(s.get("feedback") or {}).get("phase") for s in states}
            ended = states and states[-1]["status"] in ("succeeded", "aborted")
            return {"localizing", "pushing", "verifying"} <= phases and ended

        client.wait(phases_and_end, what="the push's phases and its end on the action channel")
        # log times are the instrument's stamps: the force samples in order within a trace
        times = [m.log_time for m in client.messages("/afm/viewer/force")]
        assert times[0] > 1e18  # ns since the epoch (wall time at the driver's start + instrument)


def test_a_twist_from_a_foxglove_client_moves_the_simulated_tip_through_teleop(
    nodes, ros_node, tmp_path
):
    """End to end, as the Teleop panel drives it: client -> viewer -> teleop -> driver. The
    simulator's commanded tip moves along the Twist's direction, no faster than teleop's limit,
    and stops once the client stops (the dead-man)."""
    from test_teleop_ros import MAX_SPEED, TIMEOUT, Peer, take

    nodes("driver", seed=2, real_time_factor=20.0)
    nodes("teleop")
    peer = Peer(ros_node)
    wait_for(lambda: peer.truths, 30, what="the driver's ground truth")
    take(peer)
    start = peer.commanded()[-1][1]
    u = np.array([-0.8, 0.6])
    twist = {"linear": {"x": 0.5 * MAX_SPEED * u[0], "y": 0.5 * MAX_SPEED * u[1], "z": 0.0}}
    with Probe(start_viewer(nodes, tmp_path), timeout=30.0) as client:
        client.wait(lambda: len(client.channels) == len(CHANNELS), what="every channel")
        client.advertise(1, TELEOP_TOPIC, "geometry_msgs/Twist")
        # still Twists until teleop counts one: the viewer's publisher is new, and on a fresh
        # clone teleop and the viewer took 3 s (DDS's next announcement) to discover each
        # other, so a timed drive sent before that moved nothing
        still = json.dumps({"linear": {"x": 0.0, "y": 0.0, "z": 0.0}}).encode()
        deadline = time.monotonic() + 30
        while not (peer.statuses and peer.statuses[-1].get("commands", 0) > 0):
            assert time.monotonic() < deadline, "teleop heard no Twist from the viewer in 30 s"
            client.publish(1, still)
            time.sleep(0.05)
        first = time.monotonic()
        while time.monotonic() - first < 3.0:  # 20 Hz, as the panel should be set
            client.publish(1, json.dumps(twist).encode())
            time.sleep(0.05)
        last = time.monotonic()
    wait_for(lambda: time.monotonic() > last + TIMEOUT + 1.0, 5)
    end = peer.commanded()[-1][1]
    travelled = end - start
    assert np.linalg.norm(travelled) > 0, "the tip did not move"
    assert travelled / np.linalg.norm(travelled) == pytest.approx(u, abs=1e-9)
    # no faster than the Twist asked (half the limit) over the commands' span + the dead-man
    assert np.linalg.norm(travelled) <= 0.5 * MAX_SPEED * (last - first + TIMEOUT) * (1 + 1e-9)
    settled = peer.commanded()[-1][1]
    time.sleep(1.0)
    assert np.array_equal(peer.commanded()[-1][1], settled)  # stopped: no command, no motion
