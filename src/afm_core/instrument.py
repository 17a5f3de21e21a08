"""What every instrument backend (simulator, DAQ hardware, replay) takes and returns.

Plain dataclasses in SI units; the driver node converts them to and from afm_msgs. Each
request validates itself and raises ValueError naming the field and the limit, before
anything moves: the tip never leaves the scanner range.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from afm_core import checks


@dataclass(frozen=True)
class ScannerLimits:
    """The instrument's envelope (defaults: Veeco Dimension 3100, book 7.1)."""

    range_x: float = 110e-6  # m, scanner x range [0, range_x]
    range_y: float = 110e-6  # m
    range_z: float = 7e-6  # m
    max_speed: float = 100e-6  # m/s, slew-rate limit of the lateral piezos
    max_pixels: int = 4096  # per image axis
    max_line_samples: int = 100_000  # per local scan line
    max_line_rate: float = 50.0  # Hz
    max_indent_force: float = 1e-6  # N
    max_dwell: float = 600.0  # s


class InstrumentUnavailable(RuntimeError):
    """A backend could not carry out a request it accepted (no answer, busy, lost): the
    procedures on an Instrument report it as a failure of what they were doing."""


def check_in_range(name: str, x: float, y: float, limits: ScannerLimits) -> None:
    checks.finite(f"{name}.x", x)
    checks.finite(f"{name}.y", y)
    if not 0.0 <= x <= limits.range_x:
        raise ValueError(
            f"{name}.x={x:.4e} m: outside the scanner range [0, {limits.range_x:.4e}] m"
        )
    if not 0.0 <= y <= limits.range_y:
        raise ValueError(
            f"{name}.y={y:.4e} m: outside the scanner range [0, {limits.range_y:.4e}] m"
        )


def check_speed(name: str, speed: float, limits: ScannerLimits) -> None:
    checks.finite(name, speed)
    if not 0.0 < speed <= limits.max_speed:
        raise ValueError(
            f"{name}={speed:.4e} m/s: must be > 0 and at most the slew limit "
            f"{limits.max_speed:.4e} m/s"
        )


DEFAULT_MOVE_SPEED_SHARE = 0.1  # MoveTip speed 0: a tenth of the slew limit (the driver default)


def move_speed(speed: float, limits: ScannerLimits) -> float:
    """MoveTip's speed: 0 asks for the driver's default (DEFAULT_MOVE_SPEED_SHARE of the slew
    limit); anything else must be finite, > 0 and at most the slew limit (ValueError naming
    `speed` and the limit: a negative or NaN speed is refused, not run at the default)."""
    checks.finite("speed", speed, "m/s")
    if speed == 0.0:
        return DEFAULT_MOVE_SPEED_SHARE * limits.max_speed
    check_speed("speed", speed, limits)
    return float(speed)


@dataclass
class ScanRequest:
    """A raster image: area (scanner frame), pixels, angle, direction, line rate."""

    origin_x: float
    origin_y: float
    size_x: float
    size_y: float
    pixels_x: int
    pixels_y: int
    scan_angle_deg: float = 0.0
    slow_scan_up: bool = True
    line_rate: float = 1.0  # Hz, lines (trace + retrace) per second
    mode: str = "tapping"

    def validate(self, limits: ScannerLimits = ScannerLimits()) -> None:
        for name in ("origin_x", "origin_y", "size_x", "size_y", "line_rate", "scan_angle_deg"):
            checks.finite(name, getattr(self, name))
        for name in ("size_x", "size_y"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}={getattr(self, name)}: must be > 0")
        if not 0 < self.line_rate <= limits.max_line_rate:
            raise ValueError(
                f"line_rate={self.line_rate}: must be within (0, {limits.max_line_rate}] Hz"
            )
        for name in ("pixels_x", "pixels_y"):
            # 64.5 pixels is no count (it failed later as a TypeError); 64.0 is taken as 64
            setattr(self, name, checks.count(name, getattr(self, name), 2, limits.max_pixels))
        if self.scan_angle_deg not in (0.0, 90.0):
            raise ValueError(f"scan_angle_deg={self.scan_angle_deg}: must be 0 or 90")
        if self.mode not in ("tapping", "contact"):
            raise ValueError(f"mode={self.mode!r}: must be 'tapping' or 'contact'")
        check_in_range("origin", self.origin_x, self.origin_y, limits)
        check_in_range(
            "origin + size", self.origin_x + self.size_x, self.origin_y + self.size_y, limits
        )
        fast_size = self.size_x if self.scan_angle_deg == 0.0 else self.size_y
        speed = 2.0 * fast_size * self.line_rate  # trace takes half of the line period
        if speed > limits.max_speed:
            raise ValueError(
                f"line_rate={self.line_rate} Hz: the tip would move at {speed:.3e} m/s, above the "
                f"slew limit {limits.max_speed:.3e} m/s for this size"
            )

    @property
    def lines(self) -> int:
        return self.pixels_y if self.scan_angle_deg == 0.0 else self.pixels_x

    @property
    def pixels_per_line(self) -> int:
        return self.pixels_x if self.scan_angle_deg == 0.0 else self.pixels_y

    def first_point(self) -> tuple[float, float]:
        """Where the image's first sample is commanded (m, scanner frame): the first pixel
        centre of the first line in slow-scan order; the scan's approach ends here."""
        half_x, half_y = 0.5 * self.size_x / self.pixels_x, 0.5 * self.size_y / self.pixels_y
        x, y = self.origin_x + half_x, self.origin_y + half_y
        if not self.slow_scan_up:  # the first line is the last row (0 deg) or column (90 deg)
            if self.scan_angle_deg == 0.0:
                y = self.origin_y + self.size_y - half_y
            else:
                x = self.origin_x + self.size_x - half_x
        return float(x), float(y)


@dataclass
class RasterScanData:
    height: np.ndarray  # (pixels_y, pixels_x), m, scanner-frame orientation
    pixel_size_x: float
    pixel_size_y: float
    origin_x: float
    origin_y: float
    scan_angle_deg: float
    slow_scan_up: bool
    line_period: float  # s, trace + retrace
    line_start_times: np.ndarray  # s since start_time, per line index
    start_time: float  # s, instrument clock
    mode: str
    complete: bool = True  # False when cancelled: lines not acquired are NaN


@dataclass
class LineRequest:
    """A local scan line between two scanner-frame points."""

    start_x: float
    start_y: float
    end_x: float
    end_y: float
    samples: int
    speed: float  # m/s
    mode: str = "tapping"

    def validate(self, limits: ScannerLimits = ScannerLimits()) -> None:
        check_in_range("start", self.start_x, self.start_y, limits)
        check_in_range("end", self.end_x, self.end_y, limits)
        self.samples = checks.count("samples", self.samples, 2, limits.max_line_samples)
        check_speed("speed", self.speed, limits)
        if self.mode not in ("tapping", "contact"):
            raise ValueError(f"mode={self.mode!r}: must be 'tapping' or 'contact'")
        if self.length == 0.0:
            raise ValueError("start and end: the same point; a scan line needs a length > 0")

    @property
    def length(self) -> float:
        return math.hypot(self.end_x - self.start_x, self.end_y - self.start_y)


@dataclass
class ScanLineData:
    times: np.ndarray  # s since start_time
    x: np.ndarray  # m, commanded scanner-frame positions
    y: np.ndarray
    height: np.ndarray  # m
    deflection: np.ndarray  # m
    amplitude: np.ndarray  # m (tapping) or empty
    start_time: float  # s, instrument clock
    mode: str
    complete: bool = True


@dataclass
class ForceTraceData:
    times: np.ndarray  # s since start_time
    commanded_x: np.ndarray  # m
    commanded_y: np.ndarray
    commanded_z: np.ndarray
    vertical_deflection: np.ndarray  # m
    lateral_torsion: np.ndarray  # rad
    normal_spring_constant: float  # N/m
    lateral_spring_constant: float  # N*m/rad
    sample_rate: float  # Hz
    start_time: float
    task: str  # "push", "indent"
    object_id: int = -1


@dataclass
class MoveResult:
    end_x: float  # m, commanded position where the move ended
    end_y: float
    completed: bool  # False when stopped early (cancel)
    trace: ForceTraceData | None = None  # contact moves only


@dataclass
class IndentResult:
    x: float
    y: float
    trace: ForceTraceData
    completed: bool = True


StopCheck = Callable[[], bool]  # returns True when the caller wants the motion stopped


class Instrument(Protocol):
    """What the driver node drives. Every call advances `time` (s) by what it took."""

    limits: ScannerLimits
    time: float

    def commanded_position(self) -> tuple[float, float]: ...

    def raster_scan(
        self,
        request: ScanRequest,
        on_line: Callable[[int, int], None] | None = None,
        should_stop: StopCheck | None = None,
    ) -> RasterScanData: ...

    def local_scan(
        self, request: LineRequest, should_stop: StopCheck | None = None
    ) -> ScanLineData: ...

    def move_tip(
        self,
        x: float,
        y: float,
        speed: float,
        contact: bool = False,
        should_stop: StopCheck | None = None,
    ) -> MoveResult: ...

    def indent(
        self, x: float, y: float, force: float, dwell: float, should_stop: StopCheck | None = None
    ) -> IndentResult: ...

    def close(self) -> None: ...


def validate_indent(x: float, y: float, force: float, dwell: float, limits: ScannerLimits) -> None:
    check_in_range("position", x, y, limits)
    checks.finite("force", force)
    checks.finite("dwell", dwell)
    if not 0 < force <= limits.max_indent_force:
        raise ValueError(
            f"force={force:.3e} N: must be within (0, {limits.max_indent_force:.3e}] N"
        )
    if not 0 <= dwell <= limits.max_dwell:
        raise ValueError(f"dwell={dwell} s: must be within [0, {limits.max_dwell}] s")


def validate_move(x: float, y: float, speed: float, limits: ScannerLimits) -> None:
    check_in_range("target", x, y, limits)
    check_speed("speed", speed, limits)
