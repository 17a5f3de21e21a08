"""The simulated AFM: the instrument our users do not have on their desk.

Commands go through the scanner model (hysteresis, creep, cross-coupling, line deflection)
to a true scanner position; thermal drift moves the sample against the scanner; the tip
sees the sample where it truly is at the moment of each sample. Every call advances the
instrument clock `time` by what the motion takes, so sim time runs as fast as the host
can compute. Deterministic: the same config (seed included) gives the same data.

The measurement chain on top of the physics (each off by default, and then exactly absent):
the scanner bow (the tube's end swings on an arc, adding 0.5 c r^2 to every measured height,
r from the range centre), the z sensor's gain (measured height = gain x the feedback's
height about the mean substrate plane) and its latency (every measured signal reports at t
the value it took at t - latency, while positions are stamped with the commands at t).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from afm_core.instrument import (
    ForceTraceData,
    IndentResult,
    LineRequest,
    MoveResult,
    RasterScanData,
    ScanLineData,
    ScanRequest,
    StopCheck,
    validate_indent,
    validate_move,
)
from afm_core.physics.contact import StickSlipState
from afm_core.physics.pushing import push_along_path
from afm_core.physics.sample import Electrode, Pit, Rod, Roughness, Sample, Sphere
from afm_core.pzt import LateralScanner, PrandtlIshlinskii
from afm_core.sim.config import SimConfig, load_config
from afm_core.sim.drift import ThermalDrift
from afm_core.sim.generic_terms import line_jitter_sd, parse_generic_terms, total_offset
from afm_core.sim.imaging import DilatedField, dilated_heights_at, pink_noise
from afm_core.sim.tip import Tip

LINES_PER_CHUNK = 16  # raster lines simulated at once (progress and cancel granularity)
MOVE_STEP = 2e-9  # m, path sampling of moves (pushes resolve objects finer inside)
IDLE_STEP = 0.05  # s, scanner sampling while holding still (creep keeps going)
INDENT_SAMPLES = 200
# The widest tip grid an image is simulated with: each band's dilation costs up to the grid's
# pixels times the band's, so finer pixels than this allows (a 100 nm image at 64 px is fine,
# 1 nm at 64 px would need a 10,000 px grid and took the driver to 23 GB) are refused
MAX_TIP_GRID = 257  # px across


class RasterPath:
    """The commanded path of a raster image: each line traced along the fast axis and retraced,
    the lines in slow-scan order (up or down), pixel centres."""

    def __init__(self, request: ScanRequest):
        self.fast_is_x = request.scan_angle_deg == 0.0
        self.n_fast, self.n_lines = request.pixels_per_line, request.lines
        self.pixel_x, self.pixel_y = (
            request.size_x / request.pixels_x,
            request.size_y / request.pixels_y,
        )
        fast_pixel, slow_pixel = (
            (self.pixel_x, self.pixel_y) if self.fast_is_x else (self.pixel_y, self.pixel_x)
        )
        fast_origin, slow_origin = (
            (request.origin_x, request.origin_y)
            if self.fast_is_x
            else (request.origin_y, request.origin_x)
        )
        fast_coords = fast_origin + (np.arange(self.n_fast) + 0.5) * fast_pixel
        self.line_order = (
            np.arange(self.n_lines) if request.slow_scan_up else np.arange(self.n_lines)[::-1]
        )
        self.slow_coords = slow_origin + (self.line_order + 0.5) * slow_pixel
        self.trace_back = np.concatenate([fast_coords, fast_coords[::-1]])
        self.first = self.to_xy(fast_coords[0], self.slow_coords[0])

    def to_xy(self, fast, slow):
        return (fast, slow) if self.fast_is_x else (slow, fast)

    def chunk(self, done: int):
        """(line indices, commanded x, y) of the next LINES_PER_CHUNK lines after `done`."""
        lines = self.line_order[done : done + LINES_PER_CHUNK]
        slow = np.repeat(self.slow_coords[done : done + len(lines)], 2 * self.n_fast)
        return (lines, *self.to_xy(np.tile(self.trace_back, len(lines)), slow))


class _DelayedPath:
    """Where the tip truly was `latency` before each sample time, from the path driven so far
    in one acquisition: the sensor reports at t the value it took at t - latency. Positions are
    interpolated linearly between samples (the path between samples is a straight ramp);
    before the acquisition's first sample the tip rests where it started."""

    def __init__(self, latency: float, t0: float, x0: float, y0: float):
        self.latency = latency
        self.t, self.x, self.y = np.array([t0]), np.array([x0]), np.array([y0])

    def __call__(self, times: np.ndarray, xs: np.ndarray, ys: np.ndarray):
        t, x, y = (
            np.concatenate([self.t, times]),
            np.concatenate([self.x, xs]),
            np.concatenate([self.y, ys]),
        )
        query = np.maximum(times - self.latency, t[0])
        delayed = query, np.interp(query, t, x), np.interp(query, t, y)
        # later queries start after times[-1] - latency: keep the samples from just before that
        keep = max(0, int(np.searchsorted(t, times[-1] - self.latency, side="right")) - 2)
        self.t, self.x, self.y = t[keep:], x[keep:], y[keep:]
        return delayed


def delay_samples(signal: np.ndarray, delay: float) -> np.ndarray:
    """The signal delayed by `delay` samples (fractional: linear interpolation), the first
    sample held before the start."""
    index = np.arange(signal.size, dtype=float)
    return np.interp(index - delay, index, signal)


def build_sample(config: SimConfig, rng: np.random.Generator) -> Sample:
    params = config.sample
    sample = Sample(
        roughness=Roughness(
            params.roughness_sigma, params.roughness_correlation, int(rng.integers(2**31))
        )
    )
    next_id = 0
    for spec in params.spheres:
        sample.spheres.append(
            Sphere(next_id, float(spec["x"]), float(spec["y"]), float(spec["radius"]))
        )
        next_id += 1
    x0, y0, width, height = params.random_area
    for _ in range(params.random_spheres):
        radius = max(10e-9, rng.normal(params.radius_mean, params.radius_sigma))
        sample.spheres.append(
            Sphere(next_id, x0 + rng.uniform() * width, y0 + rng.uniform() * height, radius)
        )
        next_id += 1
    for spec in params.rods:
        sample.rods.append(
            Rod(
                next_id,
                float(spec["x"]),
                float(spec["y"]),
                float(spec.get("angle", 0.0)),
                float(spec["length"]),
                float(spec["radius"]),
                spec.get("kind", "rod"),
            )
        )
        next_id += 1
    for spec in params.electrodes:
        sample.electrodes.append(
            Electrode(
                next_id,
                float(spec["x0"]),
                float(spec["y0"]),
                float(spec["x1"]),
                float(spec["y1"]),
                float(spec["thickness"]),
            )
        )
        next_id += 1
    return sample


class SimulatedAfm:
    def __init__(self, config: SimConfig | None = None):
        self.config = config if config is not None else load_config()
        self.limits = self.config.limits
        streams = np.random.SeedSequence(self.config.seed).spawn(5)
        self.noise_rng = np.random.default_rng(streams[0])
        self.sample = build_sample(self.config, np.random.default_rng(streams[1]))
        self.drift = ThermalDrift(
            self.config.drift, seed=int(np.random.default_rng(streams[2]).integers(2**31))
        )
        self.tip = Tip(self.config.tip)
        self.scanner = LateralScanner(self.config.scanner)
        self.positioning_rng = np.random.default_rng(streams[4])
        self._position_error = np.zeros(2)  # m, accumulated random error of the moves so far
        self.feed_forward = self._controller_feed_forward()
        self._generic = parse_generic_terms(self.config.generic_terms)
        self._jitter_sd = line_jitter_sd(self._generic)
        self._jitter_rng = None  # drawn from the sensor noise's seed at first use
        self._open_loop_models = None  # the controller's forward models while feed-forward is off
        self.time = 0.0
        self._commanded = tuple(float(c) for c in self.scanner.centre)  # at rest at power-on
        self.scanner.reset(*self._commanded)
        self._true_scanner = self._commanded

    def _controller_models(self):
        """Per axis, the controller's calibrated hysteresis model (the scanner's own, with the
        loop width off by model_error and the asymmetry by asymmetry_error), demagnetised; None
        when compensation is off."""
        scanner, controller = self.config.scanner, self.config.controller
        if not (
            controller.hysteresis_compensation
            and scanner.hysteresis_enabled
            and scanner.hysteresis_fraction > 0
        ):
            return None
        if not (math.isfinite(controller.model_error) and controller.model_error > -1.0):
            raise ValueError(
                f"controller.model_error={controller.model_error}: must be finite and > -1 "
                "(relative error of the calibrated loop width)"
            )
        fraction = scanner.hysteresis_fraction * (1.0 + controller.model_error)
        asymmetry = scanner.hysteresis_asymmetry - controller.asymmetry_error
        if not (math.isfinite(asymmetry) and asymmetry * asymmetry < 2.0 / 3.0):
            raise ValueError(
                f"controller.asymmetry_error={controller.asymmetry_error}: the controller's "
                f"asymmetry (scanner.hysteresis_asymmetry minus it) is {asymmetry}; need a finite "
                "value with square < 2/3"
            )
        models = [
            PrandtlIshlinskii.from_fraction(
                span, fraction, int(scanner.hysteresis_operators), asymmetry
            )
            for span in (scanner.range_x, scanner.range_y)
        ]
        for model in models:
            model.reset(0.0)
        return models

    def _controller_feed_forward(self):
        """Per axis, the inverse of the controller's model (see _controller_models); None when
        compensation is off."""
        models = self._controller_models()
        return None if models is None else [model.inverse() for model in models]

    @property
    def feed_forward_enabled(self) -> bool:
        """Whether the controller's hysteresis feed-forward (inverse PI, book eq. 5.24-5.28) is
        applied to every command.

        Switched off, commands go to the piezo amplifiers as they are: the open-loop drive the
        book's hysteresis calibration applies (7.2.2), in metres of nominal displacement (volts
        times the nominal sensitivity), and `commanded_position()` reports that drive. Switching
        never moves the tip and keeps the controller's memory consistent: off, the command
        becomes the drive the piezos receive at that moment, and the controller's forward model
        (its state recovered from the inverse's) follows the raw drive from then on; on again,
        that model is inverted with its state (exact, PrandtlIshlinskii.inverse) and the command
        becomes the position it predicts for the current drive. False, and cannot be switched
        on, when the configuration has no compensation (controller.hysteresis_compensation)."""
        return self.feed_forward is not None

    @feed_forward_enabled.setter
    def feed_forward_enabled(self, enabled: bool) -> None:
        enabled = bool(enabled)
        if enabled == self.feed_forward_enabled:
            return
        centre = self.scanner.centre
        if not enabled:
            drive, models = [], self._controller_models()
            for axis, (inverse, model) in enumerate(zip(self.feed_forward, models)):
                # re-applying the last command leaves a play operator where it is: the current
                # drive
                drive.append(
                    float(centre[axis] + inverse.apply([self._commanded[axis] - centre[axis]])[-1])
                )
                # inverse states z'_i = W_i z_i + sum_{j>i} w_j z_j (InversePrandtlIshlinskii):
                # solve for z
                w = model.weights
                coupling = np.triu(np.tile(w, (w.size, 1)), 1) + np.diag(np.cumsum(w))
                model.state = np.linalg.solve(coupling, inverse.state)
            self._open_loop_models, self.feed_forward = models, None
            self._commanded = tuple(drive)
            return
        if self._open_loop_models is None:
            raise ValueError(
                "feed_forward_enabled=True: this configuration has no hysteresis compensation "
                "(controller.hysteresis_compensation, scanner.hysteresis_enabled)"
            )
        commanded = [
            float(centre[axis] + model.apply([self._commanded[axis] - centre[axis]])[-1])
            for axis, model in enumerate(self._open_loop_models)
        ]
        self.feed_forward = [model.inverse() for model in self._open_loop_models]
        self._open_loop_models = None
        self._commanded = tuple(commanded)

    # -- the machine underneath ------------------------------------------------------------
    def commanded_position(self) -> tuple[float, float]:
        return self._commanded

    def _drive(
        self,
        cmd_x: np.ndarray,
        cmd_y: np.ndarray,
        dt: float,
        position_error: np.ndarray | None = None,
    ):
        """Send a uniformly sampled command path; returns (times, true scanner x, y).
        Sample k is taken at time + (k + 1) * dt. position_error (2, n), m: the moves' random
        error along this path (default: the error accumulated so far, held)."""
        drive_x, drive_y = np.asarray(cmd_x, float), np.asarray(cmd_y, float)
        if self.feed_forward is not None:
            centre = self.scanner.centre
            drive_x = centre[0] + self.feed_forward[0].apply(drive_x - centre[0])
            drive_y = centre[1] + self.feed_forward[1].apply(drive_y - centre[1])
        elif (
            self._open_loop_models is not None
        ):  # feed-forward off: the controller's model follows the drive
            centre = self.scanner.centre
            self._open_loop_models[0].apply(drive_x - centre[0])
            self._open_loop_models[1].apply(drive_y - centre[1])
        true_x, true_y = self.scanner.apply(drive_x, drive_y, dt)
        if self._generic:
            true_x, true_y = self._generic_displacement(true_x, true_y, dt)
        if position_error is None:
            true_x, true_y = true_x + self._position_error[0], true_y + self._position_error[1]
        else:
            true_x, true_y = true_x + position_error[0], true_y + position_error[1]
            self._position_error = position_error[:, -1].copy()
        times = self.time + dt * np.arange(1, len(cmd_x) + 1)
        self.time = float(times[-1]) if len(times) else self.time
        self._commanded = (float(cmd_x[-1]), float(cmd_y[-1]))
        self._true_scanner = (float(true_x[-1]), float(true_y[-1]))
        return times, true_x, true_y

    def _generic_displacement(self, true_x, true_y, dt):
        """The scanner's true position displaced by the generic lateral terms (x_position,
        y_position: functions of where the scanner truly is, both taken at the undisplaced
        place)."""
        times = self.time + dt * np.arange(1, np.size(true_x) + 1)
        dx = total_offset(self._generic, "x_position", times, true_x, true_y)
        dy = total_offset(self._generic, "y_position", times, true_x, true_y)
        return (
            true_x if dx is None else true_x + dx,
            true_y if dy is None else true_y + dy,
        )

    def sample_frame(self, true_x, true_y, times):
        """Where the tip is on the sample (afm_task): the sample has drifted by offset(t)."""
        offset = self.drift.offset(times)
        return true_x - offset[..., 0], true_y - offset[..., 1]

    def _measured_height(
        self, height: np.ndarray, true_x: np.ndarray, true_y: np.ndarray
    ) -> np.ndarray:
        """What the z sensor reports for the feedback's height (m above the mean substrate
        plane) with the scanner truly at (true_x, true_y): plus the scanner bow, times the
        sensor's gain. Noise is added by the caller (it is in the reported signal, not scaled)."""
        if self._has_bow():
            height = height + self._bow(true_x, true_y)
        return self._height_gain(height)

    def _line_jitter(self, lines: int) -> np.ndarray:
        """The generic line_jitter's offsets (m) of the next `lines` scan lines. Its generator
        is spawned from the sensor noise's seed without drawing from it, so the noise itself is
        the same with and without the term, and another noise seed draws other offsets."""
        if self._jitter_rng is None:
            self._jitter_rng = np.random.default_rng(
                self.noise_rng.bit_generator.seed_seq.spawn(1)[0]
            )
        return self._jitter_rng.normal(0.0, self._jitter_sd, lines)

    def _generic_offset(self, signal, at_t, at_x, at_y, values) -> np.ndarray:
        """The generic terms' offset on a raster chunk's trace pixels (values: their heights,
        rows of the chunk; at_t, at_x, at_y: the chunk's trace and retrace samples)."""
        rows, n_fast = values.shape
        trace = [a.reshape(rows, 2 * n_fast)[:, :n_fast] for a in (at_t, at_x, at_y)]
        extra = total_offset(self._generic, signal, *trace, values)
        return np.zeros_like(values) if extra is None else extra

    def _has_bow(self) -> bool:
        return self.config.scanner.bow_curvature != 0.0

    def _bow(self, true_x: np.ndarray, true_y: np.ndarray) -> np.ndarray:
        """z of the scanner bow (m): the tube's free end swings on a sphere-like arc, rising by
        0.5 c r^2 at a distance r from the range centre (where the tube is straight)."""
        cx, cy = self.scanner.centre
        return 0.5 * self.config.scanner.bow_curvature * ((true_x - cx) ** 2 + (true_y - cy) ** 2)

    def _height_gain(self, height: np.ndarray) -> np.ndarray:
        gain = self.config.noise.height_gain
        return height if gain == 1.0 else gain * height

    def hold(self, duration: float) -> None:
        """Time passes with the command held (creep and drift go on)."""
        if duration <= 0:
            return
        n = max(1, int(math.ceil(duration / IDLE_STEP)))
        self._drive(np.full(n, self._commanded[0]), np.full(n, self._commanded[1]), duration / n)

    def _ramp(self, x: float, y: float, speed: float):
        x0, y0 = self._commanded
        distance = math.hypot(x - x0, y - y0)
        n = max(2, int(math.ceil(distance / MOVE_STEP)))
        s = np.linspace(0.0, 1.0, n + 1)[1:]
        path_x, path_y = x0 + s * (x - x0), y0 + s * (y - y0)
        path_x[-1], path_y[-1] = x, y  # end exactly where commanded
        return path_x, path_y, (distance / speed) / n if distance else 1e-3

    def _imaging_depth(self) -> float:
        tallest = max(
            [2 * s.radius for s in self.sample.spheres]
            + [2 * r.radius for r in self.sample.rods]
            + [e.thickness for e in self.sample.electrodes]
            + [20e-9]
        )
        return tallest + 10e-9

    # -- raster images -----------------------------------------------------------------------
    def raster_scan(
        self,
        request: ScanRequest,
        on_line: Callable[[int, int], None] | None = None,
        should_stop: StopCheck | None = None,
    ) -> RasterScanData:
        request.validate(self.limits)
        self._check_tip_grid(request)
        path = RasterPath(request)
        fast_is_x, n_fast, n_lines, line_order = (
            path.fast_is_x,
            path.n_fast,
            path.n_lines,
            path.line_order,
        )
        px, py = path.pixel_x, path.pixel_y
        self.move_tip(*path.first, self.limits.max_speed / 10)
        line_period = 1.0 / request.line_rate
        dt = 0.5 * line_period / n_fast  # trace in the first half, retrace in the second
        field = self._field_for(request)
        latency = self.config.noise.sensor_latency
        delayed = _DelayedPath(latency, self.time, *self._true_scanner) if latency > 0 else None
        height = np.full((request.pixels_y, request.pixels_x), np.nan)
        line_start = np.full(n_lines, np.nan)
        start = self.time
        done = 0
        complete = True
        while done < n_lines:
            if should_stop is not None and should_stop():
                complete = False
                break
            chunk, cmd_x, cmd_y = path.chunk(done)
            times, tx, ty = self._drive(cmd_x, cmd_y, dt)
            # with sensor latency a pixel reports where the tip was `latency` before its time
            at_t, at_x, at_y = (times, tx, ty) if delayed is None else delayed(times, tx, ty)
            sx, sy = self.sample_frame(at_x, at_y, at_t)
            if self._jitter_sd > 0.0:  # each line read at its own offset along the fast axis
                shift = np.repeat(self._line_jitter(len(chunk)), 2 * n_fast)
                sx, sy = (sx + shift, sy) if fast_is_x else (sx, sy + shift)
            values = field.at(sx, sy).reshape(len(chunk), 2 * n_fast)[:, :n_fast]
            if self._has_bow() or self.config.noise.height_gain != 1.0:
                trace_x, trace_y = (
                    a.reshape(len(chunk), 2 * n_fast)[:, :n_fast] for a in (at_x, at_y)
                )
                values = self._measured_height(values, trace_x, trace_y)
            if self._generic:
                values = values + self._generic_offset("height", at_t, at_x, at_y, values)
            values = values + self.noise_rng.normal(
                0.0, self.config.noise.height_white_sigma, values.shape
            )
            line_times = times.reshape(len(chunk), 2 * n_fast)[:, 0] - dt - start
            for row_values, line_index, t_line in zip(values, chunk, line_times):
                if fast_is_x:
                    height[line_index, :] = row_values
                else:
                    height[:, line_index] = row_values
                line_start[line_index] = t_line
                done += 1
                if on_line is not None:
                    on_line(done, n_lines)
        acquired = np.isfinite(line_start)
        flicker = pink_noise(
            int(acquired.sum()) * n_fast, self.config.noise.height_flicker_sigma, self.noise_rng
        )
        order = [i for i in line_order if acquired[i]]
        for k, line_index in enumerate(order):
            segment = flicker[k * n_fast : (k + 1) * n_fast]
            if fast_is_x:
                height[line_index, :] += segment
            else:
                height[:, line_index] += segment
        return RasterScanData(
            height=height.astype(np.float32),
            pixel_size_x=px,
            pixel_size_y=py,
            origin_x=request.origin_x,
            origin_y=request.origin_y,
            scan_angle_deg=request.scan_angle_deg,
            slow_scan_up=request.slow_scan_up,
            line_period=line_period,
            line_start_times=line_start,
            start_time=start,
            mode=request.mode,
            complete=complete,
        )

    def _check_tip_grid(self, request: ScanRequest) -> None:
        """ValueError, before anything moves, when the image's pixels are finer than the
        simulator can dilate with this tip over this sample (MAX_TIP_GRID)."""
        pixel = min(request.size_x / request.pixels_x, request.size_y / request.pixels_y)
        reach = self.tip.reach(self._imaging_depth())
        across = 2 * math.ceil(reach / pixel) + 1
        if across > MAX_TIP_GRID:
            finest = 2 * reach / (MAX_TIP_GRID - 1)
            raise ValueError(
                f"pixel size {pixel * 1e9:.3g} nm: finer than the simulator images with this "
                f"tip and sample (its tip grid would be {across} px across, at most "
                f"{MAX_TIP_GRID}); use pixels of at least {finest * 1e9:.2g} nm (fewer pixels or "
                "a larger area)"
            )

    def _field_for(self, request: ScanRequest) -> DilatedField:
        """Dilated surface over the scan area plus a margin for where hysteresis, creep and
        drift may have put the tip: the drift offset and 5 % of the size (+20 nm) for the
        scanner's error. Where the scanner's present error (true minus commanded: the
        compensation residual, microns after a long history) alone exceeds that allowance,
        the field grows by it in whole pixels (the same lattice; an image within the
        allowance is computed as before); without it a thin rescan box missed every pit
        (issue 37: 1.7 um error against a 0.45 um allowance)."""
        pixel = min(request.size_x / request.pixels_x, request.size_y / request.pixels_y)
        allowance = 0.05 * max(request.size_x, request.size_y) + 20e-9
        margin = allowance + float(
            np.max(
                np.abs(self.drift.offset(self.time + 2 * request.lines / request.line_rate + 10.0))
            )
        )
        error = float(np.max(np.abs(np.subtract(self._true_scanner, self._commanded))))
        grow = math.ceil(error / pixel) * pixel if error > allowance else 0.0
        x0, y0 = request.origin_x - margin - grow, request.origin_y - margin - grow
        nx = int(math.ceil((request.size_x + 2 * margin) / pixel)) + 1 + 2 * round(grow / pixel)
        ny = int(math.ceil((request.size_y + 2 * margin) / pixel)) + 1 + 2 * round(grow / pixel)
        tip = self.tip.grid(pixel, self._imaging_depth())
        return DilatedField(
            self.sample.height, tip, x0, y0, nx, ny, pixel, request.scan_angle_deg == 0.0
        )

    # -- local scan lines --------------------------------------------------------------------
    def local_scan(
        self, request: LineRequest, should_stop: StopCheck | None = None
    ) -> ScanLineData:
        request.validate(self.limits)
        self.move_tip(request.start_x, request.start_y, self.limits.max_speed / 10)
        s = np.linspace(0.0, 1.0, request.samples)
        cmd_x = request.start_x + s * (request.end_x - request.start_x)
        cmd_y = request.start_y + s * (request.end_y - request.start_y)
        dt = request.length / request.speed / (request.samples - 1)
        times, tx, ty = self._drive(cmd_x, cmd_y, dt)
        times = times - dt  # the first sample is taken where the line starts, at once
        start = float(times[0])
        noise = self.config.noise
        # with sensor latency each sample reports where the tip was `latency` before its time
        at_t, at_x, at_y = (
            (times, tx, ty)
            if noise.sensor_latency == 0
            else _DelayedPath(noise.sensor_latency, float(times[0]), float(tx[0]), float(ty[0]))(
                times, tx, ty
            )
        )
        sx, sy = self.sample_frame(at_x, at_y, at_t)
        if self._jitter_sd > 0.0:  # the line read at its own offset along its direction
            shift = float(self._line_jitter(1)[0]) / max(request.length, 1e-12)
            sx = sx + shift * (request.end_x - request.start_x)
            sy = sy + shift * (request.end_y - request.start_y)
        spacing = request.length / (request.samples - 1)
        tip = self.tip.grid(max(min(spacing, 5e-9), 0.5e-9), self._imaging_depth())
        height = dilated_heights_at(self.sample, tip, max(min(spacing, 5e-9), 0.5e-9), sx, sy)
        if self._has_bow():  # the feedback follows the bow too: it is in the lag error
            height = height + self._bow(at_x, at_y)
        slope = np.gradient(height, times) if len(times) > 1 else np.zeros_like(height)
        deflection = noise.feedback_time_constant * slope + self.noise_rng.normal(
            0, noise.deflection_sigma, len(s)
        )
        height = self._height_gain(height)
        extra = total_offset(self._generic, "height", at_t, at_x, at_y, height)
        if extra is not None:  # None: no generic term on the height (a torsion one, say)
            height = height + extra
        height = height + self.noise_rng.normal(0, noise.height_white_sigma, len(s))
        height = height + pink_noise(len(s), noise.height_flicker_sigma, self.noise_rng)
        amplitude = (
            (np.full(len(s), 10e-9) - deflection) if request.mode == "tapping" else np.array([])
        )
        return ScanLineData(
            times=times - start,
            x=cmd_x,
            y=cmd_y,
            height=height,
            deflection=deflection,
            amplitude=amplitude,
            start_time=start,
            mode=request.mode,
        )

    # -- moves and pushes --------------------------------------------------------------------
    def move_tip(
        self,
        x: float,
        y: float,
        speed: float,
        contact: bool = False,
        should_stop: StopCheck | None = None,
    ) -> MoveResult:
        validate_move(x, y, speed, self.limits)
        error_path = self._positioning_error_path(x, y)
        cmd_x, cmd_y, dt = self._ramp(x, y, speed)
        start = self.time
        chunks = np.array_split(np.arange(len(cmd_x)), max(1, len(cmd_x) // 2000))
        traces = []
        completed = True
        stick_slip, last_x, last_y = None, 0.0, 0.0
        if contact:
            # the tip lands where it is: the slid distance (wear) and the stick-slip spring start
            # here
            here = self.sample_frame(
                np.array([self._true_scanner[0]]),
                np.array([self._true_scanner[1]]),
                np.array([self.time]),
            )
            last_x, last_y = float(here[0][0]), float(here[1][0])
            stick_slip = (
                StickSlipState(0.0, last_x, last_y)
                if self.config.contact.stick_slip_enabled
                else None
            )
        for index in chunks:
            if should_stop is not None and should_stop():
                completed = False
                break
            times, tx, ty = self._drive(
                cmd_x[index],
                cmd_y[index],
                dt,
                None if error_path is None else error_path[:, index],
            )
            if contact:
                sx, sy = self.sample_frame(tx, ty, times)
                result = push_along_path(self.sample, sx, sy, dt, self.config.contact, stick_slip)
                self.tip.slide(
                    float(
                        np.sum(np.hypot(np.diff(sx, prepend=last_x), np.diff(sy, prepend=last_y)))
                    )
                )
                last_x, last_y = float(sx[-1]), float(sy[-1])
                traces.append((times, cmd_x[index], cmd_y[index], result))
        trace = self._force_trace(traces, start, dt) if contact and traces else None
        end_x, end_y = self._commanded
        return MoveResult(end_x=end_x, end_y=end_y, completed=completed, trace=trace)

    def _positioning_error_path(self, x: float, y: float) -> np.ndarray | None:
        """The random error a move to (x, y) adds (variance slope x distance + offset per axis),
        growing along the move's ramp; None when the noise is off or nothing moves."""
        params = self.config.scanner
        x0, y0 = self._commanded
        distance = math.hypot(x - x0, y - y0)
        if not params.positioning_noise_enabled or distance == 0.0:
            return None
        variance = params.positioning_noise_slope * distance + params.positioning_noise_offset
        step = self.positioning_rng.normal(0.0, math.sqrt(variance), 2)
        n = len(self._ramp(x, y, 1.0)[0])
        fraction = np.arange(1, n + 1) / n
        return self._position_error[:, None] + step[:, None] * fraction[None, :]

    def _force_trace(self, pieces, start: float, dt: float) -> ForceTraceData:
        contact = self.config.contact
        times = np.concatenate([p[0] for p in pieces]) - start
        cx = np.concatenate([p[1] for p in pieces])
        cy = np.concatenate([p[2] for p in pieces])
        deflection = np.concatenate([p[3].vertical_deflection for p in pieces])
        torsion = np.concatenate([p[3].lateral_torsion for p in pieces])
        latency = self.config.noise.sensor_latency
        if latency > 0:  # the signals lag the commands (sampled at 1/dt)
            deflection, torsion = (
                delay_samples(deflection, latency / dt),
                delay_samples(torsion, latency / dt),
            )
        deflection = deflection + self.noise_rng.normal(
            0, self.config.noise.deflection_sigma, len(deflection)
        )
        if self._generic:
            # deflection_proportional scales the deflection as measured (with its noise)
            extra = total_offset(self._generic, "torsion", times + start, cx, cy, deflection)
            torsion = torsion if extra is None else torsion + extra
        moved = sorted({i for p in pieces for i in p[3].moved_ids})
        return ForceTraceData(
            times=times,
            commanded_x=cx,
            commanded_y=cy,
            commanded_z=np.zeros_like(cx),
            vertical_deflection=deflection,
            lateral_torsion=torsion,
            normal_spring_constant=contact.normal_spring_constant,
            lateral_spring_constant=contact.lateral_spring_constant,
            sample_rate=1.0 / dt,
            start_time=start,
            task="push",
            object_id=moved[0] if moved else -1,
        )

    # -- indentation -------------------------------------------------------------------------
    def indent(
        self, x: float, y: float, force: float, dwell: float, should_stop: StopCheck | None = None
    ) -> IndentResult:
        validate_indent(x, y, force, dwell, self.limits)
        move = self.move_tip(x, y, self.limits.max_speed / 10, should_stop=should_stop)
        if not move.completed:
            return IndentResult(
                x=move.end_x,
                y=move.end_y,
                completed=False,
                trace=self._indent_trace(0.0, 0.0, self.time),
            )
        params = self.config.indentation
        start = self.time
        sx, sy = self.sample_frame(
            np.array([self._true_scanner[0]]),
            np.array([self._true_scanner[1]]),
            np.array([self.time]),
        )
        depth = force / params.sample_stiffness
        radius = math.sqrt(2 * self.tip.apex_radius * depth) * 1.5
        self.sample.pits.append(
            Pit(self.sample.next_id(), float(sx[0]), float(sy[0]), radius, depth)
        )
        self.hold(params.approach_time + dwell + params.retract_time)
        trace = self._indent_trace(force, dwell, start)
        return IndentResult(x=x, y=y, trace=trace)

    def _indent_trace(self, force: float, dwell: float, start: float) -> ForceTraceData:
        params, contact = self.config.indentation, self.config.contact
        duration = params.approach_time + dwell + params.retract_time
        times = np.linspace(0.0, duration, INDENT_SAMPLES)

        def load(t):
            """The load profile (0..1) at times t: approach ramp, dwell, retract ramp."""
            up = (
                np.clip(t / params.approach_time, 0, 1)
                if params.approach_time
                else np.ones_like(t)
            )
            down = (
                np.clip((duration - t) / params.retract_time, 0, 1)
                if params.retract_time
                else np.ones_like(t)
            )
            return np.minimum(up, down)

        latency = self.config.noise.sensor_latency
        # the measured deflection lags the commanded z by the sensor latency
        profile = (
            (load(times) if latency == 0 else load(times - latency))
            * force
            / contact.normal_spring_constant
        )
        deflection = profile + self.noise_rng.normal(
            0, self.config.noise.deflection_sigma, len(times)
        )
        z = load(times) * force / self.config.indentation.sample_stiffness
        x, y = self._commanded
        return ForceTraceData(
            times=times,
            commanded_x=np.full_like(times, x),
            commanded_y=np.full_like(times, y),
            commanded_z=z,
            vertical_deflection=deflection,
            lateral_torsion=np.zeros_like(times),
            normal_spring_constant=contact.normal_spring_constant,
            lateral_spring_constant=contact.lateral_spring_constant,
            sample_rate=(len(times) - 1) / duration if duration else 0.0,
            start_time=start,
            task="indent",
        )

    # -- truth -------------------------------------------------------------------------------
    def truth(self) -> dict:
        tx, ty = self._true_scanner
        offset = self.drift.offset(self.time)
        return {
            "time": self.time,
            "tip_position": (tx - offset[0], ty - offset[1]),
            "commanded_position": self._commanded,
            "drift_offset": (float(offset[0]), float(offset[1])),
            "drift_velocity": tuple(float(v) for v in self.drift.velocity(self.time)),
            "tip_apex_radius": self.tip.apex_radius,
            "objects": self.sample.objects(),
        }

    def close(self) -> None:
        pass
