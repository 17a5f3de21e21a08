"""The planner node: its three services against the landmarks it has heard, and bad requests."""

import numpy as np
import pytest
from conftest import wait_for
from std_msgs.msg import Header
from visualization_msgs.msg import MarkerArray

from afm_core.imaging.landmarks import Landmark
from afm_core.planning import exact_order, order_cost
from afm_core.planning.book_table_6_5 import TABLE_6_5_UM
from afm_msgs.msg import LandmarkArray
from afm_msgs.srv import PlanObservation, PlanPath, PlanSequence
from afm_ros.conversions import FRAME_TASK, landmarks_to_msg, mean_cov_to_pose
from afm_ros.qos_profiles import LATCHED

pytestmark = pytest.mark.ros


def sphere(i, x, y, radius=100e-9, sigma=5e-9):
    return Landmark(
        id=i,
        kind="sphere",
        x=x,
        y=y,
        covariance=np.diag([sigma**2, sigma**2]),
        radius=radius,
        height=2 * radius,
        length=0.0,
        orientation=0.0,
    )


def call(node, srv_type, name, request, timeout=20.0):
    client = node.create_client(srv_type, name)
    assert client.wait_for_service(timeout_sec=30.0), f"no service {name}"
    future = client.call_async(request)
    wait_for(future.done, timeout, what=f"{name} response")
    return future.result()


def start_pose(x, y, sigma):
    return mean_cov_to_pose((x, y), np.diag([sigma**2, sigma**2]), Header(frame_id=FRAME_TASK))


def test_planner_services_answer_from_the_landmarks_and_refuse_the_impossible(nodes, ros_node):
    nodes("planner")
    marks = [sphere(1, 55.0e-6, 55.0e-6), sphere(2, 55.6e-6, 55.3e-6), sphere(3, 54.6e-6, 55.7e-6)]
    publisher = ros_node.create_publisher(LandmarkArray, "/afm/landmarks", LATCHED)
    publisher.publish(landmarks_to_msg(marks, Header(frame_id=FRAME_TASK)))
    markers = []
    ros_node.create_subscription(MarkerArray, "/afm/markers", markers.append, LATCHED)

    request = PlanPath.Request(start=start_pose(54.4e-6, 54.5e-6, 10e-9))
    request.target.x, request.target.y = 55.3e-6, 55.05e-6
    response = wait_for(
        lambda: (r := call(ros_node, PlanPath, "/afm/plan_path", request)).success and r,
        30,
        what="a plan once the landmarks have arrived",
    )
    plan = response.plan
    assert plan.path.header.frame_id == FRAME_TASK and plan.waypoint_role[-1] == "task"
    assert {"observe_h", "observe_v"} <= set(plan.waypoint_role)
    assert len(plan.covariance_xx) == len(plan.path.poses) == len(plan.landmark_id)
    final_sigma = np.sqrt([plan.covariance_xx[-1], plan.covariance_yy[-1]])
    assert np.all(final_sigma < 10e-9), (
        final_sigma
    )  # localized near the target, not 10 nm at start
    assert plan.expected_cost > 0
    wait_for(
        lambda: markers and len(markers[-1].markers) == len(plan.path.poses) + 2,
        10,
        what="ellipse markers",
    )

    request.localization_spot = "up"
    response = call(ros_node, PlanPath, "/afm/plan_path", request)
    assert response.success and response.plan.landmark_id[-2] >= 1
    end_of_localization = response.plan.path.poses[-2].pose.position
    observed = [m for m in marks if m.id == response.plan.landmark_id[-2]][0]
    assert end_of_localization.y > observed.y + observed.radius  # ended above the particle
    request.localization_spot = "north"
    response = call(ros_node, PlanPath, "/afm/plan_path", request)
    assert not response.success and "localization_spot" in response.message
    request.localization_spot = ""
    request.target.x = 200e-6
    response = call(ros_node, PlanPath, "/afm/plan_path", request)
    assert not response.success and "target" in response.message and "range" in response.message

    observe = PlanObservation.Request(
        start=start_pose(54.7e-6, 55.0e-6, 20e-9), landmark_id=1, direction="h"
    )
    response = call(ros_node, PlanObservation, "/afm/plan_observation", observe)
    assert response.success and len(response.line_probability) >= 1
    assert sum(response.line_probability) == pytest.approx(1.0, abs=1e-6)
    assert response.plan.waypoint_role[:2] == ["scan_start", "scan_end"]
    observe.landmark_id = 42
    response = call(ros_node, PlanObservation, "/afm/plan_observation", observe)
    assert (
        not response.success
        and "landmark_id=42" in response.message
        and "unknown" in response.message
    )

    sequence = PlanSequence.Request(distance_matrix=[float(v) for v in TABLE_6_5_UM.ravel()])
    response = call(ros_node, PlanSequence, "/afm/plan_sequence", sequence)
    assert response.success and response.optimal and sorted(response.order) == list(range(16))
    assert response.cost == pytest.approx(order_cost(TABLE_6_5_UM, response.order))
    assert (
        response.cost == pytest.approx(exact_order(TABLE_6_5_UM).cost) and response.cost < 2.4766
    )
    sequence = PlanSequence.Request(distance_matrix=[1.0, 2.0, 3.0])
    response = call(ros_node, PlanSequence, "/afm/plan_sequence", sequence)
    assert not response.success and "n x n" in response.message
