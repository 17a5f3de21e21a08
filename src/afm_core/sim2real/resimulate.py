"""Re-run a recorded session's commands on the simulated AFM, at the recorded times.

`resimulate(operations, config)` builds a `SimulatedAfm` from the given configuration and,
for each recorded operation, lets the simulator's clock run (with the command held) until
the operation's recorded start time, executes the same request, and yields the pair
(recorded operation, simulated operation). The simulated one has the same form: times on the
recording's clock, commanded geometry as the driver would report it, the measurement, plus
its lag and the simulator's truth after it.

Same configuration and seed as the session that made a simulated recording => the same
physics: the simulator is deterministic and draws its random numbers in call order, the calls
are made in the same order with the same arguments (requests rebuilt bit for bit from the
messages), and its truth is queried when the driver and RecordingInstrument query it (start-up
and after each command: the drift's knots are generated in the batches queries ask for, so
even a read-only query could move the drift's offsets by an ulp). What the message format
quantizes cannot come back to the bit: an idle gap is known to the stamps' 1 ns, an
indentation's force only as well as its noisy deflection tells it (see
test/test_sim2real_session.py for the bounds).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
from collections.abc import Iterable, Iterator

from afm_core.instrument import LineRequest, ScannerLimits, ScanRequest
from afm_core.sim.config import SimConfig, load_config, merge
from afm_core.sim.instrument import SimulatedAfm
from afm_core.sim2real.session import Operation, operation_from_call

# Gaps between a recorded and a simulated start time below this are the stamps' rounding,
# not time to let pass: the driver's stamps resolve ~0.24 us (a float epoch + time), ours 1 ns.
TIME_RESOLUTION = 1e-6  # s
# A pixel below this is no AFM's (a picometre: a hundredth of an atom); above the scanner
# range it cannot be scanned: either means a broken recording or the wrong units.
MIN_PIXEL_SIZE = 1e-12  # m
START_TOLERANCE = 1e-12  # m: the simulator already is at the first command's start


def load_sim_config(config, seed: int | None = None) -> SimConfig:
    """A SimConfig from a SimConfig, a YAML path (any subset of keys over the defaults), or a
    dict of overrides; `seed` replaces the configured seed when given."""
    if isinstance(config, SimConfig):
        loaded = copy.deepcopy(config)  # the simulator keeps it: no aliasing with the caller's
    elif isinstance(config, (str, os.PathLike)):
        loaded = load_config(config)
    elif isinstance(config, dict):
        loaded = merge(load_config(), config)
    elif config is None:
        loaded = load_config()
    else:
        raise ValueError(
            f"config={config!r}: expected a SimConfig, a YAML path or a dict of overrides"
        )
    return loaded if seed is None else dataclasses.replace(loaded, seed=int(seed))


# ------------------------------------------------------------------------------------------
# does the configuration fit the recording?
# ------------------------------------------------------------------------------------------
def _where(op: Operation) -> str:
    return f"operation {op.index} ({op.kind}, {op.start_time:.3f} s)"


def _check_point(op: Operation, name: str, x: float, y: float, limits: ScannerLimits) -> None:
    for axis, value, limit in (("x", x, limits.range_x), ("y", y, limits.range_y)):
        if not math.isfinite(value):
            raise ValueError(f"{_where(op)}: {name}.{axis}={value}: not finite")
        if not 0.0 <= value <= limit:
            raise ValueError(
                f"{_where(op)}: {name}.{axis}={value:.4e} m is outside the configured scanner "
                f"range limits.range_{axis}=[0, {limit:.4e}] m"
            )


def _check_pixel(op: Operation, name: str, size: float, limit: float) -> None:
    if not (math.isfinite(size) and MIN_PIXEL_SIZE <= size <= limit):
        raise ValueError(
            f"{_where(op)}: {name}={size:.4e} m is absurd: a pixel must be within "
            f"[{MIN_PIXEL_SIZE:.0e} m, the scanner range {limit:.4e} m]"
        )


def check_operation(op: Operation, limits: ScannerLimits) -> None:
    """ValueError naming the operation, the field and the configured limit when the simulator
    cannot execute this operation as recorded."""
    for name, (x, y) in (("start", op.start), ("end", op.end)):
        _check_point(op, name, x, y, limits)
    request = op.request
    if op.kind in ("move", "push", "scan_line"):
        speed = request.speed if isinstance(request, LineRequest) else float(request["speed"])
        if not (math.isfinite(speed) and 0 < speed <= limits.max_speed):
            raise ValueError(
                f"{_where(op)}: speed={speed:.4e} m/s is above the configured slew limit "
                f"limits.max_speed={limits.max_speed:.4e} m/s (or not > 0)"
            )
    if op.kind == "raster":
        data = op.data
        for axis, size, pixels, limit in (
            ("x", request.size_x, request.pixels_x, limits.range_x),
            ("y", request.size_y, request.pixels_y, limits.range_y),
        ):
            if not 2 <= pixels <= limits.max_pixels:
                raise ValueError(
                    f"{_where(op)}: pixels_{axis}={pixels} is outside [2, limits.max_pixels="
                    f"{limits.max_pixels}]"
                )
            _check_pixel(op, f"pixel_size_{axis}", size / pixels, limit)
            if data is not None:
                _check_pixel(op, f"pixel_size_{axis}", getattr(data, f"pixel_size_{axis}"), limit)
        _check_point(op, "origin", request.origin_x, request.origin_y, limits)
        _check_point(
            op,
            "origin + size",
            request.origin_x + request.size_x,
            request.origin_y + request.size_y,
            limits,
        )
        if not (0 < request.line_rate <= limits.max_line_rate):
            raise ValueError(
                f"{_where(op)}: line_rate={request.line_rate} Hz (1 / line_period) is outside "
                f"(0, limits.max_line_rate={limits.max_line_rate}] Hz"
            )
    elif op.kind == "scan_line":
        if not 2 <= request.samples <= limits.max_line_samples:
            raise ValueError(
                f"{_where(op)}: samples={request.samples} is outside [2, limits.max_line_samples="
                f"{limits.max_line_samples}]"
            )
    elif op.kind == "indent":
        if not 0 < request["force"] <= limits.max_indent_force:
            raise ValueError(
                f"{_where(op)}: force={request['force']:.4e} N is outside (0, "
                f"limits.max_indent_force={limits.max_indent_force:.4e}] N"
            )
        if not 0 <= request["dwell"] <= limits.max_dwell:
            raise ValueError(
                f"{_where(op)}: dwell={request['dwell']} s is outside [0, limits.max_dwell="
                f"{limits.max_dwell}] s"
            )
    if isinstance(request, (ScanRequest, LineRequest)):
        try:  # whatever else the instrument itself refuses
            request.validate(limits)
        except ValueError as exc:
            raise ValueError(f"{_where(op)}: {exc} (simulator config limits)") from exc


def check_config_matches(operations: Iterable[Operation], config) -> int:
    """Check that the simulator configured by `config` (SimConfig, YAML path or overrides) can
    execute every operation given (e.g. the first few of a recording, or all: an iterator is
    consumed); ValueError naming the operation, the field and the limit. Returns how many
    operations were checked."""
    limits = load_sim_config(config).limits
    count = 0
    for op in operations:
        check_operation(op, limits)
        count += 1
    return count


# ------------------------------------------------------------------------------------------
# re-running
# ------------------------------------------------------------------------------------------
class Resimulation:
    """Iterator of (recorded, simulated) Operation pairs; see resimulate().

    instrument: the SimulatedAfm (its truth() after the run, its time);
    origin: simulator time (s) of the recording's t = 0 (the first operation given starts at
        once; simulated operations carry times on the recording's clock, = simulator time -
        origin);
    late_operations, max_lag (s), total_lag (s): operations the simulator could not start at
    their recorded time because its previous operation took longer than the recorded one.
    """

    def __init__(
        self,
        operations: Iterable[Operation],
        config,
        seed: int | None = None,
        *,
        move_to_start: bool = True,
        settle_time: float = 10.0,
    ):
        if not (math.isfinite(settle_time) and settle_time >= 0):
            raise ValueError(f"settle_time={settle_time}: must be finite and >= 0 s")
        self.config = load_sim_config(config, seed)
        self.instrument = SimulatedAfm(self.config)
        self.move_to_start = move_to_start
        self.settle_time = float(settle_time)
        self.origin: float | None = None
        self.late_operations = 0
        self.max_lag = 0.0
        self.total_lag = 0.0
        self.count = 0
        self._operations = iter(operations)
        self._run = self._pairs()

    def __iter__(self):
        return self

    def __next__(self) -> tuple[Operation, Operation]:
        return next(self._run)

    def close(self) -> None:
        """Stop early: closes the operations' source too when it can be (an OperationStream)."""
        self._run.close()
        closer = getattr(self._operations, "close", None)
        if callable(closer):
            closer()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _pairs(self) -> Iterator[tuple[Operation, Operation]]:
        sim = self.instrument
        # the driver publishes the truth at start-up and after every command; a recording made
        # through RecordingInstrument queried it the same way: query alike (see module doc)
        sim.truth()
        for recorded in self._operations:
            check_operation(recorded, self.config.limits)
            if self.origin is None:
                self._go_to_start(recorded)
                # the recording's clock on the simulator's: the first operation given starts now
                # (it need not be the recording's first: a slice of a session runs from its start)
                self.origin = sim.time - recorded.start_time
            lag = self._wait_until(self.origin + recorded.start_time)
            simulated = self._execute(recorded)
            simulated.lag = lag
            simulated.truth = copy.deepcopy(sim.truth())  # its objects are the live ones: move on
            self.count += 1
            yield recorded, simulated

    def _go_to_start(self, first: Operation) -> None:
        """Put the tip where the recording's first command starts (at full speed), and let
        creep settle, when the simulator is not there already."""
        sim = self.instrument
        x, y = first.start
        here = sim.commanded_position()
        if not self.move_to_start or math.hypot(x - here[0], y - here[1]) <= START_TOLERANCE:
            return
        sim.move_tip(x, y, sim.limits.max_speed)
        sim.hold(self.settle_time)

    def _wait_until(self, target: float) -> float:
        """Hold until the simulator's clock reaches `target`; the lag (s) when it is already
        past."""
        sim = self.instrument
        gap = target - sim.time
        if gap > TIME_RESOLUTION:
            sim.hold(gap)
            return 0.0
        if gap < -TIME_RESOLUTION:
            self.late_operations += 1
            self.max_lag = max(self.max_lag, -gap)
            self.total_lag += -gap
            return -gap
        return 0.0

    def _execute(self, recorded: Operation) -> Operation:
        sim, request, kind = self.instrument, recorded.request, recorded.kind
        start_time, start_position = sim.time, sim.commanded_position()
        end_position = None
        if kind == "raster":
            data = sim.raster_scan(request)
        elif kind == "scan_line":
            data = sim.local_scan(request)
        elif kind in ("move", "push"):
            move = sim.move_tip(
                request["x"], request["y"], request["speed"], contact=kind == "push"
            )
            data, end_position = move.trace, (move.end_x, move.end_y)
        elif kind == "indent":
            result = sim.indent(request["x"], request["y"], request["force"], request["dwell"])
            data = result.trace
        else:
            raise ValueError(f"{_where(recorded)}: kind={kind!r} cannot be simulated")
        if data is not None:  # on the recording's clock, as the recorded data are
            data = dataclasses.replace(data, start_time=data.start_time - self.origin)
        return operation_from_call(
            recorded.index,
            kind,
            request,
            data,
            start_time=start_time - self.origin,
            end_time=sim.time - self.origin,
            start_position=start_position,
            end_position=sim.commanded_position() if end_position is None else end_position,
            landmark_id=recorded.landmark_id,
            pair_id=recorded.pair_id,
        )


def resimulate(
    operations: Iterable[Operation],
    config,
    seed: int | None = None,
    *,
    move_to_start: bool = True,
    settle_time: float = 10.0,
) -> Resimulation:
    """Re-execute recorded operations on SimulatedAfm(config) at their recorded times.

    operations: Operations in command order (e.g. read_operations(path); streamed, one at a
    time). config: SimConfig, YAML path or dict of overrides; seed replaces its seed.
    Before the first operation, when move_to_start and the simulator's tip is not commanded to
    the first operation's start, it moves there at the slew limit and holds settle_time s.
    The first operation given starts at once; each later one when the simulator's clock, counted
    alike, reaches its recorded start time (the command is held meanwhile: creep and drift go on);
    when the simulator is already later, it starts at once and the lag is counted (the
    Resimulation's late_operations, max_lag, total_lag; the simulated Operation's lag).
    Every operation is checked against the configuration first (check_operation): ValueError
    naming the field and the limit. Yields (recorded, simulated) pairs.
    """
    return Resimulation(
        operations, config, seed, move_to_start=move_to_start, settle_time=settle_time
    )
