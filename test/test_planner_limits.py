"""The planner on big maps and odd requests: the chain search computes only the edges that can
matter, gives the same chain as the full matrix, refuses up front what would take too long, and
names the request field in every refusal."""

import math
import time

import numpy as np
import pytest
from conftest import wait_for
from geometry_msgs.msg import Point
from scipy import integrate
from std_msgs.msg import Header
from test_planner_node import sphere as planner_node_sphere

from afm_core.localization.calibration.model import Calibration
from afm_core.localization.motion_noise import MotionNoise
from afm_core.planning import (
    MAX_ACO_POINTS,
    MAX_SEQUENCE_LANDMARKS,
    cheapest_chain,
    plan_landmark_chain,
)
from afm_core.planning import landmark_chain as chain_module
from afm_core.planning.observation_plan import _strip_mass
from afm_msgs.msg import LandmarkArray
from afm_msgs.srv import PlanObservation, PlanPath, PlanSequence
from afm_ros.conversions import FRAME_TASK, landmarks_to_msg, mean_cov_to_pose
from afm_ros.qos_profiles import LATCHED

NM, UM = 1e-9, 1e-6


def sphere(i, x, y, radius=50e-9, sigma=3.2e-9):
    """The planner node tests' sphere, smaller and better known by default."""
    return planner_node_sphere(i, x, y, radius=radius, sigma=sigma)


def grid(n, pitch=300e-9, origin=50e-6, first_id=1000):
    """The tester's map: n particles on a square grid, `pitch` apart (probe 57, p13)."""
    side = int(math.ceil(math.sqrt(n)))
    return [
        sphere(first_id + i, origin + (i % side) * pitch, origin + (i // side) * pitch)
        for i in range(n)
    ]


# -- the chain search (no ROS) ----------------------------------------------------------------
def test_strip_mass_matches_the_adaptive_integral():
    def integrand(t):
        return (
            math.exp(-0.5 * t * t)
            / math.sqrt(2 * math.pi)
            * math.erf(math.sqrt(9 - t * t) / 2**0.5)
        )

    rng = np.random.default_rng(3)
    for t1, t2 in np.sort(rng.uniform(-3.4, 3.4, (200, 2)), axis=1):
        lo, hi = max(t1, -3.0), min(t2, 3.0)
        want = integrate.quad(integrand, lo, hi, epsabs=1e-13)[0] if hi > lo else 0.0
        assert _strip_mass(t1, t2) == pytest.approx(want, abs=1e-11)


def test_chain_on_a_big_map_computes_few_edges_and_stays_cheap():
    """2000 landmarks: the full matrix has 4 million edges (minutes, gigabytes: probe 57 saw
    3.3 GB for 20000); the search needs only those near the route."""
    marks = grid(2000)
    noise = Calibration().motion_noise()
    start, cov = np.array([49e-6, 49e-6]), np.eye(2) * 1e-16
    chain = plan_landmark_chain(start, cov, marks, (52e-6, 52e-6), 50e-9, noise)
    n = len(marks)
    assert chain.weights.shape == (n + 2, n + 2)
    assert 0 < chain.edges_computed < 0.001 * n * n
    # the chain's cost is its edges' sum, each edge as the matrix gives it
    path = [0] + [1 + [m.id for m in marks].index(i) for i in chain.landmark_ids] + [n + 1]
    assert chain.cost == pytest.approx(sum(chain.weights[a, b] for a, b in zip(path, path[1:])))


@pytest.mark.parametrize("seed", range(6))
def test_chain_search_finds_the_cheapest_chain_of_the_full_matrix(seed, monkeypatch):
    """Against scipy's Dijkstra over every edge of eq. 6.12 (computed through chain.weights);
    with candidate chunks of 2 on odd seeds, so that the later chunks are used too."""
    if seed % 2:
        monkeypatch.setattr(chain_module, "CHUNK", 2)
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 12))
    span = rng.uniform(0.8, 4.0) * UM
    marks = [
        sphere(3 * k + 1, *rng.uniform(0, span, 2), radius=rng.uniform(30, 70) * NM)
        for k in range(n)
    ]
    noise = (Calibration().motion_noise(), MotionNoise.isotropic(0.1 * NM, cross_fraction=1.0))[
        seed % 2
    ]
    start, task = rng.uniform(0, span, 2), rng.uniform(0, span, 2)
    required = 20 * NM if seed % 3 == 0 else None
    chain = plan_landmark_chain(
        start, np.eye(2) * (8 * NM) ** 2, marks, task, 50e-9, noise, required_sigma=required
    )
    full = np.array([[chain.weights[i, j] for j in range(n + 2)] for i in range(n + 2)])
    _, best = cheapest_chain(full, 0, n + 1)
    assert chain.cost == pytest.approx(best, rel=1e-9)


def test_chain_search_refuses_beyond_its_edge_limit(monkeypatch):
    monkeypatch.setattr(chain_module.limits, "MAX_CHAIN_EDGES", 30)
    with pytest.raises(ValueError, match=r"landmarks: .*more than 30 observation edges"):
        plan_landmark_chain(
            (49e-6, 49e-6),
            np.eye(2) * 1e-16,
            grid(400),
            (60e-6, 60e-6),
            50e-9,
            Calibration().motion_noise(),
        )


# -- the node ---------------------------------------------------------------------------------
def start_pose(x, y, sigma, frame=FRAME_TASK):
    return mean_cov_to_pose((x, y), np.diag([sigma**2, sigma**2]), Header(frame_id=frame))


def call(node, srv_type, name, request, timeout=20.0):
    client = node.create_client(srv_type, name)
    assert client.wait_for_service(timeout_sec=30.0), f"no service {name}"
    future = client.call_async(request)
    wait_for(future.done, timeout, what=f"{name} response")
    return future.result()


def publish_map(ros_node, marks):
    publisher = ros_node.create_publisher(LandmarkArray, "/afm/landmarks", LATCHED)
    publisher.publish(landmarks_to_msg(marks, Header(frame_id=FRAME_TASK)))
    return publisher


def path_request(frame=FRAME_TASK, required=0.0, target=(52e-6, 52e-6)):
    request = PlanPath.Request(start=start_pose(49e-6, 49e-6, 10e-9, frame))
    request.target.x, request.target.y = target
    request.required_sigma = required
    return request


def planner_with_map(nodes, ros_node, marks):
    nodes("planner")
    publish_map(ros_node, marks)
    observe = PlanObservation.Request(start=start_pose(49.5e-6, 50.0e-6, 20e-9), landmark_id=1000)
    wait_for(
        lambda: call(ros_node, PlanObservation, "/afm/plan_observation", observe).success,
        30,
        what="the planner with the map",
    )
    return observe


@pytest.mark.ros
def test_planner_refuses_a_start_in_another_frame(nodes, ros_node):
    observe = planner_with_map(nodes, ros_node, grid(9))
    # an empty frame is an unset header: afm_task, as every plan
    assert call(ros_node, PlanPath, "/afm/plan_path", path_request(frame="")).success
    assert call(ros_node, PlanPath, "/afm/plan_path", path_request(frame=FRAME_TASK)).success
    for frame in ("afm_scanner", "map"):
        response = call(ros_node, PlanPath, "/afm/plan_path", path_request(frame=frame))
        assert not response.success and "start.header.frame_id" in response.message, frame
        observe.start.header.frame_id = frame
        response = call(ros_node, PlanObservation, "/afm/plan_observation", observe)
        assert not response.success and "start.header.frame_id" in response.message, frame


@pytest.mark.ros
def test_planner_refuses_a_negative_or_non_finite_required_sigma(nodes, ros_node):
    planner_with_map(nodes, ros_node, grid(9))
    assert call(ros_node, PlanPath, "/afm/plan_path", path_request(required=0.0)).success
    for sigma in (-5e-9, math.nan, math.inf):
        response = call(ros_node, PlanPath, "/afm/plan_path", path_request(required=sigma))
        assert not response.success and response.message.startswith("required_sigma="), sigma


@pytest.mark.ros
def test_planner_refusals_name_the_request_field(nodes, ros_node):
    observe = planner_with_map(nodes, ros_node, grid(9))
    request = path_request()
    request.start.pose.pose.position.x = math.nan
    response = call(ros_node, PlanPath, "/afm/plan_path", request)
    assert not response.success
    assert response.message.startswith("start.pose.pose.position.x=nan")
    observe.start.pose.pose.position.y = math.inf
    response = call(ros_node, PlanObservation, "/afm/plan_observation", observe)
    assert not response.success
    assert response.message.startswith("start.pose.pose.position.y=inf")
    observe.start = start_pose(49.5e-6, 50.0e-6, 20e-9)
    observe.landmark_id, observe.radius = -1, 50e-9
    observe.position.x, observe.position.y = math.nan, 50e-6
    response = call(ros_node, PlanObservation, "/afm/plan_observation", observe)
    assert not response.success and response.message.startswith("position.x=nan")
    for message in (response.message,):
        assert "np.float64" not in message and "particle_center" not in message


@pytest.mark.ros
def test_unknown_id_lists_a_few_known_ids(nodes, ros_node):
    marks = grid(300)
    observe = planner_with_map(nodes, ros_node, marks)
    observe.landmark_id = 5
    response = call(ros_node, PlanObservation, "/afm/plan_observation", observe)
    assert not response.success and response.message.startswith("landmark_id=5: unknown")
    assert f"and {len(marks) - 8} more" in response.message and len(response.message) < 200


@pytest.mark.ros
def test_planner_refuses_a_landmark_id_below_minus_one(nodes, ros_node):
    observe = planner_with_map(nodes, ros_node, grid(9))
    observe.landmark_id, observe.radius = -1, 50e-9
    observe.position.x, observe.position.y = 50e-6, 50e-6
    assert call(ros_node, PlanObservation, "/afm/plan_observation", observe).success
    for bad in (-2, -7):
        observe.landmark_id = bad
        response = call(ros_node, PlanObservation, "/afm/plan_observation", observe)
        assert not response.success and response.message.startswith(f"landmark_id={bad}")


@pytest.mark.ros
def test_planner_refuses_sequences_beyond_the_limits(nodes, ros_node):
    nodes("planner")
    marks = grid(MAX_SEQUENCE_LANDMARKS + 1, pitch=500e-9)
    publish_map(ros_node, marks)
    wait_for(
        lambda: (
            call(
                ros_node,
                PlanSequence,
                "/afm/plan_sequence",
                PlanSequence.Request(landmark_ids=[1000]),
            ).success
        ),
        30,
        what="the map",
    )
    request = PlanSequence.Request(landmark_ids=[m.id for m in marks])
    response = call(ros_node, PlanSequence, "/afm/plan_sequence", request)
    assert not response.success and response.message.startswith("landmark_ids:")
    assert str(MAX_SEQUENCE_LANDMARKS) in response.message
    rng = np.random.default_rng(0)
    request = PlanSequence.Request(method="aco")
    request.positions = [
        Point(x=x, y=y) for x, y in rng.uniform(0, 10e-6, (MAX_ACO_POINTS + 1, 2))
    ]
    started = time.monotonic()
    response = call(ros_node, PlanSequence, "/afm/plan_sequence", request)
    assert not response.success and response.message.startswith("positions:")
    assert str(MAX_ACO_POINTS) in response.message and time.monotonic() - started < 5
    request.positions = request.positions[:MAX_ACO_POINTS]
    request.positions[3].x = math.nan
    response = call(ros_node, PlanSequence, "/afm/plan_sequence", request)
    assert not response.success and response.message.startswith("positions[3]=(nan")


@pytest.mark.ros
def test_a_small_sequence_is_answered_while_a_long_path_is_planned(nodes, ros_node):
    """A route across a dense map of 2000 landmarks runs to the search's edge limit (seconds);
    meanwhile a two-point PlanSequence must be answered at once (its own callback group)."""
    nodes("planner")
    publish_map(ros_node, grid(2000))
    small = PlanSequence.Request()
    small.positions = [Point(x=1e-6, y=1e-6), Point(x=2e-6, y=1e-6)]
    near = path_request(target=(50e-6, 50.4e-6))
    wait_for(
        lambda: call(ros_node, PlanPath, "/afm/plan_path", near).success,
        60,
        what="the planner with the map",
    )
    path_client = ros_node.create_client(PlanPath, "/afm/plan_path")
    long_call = path_client.call_async(path_request(target=(62e-6, 62e-6)))
    time.sleep(1.0)
    assert not long_call.done(), "the long plan finished before the small request was sent"
    started = time.monotonic()
    response = call(ros_node, PlanSequence, "/afm/plan_sequence", small, timeout=5.0)
    assert response.success and sorted(response.order) == [0, 1]
    assert time.monotonic() - started < 5.0
    assert not long_call.done(), "the small request was not answered while the long one ran"
    wait_for(long_call.done, 60, what="the long plan's answer")
