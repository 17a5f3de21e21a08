"""Reads a recorded session back (ours, or any MCAP with ros2msg schemas on the same topics,
such as rosbag2 writes) as `Operation`s in command order (`read_operations`), streaming: at
most a few commands and their data messages are held at a time (session.py: the topics and
messages)."""

from __future__ import annotations

import math
import os
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from afm_core.instrument import (
    ForceTraceData,
    LineRequest,
    RasterScanData,
    ScanLineData,
    ScanRequest,
)
from afm_core.recording import RecordingError, RecordingReader
from afm_core.recording.reader import image_to_array
from afm_core.sim2real.session import (
    DATA_TOPIC,
    FORCE_TRACE,
    KIND_NAMES,
    SCAN,
    SCAN_LINE,
    TIP_COMMAND,
    TRACE_TASK,
    TYPES,
    Operation,
    SessionError,
)

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


# how a user leaves out what a cut-short recording lacks, in the CLI and in Python
SKIP_HINT = "`afm sim2real --skip-incomplete` (read_operations(..., missing_data='skip'))"


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
                        f"{self.path}: topic {topic} has type {info.type!r}, "
                        f"expected {TYPES[topic]!r}"
                    )
                if topic in TYPES and info.schema_encoding != "ros2msg":
                    raise SessionError(
                        f"{self.path}: topic {topic} has schema encoding "
                        f"{info.schema_encoding!r}, "
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
                # emit what is complete; a measurement not in after LOOKAHEAD later commands is
                # missing
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
                f"{self.path}: a {topic} message stamped {when} matches no {TIP_COMMAND} (no "
                "command of its kind whose time window and geometry contain it); "
                f"{SKIP_HINT} ignores such messages"
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
                f"{self.path}: command {command.index} ({command.kind}) at {start_time:.6f} s "
                "after the first "
                f"command has no measurement: expected {what} on {topic} stamped within "
                f"[{start_time:.6f}, {start_time + cmd.duration:.6f}] s and matching its geometry "
                f"(start {cmd.start.x:.4e}, {cmd.start.y:.4e} m, "
                f"end {cmd.end.x:.4e}, {cmd.end.y:.4e} m). "
                f"Cancelled, or not recorded? {SKIP_HINT} leaves such commands out"
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
                f"line_start_times has {len(msg.line_start_times)} entries, "
                f"the image has {lines} lines"
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
