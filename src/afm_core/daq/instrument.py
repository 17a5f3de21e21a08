"""The DAQ backend: the Instrument protocol on a real scanner driven through a DAQ card.

As on the book's platform (Veeco Dimension 3100): analog outputs drive the x/y piezo inputs
of the controller (optionally a z offset for indentation), analog inputs read the z-piezo
monitor (topography from the controller's own z feedback) and the cantilever deflection
(optionally lateral). Every motion is a hardware-timed ramp with synchronised acquisition
(`DaqBoundary.write_read`), cut into chunks so a cancel can stop it between two of them.

Safety model: a request is planned in full and checked (request validators from
afm_core.instrument, slew rate between every two samples, AO clamps after the inverse
hysteresis feed-forward) before the first sample is written; the same plan is then executed.
A last guard refuses to write any sample outside the clamps.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from afm_core.daq.boundary import DaqBoundary, DaqUnavailable
from afm_core.daq.calibration import DaqCalibration
from afm_core.daq.trace import TraceRecorder
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
    StopCheck,
    check_speed,
    validate_indent,
    validate_move,
)


class FeedForward(Protocol):
    """Inverse hysteresis model: desired positions (m) -> command positions (m).

    Stateful across calls: it is fed every commanded sample of an axis in order, exactly
    once, so a rate-independent model (e.g. Prandtl-Ishlinskii) keeps its history right.
    """

    def apply(self, desired: np.ndarray) -> np.ndarray: ...

    def reset(self) -> None: ...


class IdentityFeedForward:
    """No compensation: command = desired."""

    def apply(self, desired: np.ndarray) -> np.ndarray:
        return np.asarray(desired, dtype=float)

    def reset(self) -> None:
        pass


class _FunctionFeedForward:
    """A stateless function of position used as a feed-forward."""

    def __init__(self, function: Callable[[np.ndarray], np.ndarray]):
        self.function = function

    def apply(self, desired: np.ndarray) -> np.ndarray:
        return np.asarray(self.function(np.asarray(desired, dtype=float)), dtype=float)

    def reset(self) -> None:
        pass


def as_feed_forward(model: Any) -> FeedForward:
    """None -> identity; an object with apply/reset as is; a plain callable wrapped."""
    if model is None:
        return IdentityFeedForward()
    if hasattr(model, "apply"):
        return model
    if callable(model):
        return _FunctionFeedForward(model)
    raise TypeError(
        f"feed-forward {model!r}: needs apply(np.ndarray) -> np.ndarray or to be callable"
    )


@dataclass
class _Step:
    """One chunk of a plan: desired positions per sample (m) and how to treat it."""

    kind: str  # "travel" (no data), "line" (raster line), "scan" (local scan), "press" (indent)
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray  # z output command (m), held constant outside indentation
    field: str  # request field(s) to name when this chunk is refused
    index: int = -1  # raster line index


class DaqInstrument:
    """An AFM scanner driven through `boundary`; implements afm_core.instrument.Instrument.

    At start-up the lateral outputs are set to the position the calibration maps to 0 V (the
    DAQ's power-up level, clipped into the range) so the commanded position is known.
    `travel_speed` (default half the slew limit) is used to reach the start of a scan or an
    indentation; `indent_speed` is the z ramp rate; `chunk_seconds` bounds how long a cancel
    waits during moves; `max_motion_seconds` refuses a move, press or dwell longer than that.
    A card failure during a request raises InstrumentUnavailable (afm_core.instrument) with the
    outputs back at the last levels known and, in an indentation, z retracted.
    """

    def __init__(
        self,
        boundary: DaqBoundary,
        calibration: DaqCalibration,
        limits: ScannerLimits = ScannerLimits(),
        clock: Callable[[], float] = time.monotonic,
        *,
        travel_speed: float | None = None,
        indent_speed: float = 1e-6,
        chunk_seconds: float = 0.1,
        max_motion_seconds: float = 3600.0,
    ):
        calibration.validate()
        self.boundary = boundary
        self.calibration = calibration
        self.limits = limits
        self._clock = clock
        self._t0 = clock()
        self.travel_speed = 0.5 * limits.max_speed if travel_speed is None else travel_speed
        check_speed("travel_speed", self.travel_speed, limits)
        if not (math.isfinite(indent_speed) and indent_speed > 0):
            raise ValueError(f"indent_speed={indent_speed}: must be finite and > 0")
        self.indent_speed = indent_speed
        self.fs = calibration.sample_rate
        if not (math.isfinite(max_motion_seconds) and max_motion_seconds > 0):
            raise ValueError(f"max_motion_seconds={max_motion_seconds}: must be finite and > 0")
        self.max_motion_samples = int(max_motion_seconds * self.fs)
        self._chunk = max(2, int(round(chunk_seconds * self.fs)))
        self._ffx = as_feed_forward(calibration.x_feed_forward)
        self._ffy = as_feed_forward(calibration.y_feed_forward)
        self._ffx.reset()
        self._ffy.reset()
        c = calibration
        self._axes = [("x", c.x_volts_limits), ("y", c.y_volts_limits)] + (
            [("z", c.z_volts_limits)] if c.ao_z else []
        )
        self._ai_channels = [c.ai_z, c.ai_deflection] + ([c.ai_lateral] if c.ai_lateral else [])

        def zero_volt_position(offset, v_per_m, volt_limits, span):
            return float(np.clip((np.clip(0.0, *volt_limits) - offset) / v_per_m, 0.0, span))

        x0 = zero_volt_position(
            c.x_offset_volts, c.x_volts_per_metre, c.x_volts_limits, limits.range_x
        )
        y0 = zero_volt_position(
            c.y_offset_volts, c.y_volts_per_metre, c.y_volts_limits, limits.range_y
        )
        volts = self._volts(np.array([x0]), np.array([y0]), np.zeros(1), self._ffx, self._ffy)
        self._check_volts(volts, "calibration (start-up position)", ValueError)
        try:
            boundary.configure(
                [c.ao_x, c.ao_y] + ([c.ao_z] if c.ao_z else []),
                self._ai_channels,
                self.fs,
                (min(lo for _, (lo, _) in self._axes), max(hi for _, (_, hi) in self._axes)),
                c.ai_range,
            )
            boundary.write_static(volts[:, 0])
        except (ValueError, DaqUnavailable):
            raise
        except Exception as exc:
            # A driver error at start-up: the node stops with this message, not a traceback.
            raise DaqUnavailable(f"DAQ set-up failed: {type(exc).__name__}: {exc}") from exc
        self._last = volts[:, 0].copy()
        self._pos = (x0, y0)
        self._z = 0.0

    # ---- state -----------------------------------------------------------------------------
    @property
    def time(self) -> float:
        """s since this instrument started, from its clock."""
        return self._clock() - self._t0

    def commanded_position(self) -> tuple[float, float]:
        return self._pos

    def hold(self, duration: float) -> None:
        """Wait `duration` s with the outputs held (the last static voltages stay written):
        what a creep settle before an image asks of a real scanner."""
        if duration > 0:
            time.sleep(duration)

    def close(self) -> None:
        self.boundary.close()

    # ---- conversions -----------------------------------------------------------------------
    def _volts(self, x, y, z, ffx: FeedForward, ffy: FeedForward) -> np.ndarray:
        c = self.calibration
        rows = [
            c.x_offset_volts + c.x_volts_per_metre * ffx.apply(x),
            c.y_offset_volts + c.y_volts_per_metre * ffy.apply(y),
        ]
        if c.ao_z:
            rows.append(c.z_offset_volts + c.z_volts_per_metre * np.asarray(z, dtype=float))
        return np.vstack(rows)

    def _check_volts(self, volts: np.ndarray, field: str, error: type) -> None:
        for row, (axis, (lo, hi)) in enumerate(self._axes):
            v = volts[row]
            excess = np.where(np.isfinite(v), np.maximum(lo - v, v - hi), np.inf)
            if excess.max() > 0:
                i = int(np.argmax(excess))  # report the worst sample
                raise error(
                    f"{field}: the {axis} output would be {v[i]:.4g} V, outside the AO clamp "
                    f"[{lo:g}, {hi:g}] V (DaqCalibration.{axis}_volts_limits)"
                )

    def _measure(self, ai: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """AI volts -> topography (m), deflection (m), torsion (rad)."""
        c = self.calibration
        height = c.z_monitor_metres_per_volt * (ai[0] - c.z_monitor_offset_volts)
        deflection = c.deflection_metres_per_volt * (ai[1] - c.deflection_offset_volts)
        lateral = (
            c.lateral_radians_per_volt * (ai[2] - c.lateral_offset_volts)
            if c.ai_lateral
            else np.zeros(ai.shape[1])
        )
        return height, deflection, lateral

    # ---- planning --------------------------------------------------------------------------
    def _ramp(self, start, end, duration: float, kind: str, field: str) -> Iterator[_Step]:
        """Linear ramp (x, y, z) start -> end over `duration`, sample k at (k+1)/fs, in chunks."""
        n = max(2, math.ceil(duration * self.fs - 1e-9))
        if n > self.max_motion_samples:
            raise ValueError(
                f"{field}: the motion would take {n / self.fs:.4g} s ({n} DAQ samples at "
                f"sample_rate {self.fs:g} Hz), above the {self.max_motion_samples / self.fs:.4g}"
                " s one motion may take; ask for a higher speed"
            )
        # Chunk by chunk: a slow move's whole path (hours at 100 kHz) must never be in memory.
        starts = list(range(0, n, self._chunk))
        if len(starts) > 1 and n - starts[-1] < 2:
            del starts[-1]  # finite AO needs >= 2 samples: fold a lone tail into the chunk before
        for i, j in zip(starts, starts[1:] + [n]):
            k = np.arange(i + 1, j + 1) / n
            path = [a + (b - a) * k for a, b in zip(start, end)]
            if j == n:
                for axis, b in zip(path, end):
                    axis[-1] = b  # land exactly on the target, free of rounding
            yield _Step(kind, path[0], path[1], path[2], field)

    def _travel(
        self, x: float, y: float, speed: float, field: str, kind: str = "travel"
    ) -> Iterator[_Step]:
        x0, y0 = self._pos
        distance = math.hypot(x - x0, y - y0)
        if distance > 0.0:
            yield from self._ramp(
                (x0, y0, self._z), (x, y, self._z), distance / speed, kind, field
            )

    def _check_plan(self, steps: Iterator[_Step]) -> dict[str, int]:
        """Run the plan on copies of the feed-forward state: slew and clamps, nothing written.
        Returns the planned samples per kind of step."""
        ffx, ffy = copy.deepcopy(self._ffx), copy.deepcopy(self._ffy)
        px, py = self._pos
        samples: dict[str, int] = {}
        for step in steps:
            samples[step.kind] = samples.get(step.kind, 0) + len(step.x)
            dx = np.diff(step.x, prepend=px)
            dy = np.diff(step.y, prepend=py)
            speed = float(np.max(np.hypot(dx, dy))) * self.fs
            if speed > self.limits.max_speed * (1 + 1e-9):
                raise ValueError(
                    f"{step.field}: the path would move the tip at {speed:.3e} m/s, above the "
                    f"slew limit {self.limits.max_speed:.3e} m/s"
                )
            px, py = step.x[-1], step.y[-1]
            self._check_volts(
                self._volts(step.x, step.y, step.z, ffx, ffy), step.field, ValueError
            )
        return samples

    # ---- execution -------------------------------------------------------------------------
    def _write(self, step: _Step) -> np.ndarray:
        volts = self._volts(step.x, step.y, step.z, self._ffx, self._ffy)
        self._check_volts(volts, f"internal guard ({step.field})", RuntimeError)
        try:
            ai = self.boundary.write_read(volts)
        except Exception as exc:
            # The outputs stopped somewhere on this ramp: go back to the last levels known,
            # so the commanded position is true again and the next plan starts from it.
            self._recover(exc, step)
        self._last = volts[:, -1].copy()
        self._pos = (float(step.x[-1]), float(step.y[-1]))
        self._z = float(step.z[-1])
        # A returned ramp is done (the outputs hold its end) even if its readings are unusable.
        expected = (len(self._ai_channels), volts.shape[1])
        ai = np.asarray(ai, dtype=float) if ai is not None else np.empty(0)
        if ai.shape != expected:
            raise InstrumentUnavailable(
                f"DAQ during {step.field}: the card returned readings of shape {ai.shape}, "
                f"expected {expected} (AI channels {self._ai_channels} x samples written); "
                "nothing of this request is reported"
            )
        if not np.all(np.isfinite(ai)):
            raise InstrumentUnavailable(
                f"DAQ during {step.field}: {int(np.sum(~np.isfinite(ai)))} AI readings are "
                "not finite (NaN/inf); nothing of this request is reported"
            )
        return ai

    def _recover(self, exc: Exception, step: _Step):
        """After a failed ramp: write the last levels known again, and raise."""
        try:
            self.boundary.write_static(self._last.copy())
        except Exception as hold_exc:  # noqa: BLE001 - the first failure is the one to report
            raise InstrumentUnavailable(
                f"DAQ failed during {step.field}: {type(exc).__name__}: {exc}; holding the "
                f"last levels failed too ({type(hold_exc).__name__}: {hold_exc}): the "
                "outputs are where the card left them"
            ) from exc
        raise InstrumentUnavailable(
            f"DAQ failed during {step.field}: {type(exc).__name__}: {exc}; the outputs are "
            "back at the last levels written before it"
        ) from exc

    def _hold(self) -> None:
        """Stop here: keep the outputs at the last written levels."""
        try:
            self.boundary.write_static(self._last.copy())
        except Exception as exc:
            raise InstrumentUnavailable(
                f"DAQ failed holding the outputs after a cancel: {type(exc).__name__}: {exc}"
            ) from exc

    def _check_ramp_samples(self, n: int, what: str) -> None:
        """One synchronised ramp is planned, written and read whole: bound its memory."""
        most = self.calibration.max_ramp_samples
        if n > most:
            raise ValueError(
                f"{what} would be one ramp of {n} DAQ samples ({n / self.fs:.4g} s at "
                f"sample_rate {self.fs:g} Hz), above max_ramp_samples={most} "
                f"({most / self.fs:.4g} s); go faster or lower the sample rate"
            )

    @staticmethod
    def _stopped(should_stop: StopCheck | None) -> bool:
        return bool(should_stop and should_stop())

    # ---- raster ----------------------------------------------------------------------------
    def _raster_geometry(self, r: ScanRequest):
        fast_x = r.scan_angle_deg == 0.0
        lines, pixels = r.lines, r.pixels_per_line
        n_half = max(2, math.ceil(self.fs / (2.0 * r.line_rate) - 1e-9))
        fast0, fast_size = (r.origin_x, r.size_x) if fast_x else (r.origin_y, r.size_y)
        slow0, pitch = (
            (r.origin_y, r.size_y / r.pixels_y) if fast_x else (r.origin_x, r.size_x / r.pixels_x)
        )
        return (
            fast_x,
            lines,
            pixels,
            n_half,
            fast0,
            fast_size,
            slow0 + (np.arange(lines) + 0.5) * pitch,
        )

    def _raster_steps(self, r: ScanRequest) -> Iterator[_Step]:
        fast_x, lines, _, n_half, fast0, fast_size, slow = self._raster_geometry(r)
        order = list(range(lines)) if r.slow_scan_up else list(range(lines))[::-1]
        first = (fast0, slow[order[0]]) if fast_x else (slow[order[0]], fast0)
        yield from self._travel(*first, self.travel_speed, "origin")
        k = np.arange(1, n_half + 1) / n_half
        fast = np.concatenate(
            [fast0 + fast_size * k, fast0 + fast_size * (1.0 - k)]
        )  # trace, retrace
        z = np.full(2 * n_half, self._z)
        for i, line in enumerate(order):
            here, there = slow[line], slow[order[i + 1]] if i + 1 < lines else slow[line]
            s = np.concatenate(
                [np.full(n_half, here), here + (there - here) * k]
            )  # step during retrace
            x, y = (fast, s) if fast_x else (s, fast)
            yield _Step("line", x, y, z, "line_rate / size (line path)", line)

    def raster_scan(
        self,
        request: ScanRequest,
        on_line: Callable[[int, int], None] | None = None,
        should_stop: StopCheck | None = None,
    ) -> RasterScanData:
        """Image an area: one synchronised trace + retrace per line, topography from the z monitor
        averaged into pixels; the slow axis steps during the retrace."""
        request.validate(self.limits)
        fast_x, lines, pixels, n_half, *_ = self._raster_geometry(request)
        if n_half < pixels:
            name = "pixels_x" if fast_x else "pixels_y"
            raise ValueError(
                f"{name}={pixels}: a trace at line_rate {request.line_rate} Hz "
                f"has {n_half} samples at "
                f"sample_rate {self.fs:g} Hz, fewer than one per pixel; "
                "lower line_rate to at most "
                f"{self.fs / (2 * pixels):.4g} Hz"
            )
        self._check_ramp_samples(2 * n_half, f"line_rate={request.line_rate} Hz: a line")
        self._check_plan(self._raster_steps(request))

        height = np.full((request.pixels_y, request.pixels_x), np.nan)
        line_times = np.full(lines, np.nan)
        bins = np.arange(n_half) * pixels // n_half
        counts = np.bincount(bins, minlength=pixels)
        start, done, wrote, complete = None, 0, False, True
        for step in self._raster_steps(request):
            if self._stopped(should_stop):
                if wrote:
                    self._hold()
                complete = False
                break
            if step.kind == "line" and start is None:
                start = self.time
            t = self.time
            ai = self._write(step)
            wrote = True
            if step.kind != "line":
                continue
            topography = self._measure(ai)[0][:n_half]
            pixel_values = np.bincount(bins, weights=topography, minlength=pixels) / counts
            if fast_x:
                height[step.index, :] = pixel_values
            else:
                height[:, step.index] = pixel_values
            line_times[step.index] = t - start
            done += 1
            if on_line:
                on_line(done, lines)
        return RasterScanData(
            height=height,
            pixel_size_x=request.size_x / request.pixels_x,
            pixel_size_y=request.size_y / request.pixels_y,
            origin_x=request.origin_x,
            origin_y=request.origin_y,
            scan_angle_deg=request.scan_angle_deg,
            slow_scan_up=request.slow_scan_up,
            line_period=2 * n_half / self.fs,
            line_start_times=line_times,
            start_time=self.time if start is None else start,
            mode=request.mode,
            complete=complete,
        )

    # ---- local scan ------------------------------------------------------------------------
    def local_scan(
        self, request: LineRequest, should_stop: StopCheck | None = None
    ) -> ScanLineData:
        """One synchronised ramp start -> end at `speed`; the DAQ samples are averaged into
        `samples` equal bins (times, positions and signals are the bin means)."""
        request.validate(self.limits)
        n = max(2, math.ceil(request.length / request.speed * self.fs - 1e-9))
        if n < request.samples:
            raise ValueError(
                f"samples={request.samples}: the line takes {n / self.fs:.4g} s, "
                f"only {n} DAQ samples at "
                f"sample_rate {self.fs:g} Hz; request at most {n} samples or a lower speed"
            )
        self._check_ramp_samples(n, f"speed={request.speed:.4e} m/s: the line")

        def plan():
            yield from self._travel(request.start_x, request.start_y, self.travel_speed, "start")
            k = np.arange(1, n + 1) / n
            yield _Step(
                "scan",
                request.start_x + (request.end_x - request.start_x) * k,
                request.start_y + (request.end_y - request.start_y) * k,
                np.full(n, self._z),
                "start / end / speed",
            )

        self._check_plan(plan())

        bins = np.arange(n) * request.samples // n
        counts = np.bincount(bins, minlength=request.samples)

        def binned(values):
            return np.bincount(bins, weights=values, minlength=request.samples) / counts

        wrote = False
        for step in plan():
            if self._stopped(should_stop):
                if wrote:
                    self._hold()
                nan = np.full(request.samples, np.nan)
                return ScanLineData(
                    times=nan,
                    x=nan.copy(),
                    y=nan.copy(),
                    height=nan.copy(),
                    deflection=nan.copy(),
                    amplitude=np.empty(0),
                    start_time=self.time,
                    mode=request.mode,
                    complete=False,
                )
            start = self.time
            ai = self._write(step)
            wrote = True
        height, deflection, _ = self._measure(ai)
        return ScanLineData(
            times=binned(np.arange(1, n + 1) / self.fs),
            x=binned(step.x),
            y=binned(step.y),
            height=binned(height),
            deflection=binned(deflection),
            amplitude=np.empty(0),
            start_time=start,
            mode=request.mode,
        )

    # ---- move ------------------------------------------------------------------------------
    def _recorder(self, planned_samples: int) -> TraceRecorder:
        return TraceRecorder(self.fs, planned_samples, self.calibration.max_trace_samples)

    def _record(self, recorder: TraceRecorder, step: _Step, t: float, ai: np.ndarray) -> None:
        """One written chunk into the trace; `t` is when it started, relative to the trace."""
        _, deflection, lateral = self._measure(ai)
        times = t + np.arange(1, len(step.x) + 1) / self.fs
        recorder.add(t=times, x=step.x, y=step.y, z=step.z, d=deflection, l=lateral)

    def _trace(self, recorder: TraceRecorder, start: float, task: str) -> ForceTraceData:
        cat = recorder.arrays()
        c = self.calibration
        return ForceTraceData(
            times=cat["t"],
            commanded_x=cat["x"],
            commanded_y=cat["y"],
            commanded_z=cat["z"],
            vertical_deflection=cat["d"],
            lateral_torsion=cat["l"],
            normal_spring_constant=c.normal_spring_constant,
            lateral_spring_constant=c.lateral_spring_constant,
            sample_rate=recorder.sample_rate,
            start_time=start,
            task=task,
        )

    def move_tip(
        self,
        x: float,
        y: float,
        speed: float,
        contact: bool = False,
        should_stop: StopCheck | None = None,
    ) -> MoveResult:
        """Rate-limited ramp to (x, y); in contact (a push) deflection and torsion are recorded."""
        validate_move(x, y, speed, self.limits)
        planned = self._check_plan(self._travel(x, y, speed, "target / speed"))
        start, completed = self.time, True
        recorder = self._recorder(sum(planned.values()))
        for i, step in enumerate(self._travel(x, y, speed, "target / speed")):
            if self._stopped(should_stop):
                if i:
                    self._hold()
                completed = False
                break
            t = self.time
            ai = self._write(step)
            if contact:
                self._record(recorder, step, t - start, ai)
        trace = self._trace(recorder, start, "push") if contact else None
        return MoveResult(end_x=self._pos[0], end_y=self._pos[1], completed=completed, trace=trace)

    # ---- indent ----------------------------------------------------------------------------
    def _retract_now(self, z0: float) -> str:
        """The card failed while the tip may be pressed in: one static step of the z output
        back to `z0` (away from the sample: never leave the tip pressed in), x/y kept.
        Returns what went wrong, or "" when z is back at `z0`."""
        if self._z == z0:
            return ""
        c = self.calibration
        levels = self._last.copy()
        levels[2] = c.z_offset_volts + c.z_volts_per_metre * z0
        try:
            self.boundary.write_static(levels)
        except Exception as exc:  # noqa: BLE001 - reported with the card's first failure
            return f"{type(exc).__name__}: {exc}"
        self._last, self._z = levels, z0
        return ""

    def indent(
        self, x: float, y: float, force: float, dwell: float, should_stop: StopCheck | None = None
    ) -> IndentResult:
        """Press at (x, y): ramp the z output by force / normal_spring_constant from the current
        (in contact, zero deflection) level, dwell, retract; returns the deflection trace.

        On a stiff sample the cantilever bends by that z travel, so the force reaches `force`;
        on a soft one it stays lower, which the returned deflection shows. A cancel during the
        press still retracts: the tip is never left pressed into the sample.
        """
        validate_indent(x, y, force, dwell, self.limits)
        c = self.calibration
        if not c.ao_z:
            raise ValueError(
                "indent: needs an AO z channel (DaqCalibration.ao_z is not set); this DAQ "
                "set-up can only move laterally"
            )
        depth = force / c.normal_spring_constant
        if depth > self.limits.range_z:
            raise ValueError(
                f"force={force:.3e} N: needs {depth:.3e} m of z travel "
                "(force / normal_spring_constant), "
                f"above range_z {self.limits.range_z:.3e} m"
            )
        z0 = self._z
        field = f"force={force:.3e} N"

        def press():
            yield from self._ramp(
                (x, y, z0), (x, y, z0 + depth), depth / self.indent_speed, "press", field
            )
            if dwell > 0:
                yield from self._ramp(
                    (x, y, z0 + depth), (x, y, z0 + depth), dwell, "press", field
                )

        def plan():
            yield from self._travel(x, y, self.travel_speed, "position")
            yield from press()
            yield from self._ramp(
                (x, y, z0 + depth), (x, y, z0), depth / self.indent_speed, "retract", field
            )

        planned = self._check_plan(plan())
        recorder = self._recorder(planned.get("press", 0) + planned.get("retract", 0))
        wrote, completed, start = False, True, None
        for step in self._travel(x, y, self.travel_speed, "position"):
            if self._stopped(should_stop):
                if wrote:
                    self._hold()
                return IndentResult(
                    x=self._pos[0],
                    y=self._pos[1],
                    trace=self._trace(recorder, self.time, "indent"),
                    completed=False,
                )
            self._write(step)
            wrote = True
        start = self.time
        try:
            for step in press():
                if self._stopped(should_stop):
                    completed = False
                    break
                t = self.time
                self._record(recorder, step, t - start, self._write(step))
            if self._z != z0:  # always retract, from wherever the press stopped
                for step in self._ramp(
                    (x, y, self._z),
                    (x, y, z0),
                    abs(self._z - z0) / self.indent_speed,
                    "retract",
                    field,
                ):
                    t = self.time
                    self._record(recorder, step, t - start, self._write(step))
        except InstrumentUnavailable as exc:
            problem = self._retract_now(z0)
            if problem:
                raise InstrumentUnavailable(
                    f"{exc}; retracting z failed too ({problem}): the tip may still be pressed in"
                ) from exc
            raise
        return IndentResult(
            x=x, y=y, trace=self._trace(recorder, start, "indent"), completed=completed
        )
