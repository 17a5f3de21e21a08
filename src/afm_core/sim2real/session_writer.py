"""Writes a session as the driver publishes it, from any core `Instrument`, without ROS
(`RecordingInstrument`, `SessionWriter`): CDR is encoded by recording.cdr from the full ros2msg
schema text, the container is our `RecordingWriter` (`.part` until closed, never overwrites,
rosbag2's metadata and QoS), so our RecordingReader, the ReplayInstrument, rosbag2 and
Foxglove read it (session.py: the topics and messages)."""

from __future__ import annotations

import math
import os
import time as wall_time
from pathlib import Path

import numpy as np

from afm_core.instrument import (
    ForceTraceData,
    IndentResult,
    LineRequest,
    MoveResult,
    RasterScanData,
    ScanLineData,
    ScanRequest,
)
from afm_core.recording import RecordingError, RecordingWriter
from afm_core.recording.cdr import encoder
from afm_core.recording.definitions import full_message_definition
from afm_core.sim2real.session import (
    FORCE_TRACE,
    FRAME_SCANNER,
    FRAME_TASK,
    GROUND_TRUTH,
    KIND_CODES,
    OBJECT_KINDS,
    OFFERED_QOS,
    SCAN,
    SCAN_LINE,
    TIP_COMMAND,
    TYPES,
    Operation,
    SessionError,
    operation_from_call,
)


def _floats(values) -> list:
    """float64[] field value (the encoder takes sequences)."""
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
        self._encoders = {topic: encoder(TYPES[topic], definitions[topic]) for topic in topics}
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
