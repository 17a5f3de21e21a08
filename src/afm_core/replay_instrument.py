"""An instrument that answers with a recorded session: the driver's `replay` backend.

Scans, scan lines and force traces come back in the order they were recorded, each only
for a request that matches what was recorded (same area, angle and direction; same line;
same kind of force trace), so a replayed session is driven by the commands that made it.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np

from afm_core.instrument import (
    ForceTraceData,
    IndentResult,
    LineRequest,
    MoveResult,
    RasterScanData,
    ScanLineData,
    ScannerLimits,
    ScanRequest,
    validate_indent,
    validate_move,
)
from afm_core.recording import RecordingReader
from afm_core.recording.reader import image_to_array

TOPICS = {"scan": "/afm/scan", "line": "/afm/scan_line", "trace": "/afm/force_trace"}
MATCH_TOLERANCE = 1e-9  # m: recorded and requested geometry must agree this closely


def _stamp(header) -> float:
    return header.stamp.sec + header.stamp.nanosec * 1e-9


class ReplayInstrument:
    def __init__(self, path, limits: ScannerLimits = ScannerLimits()):
        self.reader = RecordingReader(path)
        recorded = self.reader.topics()
        self.available = {k: t for k, t in TOPICS.items() if t in recorded}
        if not self.available:
            raise ValueError(
                f"replay_input {str(path)!r}: none of {sorted(TOPICS.values())} was recorded"
            )
        self.limits = limits
        self.time = 0.0
        self._epoch: float | None = None
        self._position = (0.5 * limits.range_x, 0.5 * limits.range_y)
        self._pending: dict = {}
        self._streams: dict[str, Iterator] = {
            k: (m for _t, _l, m in self.reader.messages([t])) for k, t in self.available.items()
        }

    def _peek(self, kind: str, what: str):
        """The next recorded message of this kind, left in place until _take."""
        if kind not in self._streams:
            raise ValueError(f"{what}: the recording has no {TOPICS[kind]}")
        if kind not in self._pending:
            self._pending[kind] = next(self._streams[kind], None)
        if self._pending[kind] is None:
            raise ValueError(f"{what}: the recording has no more {TOPICS[kind]} messages")
        return self._pending[kind]

    def _take(self, kind: str):
        message = self._pending.pop(kind)
        stamp = _stamp(message.header)
        if self._epoch is None:
            self._epoch = stamp
        self.time = max(self.time, stamp - self._epoch)
        return message, stamp - self._epoch

    def commanded_position(self) -> tuple[float, float]:
        return self._position

    def raster_scan(self, request: ScanRequest, on_line=None, should_stop=None) -> RasterScanData:
        request.validate(self.limits)
        msg = self._peek("scan", "scan")
        recorded = (
            msg.origin.x,
            msg.origin.y,
            msg.size_x,
            msg.size_y,
            msg.scan_angle_deg,
            msg.slow_scan_up,
        )
        wanted = (
            request.origin_x,
            request.origin_y,
            request.size_x,
            request.size_y,
            request.scan_angle_deg,
            request.slow_scan_up,
        )
        if not all(math.isclose(a, b, abs_tol=MATCH_TOLERANCE) for a, b in zip(recorded, wanted)):
            raise ValueError(
                f"scan request {wanted} does not match the next recorded scan {recorded}"
            )
        msg, start = self._take("scan")
        height = image_to_array(msg.height)
        lines = len(msg.line_start_times)
        if on_line is not None:
            for done in range(1, lines + 1):
                on_line(done, lines)
        self.time += msg.line_period * lines
        self._position = (request.origin_x + request.size_x, request.origin_y + request.size_y)
        return RasterScanData(
            height=height.astype(np.float32),
            pixel_size_x=msg.pixel_size_x,
            pixel_size_y=msg.pixel_size_y,
            origin_x=msg.origin.x,
            origin_y=msg.origin.y,
            scan_angle_deg=msg.scan_angle_deg,
            slow_scan_up=msg.slow_scan_up,
            line_period=msg.line_period,
            line_start_times=np.asarray(msg.line_start_times),
            start_time=start,
            mode=msg.mode,
        )

    def local_scan(self, request: LineRequest, should_stop=None) -> ScanLineData:
        request.validate(self.limits)
        msg = self._peek("line", "scan line")
        recorded = (
            msg.commanded_start.x,
            msg.commanded_start.y,
            msg.commanded_end.x,
            msg.commanded_end.y,
        )
        wanted = (request.start_x, request.start_y, request.end_x, request.end_y)
        if not all(math.isclose(a, b, abs_tol=MATCH_TOLERANCE) for a, b in zip(recorded, wanted)):
            raise ValueError(
                f"scan line {wanted} does not match the next recorded line {recorded}"
            )
        msg, start = self._take("line")
        self._position = (request.end_x, request.end_y)
        if len(msg.times):
            self.time = max(self.time, start + float(msg.times[-1]))
        return ScanLineData(
            times=np.asarray(msg.times),
            x=np.asarray(msg.x),
            y=np.asarray(msg.y),
            height=np.asarray(msg.height),
            deflection=np.asarray(msg.deflection),
            amplitude=np.asarray(msg.amplitude),
            start_time=start,
            mode=msg.mode,
        )

    def _trace(self, task: str, what: str) -> ForceTraceData:
        msg = self._peek("trace", what)
        if msg.task != task:
            raise ValueError(
                f"{what}: the next recorded force trace is a {msg.task!r}, not a {task!r}"
            )
        msg, start = self._take("trace")
        if len(msg.times):
            self.time = max(self.time, start + float(msg.times[-1]))
        return ForceTraceData(
            times=np.asarray(msg.times),
            commanded_x=np.asarray(msg.commanded_x),
            commanded_y=np.asarray(msg.commanded_y),
            commanded_z=np.asarray(msg.commanded_z),
            vertical_deflection=np.asarray(msg.vertical_deflection),
            lateral_torsion=np.asarray(msg.lateral_torsion),
            normal_spring_constant=msg.normal_spring_constant,
            lateral_spring_constant=msg.lateral_spring_constant,
            sample_rate=msg.sample_rate,
            start_time=start,
            task=msg.task,
            object_id=msg.object_id,
        )

    def move_tip(
        self, x: float, y: float, speed: float, contact: bool = False, should_stop=None
    ) -> MoveResult:
        validate_move(x, y, speed, self.limits)
        trace = self._trace("push", "contact move") if contact else None
        if not contact:
            self.time += math.hypot(x - self._position[0], y - self._position[1]) / speed
        self._position = (x, y)
        return MoveResult(end_x=x, end_y=y, completed=True, trace=trace)

    def indent(
        self, x: float, y: float, force: float, dwell: float, should_stop=None
    ) -> IndentResult:
        validate_indent(x, y, force, dwell, self.limits)
        self._position = (x, y)
        return IndentResult(x=x, y=y, trace=self._trace("indent", "indentation"))

    def truth(self) -> dict:
        raise ValueError("a replayed session has no ground truth")

    def close(self) -> None:
        self.reader.close()
