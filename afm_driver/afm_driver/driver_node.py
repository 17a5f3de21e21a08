"""Driver node: the instrument behind ROS actions.

Backends: `sim` (afm_core.sim, publishes ground truth and /clock), `daq` (a scanner driven
through an NI DAQ card, afm_core.daq), `replay` (answers the actions with a recorded
session's data, afm_core.replay_instrument). One motion at a time: goals wait in a FIFO
queue of at most `max_queued_goals`; cancel stops a running motion where the tip is, or
removes a waiting goal. One owner of the tip at a time (afm_driver.tip_owner): while teleop
holds it, only MoveTip goals on /afm/teleop/move_tip run and every other goal is refused.
With a `calibration_file`, ScanImage first approaches the image's
first sample and waits there as long as the calibrated creep model says the creep still to
come exceeds `creep_settle_tolerance` (afm_core.localization.creep_settle), and its result
message says how long and why.
"""

from __future__ import annotations

import math
import sys
import threading
import time

from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Image
from std_msgs.msg import Header
from tf2_msgs.msg import TFMessage

from afm_core.backends import open_instrument
from afm_core.imaging.raster_approach import RASTER_APPROACH_OVERSHOOT, approach_point
from afm_core.instrument import LineRequest, ScanRequest, move_speed, validate_move
from afm_core.localization.calibration.model import load_calibration
from afm_core.localization.creep_settle import (
    CREEP_SETTLE_TOLERANCE,
    MAX_CREEP_WAIT,
    CreepSettler,
    settle_before,
)
from afm_core.parameters import Parameter, ParameterTable
from afm_driver.tip_owner import TipOwner
from afm_msgs.action import Indent, LocalScan, MoveTip, ScanImage
from afm_msgs.msg import ForceTrace, GroundTruth, RasterScan, ScanLine, TipCommand
from afm_ros import frames, params, topics
from afm_ros.conversions import (
    FRAME_SCANNER,
    FRAME_TASK,
    force_trace_to_msg,
    raster_scan_to_msg,
    scan_line_to_msg,
    seconds_to_time,
    truth_to_msg,
)
from afm_ros.height_image import height_image_msg
from afm_ros.node_main import run
from afm_ros.qos_profiles import EVENTS, FEEDBACK, LATCHED, SCANS, STREAM_OFFERED

# each waiting goal holds one of the node's threads (the gate blocks it): the node runs this many
# plus SERVICE_THREADS, so cancels and new goals are answered however full the queue is
MAX_QUEUED_GOALS = 64
# the running goal, goal/cancel requests, the clock timer, the tip owner's service and timer
SERVICE_THREADS = 4

PARAMETERS = ParameterTable(
    Parameter(
        "backend",
        "sim",
        "Instrument: 'sim' (simulated AFM), 'daq' (NI DAQ card), 'replay' (a recorded session).",
        choices=("sim", "daq", "replay"),
    ),
    Parameter(
        "sim_config",
        "",
        "YAML file of simulator parameters "
        "(any subset; defaults: afm_core/sim/default_config.yaml).",
    ),
    Parameter("seed", -1, "Simulator random seed; -1 keeps the config file's seed.", minimum=-1),
    Parameter(
        "real_time_factor",
        0.0,
        "Simulated seconds per wall second (1.0 = real time); 0 = as fast as possible.",
        minimum=0.0,
    ),
    Parameter(
        "publish_clock",
        True,
        "Publish the instrument's time on /clock (sim and replay) for use_sim_time nodes.",
    ),
    Parameter(
        "clock_frequency",
        20.0,
        "Rate (wall time) of /clock messages while idle.",
        unit="Hz",
        minimum=0.0,
        above_minimum=True,
    ),
    Parameter(
        "max_queued_goals",
        8,
        "Goals that may wait while one runs; more are rejected when they arrive.",
        minimum=0,
        maximum=MAX_QUEUED_GOALS,
    ),
    Parameter("daq_device", "Dev1", "NI-DAQmx device name (daq backend)."),
    Parameter(
        "daq_calibration",
        "",
        "YAML file of the DAQ calibration (daq backend; defaults: afm_core.daq.DaqCalibration).",
    ),
    Parameter(
        "calibration_file",
        "",
        "Calibration YAML written by `afm calibrate` (the localizer's): its creep model sets the "
        "wait before an image after a long move; empty: no wait.",
    ),
    CREEP_SETTLE_TOLERANCE,
    MAX_CREEP_WAIT,
    RASTER_APPROACH_OVERSHOOT,
    Parameter(
        "replay_input",
        "",
        "Recording (.mcap) whose scans, lines and force traces the replay backend serves.",
    ),
)


def make_instrument(config: dict):
    try:
        return open_instrument(
            config["backend"],
            config["sim_config"],
            config["seed"],
            config["daq_device"],
            config["daq_calibration"],
            config["replay_input"],
        )
    except ValueError as exc:
        raise ValueError(f"parameter {exc}") from exc


class FifoGate:
    """One holder at a time, served in arrival order; a waiter may give up (cancel).

    `admit` reserves a place when a goal is accepted (one running, `capacity` waiting) and
    `leave` frees it when the goal ends: goals accepted but not yet executing count, so the
    limit holds however fast goals arrive."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self.condition = threading.Condition()
        self.next_ticket = 0
        self.serving = 0
        self.abandoned: set[int] = set()
        self.admitted = 0

    def admit(self) -> bool:
        with self.condition:
            if self.admitted > self.capacity:
                return False
            self.admitted += 1
            return True

    def leave(self) -> None:
        with self.condition:
            self.admitted = max(0, self.admitted - 1)

    def take(self) -> int:
        with self.condition:
            ticket = self.next_ticket
            self.next_ticket += 1
            return ticket

    def wait(self, ticket: int, give_up) -> bool:
        """True when it is this ticket's turn; False (turn passed on) if the waiter gave up,
        even if the turn came in the same instant."""
        with self.condition:
            while self.serving != ticket:
                if give_up():
                    self.abandoned.add(ticket)
                    self.condition.notify_all()
                    return False
                self.condition.wait(timeout=0.05)
        if give_up():
            self.release()
            return False
        return True

    def release(self) -> None:
        with self.condition:
            self.serving += 1
            while self.serving in self.abandoned:
                self.abandoned.discard(self.serving)
                self.serving += 1
            self.condition.notify_all()


class DriverNode(Node):
    def __init__(self):
        started = time.monotonic()
        super().__init__("afm_driver")
        self.config = params.declare(self, PARAMETERS)
        self.instrument = make_instrument(self.config)
        self.is_sim = self.config["backend"] == "sim"
        self.epoch = time.time()  # instrument time 0 <-> wall time at start
        self.gate = FifoGate(self.config["max_queued_goals"])
        self.pacing_origin = (time.monotonic(), self.instrument.time)
        self.settler = self._settler()
        self.scan_pub = self.create_publisher(RasterScan, topics.SCAN, SCANS)
        self.scan_image_pub = self.create_publisher(Image, topics.SCAN_IMAGE, SCANS)
        # the driver is in every graph, so it carries the tree's fixed part (stamped at the
        # instrument's time 0, the start of the session)
        self.tf_static_pub = self.create_publisher(TFMessage, topics.TF_STATIC, frames.STATIC_QOS)
        self.tf_static_pub.publish(frames.static_tree(self.stamp(self.instrument.time)))
        self.line_pub = self.create_publisher(ScanLine, topics.SCAN_LINE, STREAM_OFFERED)
        self.trace_pub = self.create_publisher(ForceTrace, topics.FORCE_TRACE, STREAM_OFFERED)
        self.command_pub = self.create_publisher(TipCommand, topics.TIP_COMMAND, EVENTS)
        self.truth_pub = (
            self.create_publisher(GroundTruth, topics.GROUND_TRUTH, LATCHED)
            if self.is_sim
            else None
        )
        self.clock_pub = (
            self.create_publisher(Clock, "/clock", 10)
            if self.config["publish_clock"] and self.config["backend"] != "daq"
            else None
        )
        group = ReentrantCallbackGroup()
        self.owner = TipOwner(self, self.gate, self.instrument.commanded_position)
        for action_type, name, execute in (
            (ScanImage, topics.ACTION_SCAN_IMAGE, self.execute_scan),
            (LocalScan, topics.ACTION_LOCAL_SCAN, self.execute_line),
            (MoveTip, topics.ACTION_MOVE_TIP, self.execute_move),
            (Indent, topics.ACTION_INDENT, self.execute_indent),
            (MoveTip, topics.ACTION_TELEOP_MOVE_TIP, self.execute_move),
        ):
            ActionServer(
                self,
                action_type,
                name,
                self._queued(action_type, execute, name == topics.ACTION_TELEOP_MOVE_TIP),
                callback_group=group,
                feedback_pub_qos_profile=FEEDBACK,
                goal_callback=self.accept_goal,
                cancel_callback=lambda _g: CancelResponse.ACCEPT,
            )
        if self.clock_pub is not None:
            self.create_timer(1.0 / self.config["clock_frequency"], self.publish_clock)
        self.publish_truth()
        # one line when the servers exist: a client that finds them listed but unanswered
        # (a test's driver killed at its end) can tell a driver that never got here
        self.get_logger().info(
            f"ready: {self.config['backend']} instrument, actions served, "
            f"{time.monotonic() - started:.2f} s after the node was created"
        )

    def _settler(self) -> CreepSettler | None:
        """The creep model that times the wait before an image (none without a calibration,
        or on an instrument that cannot hold: the replay backend serves what was recorded)."""
        if not self.config["calibration_file"] or not hasattr(self.instrument, "hold"):
            return None
        try:
            calibration = load_calibration(self.config["calibration_file"])
        except ValueError as exc:
            raise ValueError(f"parameter calibration_file: {exc}") from exc
        settler = CreepSettler(
            calibration, self.instrument.commanded_position(), self.instrument.time
        )
        return settler if settler.enabled else None

    # -- plumbing ----------------------------------------------------------------------------
    def accept_goal(self, _goal):
        if not self.gate.admit():
            self.get_logger().warning(
                f"goal rejected: {self.config['max_queued_goals']} goals already wait "
                "(max_queued_goals)"
            )
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def _queued(self, action_type, execute, teleop: bool):
        def run_in_turn(goal_handle):
            ticket = self.gate.take()
            if not self.gate.wait(ticket, lambda: goal_handle.is_cancel_requested):
                self.gate.leave()
                goal_handle.canceled()
                return action_type.Result(
                    success=False, message="cancelled while waiting for the instrument"
                )
            try:
                refusal = self.owner.refusal(teleop)
                if refusal:
                    return self.refuse(goal_handle, action_type.Result(), refusal)
                return execute(goal_handle)
            except ValueError as exc:  # the instrument refused (e.g. a replay mismatch)
                return self.refuse(goal_handle, action_type.Result(), exc)
            except Exception as exc:  # noqa: BLE001 - report it and keep serving
                self.get_logger().error(f"{action_type.__name__} failed: {exc!r}")
                goal_handle.abort()
                # the type too: a MemoryError's text is empty ("driver error: " said nothing)
                return action_type.Result(
                    success=False,
                    message=f"driver error: {type(exc).__name__}: {exc}".rstrip(": "),
                )
            finally:
                self.gate.release()
                self.gate.leave()
                self.publish_truth()
                self.publish_clock()

        return run_in_turn

    def stamp(self, instrument_time: float):
        return seconds_to_time(self.epoch + instrument_time)

    def header(self, instrument_time: float, frame=FRAME_SCANNER) -> Header:
        return Header(stamp=self.stamp(instrument_time), frame_id=frame)

    def pace(self) -> None:
        """Hold sim time to real_time_factor x wall time (0: no holding back)."""
        factor = self.config["real_time_factor"]
        if factor <= 0:
            return
        wall0, sim0 = self.pacing_origin
        ahead = (self.instrument.time - sim0) / factor - (time.monotonic() - wall0)
        if ahead > 0:
            time.sleep(ahead)

    def stop_check(self, goal_handle):
        """Asked by the instrument between chunks of a motion: keeps real-time pacing inside
        long motions, so a cancel lands where the tip is now."""

        def should_stop() -> bool:
            self.pace()
            self.publish_clock()
            return goal_handle.is_cancel_requested

        return should_stop

    def publish_clock(self) -> None:
        if self.clock_pub is not None:
            self.clock_pub.publish(Clock(clock=self.stamp(self.instrument.time)))

    def publish_truth(self) -> None:
        if self.truth_pub is not None:
            self.truth_pub.publish(
                truth_to_msg(
                    self.instrument.truth(), self.header(self.instrument.time, FRAME_TASK)
                )
            )

    def command(self, kind, start_time, start, end, duration, speed=0.0):
        msg = TipCommand(
            header=self.header(start_time), kind=kind, speed=float(speed), duration=float(duration)
        )
        msg.start.x, msg.start.y = map(float, start)
        msg.end.x, msg.end.y = map(float, end)
        msg.start_voltage = msg.end_voltage = [float("nan")] * 3
        self.command_pub.publish(msg)
        if self.settler is not None:
            self.settler.observe(start, end, start_time, start_time + duration)
        return msg

    def refuse(self, goal_handle, result, exc):
        goal_handle.abort()
        result.success, result.message = False, f"refused: {exc}"
        return result

    def finish(self, goal_handle, result, completed: bool, what: str):
        x, y = self.instrument.commanded_position()
        if completed:
            goal_handle.succeed()
            result.success, result.message = True, "ok"
        else:
            goal_handle.canceled()
            result.success = False
            result.message = (
                f"{what} cancelled; tip held at ({x * 1e9:.1f} nm, {y * 1e9:.1f} nm) "
                "in afm_scanner"
            )
        return result

    # -- actions -----------------------------------------------------------------------------
    def execute_scan(self, goal_handle) -> ScanImage.Result:
        goal, result = goal_handle.request, ScanImage.Result()
        request = ScanRequest(
            goal.origin.x,
            goal.origin.y,
            goal.size_x,
            goal.size_y,
            goal.pixels_x,
            goal.pixels_y,
            goal.scan_angle_deg,
            goal.slow_scan_up,
            goal.line_rate,
            goal.mode or "tapping",
        )
        try:
            request.validate(self.instrument.limits)
        except ValueError as exc:
            return self.refuse(goal_handle, result, exc)

        def on_line(done, total):
            goal_handle.publish_feedback(ScanImage.Feedback(lines_done=done, lines_total=total))
            self.pace()

        should_stop = self.stop_check(goal_handle)
        self.approach_from_beyond(request, should_stop)
        settled = self.settle_before_scan(request, should_stop)
        if settled:
            self.get_logger().info(
                f"scan at ({request.origin_x * 1e6:.2f}, "
                f"{request.origin_y * 1e6:.2f}) um: {settled}"
            )
        start_time, start = self.instrument.time, self.instrument.commanded_position()
        scan = self.instrument.raster_scan(request, on_line=on_line, should_stop=should_stop)
        duration = self.instrument.time - start_time
        fast_size = request.size_x if request.scan_angle_deg == 0.0 else request.size_y
        path_length = 2 * fast_size * request.lines + math.dist(
            start, (request.origin_x, request.origin_y)
        )
        result.command = self.command(
            TipCommand.RASTER,
            start_time,
            start,
            self.instrument.commanded_position(),
            duration,
            path_length / duration if duration > 0 else 0.0,
        )
        msg = raster_scan_to_msg(
            scan, self.header(scan.start_time), scan_id=self._next_scan_id(), pair_id=goal.pair_id
        )
        if scan.complete:
            self.scan_pub.publish(msg)
            self.scan_image_pub.publish(height_image_msg(scan.height, msg.header)[0])
        result.scan = msg
        result = self.finish(goal_handle, result, scan.complete, "scan")
        if settled:
            result.message = f"{result.message}; {settled}"
        return result

    def approach_from_beyond(self, request: ScanRequest, should_stop) -> None:
        """A lifted move to beyond the image's start (afm_core raster_approach), so both axes
        image on a reversed hysteresis branch wherever the image is."""
        overshoot = self.config["raster_approach_overshoot"]
        if overshoot <= 0:
            return
        start_time, start = self.instrument.time, self.instrument.commanded_position()
        speed = self.instrument.limits.max_speed / 10  # the scan's own approach speed
        target = approach_point(request, overshoot, self.instrument.limits)
        move = self.instrument.move_tip(*target, speed, should_stop=should_stop)
        duration = self.instrument.time - start_time
        self.command(TipCommand.MOVE, start_time, start, (move.end_x, move.end_y), duration, speed)

    def settle_before_scan(self, request: ScanRequest, should_stop) -> str:
        """Approach the image's first sample and wait there for creep (afm_core creep_settle);
        what was done, in words ("" when no wait was needed)."""
        if self.settler is None:
            return ""

        def on_move(start, end, start_time, duration):
            self.command(
                TipCommand.MOVE,
                start_time,
                start,
                end,
                duration,
                math.dist(start, end) / duration if duration > 0 else 0.0,
            )

        approach = self.instrument.limits.max_speed / 10  # the scan's own approach speed
        settling = settle_before(
            self.instrument,
            self.settler,
            *request.first_point(),
            approach,
            self.config["creep_settle_tolerance"],
            self.config["max_creep_wait"],
            on_move=on_move,
            should_stop=should_stop,
        )
        return settling.describe()

    def _next_scan_id(self) -> int:
        self._scan_count = getattr(self, "_scan_count", 0) + 1
        return self._scan_count

    def execute_line(self, goal_handle) -> LocalScan.Result:
        goal, result = goal_handle.request, LocalScan.Result()
        speed = goal.speed  # LineRequest.validate: finite, > 0, at most the slew limit
        request = LineRequest(
            goal.start.x,
            goal.start.y,
            goal.end.x,
            goal.end.y,
            goal.samples,
            speed,
            goal.mode or "tapping",
        )
        try:
            request.validate(self.instrument.limits)
        except ValueError as exc:
            return self.refuse(goal_handle, result, exc)
        start_time = self.instrument.time
        line = self.instrument.local_scan(request, should_stop=self.stop_check(goal_handle))
        self.pace()
        result.command = self.command(
            TipCommand.SCAN_LINE,
            start_time,
            (request.start_x, request.start_y),
            (request.end_x, request.end_y),
            self.instrument.time - start_time,
            speed,
        )
        msg = scan_line_to_msg(
            line,
            self.header(line.start_time),
            (request.start_x, request.start_y),
            (request.end_x, request.end_y),
            goal.landmark_id,
        )
        goal_handle.publish_feedback(
            LocalScan.Feedback(fraction_done=1.0 if line.complete else 0.0)
        )
        if line.complete:
            self.line_pub.publish(msg)
        result.line = msg
        return self.finish(goal_handle, result, line.complete, "scan line")

    def execute_move(self, goal_handle) -> MoveTip.Result:
        goal, result = goal_handle.request, MoveTip.Result()
        start_time, start = self.instrument.time, self.instrument.commanded_position()
        try:
            if goal.target.header.frame_id not in ("", FRAME_SCANNER, FRAME_TASK):
                raise ValueError(
                    f"target.header.frame_id={goal.target.header.frame_id!r}: expected "
                    f"{FRAME_SCANNER!r} or {FRAME_TASK!r}"
                )
            speed = move_speed(goal.speed, self.instrument.limits)
            validate_move(goal.target.point.x, goal.target.point.y, speed, self.instrument.limits)
            move = self.instrument.move_tip(
                goal.target.point.x,
                goal.target.point.y,
                speed,
                goal.contact,
                should_stop=self.stop_check(goal_handle),
            )
        except ValueError as exc:
            return self.refuse(goal_handle, result, exc)
        self.pace()
        result.command = self.command(
            TipCommand.PUSH if goal.contact else TipCommand.MOVE,
            start_time,
            start,
            (move.end_x, move.end_y),
            self.instrument.time - start_time,
            speed,
        )
        result.commanded_position.x, result.commanded_position.y = move.end_x, move.end_y
        goal_handle.publish_feedback(
            MoveTip.Feedback(commanded_position=result.commanded_position)
        )
        if move.trace is not None:
            result.trace = force_trace_to_msg(move.trace, self.header(move.trace.start_time))
            self.trace_pub.publish(result.trace)
        return self.finish(goal_handle, result, move.completed, "move")

    def execute_indent(self, goal_handle) -> Indent.Result:
        goal, result = goal_handle.request, Indent.Result()
        start_time = self.instrument.time
        try:
            indent = self.instrument.indent(
                goal.position.x,
                goal.position.y,
                goal.force,
                goal.dwell,
                should_stop=self.stop_check(goal_handle),
            )
        except ValueError as exc:
            return self.refuse(goal_handle, result, exc)
        self.pace()
        result.command = self.command(
            TipCommand.INDENT,
            start_time,
            (indent.x, indent.y),
            (indent.x, indent.y),
            self.instrument.time - start_time,
        )
        goal_handle.publish_feedback(Indent.Feedback(phase="retract"))
        result.trace = force_trace_to_msg(indent.trace, self.header(indent.trace.start_time))
        if indent.completed:
            self.trace_pub.publish(result.trace)
        return self.finish(goal_handle, result, indent.completed, "indentation")

    def destroy_node(self):
        self.instrument.close()
        super().destroy_node()


def main(args=None):
    return run(
        DriverNode,
        "afm driver",
        args,
        config_errors=(ValueError, RuntimeError),
        threads=lambda node: node.config["max_queued_goals"] + SERVICE_THREADS,
    )


if __name__ == "__main__":
    sys.exit(main())
