"""The driver node seen as an `afm_core.instrument.Instrument`, through its actions.

The localizer and the nano-hand run the core library's procedures (observe a landmark,
push along a path) unchanged in the graph: those procedures call `move_tip`,
`local_scan`, `indent`, `raster_scan` and read `time`; here each call becomes a goal to
the driver and blocks until its result. Call it from a thread that is not the one
spinning the node (an action server's execute callback in a MultiThreadedExecutor with a
reentrant callback group does this).

`time` is the instrument clock in ROS-stamp seconds: the end of the last command the
driver reported (its results carry the executed TipCommand).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

import numpy as np
from rclpy.callback_groups import ReentrantCallbackGroup

from afm_core.instrument import (
    ForceTraceData,
    IndentResult,
    InstrumentUnavailable,
    LineRequest,
    MoveResult,
    RasterScanData,
    ScanLineData,
    ScannerLimits,
    ScanRequest,
    check_in_range,
    validate_indent,
    validate_move,
)
from afm_msgs.action import Indent, LocalScan, MoveTip, ScanImage
from afm_msgs.msg import TipCommand
from afm_ros import topics
from afm_ros.action_client import (
    CANCEL_ACK_TIMEOUT_S,
    STOPPING,
    Heartbeat,
    SafeActionClient,
)
from afm_ros.conversions import FRAME_SCANNER, msg_to_raster_scan
from afm_ros.qos_profiles import FEEDBACK


class DriverUnavailable(InstrumentUnavailable):
    """An action server (the driver, the localizer) did not answer: not running, goal rejected,
    or no result within the timeout."""


def stamp_seconds(stamp) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


TIP_COMMAND_KINDS = {
    TipCommand.MOVE: "MOVE",
    TipCommand.SCAN_LINE: "SCAN_LINE",
    TipCommand.RASTER: "RASTER",
    TipCommand.PUSH: "PUSH",
    TipCommand.INDENT: "INDENT",
}


def tip_command_problem(command, limits: ScannerLimits) -> str | None:
    """Why a reported TipCommand cannot be one a driver executed on a scanner with `limits`
    (None: it can). Every node that follows /afm/tip_command takes the last one's end as
    where the tip is commanded: one bogus message (an end at 1 m, another program's test)
    otherwise put the localizer's estimate there for good."""
    if command.kind not in TIP_COMMAND_KINDS:
        known = ", ".join(f"{name}={kind}" for kind, name in TIP_COMMAND_KINDS.items())
        return f"kind={command.kind}: not a TipCommand kind ({known})"
    start = stamp_seconds(command.header.stamp)
    if not start > 0.0:
        return f"header.stamp={start} s: must be after the epoch (when the command started)"
    if not (math.isfinite(command.duration) and command.duration >= 0.0):
        return f"duration={command.duration}: must be finite and >= 0 (s)"
    for name, point in (("start", command.start), ("end", command.end)):
        try:
            check_in_range(name, point.x, point.y, limits)
        except ValueError as exc:
            return str(exc)
    return None


def msg_to_scan_line(msg) -> ScanLineData:
    return ScanLineData(
        times=np.asarray(msg.times, float),
        x=np.asarray(msg.x, float),
        y=np.asarray(msg.y, float),
        height=np.asarray(msg.height, float),
        deflection=np.asarray(msg.deflection, float),
        amplitude=np.asarray(msg.amplitude, float),
        start_time=stamp_seconds(msg.header.stamp),
        mode=msg.mode,
    )


def msg_to_force_trace(msg) -> ForceTraceData:
    return ForceTraceData(
        times=np.asarray(msg.times, float),
        commanded_x=np.asarray(msg.commanded_x, float),
        commanded_y=np.asarray(msg.commanded_y, float),
        commanded_z=np.asarray(msg.commanded_z, float),
        vertical_deflection=np.asarray(msg.vertical_deflection, float),
        lateral_torsion=np.asarray(msg.lateral_torsion, float),
        normal_spring_constant=msg.normal_spring_constant,
        lateral_spring_constant=msg.lateral_spring_constant,
        sample_rate=msg.sample_rate,
        start_time=stamp_seconds(msg.header.stamp),
        task=msg.task,
        object_id=msg.object_id,
    )


DRIVER_ACTIONS = {
    topics.ACTION_SCAN_IMAGE,
    topics.ACTION_LOCAL_SCAN,
    topics.ACTION_MOVE_TIP,
    topics.ACTION_INDENT,
}


def _who(action_name: str) -> str:
    return "driver" if action_name in DRIVER_ACTIONS else f"server of {action_name}"


def call_action(
    client,
    goal,
    server_timeout: float,
    result_timeout: float,
    should_stop: Callable[[], bool] | None = None,
):
    """Send a goal and block until its result (from a thread that is not spinning the node).
    should_stop() is polled while waiting; when it turns true the goal is cancelled and its
    (cancelled) result still awaited. DriverUnavailable when the server is missing, rejects
    the goal, gives no result within result_timeout s, does not acknowledge a cancel within
    CANCEL_ACK_TIMEOUT_S, or stops answering (a heartbeat, SERVER_SILENCE_S): then the
    message starts with "aborted: driver gone" ("aborted: server of NAME gone" for another
    server)."""
    name = client._action_name
    if STOPPING.is_set():
        raise DriverUnavailable(f"{name}: not sent, this node is stopping")
    if not client.wait_until_answering(server_timeout):
        raise DriverUnavailable(
            f"action {name} did not answer within {server_timeout} s "
            f"({client.not_answering}); is its node running?"
        )
    done = threading.Event()
    sent = client.send_goal_async(goal)
    sent.add_done_callback(lambda _f: done.set())
    if not done.wait(server_timeout):
        raise DriverUnavailable(f"{name}: goal not acknowledged within {server_timeout} s")
    handle = sent.result()
    if not handle.accepted:
        raise DriverUnavailable(f"{name}: goal rejected (server busy)")
    finished = threading.Event()
    result_future = handle.get_result_async()
    result_future.add_done_callback(lambda _f: finished.set())
    heartbeat = Heartbeat(client)
    cancel = None
    started = time.monotonic()
    try:
        while not finished.wait(0.05):
            heartbeat.beat()
            if heartbeat.gone():
                raise DriverUnavailable(
                    f"aborted: {_who(name)} gone: {name} stopped answering (no reply for "
                    f"{heartbeat.silent_for():.1f} s); its goal is abandoned"
                )
            if STOPPING.is_set():
                handle.cancel_goal_async()
                raise DriverUnavailable(f"{name}: abandoned, this node is stopping")
            if cancel is None and should_stop is not None and should_stop():
                cancel = (handle.cancel_goal_async(), time.monotonic())
            if cancel is not None and not cancel[0].done():
                if time.monotonic() - cancel[1] > CANCEL_ACK_TIMEOUT_S:
                    raise DriverUnavailable(
                        f"aborted: {_who(name)} gone: {name} did not acknowledge a cancel "
                        f"within {CANCEL_ACK_TIMEOUT_S} s"
                    )
            if time.monotonic() - started > result_timeout:
                handle.cancel_goal_async()
                raise DriverUnavailable(f"{name}: no result within {result_timeout} s")
    finally:
        heartbeat.forget()
    return result_future.result().result


def call_service(client, request, server_timeout: float, result_timeout: float, hint: str = ""):
    """Call a service and block until its response (from a thread that is not spinning the
    node). DriverUnavailable when the service is missing or gives no response in time."""
    name = client.srv_name
    if not client.wait_for_service(timeout_sec=server_timeout):
        raise DriverUnavailable(f"service {name} not available{hint}")
    done = threading.Event()
    future = client.call_async(request)
    future.add_done_callback(lambda _f: done.set())
    started = time.monotonic()
    while not done.wait(0.05):
        if STOPPING.is_set():
            raise DriverUnavailable(f"{name}: abandoned, this node is stopping")
        if time.monotonic() - started > result_timeout:
            raise DriverUnavailable(f"{name}: no answer within {result_timeout} s")
    return future.result()


class ActionInstrument:
    """Instrument protocol over the driver's actions. Refusals come back as ValueError with
    the driver's message (which names the field and the limit); cancellation of the caller
    is passed on through `should_stop`."""

    def __init__(
        self,
        node,
        limits: ScannerLimits | None = None,
        server_timeout: float = 10.0,
        result_timeout: float = 600.0,
        scan_pair_id: str = "",
    ):
        """scan_pair_id: the pair_id every raster scan is requested with (e.g. "local..." for
        checks the imaging node should not turn into the map)."""
        self.node = node
        self.scan_pair_id = scan_pair_id
        self.limits = limits or ScannerLimits()
        self.server_timeout = server_timeout
        self.result_timeout = result_timeout
        group = ReentrantCallbackGroup()
        self._clients = {
            "scan": SafeActionClient(
                node,
                ScanImage,
                topics.ACTION_SCAN_IMAGE,
                callback_group=group,
                feedback_sub_qos_profile=FEEDBACK,
            ),
            "line": SafeActionClient(
                node,
                LocalScan,
                topics.ACTION_LOCAL_SCAN,
                callback_group=group,
                feedback_sub_qos_profile=FEEDBACK,
            ),
            "move": SafeActionClient(
                node,
                MoveTip,
                topics.ACTION_MOVE_TIP,
                callback_group=group,
                feedback_sub_qos_profile=FEEDBACK,
            ),
            "indent": SafeActionClient(
                node,
                Indent,
                topics.ACTION_INDENT,
                callback_group=group,
                feedback_sub_qos_profile=FEEDBACK,
            ),
        }
        self._commanded: tuple[float, float] | None = None
        self.time = 0.0
        self.last_command = None
        self._lock = threading.Lock()

    # -- plumbing ----------------------------------------------------------------------------
    def _call(self, name: str, goal, should_stop: Callable[[], bool] | None = None):
        result = call_action(
            self._clients[name], goal, self.server_timeout, self.result_timeout, should_stop
        )
        command = getattr(result, "command", None)
        if command is not None and command.header.stamp.sec:
            self.observe_command(command)
        if not result.success and result.message.startswith("refused"):
            raise ValueError(result.message)
        if not result.success and "cancelled" not in result.message:
            raise DriverUnavailable(f"{self._clients[name]._action_name}: {result.message}")
        return result

    def observe_command(self, command) -> bool:
        """A TipCommand the driver executed (ours, from a result, or anyone's, from
        /afm/tip_command): the instrument is now where and when it ended, unless a later
        command is already known. One that no driver can have executed (tip_command_problem)
        is logged and ignored: False."""
        problem = tip_command_problem(command, self.limits)
        if problem is not None:
            self.node.get_logger().error(f"{topics.TIP_COMMAND} message ignored: {problem}")
            return False
        end_time = stamp_seconds(command.header.stamp) + command.duration
        with self._lock:
            if end_time > self.time or self._commanded is None:
                self.time = end_time
                self._commanded = (command.end.x, command.end.y)
                self.last_command = command
        return True

    def rest_at(self, position, time: float) -> None:
        """Declare where and when the instrument was before the first command we know of."""
        with self._lock:
            self._commanded = (float(position[0]), float(position[1]))
            self.time = float(time)

    # -- the Instrument protocol -------------------------------------------------------------
    def commanded_position(self) -> tuple[float, float]:
        if self._commanded is None:
            raise DriverUnavailable(
                "commanded position unknown until the driver has executed a command"
            )
        return self._commanded

    def move_tip(
        self,
        x: float,
        y: float,
        speed: float,
        contact: bool = False,
        should_stop: Callable[[], bool] | None = None,
    ) -> MoveResult:
        validate_move(x, y, speed, self.limits)
        goal = MoveTip.Goal(speed=float(speed), contact=bool(contact))
        goal.target.header.frame_id = FRAME_SCANNER
        goal.target.point.x, goal.target.point.y = float(x), float(y)
        result = self._call("move", goal, should_stop)
        trace = msg_to_force_trace(result.trace) if contact and result.trace.times else None
        return MoveResult(
            end_x=result.commanded_position.x,
            end_y=result.commanded_position.y,
            completed=result.success,
            trace=trace,
        )

    def local_scan(
        self,
        request: LineRequest,
        should_stop: Callable[[], bool] | None = None,
        landmark_id: int = -1,
    ) -> ScanLineData:
        request.validate(self.limits)
        goal = LocalScan.Goal(
            samples=int(request.samples),
            speed=float(request.speed),
            mode=request.mode,
            landmark_id=int(landmark_id),
        )
        goal.start.x, goal.start.y = float(request.start_x), float(request.start_y)
        goal.end.x, goal.end.y = float(request.end_x), float(request.end_y)
        result = self._call("line", goal, should_stop)
        line = msg_to_scan_line(result.line)
        line.complete = result.success
        return line

    def indent(
        self,
        x: float,
        y: float,
        force: float,
        dwell: float,
        should_stop: Callable[[], bool] | None = None,
    ) -> IndentResult:
        validate_indent(x, y, force, dwell, self.limits)
        goal = Indent.Goal(force=float(force), dwell=float(dwell))
        goal.position.x, goal.position.y = float(x), float(y)
        result = self._call("indent", goal, should_stop)
        return IndentResult(
            x=float(x),
            y=float(y),
            trace=msg_to_force_trace(result.trace),
            completed=result.success,
        )

    def raster_scan(
        self, request: ScanRequest, on_line=None, should_stop: Callable[[], bool] | None = None
    ) -> RasterScanData:
        request.validate(self.limits)
        goal = ScanImage.Goal(
            size_x=request.size_x,
            size_y=request.size_y,
            pixels_x=request.pixels_x,
            pixels_y=request.pixels_y,
            scan_angle_deg=request.scan_angle_deg,
            slow_scan_up=request.slow_scan_up,
            line_rate=request.line_rate,
            mode=request.mode,
            pair_id=self.scan_pair_id,
        )
        goal.origin.x, goal.origin.y = float(request.origin_x), float(request.origin_y)
        result = self._call("scan", goal, should_stop)
        scan = msg_to_raster_scan(result.scan)
        scan.complete = result.success
        return scan

    def close(self) -> None:
        for client in self._clients.values():
            client.destroy()
