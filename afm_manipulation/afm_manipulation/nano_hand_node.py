"""NanoHand node: push particles to goals with the virtual nano-hand (book 6.4, 7.3).

The algorithms are afm_core.manipulation (plans, the pushing model, execution on an
Instrument, verification); this node strings them together through the graph:

PushParticle: refuse what cannot work (unknown particle, goal off-range, another particle in
the way) -> punch control pits and scan the area ("before") -> localize the tip on the
particle (the localizer's Localize action) -> plan the strokes -> execute them through the
driver's actions, feedback per stroke -> rescan ("after") and verify the particle's position
against the goal with the pits (and other particles) as control points -> result. Cancel stops
after the stroke in progress, lifts the tip clear of the particle and reports where the tip and
the particle are.

Assemble: many particles to many goals, in the planner's order (/afm/plan_sequence) unless
keep_order, each pushed as above.

After every push the node publishes the landmark map with the pushed particle where the
rescan found it (/afm/landmarks, newest map by stamp wins), so the localizer and planner
know where it went.
"""

from __future__ import annotations

import math
import sys
import threading
from types import SimpleNamespace

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from std_msgs.msg import Header

from afm_core.instrument import ScannerLimits, ScanRequest, check_in_range
from afm_core.localization.calibration.model import Calibration, load_calibration
from afm_core.manipulation import (
    NanoHandParams,
    ParticleEstimate,
    centre_push_plan,
    choose_nano_hand_params,
    execute_plan,
    nano_hand_plan,
    path_blocker,
    rod_hand_plan,
    verify_push,
)
from afm_core.manipulation.execute import pushed_object_after
from afm_core.parameters import Parameter, ParameterTable
from afm_msgs.action import Assemble, Localize, PushParticle
from afm_msgs.msg import LandmarkArray, PlannedPath, TipCommand
from afm_msgs.srv import PlanSequence
from afm_ros import params, topics
from afm_ros.action_client import SafeActionClient
from afm_ros.action_instrument import ActionInstrument, DriverUnavailable, call_action
from afm_ros.conversions import (
    FRAME_TASK,
    landmarks_to_msg,
    msg_to_landmarks,
    newer_landmarks,
    pose_to_mean_cov,
    seconds_to_time,
    stamp_of,
    wait_for_landmarks,
)
from afm_ros.node_main import run
from afm_ros.qos_profiles import EVENTS, FEEDBACK, LATCHED

PARAMETERS = ParameterTable(
    Parameter(
        "calibration_file",
        "",
        "Calibration YAML (afm calibrate): its scanner matrix maps task-frame strokes to "
        "commands; empty: identity.",
    ),
    Parameter(
        "tip_radius",
        50e-9,
        "Effective contact radius of the tip (R_T; book's simulation: 50 nm).",
        unit="m",
        minimum=0.0,
        above_minimum=True,
        runtime=True,
    ),
    Parameter(
        "default_tolerance",
        20e-9,
        "Success radius around the goal when a goal's tolerance is 0.",
        unit="m",
        minimum=0.0,
        above_minimum=True,
        runtime=True,
    ),
    Parameter(
        "push_speed",
        0.5e-6,
        "Speed of the tip in contact.",
        unit="m/s",
        minimum=0.0,
        above_minimum=True,
        maximum=ScannerLimits().max_speed,
        runtime=True,
    ),
    Parameter(
        "rescan_margin",
        300e-9,
        "Margin around the particle and the goal in the before/after rescans.",
        unit="m",
        minimum=0.0,
        above_minimum=True,
        runtime=True,
    ),
    Parameter(
        "rescan_pixel",
        8e-9,
        "Pixel size of the before/after rescans.",
        unit="m",
        minimum=0.0,
        above_minimum=True,
        runtime=True,
    ),
    Parameter(
        "rescan_line_rate",
        4.0,
        "Line rate of the before/after rescans.",
        unit="Hz",
        minimum=0.0,
        above_minimum=True,
        maximum=ScannerLimits().max_line_rate,
        runtime=True,
    ),
    Parameter(
        "match_radius",
        300e-9,
        "A particle given by position is the nearest landmark within this.",
        unit="m",
        minimum=0.0,
        above_minimum=True,
        runtime=True,
    ),
    Parameter(
        "control_pits",
        2,
        "Indentation pits punched in the rescan's corners before a push: control points that "
        "tie the after image to the before image (book 7.3); 0: none.",
        minimum=0,
        maximum=4,
        runtime=True,
    ),
    Parameter(
        "pit_force",
        0.5e-6,
        "Indentation force of the control pits (a ~10 nm deep pit on the default sample).",
        unit="N",
        minimum=0.0,
        above_minimum=True,
        maximum=ScannerLimits().max_indent_force,
        runtime=True,
    ),
    Parameter(
        "localize_first",
        True,
        "Localize the tip on the particle before planning (book 7.3); false: trust the "
        "current estimate.",
        runtime=True,
    ),
    Parameter(
        "action_timeout",
        600.0,
        "Longest wait for any one driver, localizer or planner answer.",
        unit="s",
        minimum=0.0,
        above_minimum=True,
    ),
)
STRATEGIES = ("nano_hand", "center", "centre", "rod_hand")


class PushFailed(Exception):
    """A push that started could not finish; the message says what happened and where things
    are."""


class NanoHandNode(Node):
    def __init__(self):
        super().__init__("afm_nano_hand")
        self.config = params.declare(self, PARAMETERS)
        path = self.config["calibration_file"]
        self.calibration = load_calibration(path) if path else Calibration()
        self.limits = ScannerLimits()
        self.instrument = ActionInstrument(
            self,
            self.limits,
            result_timeout=self.config["action_timeout"],
            scan_pair_id="local-nano-hand",
        )
        self.busy = threading.Lock()  # one manipulation at a time
        self.state_lock = threading.Lock()
        self.landmarks: dict[int, object] = {}
        self.landmarks_stamp: float | None = None
        self.landmarks_header = Header(frame_id=FRAME_TASK)
        self.tip_pose: PoseWithCovarianceStamped | None = None
        inputs = MutuallyExclusiveCallbackGroup()
        self.create_subscription(
            LandmarkArray, topics.LANDMARKS, self.on_landmarks, LATCHED, callback_group=inputs
        )
        self.create_subscription(
            PoseWithCovarianceStamped, topics.TIP_POSE, self.on_tip_pose, 10, callback_group=inputs
        )
        self.create_subscription(
            TipCommand,
            topics.TIP_COMMAND,
            self.instrument.observe_command,
            EVENTS,
            callback_group=inputs,
        )
        self.landmark_pub = self.create_publisher(LandmarkArray, topics.LANDMARKS, LATCHED)
        self.path_pub = self.create_publisher(PlannedPath, topics.PLANNED_PATH, EVENTS)
        clients = ReentrantCallbackGroup()
        self.localize_client = SafeActionClient(
            self,
            Localize,
            topics.ACTION_LOCALIZE,
            callback_group=clients,
            feedback_sub_qos_profile=FEEDBACK,
        )
        self.sequence_client = self.create_client(
            PlanSequence, topics.SERVICE_PLAN_SEQUENCE, callback_group=clients
        )
        servers = ReentrantCallbackGroup()
        ActionServer(
            self,
            PushParticle,
            topics.ACTION_PUSH_PARTICLE,
            self.execute_push,
            callback_group=servers,
            goal_callback=self.accept,
            cancel_callback=lambda _g: CancelResponse.ACCEPT,
            feedback_pub_qos_profile=FEEDBACK,
        )
        ActionServer(
            self,
            Assemble,
            topics.ACTION_ASSEMBLE,
            self.execute_assemble,
            callback_group=servers,
            goal_callback=self.accept,
            cancel_callback=lambda _g: CancelResponse.ACCEPT,
            feedback_pub_qos_profile=FEEDBACK,
        )

    # -- inputs ------------------------------------------------------------------------------
    def on_landmarks(self, msg: LandmarkArray) -> None:
        if not newer_landmarks(msg, self.landmarks_stamp):
            return
        try:
            marks = {mark.id: mark for mark in msg_to_landmarks(msg)}
        except ValueError as exc:
            self.get_logger().error(f"landmarks ignored: {exc}")
            return
        with self.state_lock:
            self.landmarks, self.landmarks_stamp, self.landmarks_header = (
                marks,
                stamp_of(msg.header),
                msg.header,
            )

    def on_tip_pose(self, msg: PoseWithCovarianceStamped) -> None:
        with self.state_lock:
            self.tip_pose = msg

    def accept(self, _goal):
        if self.busy.locked():
            self.get_logger().warning("goal rejected: a manipulation is running (one at a time)")
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    # -- checks ------------------------------------------------------------------------------
    def particle_for(self, particle_id: int, position) -> object:
        known = wait_for_landmarks(lambda: self.landmarks)
        if particle_id >= 0:
            if particle_id not in known:
                raise ValueError(
                    f"particle_id={particle_id}: unknown "
                    f"(known ids: {sorted(known) or 'none yet'})"
                )
            return known[particle_id]
        point = np.array([position.x, position.y])
        if not np.all(np.isfinite(point)):
            raise ValueError("particle_position: must be finite (m)")
        if not known:
            raise ValueError(f"no landmark known yet (nothing on {topics.LANDMARKS})")
        nearest = min(known.values(), key=lambda m: math.hypot(m.x - point[0], m.y - point[1]))
        if math.hypot(nearest.x - point[0], nearest.y - point[1]) > self.config["match_radius"]:
            raise ValueError(
                f"particle_position: no particle within match_radius="
                f"{self.config['match_radius'] * 1e9:.0f} nm"
            )
        return nearest

    def check_goal(self, particle, goal: np.ndarray, strategy: str, tolerance: float) -> None:
        if strategy not in STRATEGIES:
            raise ValueError(
                f"strategy={strategy!r}: must be one of {list(STRATEGIES)} "
                "(arc_hand: use Assemble)"
            )
        if not np.all(np.isfinite(goal)):
            raise ValueError("goal: must be finite (m)")
        check_in_range("goal", goal[0], goal[1], self.limits)
        if not (math.isfinite(tolerance) and tolerance >= 0):
            raise ValueError(f"tolerance={tolerance}: must be finite and >= 0 (m)")
        if strategy == "rod_hand" and particle.kind not in ("tube", "rod"):
            raise ValueError(
                f"strategy='rod_hand': landmark {particle.id} is a {particle.kind}, "
                "not a tube or rod"
            )
        if strategy != "rod_hand" and particle.kind != "sphere":
            raise ValueError(
                f"strategy={strategy!r}: landmark {particle.id} is a {particle.kind}; "
                "use 'rod_hand'"
            )
        start = np.array([particle.x, particle.y])
        with self.state_lock:
            others = [m for m in self.landmarks.values() if m.id != particle.id]
        blocker = path_blocker(start, goal, particle.radius, self.config["tip_radius"], others)
        if blocker is not None:
            raise ValueError(
                f"path blocked: landmark {blocker.id} at ({blocker.x * 1e9:.0f} nm, "
                f"{blocker.y * 1e9:.0f} nm) lies in the way from particle {particle.id} to the "
                "goal"
            )

    # -- one push ----------------------------------------------------------------------------
    def execute_push(self, goal_handle) -> PushParticle.Result:
        goal, result = goal_handle.request, PushParticle.Result()
        with self.busy:
            try:
                particle = self.particle_for(goal.particle_id, goal.particle_position)
                target = np.array([goal.goal.x, goal.goal.y])
                strategy = goal.strategy or "nano_hand"
                tolerance = goal.tolerance or self.config["default_tolerance"]
                self.check_goal(particle, target, strategy, tolerance)
            except ValueError as exc:
                goal_handle.abort()
                result.success, result.message = False, f"refused: {exc}"
                return result

            def feedback(**fields):
                goal_handle.publish_feedback(PushParticle.Feedback(**fields))

            try:
                outcome = self.push(
                    particle,
                    target,
                    strategy,
                    tolerance,
                    goal,
                    feedback,
                    lambda: goal_handle.is_cancel_requested,
                )
            except (PushFailed, ValueError, DriverUnavailable) as exc:
                if goal_handle.is_cancel_requested:
                    goal_handle.canceled()
                else:
                    goal_handle.abort()
                result.success, result.message = False, str(exc)
                return result
        result.achieved.x, result.achieved.y = map(float, outcome["achieved"])
        result.error, result.steps = float(outcome["error"]), int(outcome["steps"])
        result.success = outcome["error"] <= tolerance
        result.message = outcome["message"]
        if result.success:
            goal_handle.succeed()
        else:
            goal_handle.abort()
        return result

    def push(
        self,
        particle,
        target: np.ndarray,
        strategy: str,
        tolerance: float,
        goal,
        feedback,
        should_stop,
    ) -> dict:
        """Localize, scan, plan, execute, rescan, verify one particle; returns achieved, error,
        steps and a message. PushFailed when cancelled or when a step cannot be done."""
        start_xy = np.array([particle.x, particle.y])
        # control pits and the before image first: moving the tip there after localizing would
        # spend the localization (a raster leaves the tip tens of nm from where the model says)
        feedback(
            phase="scanning",
            particle_estimate=point(start_xy),
            particle_covariance=list(particle.covariance.ravel()),
        )
        # the map is an image, in commanded scanner coordinates: the rescan is requested in them
        request = self.rescan_request(start_xy, target)
        for pit in control_pit_sites(request, start_xy, target, self.config["control_pits"]):
            self.instrument.indent(
                pit[0], pit[1], self.config["pit_force"], 0.1, should_stop=should_stop
            )
        before = self.instrument.raster_scan(request, should_stop=should_stop)
        if should_stop() or not before.complete:
            raise PushFailed("cancelled before pushing; nothing was pushed")
        pose = self.localize(particle, feedback, should_stop)
        tip_mean, tip_cov = pose_to_mean_cov(pose)
        commanded = np.array(self.instrument.commanded_position())
        to_instrument = task_to_command(
            tip_mean, commanded, np.array(self.calibration.scanner_matrix)
        )

        plan = self.plan(particle, target, strategy, tip_cov, goal)
        self.path_pub.publish(plan_to_msg(plan, tip_cov, particle.id, self.instrument.time))
        feedback(
            step=0,
            steps_total=len(plan.strokes),
            phase="pushing",
            particle_estimate=point(start_xy),
            particle_covariance=list(particle.covariance.ravel()),
            tip_pose=pose,
        )

        def on_step(report):
            estimate, _, _ = pushed_object_after(plan, report.index + 1)
            with self.state_lock:
                tip = self.tip_pose if self.tip_pose is not None else pose
            feedback(
                step=report.index + 1,
                steps_total=report.total,
                phase="pushing",
                particle_estimate=point(estimate),
                particle_covariance=list(particle.covariance.ravel()),
                tip_pose=tip,
                peak_lateral_force=float(report.peak_lateral_force),
                peak_normal_force=float(report.peak_normal_force),
            )

        execution = execute_plan(
            self.instrument,
            plan,
            speed=self.config["push_speed"],
            on_step=on_step,
            should_stop=should_stop,
            to_instrument=to_instrument,
        )
        if execution.cancelled:
            lifted = execution.lift_position
            estimate = (
                execution.predicted_particle
                if execution.predicted_particle is not None
                else start_xy
            )
            raise PushFailed(
                f"cancelled after {execution.strokes_done} of {len(plan.strokes)} strokes; "
                "tip lifted "
                f"clear to ({lifted[0] * 1e9:.1f} nm, {lifted[1] * 1e9:.1f} nm) in afm_scanner; "
                f"particle {particle.id} predicted at ({estimate[0] * 1e9:.1f} nm, "
                f"{estimate[1] * 1e9:.1f} nm) in afm_task (not verified)"
            )
        predicted = plan.predicted if plan.predicted is not None else target
        feedback(
            step=len(plan.strokes),
            steps_total=len(plan.strokes),
            phase="verifying",
            particle_estimate=point(predicted),
            particle_covariance=list(particle.covariance.ravel()),
            tip_pose=pose,
        )
        # the rescan sees the particle in scan coordinates; its position before the push in the
        # same scan ties the scan to the map (task frame), control points remove drift between
        # scans
        before_particle = nearest_particle(before, start_xy)
        map_to_scan = before_particle - start_xy
        # the particle may end far from the plan (a centre push slides it off): look for it
        # anywhere it could have gone
        reach = float(np.hypot(*(target - start_xy))) + 2 * particle.radius + 100e-9
        # a cancel is honoured until the result is sent: the strokes can be done before a cancel
        # sent on their first feedback arrives, and the rescan takes longer than all of them
        after = self.instrument.raster_scan(request, should_stop=should_stop)
        if should_stop() or not after.complete:
            raise PushFailed(
                f"cancelled while verifying, after all {len(plan.strokes)} strokes; tip lifted "
                "off the particle for the rescan, which was stopped; particle "
                f"{particle.id} predicted at ({predicted[0] * 1e9:.1f} nm, "
                f"{predicted[1] * 1e9:.1f} nm) in afm_task (not verified)"
            )
        verification = verify_push(
            self.instrument,
            request,
            target + map_to_scan,
            after=after,
            expected=predicted + map_to_scan,
            start=before_particle,
            before=before,
            particle_radius=particle.radius,
            particle_match_radius=reach,
        )
        # images are in commanded scanner coordinates: the particle's displacement between the
        # before and after images becomes a true one through the calibrated scanner matrix
        image_displacement = np.asarray(verification.achieved) - before_particle
        achieved = start_xy + np.array(self.calibration.scanner_matrix) @ image_displacement
        error = float(np.hypot(*(achieved - target)))
        self.publish_moved(particle, achieved)
        used = sum(1 for c in verification.control_points if c.used)
        return {
            "achieved": achieved,
            "error": error,
            "steps": sum(1 for s in plan.strokes if s.contact),
            "message": f"{strategy}: particle {particle.id} at ({achieved[0] * 1e9:.1f} nm, "
            f"{achieved[1] * 1e9:.1f} nm), {error * 1e9:.1f} nm from the goal "
            f"(tolerance {tolerance * 1e9:.1f} nm; {used} control point(s))",
        }

    def localize(self, particle, feedback, should_stop) -> PoseWithCovarianceStamped:
        feedback(
            phase="localizing",
            particle_estimate=point((particle.x, particle.y)),
            particle_covariance=list(particle.covariance.ravel()),
        )
        if not self.config["localize_first"]:
            with self.state_lock:
                if self.tip_pose is None:
                    raise PushFailed(
                        f"no tip estimate on {topics.TIP_POSE}; is the localizer running?"
                    )
                return self.tip_pose
        result = call_action(
            self.localize_client,
            Localize.Goal(landmark_id=int(particle.id)),
            10.0,
            self.config["action_timeout"],
            should_stop,
        )
        if should_stop():
            raise PushFailed("cancelled while localizing; nothing was pushed")
        if not result.success:
            raise PushFailed(
                f"localization on particle {particle.id} failed, nothing was pushed: "
                f"{result.message}"
            )
        return result.pose

    def plan(self, particle, target, strategy: str, tip_cov, goal):
        sigma = float(math.sqrt(max(np.max(np.diag(particle.covariance)), 0.0)))
        tip_sigma = float(math.sqrt(max(np.max(np.diag(tip_cov)), 0.0)))
        tip_radius = self.config["tip_radius"]
        estimate = ParticleEstimate(
            particle.x, particle.y, particle.radius, math.hypot(sigma, tip_sigma)
        )
        if strategy in ("center", "centre"):
            return centre_push_plan(estimate, target, tip_radius=tip_radius, limits=self.limits)
        if strategy == "rod_hand":
            rod = SimpleNamespace(
                x=particle.x,
                y=particle.y,
                angle=particle.orientation,
                length=particle.length,
                radius=particle.radius,
            )
            return rod_hand_plan(
                rod,
                (target[0], target[1], particle.orientation),
                tip_radius=tip_radius,
                limits=self.limits,
            )
        chosen = choose_nano_hand_params(sigma, particle.radius, tip_radius, tip_sigma=tip_sigma)
        push = goal.push_length or chosen.left_push
        back = goal.back_length or (
            push - goal.step_length if goal.step_length else chosen.left_back
        )
        params = NanoHandParams(
            push,
            push,
            back,
            back,
            chosen.initial_h,
            2 * goal.lateral_offset if goal.lateral_offset else chosen.h,
            push - back,
        )
        return nano_hand_plan(
            estimate,
            target,
            params,
            tip_radius=tip_radius,
            limits=self.limits,
            steps=int(goal.max_steps) or None,
        )

    def rescan_request(self, a, b) -> ScanRequest:
        margin, pixel = self.config["rescan_margin"], self.config["rescan_pixel"]
        lo, hi = np.minimum(a, b) - margin, np.maximum(a, b) + margin
        size = float(max(hi - lo))  # square, so the 0 deg scan's pixels are square
        pixels = int(min(self.limits.max_pixels, math.ceil(size / pixel)))
        request = ScanRequest(
            float(lo[0]),
            float(lo[1]),
            size,
            size,
            pixels,
            pixels,
            line_rate=self.config["rescan_line_rate"],
        )
        request.validate(self.limits)
        return request

    def publish_moved(self, particle, achieved) -> None:
        from dataclasses import replace

        with self.state_lock:
            marks = dict(self.landmarks)
            marks[particle.id] = replace(particle, x=float(achieved[0]), y=float(achieved[1]))
            self.landmarks = marks
            header = Header(
                stamp=seconds_to_time(
                    max(self.instrument.time, (self.landmarks_stamp or 0) + 1e-6)
                ),
                frame_id=FRAME_TASK,
            )
            self.landmarks_stamp = stamp_of(header)
        self.landmark_pub.publish(landmarks_to_msg(list(marks.values()), header))

    # -- many pushes -------------------------------------------------------------------------
    def execute_assemble(self, goal_handle) -> Assemble.Result:
        goal, result = goal_handle.request, Assemble.Result()
        with self.busy:
            try:
                if len(goal.particle_ids) != len(goal.goals) or not goal.particle_ids:
                    raise ValueError(
                        f"particle_ids ({len(goal.particle_ids)}) and goals ({len(goal.goals)}): "
                        "need one goal per particle, at least one"
                    )
                if len(set(goal.particle_ids)) != len(goal.particle_ids):
                    raise ValueError("particle_ids: each particle once")
                strategy = goal.strategy or "nano_hand"
                tolerance = goal.tolerance or self.config["default_tolerance"]
                targets = {
                    pid: np.array([g.x, g.y]) for pid, g in zip(goal.particle_ids, goal.goals)
                }
                particles = {pid: self.particle_for(pid, None) for pid in goal.particle_ids}
                for pid in goal.particle_ids:
                    if not (math.isfinite(targets[pid][0]) and math.isfinite(targets[pid][1])):
                        raise ValueError(f"goal of particle {pid}: must be finite (m)")
                    check_in_range(
                        f"goal of particle {pid}", targets[pid][0], targets[pid][1], self.limits
                    )
                    if strategy not in STRATEGIES:
                        raise ValueError(
                            f"strategy={strategy!r}: must be one of {list(STRATEGIES)}"
                        )
                order = (
                    list(goal.particle_ids) if goal.keep_order else self.order(goal.particle_ids)
                )
            except (ValueError, DriverUnavailable) as exc:
                goal_handle.abort()
                result.success, result.message = False, f"refused: {exc}"
                return result
            achieved: dict[int, np.ndarray] = {}
            errors: dict[int, float] = {}
            messages = []
            for index, pid in enumerate(order):

                def feedback(**fields):
                    goal_handle.publish_feedback(
                        Assemble.Feedback(
                            index=index,
                            particle_id=int(pid),
                            step=int(fields.get("step", 0)),
                            phase=fields.get("phase", ""),
                            particle_estimate=fields.get("particle_estimate", point(targets[pid])),
                        )
                    )

                try:
                    particle = self.particle_for(pid, None)  # where the last pushes left it
                    self.check_goal(particle, targets[pid], strategy, tolerance)
                    # a default goal: no per-push overrides, the planner chooses the zigzag
                    outcome = self.push(
                        particle,
                        targets[pid],
                        strategy,
                        tolerance,
                        PushParticle.Goal(),
                        feedback,
                        lambda: goal_handle.is_cancel_requested,
                    )
                except (PushFailed, ValueError, DriverUnavailable) as exc:
                    messages.append(f"particle {pid}: {exc}")
                    break
                achieved[pid], errors[pid] = outcome["achieved"], outcome["error"]
                messages.append(outcome["message"])
        result.order = [int(p) for p in order]
        for pid in goal.particle_ids:
            xy = achieved.get(pid, np.array([particles[pid].x, particles[pid].y]))
            result.achieved.append(point(xy))
            result.errors.append(float(errors.get(pid, math.nan)))
        result.success = len(achieved) == len(order) and all(
            e <= tolerance for e in errors.values()
        )
        result.message = "; ".join(messages)
        if goal_handle.is_cancel_requested:
            goal_handle.canceled()
        elif result.success:
            goal_handle.succeed()
        else:
            goal_handle.abort()
        return result

    def order(self, particle_ids) -> list[int]:
        if not self.sequence_client.wait_for_service(timeout_sec=10.0):
            raise DriverUnavailable(
                f"planner service {topics.SERVICE_PLAN_SEQUENCE} not available; is the planner "
                "running? (or set keep_order)"
            )
        future = self.sequence_client.call_async(
            PlanSequence.Request(landmark_ids=[int(i) for i in particle_ids])
        )
        done = threading.Event()
        future.add_done_callback(lambda _f: done.set())
        if not done.wait(self.config["action_timeout"]):
            raise DriverUnavailable("planner: no answer to the sequencing request")
        response = future.result()
        if not response.success:
            raise ValueError(f"planner: {response.message}")
        return [int(particle_ids[i]) for i in response.order]


def point(xy):
    from geometry_msgs.msg import Point

    return Point(x=float(xy[0]), y=float(xy[1]))


def control_pit_sites(request: ScanRequest, start, goal, count: int) -> list:
    """Up to `count` indentation sites in the rescan's corners, inset by a quarter of the
    margin, farthest from the push's way: control points the before and after images share
    (book 7.3), away from what is pushed."""
    lo = np.array([request.origin_x, request.origin_y])
    inset = 0.15 * request.size_x
    corners = [
        lo + np.array([dx, dy])
        for dx in (inset, request.size_x - inset)
        for dy in (inset, request.size_y - inset)
    ]
    axis = goal - start
    length = float(np.hypot(*axis)) or 1.0

    def clearance(p):
        t = np.clip((p - start) @ axis / length**2, 0.0, 1.0)
        return float(np.hypot(*(p - (start + t * axis))))

    return sorted(corners, key=clearance, reverse=True)[: max(0, int(count))]


def plan_to_msg(plan, tip_cov, particle_id: int, time: float) -> PlannedPath:
    """The strokes as a planned path: each stroke's start reached lifted ("lift"), its end in
    contact ("push") or lifted; the tip's covariance at the start on every waypoint."""
    from geometry_msgs.msg import PoseStamped

    header = Header(stamp=seconds_to_time(time), frame_id=FRAME_TASK)
    out = PlannedPath()
    out.path.header = header
    for stroke in plan.strokes:
        for xy, role in (
            (stroke.start, "lift"),
            (stroke.end, "push" if stroke.contact else "lift"),
        ):
            pose = PoseStamped(header=header)
            pose.pose.position.x, pose.pose.position.y = float(xy[0]), float(xy[1])
            pose.pose.orientation.w = 1.0
            out.path.poses.append(pose)
            out.covariance_xx.append(float(tip_cov[0, 0]))
            out.covariance_xy.append(float(tip_cov[0, 1]))
            out.covariance_yy.append(float(tip_cov[1, 1]))
            out.waypoint_role.append(role)
            out.landmark_id.append(int(particle_id))
    return out


def task_to_command(tip_mean, commanded, scanner_matrix):
    """Task-frame point -> scanner command, linearised about the localized tip: the command that
    moves the tip from where it is estimated by the wanted displacement."""
    inverse = np.linalg.inv(scanner_matrix)

    def to_instrument(xy):
        return commanded + inverse @ (np.asarray(xy, float) - tip_mean)

    return to_instrument


def nearest_particle(scan, near) -> np.ndarray:
    from afm_core.manipulation import find_particles

    found = find_particles(scan)
    if not found:
        raise PushFailed("before scan: no particle found; nothing was pushed")
    best = min(found, key=lambda m: math.hypot(m.x - near[0], m.y - near[1]))
    return np.array([best.x, best.y])


def main(args=None):
    return run(NanoHandNode, "afm_nano_hand", args, config_errors=(ValueError,), threads=4)


if __name__ == "__main__":
    sys.exit(main())
