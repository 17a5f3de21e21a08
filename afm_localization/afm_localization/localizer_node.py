"""Localizer node: where the tip is, with its covariance, from the calibrated motion model
and landmark observations (book ch. 5, 7.2).

The algorithms are afm_core.localization (`Localizer`: motion model + filterpy Kalman filter);
this node feeds it every command the driver executes (/afm/tip_command, from any client),
publishes the estimate on /afm/tip_pose (afm_task) at a steady rate and after every update,
and serves the Localize action, which runs the local scan lines through the driver's actions
(afm_ros.action_instrument.ActionInstrument) and updates the estimate.

The task frame is the scanner frame at the first command the node hears, to within
`initial_sigma`; maps and landmarks are in the same frame.
"""

from __future__ import annotations

import collections
import math
import sys
import threading

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Header
from tf2_msgs.msg import TFMessage

from afm_core import checks
from afm_core.instrument import ScannerLimits
from afm_core.localization import Localizer, MapLandmark
from afm_core.localization.calibration.model import Calibration, load_calibration
from afm_core.localization.localizer import LOCALIZER_PARAMETERS
from afm_core.parameters import Parameter, ParameterTable
from afm_msgs.action import Localize
from afm_msgs.msg import LandmarkArray, TipCommand
from afm_ros import frames, params, topics
from afm_ros.action_instrument import (
    ActionInstrument,
    DriverUnavailable,
    stamp_seconds,
    tip_command_problem,
)
from afm_ros.conversions import (
    FRAME_TASK,
    mean_cov_to_pose,
    seconds_to_time,
    wait_until,
)
from afm_ros.landmark_map import NewestLandmarkMap
from afm_ros.node_main import run
from afm_ros.qos_profiles import EVENTS, LATCHED

PARAMETERS = ParameterTable(
    Parameter(
        "calibration_file",
        "",
        "Calibration YAML written by `afm calibrate`; empty: the book's figures (uncalibrated).",
    ),
    Parameter(
        "initial_sigma",
        50e-9,
        "1-sigma of the tip position at the first command heard (the task frame's origin).",
        unit="m",
        minimum=0.0,
        above_minimum=True,
    ),
    Parameter(
        "publish_rate",
        10.0,
        "Steady publication rate of the (predicted) estimate on /afm/tip_pose.",
        unit="Hz",
        minimum=0.0,
        above_minimum=True,
    ),
    *LOCALIZER_PARAMETERS,
    Parameter(
        "match_radius",
        300e-9,
        "A Localize goal by position observes the nearest landmark within this.",
        unit="m",
        minimum=0.0,
        above_minimum=True,
        runtime=True,
    ),
    Parameter(
        "raster_sigma",
        30e-9,
        "1-sigma per axis added after a raster image: the motion model predicts a raster by its "
        "net displacement, not the hysteresis residue its back-and-forth path leaves.",
        unit="m",
        minimum=0.0,
        runtime=True,
    ),
)
# Where a run-time change of a Localizer parameter goes on the running estimator.
APPLY = {
    "gate": lambda loc, v: setattr(loc.filter, "gate", v),
    "history_seconds": lambda loc, v: setattr(loc.filter, "history_seconds", v),
    **{
        name: (lambda loc, v, name=name: setattr(loc, name, v))
        for name in ("line_speed", "move_speed", "sample_spacing", "threshold_fraction", "margin")
    },
}
# Localize goals at once (one observes, the rest wait for it, each holding an executor
# thread); more are rejected. The threads are these plus the inputs' and two for the driver's
# answers: three goals on three threads once left none for those answers, and the running
# goal reported a live, idle driver as gone.
MAX_LOCALIZE_GOALS = 3
THREADS = MAX_LOCALIZE_GOALS + 3
FUTURE_COMMAND_S = 3600.0  # s a command may start after the newest clock heard
KINDS = {
    TipCommand.SCAN_LINE: "line",
    TipCommand.INDENT: "indent",
    TipCommand.RASTER: "raster",
}  # the rest moves as a free move would


class LocalizerNode(Node):
    def __init__(self):
        super().__init__("afm_localizer")
        self.lock = threading.Lock()  # the Localizer is not thread-safe
        self.localizer: Localizer | None = None
        self.config = params.declare(self, PARAMETERS, apply=self.apply_parameter)
        path = self.config["calibration_file"]
        self.calibration = load_calibration(path) if path else Calibration()
        self.instrument = ActionInstrument(self, ScannerLimits())
        self.pending: collections.deque = collections.deque()
        self.landmarks = NewestLandmarkMap(self.get_logger())
        self.latest_clock: float | None = None
        inputs = MutuallyExclusiveCallbackGroup()
        self.create_subscription(
            TipCommand, topics.TIP_COMMAND, self.on_command, EVENTS, callback_group=inputs
        )
        self.create_subscription(
            LandmarkArray, topics.LANDMARKS, self.landmarks.take, LATCHED, callback_group=inputs
        )
        self.create_subscription(Clock, "/clock", self.on_clock, 10, callback_group=inputs)
        self.pose_pub = self.create_publisher(PoseWithCovarianceStamped, topics.TIP_POSE, 10)
        self.tf_pub = self.create_publisher(TFMessage, topics.TF, frames.DYNAMIC_QOS)
        self.published_offset: tuple[float, float] | None = None
        self.create_timer(1.0 / self.config["publish_rate"], self.tick, callback_group=inputs)
        ActionServer(
            self,
            Localize,
            topics.ACTION_LOCALIZE,
            self.execute,
            callback_group=ReentrantCallbackGroup(),
            goal_callback=self.accept,
            cancel_callback=lambda _g: CancelResponse.ACCEPT,
        )
        self.goals = 0  # accepted and not yet ended
        self.goals_lock = threading.Lock()
        if not path:
            self.get_logger().warning(
                "no calibration_file: using the book's figures; run `afm calibrate` for "
                "this instrument"
            )

    def apply_parameter(self, name: str, value) -> None:
        """A run-time change reaches the running estimator (read at use time otherwise)."""
        with self.lock:
            if self.localizer is not None and name in APPLY:
                APPLY[name](self.localizer, value)

    # -- inputs ------------------------------------------------------------------------------
    def on_command(self, msg: TipCommand) -> None:
        self.pending.append(msg)

    def on_clock(self, msg: Clock) -> None:
        self.latest_clock = stamp_seconds(msg.clock)

    def process_pending(self) -> None:
        """Predict every command heard and not yet accounted for (call with the lock held)."""
        while self.pending:
            msg = self.pending.popleft()
            start_time = stamp_seconds(msg.header.stamp)
            problem = tip_command_problem(msg, self.instrument.limits) or self.future_problem(
                start_time
            )
            if problem is not None:
                self.get_logger().error(f"tip command ignored: {problem}")
                continue
            start, end = (msg.start.x, msg.start.y), (msg.end.x, msg.end.y)
            if self.localizer is None:
                self.instrument.rest_at(start, start_time)
                sigma = self.config["initial_sigma"]
                self.localizer = Localizer(
                    self.instrument,
                    self.calibration,
                    np.array(start),
                    np.diag([sigma**2, sigma**2]),
                    gate=self.config["gate"],
                    line_speed=self.config["line_speed"],
                    move_speed=self.config["move_speed"],
                    sample_spacing=self.config["sample_spacing"],
                    threshold_fraction=self.config["threshold_fraction"],
                    margin=self.config["margin"],
                    history_seconds=self.config["history_seconds"],
                )
            self.instrument.observe_command(msg)
            extra = self.config["raster_sigma"] ** 2 if msg.kind == TipCommand.RASTER else 0.0
            try:
                if self.localizer.predict_command(
                    KINDS.get(msg.kind, "move"),
                    start,
                    end,
                    start_time,
                    start_time + msg.duration,
                    extra,
                ):
                    self.publish(self.localizer.time)  # the estimate as each command ends
            except ValueError as exc:
                self.get_logger().error(f"tip command ignored: {exc}")

    def future_problem(self, start_time: float) -> str | None:
        """A command that starts far after the newest clock heard (one stamped 1e6 s ahead
        moved the estimate's time there, and every later command looked already accounted
        for); None if it does not. The bound is wide, as a fast simulator's /clock may lag
        its commands by many of its seconds."""
        now = self.now()
        if start_time > now + FUTURE_COMMAND_S:
            return (
                f"header.stamp={start_time:.3f} s: {start_time - now:.0f} s after the clock "
                f"({now:.3f} s); at most {FUTURE_COMMAND_S:.0f} s ahead is taken"
            )
        return None

    def heard_every_command(self) -> bool:
        """Whether every command up to the driver's /clock has reached us. The simulated driver's
        clock stands still while it is idle, so a clock past the last command heard means one is
        still on its way (DDS delivers a reliable sample it lost late, after its repair): lines
        run before it arrives would fold it into one move and drop it as an echo."""
        if self.latest_clock is None:
            return True
        heard = max(
            [self.instrument.time]
            + [stamp_seconds(m.header.stamp) + m.duration for m in list(self.pending)]
        )
        return heard >= self.latest_clock - 1e-6

    def now(self) -> float:
        """The instrument clock: /clock when the driver publishes one, else wall time."""
        if self.latest_clock is not None:
            return self.latest_clock
        return self.get_clock().now().nanoseconds * 1e-9

    # -- outputs -----------------------------------------------------------------------------
    def tick(self) -> None:
        if not self.lock.acquire(blocking=False):
            return  # an observation is running; it publishes
        try:
            self.process_pending()
            # past the last command heard the estimate assumes the tip at rest, but a clock
            # ahead of it means one is still on its way (the driver says what it did after
            # doing it): a pose for such a time would put the tip where the move started and
            # be published again, moved, once the command comes (the demo's assembly: nine
            # stamps with two poses 170-480 nm apart, read as an overconfident localizer)
            if self.localizer is not None and self.heard_every_command():
                self.publish(max(self.now(), self.localizer.time))
        finally:
            self.lock.release()

    def pose_msg(self, time: float) -> PoseWithCovarianceStamped:
        mean, covariance = self.localizer.at(time)
        return mean_cov_to_pose(
            mean, covariance, Header(stamp=seconds_to_time(time), frame_id=FRAME_TASK)
        )

    def publish(self, time: float) -> PoseWithCovarianceStamped:
        msg = self.pose_msg(time)
        self.pose_pub.publish(msg)
        self.publish_transform(msg)
        return msg

    def publish_transform(self, pose: PoseWithCovarianceStamped) -> None:
        """afm_task -> afm_scanner on /tf whenever the estimate moved it: the steady-rate pose
        at rest would repeat the same transform at publish_rate and add nothing."""
        estimate = (pose.pose.pose.position.x, pose.pose.pose.position.y)
        commanded = self.instrument.commanded_position()
        offset = (estimate[0] - commanded[0], estimate[1] - commanded[1])
        if offset != self.published_offset:
            self.tf_pub.publish(frames.scanner_in_task(pose.header.stamp, estimate, commanded))
            self.published_offset = offset

    # -- the Localize action -----------------------------------------------------------------
    def landmark_for(self, goal):
        known = self.landmarks.wait()
        if goal.landmark_id < -1:
            raise ValueError(
                f"landmark_id={goal.landmark_id}: an id >= 0, or -1 for the one at position"
            )
        if goal.landmark_id >= 0:
            if goal.landmark_id not in known:
                raise ValueError(
                    f"landmark_id={goal.landmark_id}: unknown "
                    f"(known ids: {checks.few(sorted(known)) or 'none yet'})"
                )
            return known[goal.landmark_id]
        point = np.array([goal.position.x, goal.position.y])
        if not np.all(np.isfinite(point)):
            raise ValueError("position: must be finite (m)")
        if not known:
            raise ValueError(f"no landmark known yet (nothing on {topics.LANDMARKS})")
        nearest = min(known.values(), key=lambda m: math.hypot(m.x - point[0], m.y - point[1]))
        distance = math.hypot(nearest.x - point[0], nearest.y - point[1])
        if distance > self.config["match_radius"]:
            raise ValueError(
                "position: no landmark within "
                f"match_radius={self.config['match_radius'] * 1e9:.0f} nm "
                f"(nearest, id {nearest.id}, is {distance * 1e9:.0f} nm away)"
            )
        return nearest

    def accept(self, _goal) -> GoalResponse:
        with self.goals_lock:
            if self.goals >= MAX_LOCALIZE_GOALS:
                self.get_logger().warning(
                    f"goal rejected: {self.goals} Localize goals already run or wait (at most "
                    f"{MAX_LOCALIZE_GOALS} at once)"
                )
                return GoalResponse.REJECT
            self.goals += 1
            return GoalResponse.ACCEPT

    def execute(self, goal_handle) -> Localize.Result:
        try:
            return self.localize(goal_handle)
        finally:
            with self.goals_lock:
                self.goals -= 1

    def localize(self, goal_handle) -> Localize.Result:
        goal, result = goal_handle.request, Localize.Result()
        wait_until(
            lambda: self.localizer is not None or self.pending, 5.0
        )  # commands reach us late under load
        wait_until(self.heard_every_command, 5.0)
        with self.lock:
            self.process_pending()
            try:
                if self.localizer is None:
                    raise ValueError("no tip estimate yet: the driver has executed no command")
                landmark = MapLandmark.from_landmark(self.landmark_for(goal))
                toward = None
                if goal.continue_toward:
                    toward = np.array([goal.toward.x, goal.toward.y])
                    if not np.all(np.isfinite(toward)):
                        raise ValueError("toward: must be finite (m)")
                # every line is planned before anything moves: a line out of range refuses the goal
                for_lines = dict(both_axes=not goal.one_line, toward=toward)
                self.localizer.plan_observation(landmark, **for_lines)
            except ValueError as exc:
                goal_handle.abort()
                result.success, result.message = False, f"refused: {exc}"
                return result
            if goal_handle.is_cancel_requested:
                goal_handle.canceled()
                result.success, result.message = False, "cancelled before any line"
                return result
            feedback = Localize.Feedback(
                phase="scanning", lines_done=0, pose=self.pose_msg(self.localizer.time)
            )
            goal_handle.publish_feedback(feedback)
            try:
                # a cancel ends the observation where it is, not after a search of up to
                # eight more lines
                observation = self.localizer.observe_landmark(
                    landmark, **for_lines, should_stop=lambda: goal_handle.is_cancel_requested
                )
                failure = observation.instrument_error
            except (ValueError, DriverUnavailable) as exc:
                observation, failure = None, str(exc)
            self.process_pending()
            result.pose = self.publish(self.localizer.time)
        lines = observation.lines if observation is not None else []
        goal_handle.publish_feedback(
            Localize.Feedback(phase="updating", lines_done=len(lines), pose=result.pose)
        )
        result.lost = any(line.lost for line in lines)
        result.gated_out = any(line.gated_out for line in lines)
        result.innovation = [
            float(line.innovation) for line in lines if math.isfinite(line.innovation)
        ]
        summary = observation.summary() if observation is not None else ""
        result.success = observation is not None and observation.all_accepted and not failure
        if failure:
            result.message = f"driver failure: {failure}" + (f"; {summary}" if summary else "")
        else:
            result.message = summary or "no line run"
        self.get_logger().info(f"localize on landmark {landmark.id}: {result.message}")
        if goal_handle.is_cancel_requested:
            goal_handle.canceled()
            result.message = "cancelled: " + result.message
        elif result.success:
            goal_handle.succeed()
        else:
            goal_handle.abort()
        return result


def main(args=None):
    return run(LocalizerNode, "afm_localizer", args, config_errors=(ValueError,), threads=THREADS)


if __name__ == "__main__":
    sys.exit(main())
