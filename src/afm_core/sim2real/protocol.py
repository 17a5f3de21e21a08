"""A diagnostic session protocol and an in-memory operation log / replay on the simulator.

The protocol gives every candidate physics something to act on, in about 15 minutes of
instrument time, and keeps each effect apart from the random parts of a session (thermal
drift wander, the persistent random walk every free move adds to the tip position):

- **Line pairs without moves.** Every particle visit scans a line forwards and straight back
  (no free move between them, so no positioning noise): their mean is the particle's position,
  their half difference the direction-dependent shift (sensor latency). On the first axis the
  pair is repeated after a hold with the tip parked: only drift and creep act during the hold,
  so drift and the creep tail are measured free of the random walk. Creep depends on the dwell
  since the last move (0.5-40 s), drift only on the clock.
- **Tracking.** Lines are centred where the particle is expected now: its design position plus
  the drift measured so far (as a lab tracks a particle); a large drift keeps the lines on the
  particles.
- **Excursions** of 6 um along +-x, +-y before each block: the scanner's hysteresis (with the
  controller's feed-forward error) and the creep of a long move leave offsets that change sign
  with the excursion (the first visit after one scans longer lines, along that axis first).
- **Rasters**: a 4 um image of all particles per block (their relative positions measure the
  scanner's cross-coupling and rotation free of drift and positioning noise, their heights the
  z gain), at 0/90 deg, frame up/down; a 24 um image of the bare substrate around the range
  centre at the start and the end (scanner bow).
- **Contact slides** on bare substrate between the particles, along x and along y on a grid of
  rows and columns (friction, its change over the sample, stick-slip, tip wear), and an
  indentation per block. Tip wear only acts after the first slides (block 0 is before them).

Repeated in `blocks` time blocks, so held-out checks can fit on some blocks and test on others.

`OperationLog` wraps any Instrument and keeps the session as `Operation`s in memory (the
same fields as `afm_core.sim2real.session.Operation`); `replay` re-runs operations on a
`SimulatedAfm` at the recorded start times, optionally with its random parts switched off or
re-seeded, with a given drift trajectory instead of the configured drift, or without imaging
(only the force traces are needed), and logs each free move (time, distance) for the
positioning-noise covariance.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from afm_core.instrument import LineRequest, ScanRequest
from afm_core.sim.config import SimConfig, merge

# Spheres of the diagnostic sample (m): spread around the scanner centre (55 um, 55 um).
SESSION_SPHERES = [
    (55.0e-6, 55.0e-6),
    (56.6e-6, 55.3e-6),
    (53.5e-6, 54.7e-6),
    (55.4e-6, 56.7e-6),
    (54.6e-6, 53.3e-6),
    (56.4e-6, 53.7e-6),
]
# Bare substrate among the spheres (sample frame, m): contact slides along x on these rows from
# SLIDE_X[0] to SLIDE_X[1], along y on these columns from SLIDE_Y[0] to SLIDE_Y[1].
SLIDE_ROWS = (54.15e-6, 54.45e-6, 54.25e-6, 54.35e-6)
SLIDE_X = (54.9e-6, 56.9e-6)
SLIDE_COLUMNS = (55.4e-6, 56.0e-6, 55.6e-6, 55.8e-6)
SLIDE_Y = (53.9e-6, 54.7e-6)
SLIDE_SPEED = 2e-6
INDENT_SPOT = (57.3e-6, 54.3e-6)
SLIDE_AREA = (55.9e-6, 54.3e-6)  # centre of the slide grid (kept for callers)
LINE_HALF_LENGTH = 400e-9
LONG_HALF_LENGTH = 700e-9  # the first visit after an excursion: hysteresis may have moved it
LOCATE_SIZE, LOCATE_PIXELS, LOCATE_LINE_RATE = (
    2.0e-6,
    96,
    4.0,
)  # a lost particle: a small image finds it
SAMPLES_PER_M = 1 / 5e-9  # 5 nm between line samples (the tip grid the simulator images with)
LINE_SPEED = 1e-6
MOVE_SPEED = 10e-6
DWELLS = (0.5, 2.0, 6.0, 15.0, 40.0)  # s after the move to a particle
HOLDS = (5.0, 12.0, 25.0)  # s between the two line pairs of the first axis
EXCURSION = 5e-6  # m
BOW_SIZE, BOW_PIXELS, BOW_LINE_RATE = 24e-6, 32, 1.0
CLUSTER_SIZE, CLUSTER_PIXELS, CLUSTER_LINE_RATE = 4.4e-6, 192, 4.0  # 23 nm pixels


@dataclass
class Operation:
    """One command of a session and what it returned (fields as in sim2real.session)."""

    index: int
    kind: str  # move | push | scan_line | raster | indent
    start_time: float  # s, instrument clock when the command was issued
    start: tuple  # m, commanded position before
    end: tuple  # m, commanded target
    speed: float = math.nan  # m/s (moves, pushes, lines)
    duration: float = math.nan  # s
    request: Any = None  # ScanRequest / LineRequest / dict
    data: Any = None  # RasterScanData / ScanLineData / ForceTraceData / None
    landmark_id: int = -1
    pair_id: int = -1


def session_config(base: SimConfig | None = None) -> SimConfig:
    """The diagnostic sample (spheres at SESSION_SPHERES) on `base` (default: the default
    config)."""
    from afm_core.sim.config import load_config

    base = base if base is not None else load_config()
    spheres = [{"x": x, "y": y, "radius": 100e-9} for x, y in SESSION_SPHERES]
    return merge(base, {"sample": {"spheres": spheres, "random_spheres": 0}})


class OperationLog:
    """Wraps an Instrument; every command becomes an Operation in `operations`."""

    def __init__(self, instrument):
        self.instrument = instrument
        self.operations: list[Operation] = []

    def __getattr__(self, name):
        return getattr(self.instrument, name)

    @property
    def time(self):
        return self.instrument.time

    def _log(self, kind, start_time, start, end, **kw):
        op = Operation(
            index=len(self.operations),
            kind=kind,
            start_time=start_time,
            start=start,
            end=end,
            duration=self.instrument.time - start_time,
            **kw,
        )
        self.operations.append(op)
        return op

    def move_tip(self, x, y, speed, contact=False, should_stop=None):
        t0, p0 = self.instrument.time, self.instrument.commanded_position()
        result = self.instrument.move_tip(x, y, speed, contact=contact, should_stop=should_stop)
        self._log("push" if contact else "move", t0, p0, (x, y), speed=speed, data=result.trace)
        return result

    def local_scan(self, request, should_stop=None, landmark_id=-1):
        t0, p0 = self.instrument.time, self.instrument.commanded_position()
        data = self.instrument.local_scan(request, should_stop=should_stop)
        self._log(
            "scan_line",
            t0,
            p0,
            (request.end_x, request.end_y),
            speed=request.speed,
            request=request,
            data=data,
            landmark_id=landmark_id,
        )
        return data

    def raster_scan(self, request, on_line=None, should_stop=None):
        t0, p0 = self.instrument.time, self.instrument.commanded_position()
        data = self.instrument.raster_scan(request, on_line=on_line, should_stop=should_stop)
        self._log(
            "raster", t0, p0, (request.origin_x, request.origin_y), request=request, data=data
        )
        return data

    def indent(self, x, y, force, dwell, should_stop=None):
        t0, p0 = self.instrument.time, self.instrument.commanded_position()
        result = self.instrument.indent(x, y, force, dwell, should_stop=should_stop)
        self._log(
            "indent", t0, p0, (x, y), request={"force": force, "dwell": dwell}, data=result.trace
        )
        return result


def _hold(instrument, seconds: float) -> None:
    """Dwell with the command held: instruments that can hold (the simulator) hold; on others
    the dwell is skipped (the next command's start time shows what really passed)."""
    hold = getattr(instrument, "hold", None)
    if hold is not None and seconds > 0:
        hold(seconds)


def line_mid(data) -> float | None:
    """Where a scan line crossed a particle (m along its commanded direction from its start:
    the midpoint of the half-height crossings), or None when it saw none."""
    from afm_core.sim2real.features import line_profile

    profile = line_profile(data) if data is not None else None
    return None if profile is None or profile[1] is None else float(profile[1]["mid"])


class Tracker:
    """Where the protocol's particles are now, in scanner coordinates.

    Per axis, the measured offsets (scanner coordinate - design position) are fitted with a
    common offset that follows the latest measurements (drift, jumps from moves and
    excursions) plus an affine term in the design position (a scanner whose small-move gain or
    axes are off moves particles apart or together): offset = d + v (t - t_last) + g . (p - c),
    fitted over the last minutes; d from the latest measurement."""

    WINDOW = 300.0  # s of measurements the drift velocity and the affine term are fitted over

    def __init__(self, design):
        self.design = np.asarray(design, float)
        self.centre = self.design.mean(axis=0)
        self.obs: list[list] = [[], []]  # per axis: (time, particle, offset)

    def _fit(self, axis: int):
        """(latest time, latest common offset, velocity, gain vector)."""
        obs = self.obs[axis]
        t = np.array([o[0] for o in obs])
        p = self.design[[o[1] for o in obs]] - self.centre
        d = np.array([o[2] for o in obs])
        keep = t >= t[-1] - self.WINDOW
        columns = [np.ones(keep.sum())]
        use_v = keep.sum() >= 4 and np.ptp(t[keep]) >= 30.0
        if use_v:
            columns.append(t[keep] - t[-1])
        spread = np.ptp(p[keep], axis=0)
        use_g = [keep.sum() >= 6 and spread[k] > 1e-6 for k in (0, 1)]
        for k in (0, 1):
            if use_g[k]:
                columns.append(p[keep, k])
        coef, *_ = np.linalg.lstsq(np.stack(columns, 1), d[keep], rcond=None)
        v = float(coef[1]) if use_v else 0.0
        g = np.zeros(2)
        j = 2 if use_v else 1
        for k in (0, 1):
            if use_g[k]:
                g[k] = coef[j]
                j += 1
        # the common offset now: the latest measurement less its particle's affine part
        common = d[-1] - g @ p[-1]
        return t[-1], common, v, g

    def offset_at(self, axis: int, t: float, point) -> float:
        if not self.obs[axis]:
            return 0.0
        t_last, common, v, g = self._fit(axis)
        return common + v * (t - t_last) + g @ (np.asarray(point, float) - self.centre)

    def predict(self, particle: int, t: float) -> np.ndarray:
        p = self.design[particle]
        return np.array([p[a] + self.offset_at(a, t, p) for a in (0, 1)])

    def update(self, particle: int, axis: int, t: float, coordinate: float) -> None:
        self.obs[axis].append((t, particle, coordinate - self.design[particle, axis]))

    def to_scanner(self, point, t: float) -> tuple[float, float]:
        """A sample-frame point (design coordinates) where the scanner finds it now."""
        return float(point[0] + self.offset_at(0, t, point)), float(
            point[1] + self.offset_at(1, t, point)
        )


def _line_pair(axis: int, centre, half: float, sign: int):
    ux, uy = (sign, 0) if axis == 0 else (0, sign)
    cx, cy = centre
    samples = max(20, int(round(2 * half * SAMPLES_PER_M)))
    forward = LineRequest(
        cx - ux * half, cy - uy * half, cx + ux * half, cy + uy * half, samples, LINE_SPEED
    )
    back = LineRequest(
        forward.end_x, forward.end_y, forward.start_x, forward.start_y, samples, LINE_SPEED
    )
    return forward, back


def _scan(instrument, tracker: Tracker, particle: int, axis: int, requests) -> int:
    """Scan the lines, update the tracker; how many saw the particle."""
    seen = 0
    for request in requests:
        data = instrument.local_scan(request)
        mid = line_mid(data)
        if mid is not None:
            start = (request.start_x, request.start_y)[axis]
            direction = np.sign((request.end_x, request.end_y)[axis] - start)
            tracker.update(particle, axis, float(instrument.time), float(start + direction * mid))
            seen += 1
    return seen


def _locate(instrument, tracker: Tracker, particle: int) -> bool:
    """A small raster around the particle's predicted place; the tracker learns where it is."""
    from afm_core.imaging.landmarks import scan_landmarks

    cx, cy = tracker.predict(particle, instrument.time)
    half = 0.5 * LOCATE_SIZE
    data = instrument.raster_scan(
        ScanRequest(
            cx - half,
            cy - half,
            LOCATE_SIZE,
            LOCATE_SIZE,
            LOCATE_PIXELS,
            LOCATE_PIXELS,
            line_rate=LOCATE_LINE_RATE,
        )
    )
    if data is None or not np.isfinite(np.asarray(data.height, float)).all():
        return False
    try:
        marks = scan_landmarks(data, min_height=20e-9)
    except ValueError:
        return False
    if not marks:
        return False
    m = min(marks, key=lambda lm: math.hypot(lm.x - cx, lm.y - cy))
    t = float(instrument.time)
    tracker.update(particle, 0, t, float(m.x))
    tracker.update(particle, 1, t, float(m.y))
    return True


def run_protocol(
    instrument,
    seed: int = 0,
    blocks: int = 4,
    spheres=SESSION_SPHERES,
    rasters: bool = True,
    slides: bool = True,
    bow: bool = True,
    excursions: bool = True,
    holds: bool = True,
) -> None:
    """Run the diagnostic session on any Instrument (wrap it in OperationLog or a recorder).
    The choices (order, scan directions, dwells, holds) come from `seed`; see the module
    docstring. The first command starts at the instrument's current time (the recording's t0)."""
    rng = np.random.default_rng(seed)
    spheres = np.asarray(spheres, float)
    tracker = Tracker(spheres)
    centre = spheres.mean(axis=0)
    limits = getattr(instrument, "limits", None)
    scanner_centre = (
        (55e-6, 55e-6) if limits is None else (0.5 * limits.range_x, 0.5 * limits.range_y)
    )
    directions = [(0, 1), (1, 1), (0, -1), (1, -1)]
    for block in range(blocks):
        excursion_axis = directions[block % 4][0]
        if excursions:
            axis, sign = directions[block % 4]
            here = tracker.to_scanner(centre, instrument.time)
            target = list(here)
            target[axis] += sign * EXCURSION
            instrument.move_tip(target[0], target[1], MOVE_SPEED)
            _hold(instrument, 1.0)
        order = rng.permutation(len(spheres))
        for number, i in enumerate(order):
            after_excursion = number == 0 and excursions
            first = excursion_axis if after_excursion else int(rng.integers(2))
            half = LONG_HALF_LENGTH if after_excursion else LINE_HALF_LENGTH
            dwell = float(DWELLS[int(rng.integers(len(DWELLS)))])
            hold = float(HOLDS[int(rng.integers(len(HOLDS)))])
            signs = [1 if rng.uniform() < 0.5 else -1 for _ in range(2)]
            # first axis: move, dwell, a pair
            requests = _line_pair(first, tracker.predict(i, instrument.time), half, signs[0])
            instrument.move_tip(requests[0].start_x, requests[0].start_y, MOVE_SPEED)
            _hold(instrument, dwell)
            if _scan(instrument, tracker, i, first, requests) == 0:
                # lost: a small image around where it should be finds it, then the pair again
                _locate(instrument, tracker, i)
                requests = _line_pair(first, tracker.predict(i, instrument.time), half, signs[0])
                _scan(instrument, tracker, i, first, requests)
            # second axis, centred on what the first just measured; (hold, the same pair again)
            requests = _line_pair(1 - first, tracker.predict(i, instrument.time), half, signs[1])
            _scan(instrument, tracker, i, 1 - first, requests)
            if holds:
                _hold(instrument, hold)
                _scan(instrument, tracker, i, 1 - first, requests)
        if rasters:
            angle = 0.0 if block % 2 == 0 else 90.0
            up = (block // 2) % 2 == 0
            cx, cy = tracker.to_scanner(centre, instrument.time)
            instrument.raster_scan(
                ScanRequest(
                    cx - CLUSTER_SIZE / 2,
                    cy - CLUSTER_SIZE / 2,
                    CLUSTER_SIZE,
                    CLUSTER_SIZE,
                    CLUSTER_PIXELS,
                    CLUSTER_PIXELS,
                    scan_angle_deg=angle,
                    slow_scan_up=up,
                    line_rate=CLUSTER_LINE_RATE,
                )
            )
        if slides:
            row, column = (
                SLIDE_ROWS[block % len(SLIDE_ROWS)],
                SLIDE_COLUMNS[block % len(SLIDE_COLUMNS)],
            )
            xs = SLIDE_X if block % 2 == 0 else SLIDE_X[::-1]
            ys = SLIDE_Y if (block // 2) % 2 == 0 else SLIDE_Y[::-1]
            for a, b in (((xs[0], row), (xs[1], row)), ((column, ys[0]), (column, ys[1]))):
                start = tracker.to_scanner(a, instrument.time)
                instrument.move_tip(start[0], start[1], MOVE_SPEED)
                end = tracker.to_scanner(b, instrument.time)
                instrument.move_tip(end[0], end[1], SLIDE_SPEED, contact=True)
            spot = tracker.to_scanner(INDENT_SPOT, instrument.time)
            instrument.indent(spot[0], spot[1], 1e-7, 0.2)
    if bow:
        # the bare substrate around the range centre, twice (the curvature is the scanner's)
        origin = (scanner_centre[0] - BOW_SIZE / 2, scanner_centre[1] - BOW_SIZE / 2)
        for angle, up in ((0.0, True), (90.0, False)):
            instrument.raster_scan(
                ScanRequest(
                    origin[0],
                    origin[1],
                    BOW_SIZE,
                    BOW_SIZE,
                    BOW_PIXELS,
                    BOW_PIXELS,
                    scan_angle_deg=angle,
                    slow_scan_up=up,
                    line_rate=BOW_LINE_RATE,
                )
            )


def make_session(
    config: SimConfig, protocol_seed: int = 0, blocks: int = 4, **kw
) -> list[Operation]:
    """Run the protocol on SimulatedAfm(config) in memory; the operations."""
    from afm_core.sim.instrument import SimulatedAfm

    log = OperationLog(SimulatedAfm(config))
    run_protocol(log, seed=protocol_seed, blocks=blocks, **kw)
    return log.operations


# -- deterministic and re-seeded replays -------------------------------------------------------


def deterministic(config: SimConfig, sensor_noise: bool = False) -> SimConfig:
    """The config with its random parts off: drift wander (sigma 0, mean kept), positioning
    noise; sensor noise too unless sensor_noise."""
    overrides: dict = {
        "drift": {"sigma_velocity_x": 0.0, "sigma_velocity_y": 0.0},
        "scanner": {"positioning_noise_enabled": False},
    }
    if not sensor_noise:
        overrides["noise"] = {
            "height_white_sigma": 0.0,
            "height_flicker_sigma": 0.0,
            "deflection_sigma": 0.0,
        }
    return merge(config, overrides)


class TrajectoryDrift:
    """A given drift: offset (m, per axis) linear between knots (times s), constant outside."""

    def __init__(self, times, offsets):
        self.times = np.asarray(times, float)
        self.offsets = np.asarray(offsets, float).reshape(-1, 2)
        if self.times.size == 0:
            self.times, self.offsets = np.array([0.0]), np.zeros((1, 2))

    def offset(self, t) -> np.ndarray:
        t = np.asarray(t, float)
        return np.stack([np.interp(t, self.times, self.offsets[:, a]) for a in (0, 1)], axis=-1)

    def velocity(self, t) -> np.ndarray:
        t = np.asarray(t, float)
        if self.times.size < 2:
            return np.zeros(t.shape + (2,))
        slope = np.diff(self.offsets, axis=0) / np.maximum(np.diff(self.times), 1e-12)[:, None]
        k = np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, slope.shape[0] - 1)
        inside = (t >= self.times[0]) & (t <= self.times[-1])
        return np.where(inside[..., None], slope[k], 0.0)

    def shifted(self, delta) -> TrajectoryDrift:
        return TrajectoryDrift(self.times, self.offsets + np.asarray(delta, float)[None, :])


@dataclass
class Replay:
    operations: list  # simulated Operations, one per recorded one (same index)
    moves: list = field(
        default_factory=list
    )  # (time at the end of the move, distance m) of every free move


def _drive_only(sim, rasters: bool = True):
    """Make `sim` skip imaging: scan lines and (if `rasters`) rasters drive the scanner exactly
    as they would (same command samples, same timing) and return no data. For replays whose
    features come from force traces (deterministic: the skipped sensor noise draws change
    nothing else) or from rasters only."""
    import types

    def local_scan(self, request, should_stop=None):
        request.validate(self.limits)
        self.move_tip(request.start_x, request.start_y, self.limits.max_speed / 10)
        s = np.linspace(0.0, 1.0, request.samples)
        dt = request.length / request.speed / (request.samples - 1)
        self._drive(
            request.start_x + s * (request.end_x - request.start_x),
            request.start_y + s * (request.end_y - request.start_y),
            dt,
        )
        return None

    def raster_scan(self, request, on_line=None, should_stop=None):
        from afm_core.sim.instrument import LINES_PER_CHUNK, RasterPath

        request.validate(self.limits)
        path = RasterPath(request)
        self.move_tip(*path.first, self.limits.max_speed / 10)
        dt = 0.5 / request.line_rate / path.n_fast
        for done in range(0, path.n_lines, LINES_PER_CHUNK):
            _, cmd_x, cmd_y = path.chunk(done)
            self._drive(cmd_x, cmd_y, dt)
        return None

    sim.local_scan = types.MethodType(local_scan, sim)
    if rasters:
        sim.raster_scan = types.MethodType(raster_scan, sim)


def replay(
    operations,
    config: SimConfig,
    noise_seed: int | None = None,
    drift=None,
    imaging: bool | str = True,
    drives: dict | None = None,
) -> Replay:
    """Re-run `operations` on SimulatedAfm(config) at their recorded start times (the clock is
    held up to each start). noise_seed: re-seed the random parts (sensor noise, drift wander,
    positioning noise) while keeping the sample (its seed is config.seed). drift: an object with
    offset(t) and velocity(t) (e.g. TrajectoryDrift) used instead of the configured drift.
    imaging=False: scan lines and rasters only drive the scanner (no data; deterministic
    configs only); imaging="rasters": only the scan lines do. drives: a dict to fill with,
    per operation index, the list of the scanner's
    drive calls during it: (times, commanded x, y, true scanner x, y) arrays."""
    from afm_core.sim.drift import ThermalDrift
    from afm_core.sim.instrument import SimulatedAfm

    sim = SimulatedAfm(config)
    if noise_seed is not None:
        streams = np.random.SeedSequence([int(noise_seed), 7919]).spawn(3)
        sim.noise_rng = np.random.default_rng(streams[0])
        sim.drift = ThermalDrift(
            config.drift, seed=int(np.random.default_rng(streams[1]).integers(2**31))
        )
        sim.positioning_rng = np.random.default_rng(streams[2])
    if drift is not None:
        sim.drift = drift
    if imaging is not True:
        _drive_only(sim, rasters=imaging != "rasters")
    moves: list = []
    original_move = sim.move_tip
    current = [-1]
    if drives is not None:
        original_drive = sim._drive

        def recorded_drive(cmd_x, cmd_y, dt, position_error=None):
            times, tx, ty = original_drive(cmd_x, cmd_y, dt, position_error)
            drives.setdefault(current[0], []).append(
                (times, np.asarray(cmd_x, float).copy(), np.asarray(cmd_y, float).copy(), tx, ty)
            )
            return times, tx, ty

        sim._drive = recorded_drive

    def logged_move(x, y, speed, contact=False, should_stop=None):
        x0, y0 = sim.commanded_position()
        result = original_move(x, y, speed, contact=contact, should_stop=should_stop)
        distance = math.hypot(x - x0, y - y0)
        if distance > 0:
            moves.append((sim.time, distance))
        return result

    sim.move_tip = logged_move
    log = OperationLog(sim)
    first = operations[0].start_time if operations else 0.0
    offset = 0.0 if first >= 0 else -first
    for op in operations:
        target = op.start_time + offset
        current[0] = -1  # the wait belongs to no operation
        if target > sim.time + 1e-9:
            sim.hold(target - sim.time)
        kind = op.kind
        current[0] = op.index
        if kind in ("move", "push"):
            log.move_tip(op.end[0], op.end[1], op.speed, contact=(kind == "push"))
        elif kind == "scan_line":
            log.local_scan(_copy(op.request))
        elif kind == "raster":
            log.raster_scan(_copy(op.request))
        elif kind == "indent":
            request = op.request or {}
            force = (
                float(request.get("force", 1e-7))
                if isinstance(request, dict)
                else float(request.force)
            )
            dwell = (
                float(request.get("dwell", 0.0))
                if isinstance(request, dict)
                else float(request.dwell)
            )
            log.indent(op.end[0], op.end[1], force, dwell)
        else:
            raise ValueError(f"operation {op.index}: unknown kind {kind!r}")
        log.operations[-1].index = op.index
    return Replay(log.operations, moves)


def _copy(request):
    return dataclasses.replace(request) if dataclasses.is_dataclass(request) else request
