"""A recorded session as an ordered stream of operations (command + its measurement).

The driver node publishes, for every action it executes, a TipCommand on /afm/tip_command
(stamped with the instrument time at which the command started) and then the measurement:
a RasterScan on /afm/scan, a ScanLine on /afm/scan_line or a ForceTrace on /afm/force_trace
(a lifted move has none), and in simulation a GroundTruth on /afm/ground_truth. This module

- writes exactly those messages from any core `Instrument`, without ROS
  (`RecordingInstrument`, `SessionWriter`): CDR is encoded by mcap_ros2 from the full ros2msg
  schema text, the container is our `RecordingWriter` (`.part` until closed, never
  overwrites, rosbag2's metadata and QoS), so our RecordingReader, the ReplayInstrument,
  rosbag2 and Foxglove read it;
- reads a recording back (ours, or any MCAP with ros2msg schemas on the same topics, such as
  rosbag2 writes) as `Operation`s in command order (`read_operations`), streaming: at most a
  few commands and their data messages are held at a time.

Units are SI throughout (m, s, N, m/s). Times of read operations are seconds since the first
command of the recording, on the recording's instrument clock.
"""

from __future__ import annotations

import math
import os
import time as wall_time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Union

import numpy as np
from mcap_ros2._dynamic import serialize_dynamic

from afm_core.instrument import (
    ForceTraceData,
    IndentResult,
    LineRequest,
    MoveResult,
    RasterScanData,
    ScanLineData,
    ScanRequest,
)
from afm_core.recording import QosDescription, RecordingError, RecordingReader, RecordingWriter
from afm_core.recording.definitions import full_message_definition
from afm_core.recording.qos import RMW_DURATION_INFINITE_NS
from afm_core.recording.reader import image_to_array

# -- the driver's vocabulary ---------------------------------------------------------------
TIP_COMMAND = "/afm/tip_command"
SCAN = "/afm/scan"
SCAN_LINE = "/afm/scan_line"
FORCE_TRACE = "/afm/force_trace"
GROUND_TRUTH = "/afm/ground_truth"

TYPES = {
    TIP_COMMAND: "afm_msgs/msg/TipCommand",
    SCAN: "afm_msgs/msg/RasterScan",
    SCAN_LINE: "afm_msgs/msg/ScanLine",
    FORCE_TRACE: "afm_msgs/msg/ForceTrace",
    GROUND_TRUTH: "afm_msgs/msg/GroundTruth",
}


# The QoS the driver offers (afm_ros.qos_profiles), in the form our recorder stores what it
# discovers (history and depth are not sent over the wire: "unknown", 0; durations infinite),
# so a replay republishes each topic as the driver did: commands and scans reliable and
# latched, streams best effort (sensor data), truth reliable and latched.
def _offered(reliability: str, durability: str) -> QosDescription:
    return QosDescription(
        history="unknown",
        depth=0,
        reliability=reliability,
        durability=durability,
        liveliness="automatic",
        deadline_ns=RMW_DURATION_INFINITE_NS,
        lifespan_ns=RMW_DURATION_INFINITE_NS,
        liveliness_lease_duration_ns=RMW_DURATION_INFINITE_NS,
    )


OFFERED_QOS = {
    TIP_COMMAND: _offered("reliable", "transient_local"),
    SCAN: _offered("reliable", "transient_local"),
    SCAN_LINE: _offered("best_effort", "volatile"),
    FORCE_TRACE: _offered("best_effort", "volatile"),
    GROUND_TRUTH: _offered("reliable", "transient_local"),
}

# TipCommand.kind constants (afm_msgs/msg/TipCommand.msg) <-> Operation.kind
KIND_NAMES = {0: "move", 1: "scan_line", 2: "raster", 3: "push", 4: "indent"}
KIND_CODES = {name: code for code, name in KIND_NAMES.items()}
# where each kind's measurement is published, and the ForceTrace.task it carries
DATA_TOPIC = {"scan_line": SCAN_LINE, "raster": SCAN, "push": FORCE_TRACE, "indent": FORCE_TRACE}
TRACE_TASK = {"push": "push", "indent": "indent"}
OBJECT_KINDS = {"sphere": 0, "tube": 1, "rod": 2, "pit": 3, "electrode": 4}  # ObjectState.kind

FRAME_SCANNER = "afm_scanner"
FRAME_TASK = "afm_task"

# Matching a data message to its command. Geometry as the ReplayInstrument matches requests
# (1 nm); time: the driver stamps epoch + instrument time as a float, which on a wall-clock
# epoch (~1.7e9 s) resolves ~0.24 us, so a data stamp may fall that far outside its command.
MATCH_TOLERANCE = 1e-9  # m
TIME_SLACK_NS = 1_000  # ns
# A command's measurement is published right after it, before the next command starts (the
# driver runs one motion at a time). Topics may still arrive out of order in a recording
# (different QoS, different subscriptions), so a measurement is awaited until this many later
# commands have arrived; then it is missing. This is also what bounds the memory held.
LOOKAHEAD_COMMANDS = 4
MAX_UNMATCHED_DATA = 8  # data messages held while their command has not arrived
TIME_QUANTUM = 1e-9  # s, the stamps' resolution; reconstructed dwells are rounded to it

Request = Union[ScanRequest, LineRequest, dict]
Data = Union[RasterScanData, ScanLineData, ForceTraceData, None]


class SessionError(RecordingError, ValueError):
    """A recording cannot be read as a session (or written as one); the message names the
    file, the topic and the problem."""


@dataclass
class Operation:
    """One command the instrument executed, with what it measured.

    kind: "move", "push", "scan_line", "raster" or "indent".
    start_time: s when the command started, on the session's instrument clock (read and
        simulated operations: relative to the recording's first command).
    start, end: m, commanded scanner-frame positions (a scan line: its commanded ends; an
        indent: where it indents; a move, push or raster: where the tip was commanded before
        and after).
    speed: m/s along the path (a raster: its path length / duration, as the driver reports it;
        an indent: 0). duration: s the command took, including any approach move.
    request: what reproduces it: a ScanRequest, a LineRequest, or a dict
        {x, y, speed, contact} (move, push) / {x, y, force, dwell} (indent), in m, m/s, N, s.
    data: the measurement (RasterScanData, ScanLineData, ForceTraceData; None for a move);
        its start_time is on the same clock as the operation's.
    landmark_id: the landmark a scan line observes (-1: none); pair_id: a raster's pair.
    lag: s, simulated operations only: how much later than recorded the simulator could start it.
    truth: simulated operations only: the simulator's ground truth after the operation.
    """

    index: int
    kind: str
    start_time: float
    start: tuple[float, float]
    end: tuple[float, float]
    speed: float
    duration: float
    request: Request = field(repr=False)
    data: Data = field(repr=False)
    landmark_id: int = -1
    pair_id: str = ""
    lag: float = 0.0
    truth: dict | None = field(default=None, repr=False)

    @property
    def end_time(self) -> float:
        return self.start_time + self.duration


def operation_from_call(
    index: int,
    kind: str,
    request: Request,
    data: Data,
    *,
    start_time: float,
    end_time: float,
    start_position: tuple[float, float],
    end_position: tuple[float, float],
    landmark_id: int = -1,
    pair_id: str = "",
) -> Operation:
    """The Operation (= the TipCommand fields) for one instrument call, filled as the driver
    fills its TipCommand: start/end are where the scanner was commanded before and after,
    except a scan line (its commanded ends) and an indent (its position); the speed is the
    requested one, a raster's path length / duration, an indent's 0."""
    duration = end_time - start_time
    start, end = tuple(map(float, start_position)), tuple(map(float, end_position))
    if kind in ("move", "push"):
        speed = float(request["speed"])
    elif kind == "scan_line":
        start, end, speed = (
            (request.start_x, request.start_y),
            (request.end_x, request.end_y),
            request.speed,
        )
    elif kind == "raster":
        fast_size = request.size_x if request.scan_angle_deg == 0.0 else request.size_y
        path_length = 2 * fast_size * request.lines + math.dist(
            start, (request.origin_x, request.origin_y)
        )
        speed = path_length / duration if duration > 0 else 0.0
    elif kind == "indent":
        start = end = (float(request["x"]), float(request["y"]))
        speed = 0.0
    else:
        raise ValueError(f"kind={kind!r}: expected one of {sorted(KIND_CODES)}")
    return Operation(
        index=index,
        kind=kind,
        start_time=float(start_time),
        start=start,
        end=end,
        speed=float(speed),
        duration=float(duration),
        request=request,
        data=data,
        landmark_id=int(landmark_id),
        pair_id=str(pair_id),
    )


# ------------------------------------------------------------------------------------------
# writing
# ------------------------------------------------------------------------------------------
def _floats(values) -> list:
    """float64[] field value (mcap_ros2 encodes lists)."""
    return np.asarray(values, dtype=np.float64).tolist()


def _point(x: float, y: float) -> dict:
    return {"x": float(x), "y": float(y), "z": 0.0}


class SessionWriter:
    """Writes operations as the driver publishes them, to a new MCAP recording.

    Stamps are `epoch_ns` + the operation's times (the driver's epoch is the wall time at its
    start: the default here too), in integer nanoseconds so nothing is lost to float rounding.
    Each message is logged at the end of its operation, when the driver publishes it. The file
    is `path.part` until `close()` names it `path`; an existing `path` is refused.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        epoch_ns: int | None = None,
        truth: bool = True,
        compression: str = "zstd",
        chunk_size: int = 4 * 1024 * 1024,
    ):
        self.epoch_ns = wall_time.time_ns() if epoch_ns is None else int(epoch_ns)
        topics = [t for t in TYPES if truth or t != GROUND_TRUTH]
        # schemas first: a workspace without afm_msgs fails here, before any file exists
        definitions = {topic: full_message_definition(TYPES[topic]) for topic in topics}
        self._encoders = {
            topic: serialize_dynamic(TYPES[topic], definitions[topic])[TYPES[topic]]
            for topic in topics
        }
        try:
            self._writer = RecordingWriter(path, compression=compression, chunk_size=chunk_size)
        except RecordingError as exc:
            raise SessionError(str(exc)) from exc
        self.path = self._writer.path
        self._channels = {
            topic: self._writer.add_channel(
                topic, TYPES[topic], [OFFERED_QOS[topic]], definition=definitions[topic]
            )
            for topic in topics
        }
        self._last_log_ns = 0
        self.scan_count = 0

    # -- messages ---------------------------------------------------------------------------
    def stamp_ns(self, seconds: float) -> int:
        return self.epoch_ns + int(round(seconds * 1e9))

    def _header(self, seconds: float, frame: str = FRAME_SCANNER) -> dict:
        sec, nanosec = divmod(self.stamp_ns(seconds), 1_000_000_000)
        return {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": frame}

    def _write(self, topic: str, message: dict, log_seconds: float) -> None:
        # a recorder logs arrival times, which never go backwards
        log_ns = max(self.stamp_ns(log_seconds), self._last_log_ns)
        self._last_log_ns = log_ns
        self._writer.write(self._channels[topic], log_ns, self._encoders[topic](message))

    def write_operation(self, op: Operation) -> None:
        """The TipCommand, then the measurement if the operation has one (the driver publishes
        no measurement for a cancelled scan, line or indent: pass data=None then)."""
        if op.kind not in KIND_CODES:
            raise SessionError(
                f"{self.path}: operation {op.index}: kind={op.kind!r}, expected one of "
                f"{sorted(KIND_CODES)}"
            )
        published = op.start_time + op.duration
        nan3 = [math.nan] * 3
        self._write(
            TIP_COMMAND,
            {
                "header": self._header(op.start_time),
                "kind": KIND_CODES[op.kind],
                "start": _point(*op.start),
                "end": _point(*op.end),
                "speed": float(op.speed),
                "duration": float(op.duration),
                "start_voltage": nan3,
                "end_voltage": nan3,
            },
            published,
        )
        if op.data is None:
            return
        if op.kind == "raster":
            self.scan_count += 1
            self._write(SCAN, self.raster_message(op.data, self.scan_count, op.pair_id), published)
        elif op.kind == "scan_line":
            self._write(
                SCAN_LINE, self.line_message(op.data, op.start, op.end, op.landmark_id), published
            )
        elif op.kind in ("push", "indent"):
            self._write(FORCE_TRACE, self.trace_message(op.data), published)

    def raster_message(self, scan: RasterScanData, scan_id: int, pair_id: str = "") -> dict:
        """afm_ros.conversions.raster_scan_to_msg, without rclpy."""
        header = self._header(scan.start_time)
        height = np.ascontiguousarray(scan.height, dtype="<f4")
        rows, columns = height.shape
        image = {
            "header": header,
            "height": rows,
            "width": columns,
            "encoding": "32FC1",
            "is_bigendian": 0,
            "step": 4 * columns,
            "data": height.tobytes(),
        }
        return {
            "header": header,
            "height": image,
            "pixel_size_x": float(scan.pixel_size_x),
            "pixel_size_y": float(scan.pixel_size_y),
            "origin": _point(scan.origin_x, scan.origin_y),
            "size_x": float(scan.pixel_size_x * columns),
            "size_y": float(scan.pixel_size_y * rows),
            "scan_angle_deg": float(scan.scan_angle_deg),
            "slow_scan_up": bool(scan.slow_scan_up),
            "line_period": float(scan.line_period),
            "line_start_times": _floats(scan.line_start_times),
            "mode": scan.mode,
            "scan_id": int(scan_id),
            "pair_id": str(pair_id),
        }

    def line_message(self, line: ScanLineData, start, end, landmark_id: int = -1) -> dict:
        """afm_ros.conversions.scan_line_to_msg, without rclpy."""
        return {
            "header": self._header(line.start_time),
            "commanded_start": _point(*start),
            "commanded_end": _point(*end),
            "times": _floats(line.times),
            "x": _floats(line.x),
            "y": _floats(line.y),
            "height": _floats(line.height),
            "deflection": _floats(line.deflection),
            "amplitude": _floats(line.amplitude),
            "mode": line.mode,
            "landmark_id": int(landmark_id),
        }

    def trace_message(self, trace: ForceTraceData) -> dict:
        """afm_ros.conversions.force_trace_to_msg, without rclpy."""
        return {
            "header": self._header(trace.start_time),
            "times": _floats(trace.times),
            "commanded_x": _floats(trace.commanded_x),
            "commanded_y": _floats(trace.commanded_y),
            "commanded_z": _floats(trace.commanded_z),
            "vertical_deflection": _floats(trace.vertical_deflection),
            "lateral_torsion": _floats(trace.lateral_torsion),
            "normal_spring_constant": float(trace.normal_spring_constant),
            "lateral_spring_constant": float(trace.lateral_spring_constant),
            "sample_rate": float(trace.sample_rate),
            "task": trace.task,
            "object_id": int(trace.object_id),
        }

    def write_truth(self, truth: dict) -> None:
        """A GroundTruth (afm_ros.conversions.truth_to_msg) stamped and logged at truth['time']."""
        if GROUND_TRUTH not in self._channels:
            raise SessionError(f"{self.path}: opened with truth=False; no {GROUND_TRUTH} channel")
        objects = []
        for obj in truth["objects"]:
            state = {"id": int(obj.id), "kind": OBJECT_KINDS[obj.kind]}
            if obj.kind == "electrode":
                state.update(
                    position={
                        "x": 0.5 * (obj.x0 + obj.x1),
                        "y": 0.5 * (obj.y0 + obj.y1),
                        "z": float(obj.thickness),
                    },
                    length=float(obj.x1 - obj.x0),
                    radius=float(0.5 * (obj.y1 - obj.y0)),
                    orientation=0.0,
                )
            else:
                state.update(
                    position={
                        "x": float(obj.x),
                        "y": float(obj.y),
                        "z": float(-obj.depth if obj.kind == "pit" else obj.radius),
                    },
                    radius=float(obj.radius),
                    length=float(getattr(obj, "length", 0.0)),
                    orientation=float(getattr(obj, "angle", 0.0)),
                )
            objects.append(state)
        seconds = float(truth["time"])
        vector = lambda v: {"x": float(v[0]), "y": float(v[1]), "z": 0.0}  # noqa: E731
        self._write(
            GROUND_TRUTH,
            {
                "header": self._header(seconds, FRAME_TASK),
                "tip_position": _point(*truth["tip_position"]),
                "commanded_position": _point(*truth["commanded_position"]),
                "drift_offset": vector(truth["drift_offset"]),
                "drift_velocity": vector(truth["drift_velocity"]),
                "tip_apex_radius": float(truth["tip_apex_radius"]),
                "objects": objects,
            },
            seconds,
        )

    # -- closing ----------------------------------------------------------------------------
    @property
    def message_count(self) -> int:
        return self._writer.message_count

    @property
    def closed(self) -> bool:
        return self._writer.closed

    def close(self) -> Path:
        """Finish the file (summary, indexes) and give it its final name."""
        return self._writer.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class RecordingInstrument:
    """Any core Instrument, with every call recorded as the driver would publish it.

    Each move_tip / local_scan / raster_scan / indent is forwarded unchanged and its result
    returned unchanged; then its TipCommand and measurement are written, and, when the
    instrument has `truth()` and truth=True, a GroundTruth (also one at the start, as the
    driver publishes on start-up). `hold` and every other attribute (limits, time, truth,
    commanded_position, feed_forward_enabled, sample, ...) pass through to the instrument,
    assignments too. `close()` finishes the recording (it is `path.part` until then) and
    closes the instrument.
    """

    _OWN = frozenset({"_instrument", "_writer", "_truth", "_commands"})

    def __init__(
        self,
        instrument,
        path: str | os.PathLike,
        truth: bool = True,
        *,
        epoch_ns: int | None = None,
        compression: str = "zstd",
        chunk_size: int = 4 * 1024 * 1024,
    ):
        first_truth = None
        if truth and callable(getattr(instrument, "truth", None)):
            try:  # the driver publishes the truth at start-up: so do we, first
                first_truth = instrument.truth()
            except (ValueError, NotImplementedError):  # e.g. a replayed session has none
                first_truth = None
        object.__setattr__(self, "_instrument", instrument)
        object.__setattr__(self, "_commands", 0)
        object.__setattr__(self, "_truth", first_truth is not None)
        object.__setattr__(
            self,
            "_writer",
            SessionWriter(
                path,
                epoch_ns=epoch_ns,
                truth=self._truth,
                compression=compression,
                chunk_size=chunk_size,
            ),
        )
        if first_truth is not None:
            self._writer.write_truth(first_truth)

    # -- pass-through -------------------------------------------------------------------------
    def __getattr__(self, name):
        # only called for what this class does not define: the instrument's own attributes
        if name in RecordingInstrument._OWN:
            raise AttributeError(name)
        return getattr(self._instrument, name)

    def __setattr__(self, name, value):
        if name in RecordingInstrument._OWN:
            object.__setattr__(self, name, value)
        else:  # e.g. feed_forward_enabled: it must reach the instrument, not shadow it here
            setattr(self._instrument, name, value)

    @property
    def instrument(self):
        return self._instrument

    @property
    def path(self) -> Path:
        return self._writer.path

    def hold(self, seconds: float) -> None:
        """Time passes with the command held; no command is published (the next command's
        start time shows the gap)."""
        self._instrument.hold(seconds)

    # -- recorded calls -----------------------------------------------------------------------
    def _record(
        self, kind, request, data, start_time, start_position, end_position=None, **ids
    ) -> None:
        end = self._instrument.commanded_position() if end_position is None else end_position
        op = operation_from_call(
            self._commands,
            kind,
            request,
            data,
            start_time=start_time,
            end_time=self._instrument.time,
            start_position=start_position,
            end_position=end,
            **ids,
        )
        self._writer.write_operation(op)
        self._commands += 1
        self._write_truth()

    def _write_truth(self) -> None:
        if self._truth:
            self._writer.write_truth(self._instrument.truth())

    def _before(self):
        """Time and commanded position before a call; refuses before anything moves when the
        recording is closed (nothing may run unrecorded)."""
        if self._writer.closed:
            raise SessionError(f"{self._writer.path}: the recording is closed")
        return self._instrument.time, self._instrument.commanded_position()

    def raster_scan(
        self, request: ScanRequest, on_line=None, should_stop=None, *, pair_id: str = ""
    ) -> RasterScanData:
        t0, p0 = self._before()
        scan = self._instrument.raster_scan(request, on_line=on_line, should_stop=should_stop)
        self._record("raster", request, scan if scan.complete else None, t0, p0, pair_id=pair_id)
        return scan

    def local_scan(
        self, request: LineRequest, should_stop=None, *, landmark_id: int = -1
    ) -> ScanLineData:
        t0, p0 = self._before()
        line = self._instrument.local_scan(request, should_stop=should_stop)
        self._record(
            "scan_line", request, line if line.complete else None, t0, p0, landmark_id=landmark_id
        )
        return line

    def move_tip(
        self, x: float, y: float, speed: float, contact: bool = False, should_stop=None
    ) -> MoveResult:
        t0, p0 = self._before()
        move = self._instrument.move_tip(x, y, speed, contact, should_stop=should_stop)
        request = {"x": float(x), "y": float(y), "speed": float(speed), "contact": bool(contact)}
        self._record(
            "push" if contact else "move",
            request,
            move.trace if contact else None,
            t0,
            p0,
            end_position=(move.end_x, move.end_y),
        )
        return move

    def indent(
        self, x: float, y: float, force: float, dwell: float, should_stop=None
    ) -> IndentResult:
        t0, p0 = self._before()
        result = self._instrument.indent(x, y, force, dwell, should_stop=should_stop)
        request = {
            "x": float(result.x),
            "y": float(result.y),
            "force": float(force),
            "dwell": float(dwell),
        }
        self._record("indent", request, result.trace if result.completed else None, t0, p0)
        return result

    # -- closing ------------------------------------------------------------------------------
    def close(self) -> None:
        try:
            if not self._writer.closed:
                self._writer.close()
        finally:
            self._instrument.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# ------------------------------------------------------------------------------------------
# reading
# ------------------------------------------------------------------------------------------
def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _close(a: float, b: float, tol: float = MATCH_TOLERANCE) -> bool:
    return abs(a - b) <= tol


def indent_request_from_trace(trace: ForceTraceData) -> dict:
    """The force (N) and dwell (s) an indentation trace was made with.

    The simulator's trace (SimulatedAfm._indent_trace) is a trapezoid in time: a linear
    approach over approach_time, the dwell at full load, a linear retract over retract_time,
    sampled at evenly spaced times from 0 to approach + dwell + retract; commanded_z follows
    the trapezoid exactly (no noise) and vertical_deflection follows force / k_n times it,
    plus noise. So:
    - shape s(t) = commanded_z / max(commanded_z) is known exactly, and the approach time is
      t / s(t) for any sample on the rising ramp (the retract time likewise from the end);
      dwell = duration - approach - retract, rounded to the stamps' 1 ns;
    - force = k_n x the least-squares plateau level of the deflection on that shape,
      sum(d s) / sum(s^2). Not the peak deflection: the peak of ~N noisy plateau samples is
      biased high by ~2.5 sigma; the fit's error is sigma k_n / sqrt(sum s^2) (~1e-12 N for the
      simulator's 200 samples, 0.05 nm noise, 0.2 N/m).
    Without a usable commanded_z (a real instrument may not record it), the plateau is where
    the deflection is within 5 % of its peak: force = k_n x its mean, dwell = its time span
    (to a sample spacing).
    """
    t = np.asarray(trace.times, float)
    d = np.asarray(trace.vertical_deflection, float)
    z = np.asarray(trace.commanded_z, float)
    k = float(trace.normal_spring_constant)
    if len(t) < 2:
        raise ValueError(
            f"indentation trace of {len(t)} samples: too short to tell force and dwell"
        )
    duration = float(t[-1] - t[0])
    z_max = float(np.max(z)) if len(z) == len(t) else 0.0
    if z_max > 0 and np.all(np.isfinite(z)):
        shape = z / z_max
        peak = int(np.argmax(shape))
        last_peak = len(shape) - 1 - int(np.argmax(shape[::-1]))
        rising = [i for i in range(1, peak) if 0.0 < shape[i] < 1.0]
        falling = [i for i in range(last_peak + 1, len(t) - 1) if 0.0 < shape[i] < 1.0]
        if rising and falling:
            i, j = rising[-1], falling[0]  # the samples nearest full load: least rounding
            approach = (t[i] - t[0]) / shape[i]
            retract = (t[-1] - t[j]) / shape[j]
            dwell = duration - approach - retract
        else:  # ramps shorter than a sample spacing
            dwell = float(t[last_peak] - t[peak])
        level = float(np.dot(d, shape) / np.dot(shape, shape))
    else:
        peak_value = float(np.max(d))
        plateau = np.flatnonzero(d >= 0.95 * peak_value)
        level = float(np.mean(d[plateau]))
        dwell = float(t[plateau[-1]] - t[plateau[0]])
    dwell = max(0.0, round(dwell / TIME_QUANTUM) * TIME_QUANTUM)
    x, y = float(trace.commanded_x[0]), float(trace.commanded_y[0])
    return {"x": x, "y": y, "force": level * k, "dwell": dwell}


@dataclass
class _Command:
    index: int
    kind: str
    stamp_ns: int
    duration_ns: int
    message: object
    data: object = None  # the decoded data message, once matched
    data_topic: str = ""

    @property
    def needs_data(self) -> bool:
        return self.kind != "move"

    def window_contains(self, stamp_ns: int) -> bool:
        return (
            self.stamp_ns - TIME_SLACK_NS
            <= stamp_ns
            <= self.stamp_ns + self.duration_ns + TIME_SLACK_NS
        )


def _geometry_matches(command: _Command, topic: str, msg) -> bool:
    """Whether a data message can be this command's measurement (kind, geometry)."""
    cmd = command.message
    if DATA_TOPIC.get(command.kind) != topic:
        return False
    if command.kind == "scan_line":
        return (
            _close(msg.commanded_start.x, cmd.start.x)
            and _close(msg.commanded_start.y, cmd.start.y)
            and _close(msg.commanded_end.x, cmd.end.x)
            and _close(msg.commanded_end.y, cmd.end.y)
        )
    if command.kind == "raster":
        # the scan ends with the tip on its last line, inside the area (a pixel of margin)
        margin_x = abs(msg.pixel_size_x) + MATCH_TOLERANCE
        margin_y = abs(msg.pixel_size_y) + MATCH_TOLERANCE
        return (
            msg.origin.x - margin_x <= cmd.end.x <= msg.origin.x + msg.size_x + margin_x
            and msg.origin.y - margin_y <= cmd.end.y <= msg.origin.y + msg.size_y + margin_y
        )
    if msg.task != TRACE_TASK[command.kind]:
        return False
    if not len(msg.commanded_x):
        return True
    if command.kind == "push":  # the contact path ends where the command ended
        return _close(msg.commanded_x[-1], cmd.end.x) and _close(msg.commanded_y[-1], cmd.end.y)
    return _close(msg.commanded_x[0], cmd.start.x) and _close(msg.commanded_y[0], cmd.start.y)


class OperationStream:
    """Iterator over a recording's Operations in command order (see read_operations).

    Holds the open file: use it as a context manager or call close() when stopping early
    (it closes itself once exhausted)."""

    def __init__(self, path: str | os.PathLike, missing_data: str = "error"):
        if missing_data not in ("error", "skip"):
            raise ValueError(f"missing_data={missing_data!r}: expected 'error' or 'skip'")
        self.path = Path(path)
        self.missing_data = missing_data
        try:
            self._reader = RecordingReader(self.path)
        except RecordingError as exc:
            raise SessionError(str(exc)) from exc
        try:
            recorded = self._reader.topics()
            if TIP_COMMAND not in recorded:
                raise SessionError(
                    f"{self.path}: no {TIP_COMMAND} topic, so the commands cannot be told; "
                    f"recorded: {sorted(recorded)}"
                )
            for topic, info in recorded.items():
                if topic in TYPES and info.type not in (
                    TYPES[topic],
                    TYPES[topic].replace("/msg/", "/"),
                ):
                    raise SessionError(
                        f"{self.path}: topic {topic} has type {info.type!r}, expected {TYPES[topic]!r}"
                    )
                if topic in TYPES and info.schema_encoding != "ros2msg":
                    raise SessionError(
                        f"{self.path}: topic {topic} has schema encoding {info.schema_encoding!r}, "
                        "expected 'ros2msg' (as rosbag2 writes)"
                    )
        except Exception:
            self._reader.close()
            raise
        self.topics = [t for t in (TIP_COMMAND, SCAN, SCAN_LINE, FORCE_TRACE) if t in recorded]
        self._generator = self._operations()

    def __iter__(self):
        return self

    def __next__(self) -> Operation:
        return next(self._generator)

    def close(self) -> None:
        self._generator.close()
        self._reader.close()

    def __del__(self):
        # an unstarted generator's `finally` never runs: close the file here
        reader = getattr(self, "_reader", None)
        if reader is not None:
            reader.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- the pairing ----------------------------------------------------------------------------
    def _messages(self) -> Iterator[tuple[str, object]]:
        """(topic, decoded message) in log-time order; a failure names the file and topics."""
        stream = self._reader.messages(self.topics)
        while True:
            try:
                topic, _log_ns, message = next(stream)
            except StopIteration:
                return
            except RecordingError as exc:
                raise SessionError(f"{exc} (reading {', '.join(self.topics)})") from exc
            except Exception as exc:  # noqa: BLE001 - mcap / CDR decoding of a corrupt record
                raise SessionError(
                    f"{self.path}: cannot decode a message on one of {self.topics}: "
                    f"{type(exc).__name__}: {exc}"
                ) from exc
            yield topic, message

    def _operations(self) -> Iterator[Operation]:
        pending: deque[_Command] = deque()  # commands not yet emitted, in command order
        unmatched: deque[tuple[str, int, object]] = deque()  # data whose command has not arrived
        first_ns = None  # the first command's stamp: the session's t = 0
        count = 0
        floor_ns = None  # end of the last emitted command: no open window before it
        try:
            for topic, msg in self._messages():
                if topic == TIP_COMMAND:
                    command = self._command(count, msg, first_ns)
                    count += 1
                    first_ns = command.stamp_ns if first_ns is None else first_ns
                    pending.append(command)
                    for i, (data_topic, stamp, data) in enumerate(
                        unmatched
                    ):  # its measurement may
                        if self._try_attach(
                            command, data_topic, data, stamp
                        ):  # have been logged first
                            del unmatched[i]
                            break
                else:
                    stamp = _stamp_ns(msg.header)
                    if not any(
                        c.data is None and c.needs_data and self._try_attach(c, topic, msg, stamp)
                        for c in pending
                    ):
                        unmatched.append((topic, stamp, msg))
                # emit what is complete; a measurement not in after LOOKAHEAD later commands is missing
                while pending and (
                    pending[0].data is not None
                    or not pending[0].needs_data
                    or len(pending) > LOOKAHEAD_COMMANDS
                ):
                    command = pending.popleft()
                    floor_ns = command.stamp_ns + command.duration_ns
                    operation = self._finish(command, first_ns)
                    if operation is not None:
                        yield operation
                self._drop_unclaimable(unmatched, pending, floor_ns, first_ns)
            while pending:
                operation = self._finish(pending.popleft(), first_ns)
                if operation is not None:
                    yield operation
            self._drop_unclaimable(unmatched, pending, floor_ns, first_ns, at_end=True)
        finally:
            self._reader.close()

    def _command(self, index: int, msg, first_ns: int | None) -> _Command:
        stamp = _stamp_ns(msg.header)
        when = (
            f"{(stamp - first_ns) * 1e-9:.6f} s after the first command"
            if first_ns is not None
            else "the first command"
        )
        kind = KIND_NAMES.get(int(msg.kind))
        if kind is None:
            raise SessionError(
                f"{self.path}: {TIP_COMMAND} message {index} ({when}) has kind={msg.kind}, "
                f"which is none of {KIND_NAMES}"
            )
        if not (math.isfinite(msg.duration) and msg.duration >= 0):
            raise SessionError(
                f"{self.path}: {TIP_COMMAND} message {index} ({when}): duration={msg.duration} s, "
                "must be finite and >= 0"
            )
        return _Command(index, kind, stamp, int(round(msg.duration * 1e9)), msg)

    @staticmethod
    def _try_attach(command: _Command, topic: str, msg, stamp_ns: int) -> bool:
        if command.window_contains(stamp_ns) and _geometry_matches(command, topic, msg):
            command.data, command.data_topic = msg, topic
            return True
        return False

    def _drop_unclaimable(
        self, unmatched, pending, floor_ns, first_ns, at_end: bool = False
    ) -> None:
        """Data messages no command can claim any more: stamped before every window still open
        (commands come in time order, so no later command can claim them), the oldest when too
        many wait, or all at the end. An error, unless missing_data='skip'."""
        while unmatched:
            topic, stamp, _msg = unmatched[0]
            open_from = pending[0].stamp_ns if pending else floor_ns
            too_early = open_from is not None and stamp < open_from - TIME_SLACK_NS
            if not (at_end or too_early or len(unmatched) > MAX_UNMATCHED_DATA):
                return
            unmatched.popleft()
            if self.missing_data == "skip":
                continue
            when = (
                f"{(stamp - first_ns) * 1e-9:.6f} s after the first command"
                if first_ns is not None
                else f"{stamp * 1e-9:.9f} s (no command recorded)"
            )
            raise SessionError(
                f"{self.path}: a {topic} message stamped {when} matches no {TIP_COMMAND} (no command of its "
                "kind whose time window and geometry contain it); read_operations(..., missing_data='skip') "
                "ignores such messages"
            )

    def _finish(self, command: _Command, first_ns: int) -> Operation | None:
        """The Operation of a command whose measurement is in (or a move); None when the
        measurement is missing and missing_data='skip'."""
        start_time = (command.stamp_ns - first_ns) * 1e-9
        cmd = command.message
        if command.needs_data and command.data is None:
            if self.missing_data == "skip":
                return None
            topic = DATA_TOPIC[command.kind]
            what = (
                f"a ForceTrace with task {TRACE_TASK[command.kind]!r}"
                if topic == FORCE_TRACE
                else "a message"
            )
            raise SessionError(
                f"{self.path}: command {command.index} ({command.kind}) at {start_time:.6f} s after the first "
                f"command has no measurement: expected {what} on {topic} stamped within "
                f"[{start_time:.6f}, {start_time + cmd.duration:.6f}] s and matching its geometry "
                f"(start {cmd.start.x:.4e}, {cmd.start.y:.4e} m, end {cmd.end.x:.4e}, {cmd.end.y:.4e} m). "
                "Cancelled, or not recorded? read_operations(..., missing_data='skip') drops such commands"
            )
        msg = command.data
        common = dict(
            index=command.index,
            kind=command.kind,
            start_time=start_time,
            start=(float(cmd.start.x), float(cmd.start.y)),
            end=(float(cmd.end.x), float(cmd.end.y)),
            speed=float(cmd.speed),
            duration=float(cmd.duration),
        )
        if command.kind == "move":
            request = {
                "x": float(cmd.end.x),
                "y": float(cmd.end.y),
                "speed": float(cmd.speed),
                "contact": False,
            }
            return Operation(request=request, data=None, **common)
        data_start = (_stamp_ns(msg.header) - first_ns) * 1e-9
        try:
            if command.kind == "raster":
                data, request = self._raster(msg, data_start)
                return Operation(request=request, data=data, pair_id=str(msg.pair_id), **common)
            if command.kind == "scan_line":
                data = ScanLineData(
                    times=np.asarray(msg.times, float),
                    x=np.asarray(msg.x, float),
                    y=np.asarray(msg.y, float),
                    height=np.asarray(msg.height, float),
                    deflection=np.asarray(msg.deflection, float),
                    amplitude=np.asarray(msg.amplitude, float),
                    start_time=data_start,
                    mode=msg.mode,
                )
                request = LineRequest(
                    cmd.start.x,
                    cmd.start.y,
                    cmd.end.x,
                    cmd.end.y,
                    samples=len(data.times),
                    speed=float(cmd.speed),
                    mode=msg.mode or "tapping",
                )
                return Operation(
                    request=request, data=data, landmark_id=int(msg.landmark_id), **common
                )
            data = ForceTraceData(
                times=np.asarray(msg.times, float),
                commanded_x=np.asarray(msg.commanded_x, float),
                commanded_y=np.asarray(msg.commanded_y, float),
                commanded_z=np.asarray(msg.commanded_z, float),
                vertical_deflection=np.asarray(msg.vertical_deflection, float),
                lateral_torsion=np.asarray(msg.lateral_torsion, float),
                normal_spring_constant=float(msg.normal_spring_constant),
                lateral_spring_constant=float(msg.lateral_spring_constant),
                sample_rate=float(msg.sample_rate),
                start_time=data_start,
                task=msg.task,
                object_id=int(msg.object_id),
            )
            if command.kind == "push":
                request = {
                    "x": float(cmd.end.x),
                    "y": float(cmd.end.y),
                    "speed": float(cmd.speed),
                    "contact": True,
                }
            else:
                request = indent_request_from_trace(data)
                request["x"], request["y"] = float(cmd.start.x), float(cmd.start.y)
            return Operation(request=request, data=data, **common)
        except (ValueError, RecordingError) as exc:
            raise SessionError(
                f"{self.path}: {command.data_topic} message of command {command.index} "
                f"({command.kind}) at {start_time:.6f} s: {exc}"
            ) from exc

    @staticmethod
    def _raster(msg, data_start: float) -> tuple[RasterScanData, ScanRequest]:
        height = image_to_array(msg.height).astype(np.float32)
        rows, columns = height.shape
        lines = rows if msg.scan_angle_deg == 0 else columns
        if len(msg.line_start_times) != lines:
            raise ValueError(
                f"line_start_times has {len(msg.line_start_times)} entries, the image has {lines} lines"
            )
        data = RasterScanData(
            height=height,
            pixel_size_x=float(msg.pixel_size_x),
            pixel_size_y=float(msg.pixel_size_y),
            origin_x=float(msg.origin.x),
            origin_y=float(msg.origin.y),
            scan_angle_deg=float(msg.scan_angle_deg),
            slow_scan_up=bool(msg.slow_scan_up),
            line_period=float(msg.line_period),
            line_start_times=np.asarray(msg.line_start_times, float),
            start_time=data_start,
            mode=msg.mode,
        )
        # size from the pixels, as the driver computes it; checks of absurd values are the
        # resimulation's business (check_config_matches), not the reader's
        line_rate = 1.0 / msg.line_period if msg.line_period > 0 else math.inf
        request = ScanRequest(
            origin_x=data.origin_x,
            origin_y=data.origin_y,
            size_x=float(msg.pixel_size_x * columns),
            size_y=float(msg.pixel_size_y * rows),
            pixels_x=columns,
            pixels_y=rows,
            scan_angle_deg=data.scan_angle_deg,
            slow_scan_up=data.slow_scan_up,
            line_rate=line_rate,
            mode=msg.mode or "tapping",
        )
        return data, request


def read_operations(path: str | os.PathLike, missing_data: str = "error") -> OperationStream:
    """The operations of a recording in command order, each TipCommand paired with its
    measurement (matched by time window and geometry, as the ReplayInstrument matches
    requests). Streams: decoded messages are held only until their command is complete.

    Opens and checks the file at once (SessionError, a RecordingError and ValueError, naming
    the file, topic and problem: corrupt or truncated file, no /afm/tip_command, wrong types);
    while iterating: an unknown command kind, a command without its measurement (naming its
    index and time), or a measurement matching no command. missing_data='skip' drops commands
    without their measurement instead (cancelled actions; streams a late recorder missed) and
    measurements without a command.
    """
    return OperationStream(path, missing_data)
