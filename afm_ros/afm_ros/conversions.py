"""Message <-> core-type conversions shared by the nodes (SI units both sides)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from builtin_interfaces.msg import Time
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from afm_core.instrument import ForceTraceData, RasterScanData, ScanLineData
from afm_core.recording.reader import image_to_array

if TYPE_CHECKING:  # the manipulation package is heavy to import for the nodes without it
    from afm_core.manipulation import Progress, TipEstimate

FRAME_SCANNER = "afm_scanner"
FRAME_TASK = "afm_task"
FRAME_IMAGE = "afm_image"


def array_to_image(array: np.ndarray, header=None) -> Image:
    """2-D float32 array -> sensor_msgs/Image 32FC1 (little-endian, row-major)."""
    array = np.ascontiguousarray(array, dtype="<f4")
    image = Image()
    if header is not None:
        image.header = header
    image.height, image.width = array.shape
    image.encoding = "32FC1"
    image.is_bigendian = 0
    image.step = 4 * image.width
    image.data = array.tobytes()
    return image


def image_msg_to_array(image: Image) -> np.ndarray:
    return image_to_array(image)


def floats(values) -> list:
    return [float(v) for v in values]


def seconds_to_time(seconds: float) -> Time:
    sec, nsec = divmod(int(round(seconds * 1e9)), 1_000_000_000)
    return Time(sec=sec, nanosec=nsec)


def raster_scan_to_msg(scan: RasterScanData, header, scan_id: int = 0, pair_id: str = ""):
    from afm_msgs.msg import RasterScan

    msg = RasterScan()
    msg.header = header
    msg.height = array_to_image(scan.height, header)
    msg.pixel_size_x = float(scan.pixel_size_x)
    msg.pixel_size_y = float(scan.pixel_size_y)
    msg.origin.x, msg.origin.y = float(scan.origin_x), float(scan.origin_y)
    msg.size_x = float(scan.pixel_size_x * scan.height.shape[1])
    msg.size_y = float(scan.pixel_size_y * scan.height.shape[0])
    msg.scan_angle_deg = float(scan.scan_angle_deg)
    msg.slow_scan_up = bool(scan.slow_scan_up)
    msg.line_period = float(scan.line_period)
    msg.line_start_times = [float(t) for t in scan.line_start_times]
    msg.mode = scan.mode
    msg.scan_id = int(scan_id)
    msg.pair_id = pair_id
    return msg


def msg_to_raster_scan(msg) -> RasterScanData:
    """RasterScan -> core type; ValueError naming the field when the message is inconsistent."""
    height = image_msg_to_array(msg.height).astype(np.float32)
    lines = height.shape[0] if msg.scan_angle_deg == 0 else height.shape[1]
    if len(msg.line_start_times) != lines:
        raise ValueError(
            f"line_start_times has {len(msg.line_start_times)} entries, the image has {lines} "
            "lines"
        )
    if not (msg.pixel_size_x > 0 and msg.pixel_size_y > 0):
        raise ValueError(
            f"pixel_size_x/pixel_size_y = {msg.pixel_size_x}/{msg.pixel_size_y}: must be > 0"
        )
    stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
    return RasterScanData(
        height=height,
        pixel_size_x=msg.pixel_size_x,
        pixel_size_y=msg.pixel_size_y,
        origin_x=msg.origin.x,
        origin_y=msg.origin.y,
        scan_angle_deg=msg.scan_angle_deg,
        slow_scan_up=msg.slow_scan_up,
        line_period=msg.line_period,
        line_start_times=np.asarray(msg.line_start_times),
        start_time=stamp,
        mode=msg.mode,
    )


def scan_line_to_msg(line: ScanLineData, header, start, end, landmark_id: int = -1):
    from afm_msgs.msg import ScanLine

    msg = ScanLine(header=header, mode=line.mode, landmark_id=int(landmark_id))
    msg.commanded_start.x, msg.commanded_start.y = float(start[0]), float(start[1])
    msg.commanded_end.x, msg.commanded_end.y = float(end[0]), float(end[1])
    msg.times, msg.x, msg.y = floats(line.times), floats(line.x), floats(line.y)
    msg.height, msg.deflection, msg.amplitude = (
        floats(line.height),
        floats(line.deflection),
        floats(line.amplitude),
    )
    return msg


def force_trace_to_msg(trace: ForceTraceData, header):
    from afm_msgs.msg import ForceTrace

    msg = ForceTrace(
        header=header,
        task=trace.task,
        object_id=int(trace.object_id),
        normal_spring_constant=float(trace.normal_spring_constant),
        lateral_spring_constant=float(trace.lateral_spring_constant),
        sample_rate=float(trace.sample_rate),
    )
    msg.times = floats(trace.times)
    msg.commanded_x, msg.commanded_y, msg.commanded_z = (
        floats(trace.commanded_x),
        floats(trace.commanded_y),
        floats(trace.commanded_z),
    )
    msg.vertical_deflection, msg.lateral_torsion = (
        floats(trace.vertical_deflection),
        floats(trace.lateral_torsion),
    )
    return msg


OBJECT_KINDS = {"sphere": 0, "tube": 1, "rod": 2, "pit": 3, "electrode": 4}


def truth_to_msg(truth: dict, header):
    """Simulator ground truth (afm_core.sim.instrument.SimulatedAfm.truth()) -> GroundTruth."""
    from afm_msgs.msg import GroundTruth, ObjectState

    msg = GroundTruth(header=header, tip_apex_radius=float(truth["tip_apex_radius"]))
    msg.tip_position.x, msg.tip_position.y = map(float, truth["tip_position"])
    msg.commanded_position.x, msg.commanded_position.y = map(float, truth["commanded_position"])
    msg.drift_offset.x, msg.drift_offset.y = map(float, truth["drift_offset"])
    msg.drift_velocity.x, msg.drift_velocity.y = map(float, truth["drift_velocity"])
    for obj in truth["objects"]:
        state = ObjectState(id=int(obj.id), kind=OBJECT_KINDS[obj.kind])
        if obj.kind == "electrode":
            state.position.x, state.position.y = 0.5 * (obj.x0 + obj.x1), 0.5 * (obj.y0 + obj.y1)
            state.position.z = float(obj.thickness)
            state.length = float(obj.x1 - obj.x0)
            state.radius = float(0.5 * (obj.y1 - obj.y0))
        else:
            state.position.x, state.position.y = float(obj.x), float(obj.y)
            state.radius = float(obj.radius)
            state.position.z = float(-obj.depth if obj.kind == "pit" else obj.radius)
            state.length = float(getattr(obj, "length", 0.0))
            state.orientation = float(getattr(obj, "angle", 0.0))
        msg.objects.append(state)
    return msg


LANDMARK_KINDS = {"sphere": 0, "tube": 1, "rod": 2, "pit": 3}


def landmarks_to_msg(marks, header):
    """Core landmarks (afm_core.imaging.landmarks.Landmark) -> LandmarkArray."""
    from afm_msgs.msg import Landmark, LandmarkArray

    array = LandmarkArray(header=header)
    for mark in marks:
        lm = Landmark(
            id=int(mark.id),
            kind=LANDMARK_KINDS[mark.kind],
            radius=float(mark.radius),
            height=float(mark.height),
            length=float(mark.length),
            orientation=float(mark.orientation),
        )
        lm.position.x, lm.position.y, lm.position.z = (
            float(mark.x),
            float(mark.y),
            float(mark.height),
        )
        lm.covariance = [float(v) for v in np.asarray(mark.covariance).ravel()]
        array.landmarks.append(lm)
    return array


def stamp_of(header) -> float:
    return header.stamp.sec + header.stamp.nanosec * 1e-9


def newer_landmarks(array, current_stamp: float | None) -> bool:
    """Whether a LandmarkArray replaces what a node holds. Several nodes publish landmark maps
    (imaging after a scan, the nano-hand after moving a particle), latched: a node joining late
    may get them in any order, so the newest map by its header stamp wins."""
    return current_stamp is None or stamp_of(array.header) >= current_stamp


def wait_until(condition, timeout: float) -> bool:
    """Poll condition() until it is true or `timeout` s have passed; its last value."""
    deadline = time.monotonic() + timeout
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.05)
    return bool(condition())


def wait_for_landmarks(current, timeout: float = 5.0) -> dict:
    """The landmarks known now, or, when none are yet, those that arrive within `timeout` s (a
    latched map reaches a node a moment after it is published, later under load)."""
    wait_until(current, timeout)
    return dict(current())


def msg_to_landmarks(array) -> list:
    """LandmarkArray -> core landmarks; ValueError naming the landmark and the field when the
    map cannot be one (another program's map is checked as our imaging node's: a duplicate id
    was silently collapsed to its last entry, and a covariance that is no covariance reached
    the planner's plans)."""
    from afm_core.imaging.landmarks import Landmark

    if array.header.frame_id != FRAME_TASK:
        raise ValueError(
            f"header.frame_id={array.header.frame_id!r}: landmarks are in {FRAME_TASK!r}"
        )
    kinds = {v: k for k, v in LANDMARK_KINDS.items()}
    marks, seen = [], set()
    for lm in array.landmarks:
        values = [lm.position.x, lm.position.y, lm.radius, *lm.covariance]
        if not np.all(np.isfinite(values)):
            raise ValueError(f"landmark {lm.id}: position, radius and covariance must be finite")
        if lm.kind not in kinds:
            raise ValueError(
                f"landmark {lm.id}: kind={lm.kind} unknown (expected one of {sorted(kinds)})"
            )
        if lm.id in seen:
            raise ValueError(f"landmark {lm.id}: the id occurs twice in the map")
        seen.add(lm.id)
        if not (lm.radius > 0 and lm.length >= 0 and math.isfinite(lm.length)):
            raise ValueError(
                f"landmark {lm.id}: radius={lm.radius} m must be > 0 and length={lm.length} m "
                "finite and >= 0"
            )
        check_covariance(f"landmark {lm.id}: covariance", lm.covariance)
        marks.append(
            Landmark(
                id=int(lm.id),
                kind=kinds[lm.kind],
                x=lm.position.x,
                y=lm.position.y,
                covariance=np.asarray(lm.covariance, float).reshape(2, 2),
                radius=lm.radius,
                height=lm.height,
                length=lm.length,
                orientation=lm.orientation,
            )
        )
    return marks


def check_covariance(name: str, values) -> None:
    """ValueError naming `name` unless the 4 values (row-major 2x2, m^2) are a covariance:
    symmetric and positive semi-definite (to rounding)."""
    c = np.asarray(values, float).reshape(2, 2)
    scale = max(abs(c[0, 0]), abs(c[1, 1]), 1e-300)
    if abs(c[0, 1] - c[1, 0]) > 1e-9 * scale:
        raise ValueError(f"{name}={list(values)}: not symmetric")
    if np.linalg.eigvalsh(0.5 * (c + c.T)).min() < -1e-9 * scale:
        raise ValueError(f"{name}={list(values)}: not positive semi-definite (m^2)")


def pose_to_mean_cov(pose_msg) -> tuple[np.ndarray, np.ndarray]:
    """PoseWithCovarianceStamped -> (x, y) mean and its 2x2 covariance (m, m^2)."""
    p = pose_msg.pose.pose.position
    c = pose_msg.pose.covariance
    return np.array([p.x, p.y]), np.array([[c[0], c[1]], [c[6], c[7]]])


def mean_cov_to_pose(mean, covariance, header, z_variance: float = 0.0):
    """(x, y) and 2x2 covariance -> PoseWithCovarianceStamped; unknowns (z, rotations) get a
    variance so large a consumer treats them as unestimated (robot_localization's habit)."""
    from geometry_msgs.msg import PoseWithCovarianceStamped

    msg = PoseWithCovarianceStamped(header=header)
    msg.pose.pose.position.x, msg.pose.pose.position.y = float(mean[0]), float(mean[1])
    msg.pose.pose.orientation.w = 1.0
    cov = [0.0] * 36
    c = np.asarray(covariance, float)
    cov[0], cov[1], cov[6], cov[7] = float(c[0, 0]), float(c[0, 1]), float(c[1, 0]), float(c[1, 1])
    cov[14] = float(z_variance) if z_variance > 0 else 1e6
    cov[21] = cov[28] = cov[35] = 1e6
    msg.pose.covariance = cov
    return msg


def xy_to_point(xy):
    """(x, y) -> geometry_msgs/Point (z = 0)."""
    from geometry_msgs.msg import Point

    return Point(x=float(xy[0]), y=float(xy[1]))


@dataclass(frozen=True)
class PoseEstimate:
    """A tip estimate (the fields of afm_core.manipulation.TipEstimate) that keeps the pose
    message it came from: converted back, it is that message, exact to the nanosecond of its
    stamp (float seconds of a wall-clock stamp are not)."""

    mean: np.ndarray  # (2,) m
    covariance: np.ndarray  # (2, 2) m^2
    time: float  # s, the stamp
    message: object


def pose_to_tip_estimate(pose_msg) -> PoseEstimate:
    """PoseWithCovarianceStamped -> the core's tip estimate (mean, 2x2 covariance, stamp in s)."""
    mean, covariance = pose_to_mean_cov(pose_msg)
    return PoseEstimate(mean, covariance, stamp_of(pose_msg.header), pose_msg)


def tip_estimate_to_pose(estimate: TipEstimate):
    """The core's tip estimate -> PoseWithCovarianceStamped in the task frame (the message it
    came from, if it came from one)."""
    if isinstance(estimate, PoseEstimate):
        return estimate.message
    header = Header(stamp=seconds_to_time(estimate.time), frame_id=FRAME_TASK)
    return mean_cov_to_pose(estimate.mean, estimate.covariance, header)


def push_plan_to_msg(plan, tip_cov, particle_id: int, time: float):
    """A push plan (afm_core.manipulation.PushPlan) as a PlannedPath: each stroke's start reached
    lifted ("lift"), its end in contact ("push") or lifted; the tip's covariance at the start on
    every waypoint."""
    from geometry_msgs.msg import PoseStamped

    from afm_msgs.msg import PlannedPath

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


def progress_to_push_feedback(progress: Progress):
    """A push's progress report (afm_core.manipulation.Progress) -> PushParticle feedback."""
    from afm_msgs.action import PushParticle

    feedback = PushParticle.Feedback(
        step=progress.step,
        steps_total=progress.steps_total,
        phase=progress.phase,
        particle_estimate=xy_to_point(progress.particle_estimate),
        particle_covariance=list(progress.particle_covariance.ravel()),
        peak_lateral_force=progress.peak_lateral_force,
        peak_normal_force=progress.peak_normal_force,
        note=progress.note,
    )
    if progress.tip is not None:
        feedback.tip_pose = tip_estimate_to_pose(progress.tip)
    return feedback


def progress_to_assemble_feedback(progress: Progress):
    """An assembly's progress report -> Assemble feedback."""
    from afm_msgs.action import Assemble

    return Assemble.Feedback(
        index=progress.index,
        particle_id=progress.particle_id,
        step=progress.step,
        phase=progress.phase,
        particle_estimate=xy_to_point(progress.particle_estimate),
    )


def outcome_to_result(outcome, result):
    """A PushResult into a PushParticle result, an AssemblyResult into an Assemble result."""
    if hasattr(result, "order"):
        result.order, result.errors = outcome.order, [float(e) for e in outcome.errors]
        result.achieved = [xy_to_point(xy) for xy in outcome.achieved]
        result.duration = float(sum(push.cost.duration for push in outcome.pushes))
    else:
        result.achieved = xy_to_point(outcome.achieved)
        result.error, result.steps = outcome.error, outcome.steps
        if outcome.verdict is not None:
            result.error_sigma = float(outcome.verdict.sigma)
            result.verdict = outcome.verdict.verdict
        cost = outcome.cost
        result.duration, result.lines = float(cost.duration), int(cost.lines)
        result.observations, result.slid = int(cost.observations), float(cost.slid)
        result.achieved_angle = float(outcome.achieved_angle)
        result.angle_error = float(outcome.angle_error)
    result.success, result.message = outcome.success, outcome.message
    return result
