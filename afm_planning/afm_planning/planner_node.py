"""Planner node: landmark paths, observation lines and push sequences as services.

The algorithms are afm_core.planning (book chapter 6); this node keeps the latest landmarks
(/afm/landmarks) and tip estimate (/afm/tip_pose), answers the three planning services,
publishes every planned path on /afm/planned_path and its 3-sigma ellipses as markers on
/afm/markers (Foxglove / RViz). An impossible request gets success=false and a message
naming what is wrong; the node keeps running.
"""

from __future__ import annotations

import math
import sys
import threading

import numpy as np
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from std_msgs.msg import Header
from visualization_msgs.msg import Marker, MarkerArray

from afm_core import checks
from afm_core.instrument import ScannerLimits, check_in_range
from afm_core.localization.calibration.model import Calibration, load_calibration
from afm_core.parameters import Parameter, ParameterTable
from afm_core.planning import (
    SPOTS,
    ant_colony_order,
    best_order,
    exact_order,
    heuristic_order,
    observation_distance_matrix,
    plan_landmark_chain,
    plan_landmark_route,
    plan_observation,
)
from afm_msgs.msg import LandmarkArray, PlannedPath
from afm_msgs.srv import PlanObservation, PlanPath, PlanSequence
from afm_ros import params, topics
from afm_ros.conversions import FRAME_TASK, stamp_of
from afm_ros.instrument_clock import InstrumentClock
from afm_ros.landmark_map import NewestLandmarkMap
from afm_ros.markers import sigma_ellipse
from afm_ros.node_main import run
from afm_ros.qos_profiles import EVENTS, LATCHED

from . import request_checks as requests

PARAMETERS = ParameterTable(
    Parameter(
        "calibration_file",
        "",
        "Localization calibration YAML (afm calibrate); empty: the book's figures.",
    ),
    Parameter(
        "tip_radius",
        50e-9,
        "Tip radius R_T kept clear of a particle while observing it (book 6.1).",
        unit="m",
        minimum=0.0,
        runtime=True,
    ),
    Parameter(
        "range_x",
        110e-6,
        "Scanner x range: targets outside [0, range_x] are refused.",
        unit="m",
        minimum=0.0,
        above_minimum=True,
    ),
    Parameter("range_y", 110e-6, "Scanner y range.", unit="m", minimum=0.0, above_minimum=True),
    Parameter(
        "sequence_seed",
        0,
        "Seed of the heuristic and ant-colony sequencers (results are reproducible).",
        minimum=0,
        runtime=True,
    ),
)
SEQUENCERS = {
    "best": best_order,
    "exact": exact_order,
    "heuristic": heuristic_order,
    "aco": ant_colony_order,
}


class PlannerNode(Node):
    def __init__(self):
        super().__init__("afm_planner")
        self.config = params.declare(self, PARAMETERS)
        path = self.config["calibration_file"]
        self.calibration = load_calibration(path) if path else Calibration()
        self.noise = self.calibration.motion_noise()
        self.limits = ScannerLimits(range_x=self.config["range_x"], range_y=self.config["range_y"])
        self.lock = threading.Lock()
        self.landmarks = NewestLandmarkMap(self.get_logger())
        self.tip_pose: PoseWithCovarianceStamped | None = None
        # one group per service, so a long PlanPath does not hold a small PlanSequence (main()
        # gives the executor a thread per group)
        inputs = MutuallyExclusiveCallbackGroup()
        path_group, observation_group, sequence_group = (
            MutuallyExclusiveCallbackGroup() for _ in range(3)
        )
        self.create_subscription(
            LandmarkArray, topics.LANDMARKS, self.landmarks.take, LATCHED, callback_group=inputs
        )
        self.create_subscription(
            PoseWithCovarianceStamped, topics.TIP_POSE, self.on_tip_pose, 10, callback_group=inputs
        )
        # plans and markers are stamped on the instrument's clock, as every other message
        self.instrument_clock = InstrumentClock(self, callback_group=inputs)
        self.path_pub = self.create_publisher(PlannedPath, topics.PLANNED_PATH, EVENTS)
        self.marker_pub = self.create_publisher(MarkerArray, topics.MARKERS, LATCHED)
        self.create_service(
            PlanPath, topics.SERVICE_PLAN_PATH, self.on_plan_path, callback_group=path_group
        )
        self.create_service(
            PlanObservation,
            topics.SERVICE_PLAN_OBSERVATION,
            self.on_plan_observation,
            callback_group=observation_group,
        )
        self.create_service(
            PlanSequence,
            topics.SERVICE_PLAN_SEQUENCE,
            self.on_plan_sequence,
            callback_group=sequence_group,
        )
        self.get_logger().info(f"planning with {self.calibration.source!r} calibration")

    # -- inputs ------------------------------------------------------------------------------
    def on_tip_pose(self, msg: PoseWithCovarianceStamped) -> None:
        with self.lock:
            self.tip_pose = msg

    def stamp_now(self):
        """The instrument time for a plan: never before the map or the tip pose it used."""
        with self.lock:
            pose = self.tip_pose
        inputs = [self.landmarks.stamp, stamp_of(pose.header) if pose is not None else None]
        return self.instrument_clock.now(not_before=max((s for s in inputs if s), default=None))

    def start_estimate(self, start: PoseWithCovarianceStamped):
        """The request's start, or the localizer's latest estimate when the request leaves the
        covariance at zero (an unset pose). Refusals name the request field."""
        requests.start_frame("start", start)
        c = start.pose.covariance
        if not any(c[k] for k in (0, 1, 6, 7)):
            with self.lock:
                latest = self.tip_pose
            if latest is None:
                raise ValueError(
                    "start.pose.covariance: zero and no tip estimate has arrived on "
                    f"{topics.TIP_POSE}; give the start with its covariance"
                )
            name = f"{topics.TIP_POSE} (start.pose.covariance is 0)"
            return requests.pose_mean_cov(name, latest)
        return requests.pose_mean_cov("start", start)

    def known_landmarks(self) -> list:
        """The landmarks, waiting a moment for the first map (it reaches us late under load)."""
        return list(self.landmarks.wait().values())

    def landmark(self, landmark_id: int, field: str = "landmark_id"):
        marks = self.known_landmarks()
        for mark in marks:
            if mark.id == landmark_id:
                return mark
        raise requests.unknown_id(field, landmark_id, (m.id for m in marks))

    # -- services ----------------------------------------------------------------------------
    def on_plan_path(self, request, response):
        try:
            mean, cov = self.start_estimate(request.start)
            target = requests.point("target", request.target)
            check_in_range("target", target[0], target[1], self.limits)
            required = requests.required_sigma(request.required_sigma)
            spot = request.localization_spot
            if spot and spot not in SPOTS:
                raise ValueError(
                    f"localization_spot={spot!r}: must be one of {sorted(SPOTS)} or empty"
                )
            marks = self.known_landmarks()
            if not marks:
                raise ValueError(f"no landmark known yet (nothing on {topics.LANDMARKS})")
            chain = plan_landmark_chain(
                mean,
                cov,
                marks,
                target,
                self.config["tip_radius"],
                self.noise,
                required_sigma=required,
            )
            route = chain.route
            if spot and not chain.landmark_ids:
                raise ValueError(
                    f"localization_spot={spot!r}: the cheapest way observes no landmark "
                    "(required_sigma is met without one); leave localization_spot empty"
                )
            if spot:
                route = plan_landmark_route(
                    mean,
                    cov,
                    self.landmark(chain.landmark_ids[-1]),
                    self.config["tip_radius"],
                    self.noise,
                    task_point=target,
                    spot=spot,
                )
            response.plan = self.route_to_msg(route)
            response.success = True
            response.message = (
                f"via landmarks {list(chain.landmark_ids)}; final sigma "
                f"({route.final_sigma[0] * 1e9:.1f}, {route.final_sigma[1] * 1e9:.1f}) nm"
                + ("" if chain.meets_required else "; the required sigma is not reached")
            )
            self.publish(response.plan)
        except ValueError as exc:
            response.success, response.message = False, requests.request_names(str(exc))
        return response

    def on_plan_observation(self, request, response):
        try:
            mean, cov = self.start_estimate(request.start)
            if requests.landmark_id(request.landmark_id) >= 0:
                mark = self.landmark(request.landmark_id)
                centre, radius = (mark.x, mark.y), mark.radius
            else:
                centre = requests.point("position", request.position)
                radius = checks.positive("radius", request.radius, "m")
            direction = request.direction or "h"
            if direction not in ("h", "v"):
                raise ValueError(
                    f"direction={direction!r}: must be 'h' (lines along x), 'v' or empty"
                )
            plan = plan_observation(
                mean,
                cov,
                centre,
                radius,
                self.config["tip_radius"],
                self.noise,
                direction=direction,
            )
            header = Header(stamp=self.stamp_now(), frame_id=FRAME_TASK)
            out = PlannedPath()
            out.path.header = header
            for line in plan.lines:
                for point, covariance, role in (
                    (line.start, line.start_covariance, "scan_start"),
                    (line.end, line.end_covariance, "scan_end"),
                ):
                    self.append_waypoint(out, header, point, covariance, role, request.landmark_id)
            out.expected_cost = float(plan.expected_cost)
            response.plan = out
            response.line_probability = [float(line.probability) for line in plan.lines]
            response.success_probability = float(plan.success_probability)
            response.success = True
            response.message = (
                f"{len(plan.lines)} line(s), expected travel {plan.expected_cost * 1e9:.0f} nm"
            )
            self.publish(out)
        except ValueError as exc:
            response.success, response.message = False, requests.request_names(str(exc))
        return response

    def on_plan_sequence(self, request, response):
        try:
            method = request.method or "best"
            if method not in SEQUENCERS:
                raise ValueError(f"method={method!r}: must be one of {sorted(SEQUENCERS)}")
            requests.sequence_size(method, request)
            if request.distance_matrix:
                n = math.isqrt(len(request.distance_matrix))
                if n * n != len(request.distance_matrix):
                    raise ValueError(
                        f"distance_matrix: {len(request.distance_matrix)} values is not n x n"
                    )
                matrix = np.asarray(request.distance_matrix, float).reshape(n, n)
            elif request.landmark_ids:
                marks = [
                    self.landmark(i, f"landmark_ids[{k}]")
                    for k, i in enumerate(request.landmark_ids)
                ]
                matrix = observation_distance_matrix(
                    marks, self.config["tip_radius"], self.noise, symmetric=True
                )
            else:
                points = requests.positions(request)
                if len(points) == 0:
                    raise ValueError(
                        "landmark_ids, positions and distance_matrix are all empty: "
                        "nothing to order"
                    )
                matrix = np.hypot(*(points[:, None, :] - points[None, :, :]).transpose(2, 0, 1))
            expected = len(request.landmark_ids) or len(request.positions) or len(matrix)
            if len(matrix) != expected:
                raise ValueError(
                    f"distance_matrix is {len(matrix)} x {len(matrix)} but {expected} "
                    "particles given"
                )
            result = (
                SEQUENCERS[method](matrix, seed=self.config["sequence_seed"])
                if method != "exact"
                else exact_order(matrix)
            )
            response.order = [int(i) for i in result.order]
            response.cost = float(result.cost)
            response.optimal = bool(result.optimal)
            response.method_used = result.method
            response.success = True
            response.message = (
                f"{len(result.order)} particles, cost {result.cost * 1e6:.3f} um ({result.method})"
            )
        except ValueError as exc:
            response.success, response.message = False, str(exc)
        return response

    # -- outputs -----------------------------------------------------------------------------
    def route_to_msg(self, route) -> PlannedPath:
        header = Header(stamp=self.stamp_now(), frame_id=FRAME_TASK)
        out = PlannedPath()
        out.path.header = header
        for waypoint in route.waypoints:
            self.append_waypoint(
                out,
                header,
                waypoint.position,
                waypoint.covariance,
                waypoint.role,
                waypoint.landmark_id,
            )
        out.expected_cost = float(route.expected_cost)
        return out

    @staticmethod
    def append_waypoint(
        out: PlannedPath, header, point, covariance, role: str, landmark_id: int
    ) -> None:
        pose = PoseStamped(header=header)
        pose.pose.position.x, pose.pose.position.y = float(point[0]), float(point[1])
        pose.pose.orientation.w = 1.0
        out.path.poses.append(pose)
        out.covariance_xx.append(float(covariance[0][0]))
        out.covariance_xy.append(float(covariance[0][1]))
        out.covariance_yy.append(float(covariance[1][1]))
        out.waypoint_role.append(role)
        out.landmark_id.append(int(landmark_id))

    def publish(self, plan: PlannedPath) -> None:
        self.path_pub.publish(plan)
        self.marker_pub.publish(plan_markers(plan))


PLAN_SIGMA = (0.9, 0.0, 0.2, 0.4)  # rgba of the waypoints' 3-sigma ellipses


def plan_markers(plan: PlannedPath) -> MarkerArray:
    """The path as a line strip and each waypoint's 3-sigma ellipse as a flat cylinder."""
    header = plan.path.header
    markers = MarkerArray(markers=[Marker(header=header, ns="afm_plan", action=Marker.DELETEALL)])
    strip = Marker(header=header, ns="afm_plan", id=0, type=Marker.LINE_STRIP, action=Marker.ADD)
    strip.scale.x = 2e-9
    strip.color.g, strip.color.a = 0.8, 1.0
    strip.pose.orientation.w = 1.0
    strip.points = [pose.pose.position for pose in plan.path.poses]
    markers.markers.append(strip)
    for k, pose in enumerate(plan.path.poses):
        cov = [
            [plan.covariance_xx[k], plan.covariance_xy[k]],
            [plan.covariance_xy[k], plan.covariance_yy[k]],
        ]
        markers.markers.append(
            sigma_ellipse(header, "afm_plan_sigma", k + 1, pose.pose.position, cov, PLAN_SIGMA)
        )
    return markers


def main(args=None):
    # a thread for the inputs and one per service (each service its own callback group)
    return run(PlannerNode, "afm_planner", args, config_errors=(ValueError,), threads=4)


if __name__ == "__main__":
    sys.exit(main())
