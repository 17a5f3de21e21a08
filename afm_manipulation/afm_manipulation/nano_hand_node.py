"""NanoHand node: push particles to goals with the virtual nano-hand (book 6.4, 7.3).

The push is afm_core.manipulation.PushProcedure (control pits and the before image, localize on
the particle, plan, execute stroke by stroke, the after image, verification); this node runs it
on the driver's actions (ActionInstrument) with the localizer's Localize action, the newest map
on /afm/landmarks and the estimate on /afm/tip_pose. PushParticle: one particle, feedback per
phase and stroke; a cancel stops after the stroke in progress, lifts the tip clear of the
particle and reports where the tip and the particle are. Assemble: many particles, in the
planner's order (/afm/plan_sequence) unless keep_order. The planned strokes go on
/afm/planned_path; after every push the map with the particle where the rescan found it goes on
/afm/landmarks, so the localizer and planner know where it went. The particle as the push
model predicts it after each stroke, and where local lines or the rescan observe it, goes on
/afm/objects/believed (ObjectArray, origin "nano_hand") for live views. When the newest map on
/afm/map is one image (an empty pair_id: not a drift-corrected 0/90 pair), its line timing goes
to the verdict, which adds the map's own drift stretch between the particle's start and its end
(afm_core.manipulation.verdict.map_stretch).
"""

from __future__ import annotations

import sys
import threading
from dataclasses import fields
from functools import partial

from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from std_msgs.msg import Header
from visualization_msgs.msg import MarkerArray

from afm_core.instrument import ScannerLimits
from afm_core.localization.calibration.model import Calibration, load_calibration
from afm_core.manipulation import (
    PUSH_PARAMETERS,
    Localization,
    Progress,
    PushFailed,
    PushProcedure,
    PushRefused,
    ZigzagOverrides,
)
from afm_core.manipulation.execute import OBSERVED
from afm_core.manipulation.verify import scan_time
from afm_core.parameters import Parameter, ParameterTable
from afm_msgs.action import Assemble, Localize, PushParticle
from afm_msgs.msg import LandmarkArray, ObjectArray, PlannedPath, RasterScan, TipCommand
from afm_msgs.srv import PlanSequence
from afm_ros import params, topics
from afm_ros.action_client import SafeActionClient
from afm_ros.action_instrument import ActionInstrument, call_action, call_service
from afm_ros.conversions import (
    FRAME_TASK,
    msg_to_raster_scan,
    outcome_to_result,
    pose_to_tip_estimate,
    progress_to_assemble_feedback,
    progress_to_push_feedback,
    push_plan_to_msg,
    seconds_to_time,
    stamp_of,
    wait_until,
)
from afm_ros.landmark_map import NewestLandmarkMap
from afm_ros.markers import landmark_markers
from afm_ros.node_main import run
from afm_ros.objects_believed import believed_objects
from afm_ros.qos_profiles import EVENTS, FEEDBACK, LATCHED

PARAMETERS = ParameterTable(
    Parameter(
        "calibration_file",
        "",
        "Calibration YAML (afm calibrate): its scanner matrix maps task-frame strokes to "
        "commands; empty: identity.",
    ),
    *PUSH_PARAMETERS,
    Parameter(
        "action_timeout",
        600.0,
        "Longest wait for any one driver, localizer or planner answer.",
        unit="s",
        minimum=0.0,
        above_minimum=True,
    ),
)

ZIGZAG_FIELDS = [f.name for f in fields(ZigzagOverrides)]  # PushParticle's fields of that name


class NanoHandNode(Node):
    def __init__(self):
        super().__init__("afm_nano_hand")
        self.config = params.declare(self, PARAMETERS, apply=self.apply_parameter)
        path = self.config["calibration_file"]
        self.instrument = ActionInstrument(
            self,
            ScannerLimits(),
            result_timeout=self.config["action_timeout"],
            scan_pair_id="local-nano-hand",
        )
        # one manipulation at a time, claimed at acceptance: two goals arriving at once were
        # both accepted, the second waiting for the first instead of being rejected
        self.claim_lock = threading.Lock()
        self.claimed = False
        self.state_lock = threading.Lock()
        self.landmarks = NewestLandmarkMap(self.get_logger())
        self.tip_pose: PoseWithCovarianceStamped | None = None
        self.single_image_map = None  # the newest /afm/map if it is one image (RasterScanData)
        self.procedure = PushProcedure(
            self.instrument,
            self.localize,
            self.landmarks.wait,
            calibration=load_calibration(path) if path else Calibration(),
            settings={name: self.config[name] for name in PUSH_PARAMETERS.names()},
            tip_estimate=self.current_tip,
            on_moved=self.on_moved,
            on_lost=self.on_lost,
            map_time=self.map_time,
        )
        inputs = MutuallyExclusiveCallbackGroup()
        for msg_type, topic, callback, qos in (
            (LandmarkArray, topics.LANDMARKS, self.landmarks.take, LATCHED),
            (RasterScan, topics.CORRECTED_MAP, self.on_map, LATCHED),
            (PoseWithCovarianceStamped, topics.TIP_POSE, self.on_tip_pose, 10),
            (TipCommand, topics.TIP_COMMAND, self.instrument.observe_command, EVENTS),
        ):
            self.create_subscription(msg_type, topic, callback, qos, callback_group=inputs)
        self.landmark_pub = self.create_publisher(LandmarkArray, topics.LANDMARKS, LATCHED)
        self.landmark_marker_pub = self.create_publisher(
            MarkerArray, topics.LANDMARK_MARKERS, LATCHED
        )
        self.path_pub = self.create_publisher(PlannedPath, topics.PLANNED_PATH, EVENTS)
        self.goal_pub = self.create_publisher(PointStamped, topics.PUSH_GOAL, EVENTS)
        self.believed_pub = self.create_publisher(ObjectArray, topics.OBJECTS_BELIEVED, EVENTS)
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
        for action, name, execute in (
            (PushParticle, topics.ACTION_PUSH_PARTICLE, self.execute_push),
            (Assemble, topics.ACTION_ASSEMBLE, self.execute_assemble),
        ):
            ActionServer(
                self,
                action,
                name,
                self.releasing(execute),
                callback_group=servers,
                goal_callback=self.accept,
                cancel_callback=lambda _g: CancelResponse.ACCEPT,
                feedback_pub_qos_profile=FEEDBACK,
            )

    def on_map(self, msg: RasterScan) -> None:
        """The map's timing, kept when it is one image: its own drift stretches it."""
        try:
            scan = None if msg.pair_id else msg_to_raster_scan(msg)
        except ValueError as exc:
            self.get_logger().error(f"map {msg.scan_id}: its timing is not used: {exc}")
            scan = None
        with self.state_lock:
            self.single_image_map = scan

    def map_time(self):
        """The procedure's map_time: the one-image map's pixel times, None for a pair's."""
        with self.state_lock:
            scan = self.single_image_map
        return None if scan is None else partial(scan_time, scan)

    def on_moved(self, moved) -> None:
        """A pushed particle where the rescan found it: the map, and the observed object."""
        time = self.instrument.time
        self.publish_landmarks(self.landmarks.moved(moved, time))
        self.believed_pub.publish(
            believed_objects(
                moved, (moved.x, moved.y), moved.covariance, OBSERVED, "nano_hand", time
            )
        )

    def on_lost(self, particle) -> None:
        """A particle whose push failed after its strokes: dropped from the map, so no later
        push or localization anchors on where it was (a failed sphere push's ghost misled the
        rod loop that came after it in 7 of 8 of the graph bench's rod misses)."""
        self.get_logger().warning(
            f"particle {particle.id} dropped from the map: its push failed after the strokes"
        )
        self.publish_landmarks(self.landmarks.dropped(particle.id, self.instrument.time))

    def publish_believed(self, p: Progress) -> None:
        """The particle as the push model predicts it after a stroke, or as lines saw it."""
        particle = self.landmarks.current().get(p.particle_id)
        if not p.belief or particle is None:
            return
        self.believed_pub.publish(
            believed_objects(
                particle, p.particle_estimate, p.belief_covariance, p.belief, "nano_hand", p.time
            )
        )

    def publish_landmarks(self, array: LandmarkArray) -> None:
        """The map with a moved landmark, and its markers for viewers."""
        self.landmark_pub.publish(array)
        self.landmark_marker_pub.publish(landmark_markers(array))

    def apply_parameter(self, name: str, value) -> None:
        """A run-time change reaches the procedure's next step that reads it."""
        if name in PUSH_PARAMETERS:
            self.procedure.settings[name] = value

    # -- inputs ------------------------------------------------------------------------------
    def on_tip_pose(self, msg: PoseWithCovarianceStamped) -> None:
        with self.state_lock:
            self.tip_pose = msg

    def current_tip(self):
        with self.state_lock:
            pose = self.tip_pose
        return None if pose is None else pose_to_tip_estimate(pose)

    def accept(self, _goal):
        with self.claim_lock:
            if self.claimed:
                self.get_logger().warning(
                    "goal rejected: a manipulation is running (one at a time)"
                )
                return GoalResponse.REJECT
            self.claimed = True
            return GoalResponse.ACCEPT

    def releasing(self, execute):
        """`execute` that gives the claim back when its goal ends, however it ends."""

        def run(goal_handle):
            try:
                return execute(goal_handle)
            finally:
                with self.claim_lock:
                    self.claimed = False

        return run

    # -- what the procedure calls ------------------------------------------------------------
    def localize(self, particle, should_stop) -> Localization:
        result = call_action(
            self.localize_client,
            Localize.Goal(landmark_id=int(particle.id)),
            10.0,
            self.config["action_timeout"],
            should_stop,
        )
        # The driver's record of the localizer's lines reaches this node on /afm/tip_command, on
        # a path of its own: the strokes are mapped from the commanded position after them, so
        # wait for it (a stale one shifts every stroke by the lines' length, and they miss).
        lines_end = stamp_of(result.pose.header) - 1e-6
        if result.success and not wait_until(lambda: self.instrument.time >= lines_end, 5.0):
            return Localization(
                False, None, f"the localizer's lines did not reach {topics.TIP_COMMAND} in 5 s"
            )
        return Localization(result.success, pose_to_tip_estimate(result.pose), result.message)

    def order(self, particle_ids) -> list[int]:
        request = PlanSequence.Request(landmark_ids=[int(i) for i in particle_ids])
        hint = "; is the planner running? (or set keep_order)"
        response = call_service(
            self.sequence_client, request, 10.0, self.config["action_timeout"], hint
        )
        if not response.success:
            raise ValueError(f"planner: {response.message}")
        return [int(particle_ids[i]) for i in response.order]

    def reporter(self, goal_handle, to_feedback):
        """Progress as feedback; the planned strokes on /afm/planned_path when they come."""

        goals_published = set()  # an assembly's positions in its order

        def report(p: Progress) -> None:
            if p.plan is not None:
                if p.index not in goals_published:
                    # once per particle, before its first stroke: what an offline evaluation
                    # scores the particle's end against (every leg of a closed loop shares it)
                    goals_published.add(p.index)
                    self.goal_pub.publish(push_goal_msg(p.plan.goal, p.time))
                tip_cov = p.tip.covariance
                self.path_pub.publish(push_plan_to_msg(p.plan, tip_cov, p.particle_id, p.time))
            self.publish_believed(p)
            goal_handle.publish_feedback(to_feedback(p))

        return report

    # -- the actions -------------------------------------------------------------------------
    def execute_push(self, goal_handle) -> PushParticle.Result:
        goal = goal_handle.request
        overrides = ZigzagOverrides(**{f: getattr(goal, f) for f in ZIGZAG_FIELDS})

        def push(progress, should_stop):
            if not goal.use_goal_angle and goal.goal_angle != 0.0:
                # an angle that would be silently ignored is refused
                raise PushRefused(
                    f"goal_angle={goal.goal_angle}: set while use_goal_angle is false "
                    "(set use_goal_angle to turn a tube or rod, or leave goal_angle 0)"
                )
            return self.procedure.push(
                goal.particle_id,
                (goal.goal.x, goal.goal.y),
                position=(goal.particle_position.x, goal.particle_position.y),
                strategy=goal.strategy,
                tolerance=goal.tolerance,
                overrides=overrides,
                progress=progress,
                should_stop=should_stop,
                goal_angle=goal.goal_angle if goal.use_goal_angle else None,
                angle_tolerance=goal.angle_tolerance,
            )

        return self.run_goal(goal_handle, PushParticle.Result(), push, progress_to_push_feedback)

    def execute_assemble(self, goal_handle) -> Assemble.Result:
        goal = goal_handle.request
        return self.run_goal(
            goal_handle,
            Assemble.Result(),
            lambda progress, should_stop: self.procedure.assemble(
                goal.particle_ids,
                [(g.x, g.y) for g in goal.goals],
                strategy=goal.strategy,
                tolerance=goal.tolerance,
                order=None if goal.keep_order else self.order,
                progress=progress,
                should_stop=should_stop,
            ),
            progress_to_assemble_feedback,
        )

    def run_goal(self, goal_handle, result, procedure, to_feedback):
        """Refused before anything moved, failed or cancelled after it started, or its outcome;
        the goal ends accordingly (one at a time: accept and releasing)."""
        try:
            outcome = procedure(
                self.reporter(goal_handle, to_feedback),
                lambda: goal_handle.is_cancel_requested,
            )
        except PushRefused as exc:
            result.success, result.message = False, f"refused: {exc}"
            goal_handle.abort()
            return result
        except PushFailed as exc:
            result.success, result.message = False, str(exc)
            (goal_handle.canceled if goal_handle.is_cancel_requested else goal_handle.abort)()
            return result
        outcome_to_result(outcome, result)
        if isinstance(result, Assemble.Result) and goal_handle.is_cancel_requested:
            goal_handle.canceled()
        elif result.success:
            goal_handle.succeed()
        else:
            goal_handle.abort()
        return result


def push_goal_msg(goal, time: float) -> PointStamped:
    msg = PointStamped(header=Header(stamp=seconds_to_time(time), frame_id=FRAME_TASK))
    msg.point.x, msg.point.y = float(goal[0]), float(goal[1])
    return msg


def main(args=None):
    return run(NanoHandNode, "afm_nano_hand", args, config_errors=(ValueError,), threads=4)


if __name__ == "__main__":
    sys.exit(main())
