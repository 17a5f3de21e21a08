"""Effects outside the sim-to-real library, injected where the diagnosis cannot see how.

Each effect is physics no library term has (candidates.py), with its magnitude drawn per seed
and its *kind of signature* as ground truth (`Signature`: the signals it lives in, its form in
time or space, its relation to other signals), so that a describer of unexplained residuals
can be scored. Two ways in, neither visible to the diagnosis:

- **post-processing the recorded messages**: the MCAP file the protocol wrote is read back
  (`read_operations`, what the diagnosis reads) and written again with each measurement
  changed (`rewrite_recording`); the per-message changes are the pure functions below, each
  adding a closed-form amount (the unit tests check it);
- **simulator extensions**: a `SimulatedAfm` subclass whose scanner has an x nonlinearity the
  simulator lacks, or a truth sample whose particles differ from the model's description.

Conventions of the closed forms: a raster pixel is at the commanded scanner position of its
centre (origin + (index + 0.5) pixel) and was measured at start_time + line_start_times[line]
+ (k + 1) dt, k its index along the fast axis in trace order, dt = line_period / (2 pixels
along the fast axis) (the simulator's trace: the first half of the line period). A scan line's
samples carry their own times and commanded x, y. Times `t` below are on the recording's clock
(s since its first command).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

NM = 1e-9


@dataclass(frozen=True)
class Signature:
    """The kind of signature an effect leaves: what a describer should say.

    signals: recorded signals it lives in ("height", "torsion", "lateral position").
    form: its form in a microscopist's words (periodic in time, a step in time, ...).
    keywords: accepted words, grouped: a description matches when, for every group, it
        contains at least one of the group's words (case-insensitive). The first group is the
        signal, the second the form, a third (where the form exists both ways) time or space.
    """

    signals: tuple
    form: str
    keywords: tuple
    accepts: tuple = ()


# `accepts`: the same truth in the terms of a structured describer (a signature with `kind` z |
# lateral | torsion | noise, a form in `time` and across the sample in `space`, per-particle
# agreement in `particles`, `relations` to covariates), any one alternative sufficing:
# {"kind": kinds, "time": forms (optional), "space": forms (optional), "particles_differ": True
# (optional), "relation": a covariate's name part (optional)}. A signal faster than any
# feature's sampling (50 Hz in z) reaches the features as extra noise: "noise" is its kind there.
# "smooth": signature.py's low-degree polynomial in time (a settling, a slow bend)
CHANGING_IN_TIME = ("linear trend", "random walk", "step", "smooth")


@dataclass
class Injection:
    """One out-of-library effect of one case: its parameters and how it enters.

    rewrite(operations) -> operations: the post-processing of the recorded session (None:
    none). truth_overrides: config changes of the truth that the model does not have (the
    sample). simulator: a SimulatedAfm subclass taking (config, **simulator_kwargs)."""

    name: str
    signature: Signature
    parameters: dict
    rewrite: Callable | None = None
    truth_overrides: dict = field(default_factory=dict)
    simulator: type | None = None
    simulator_kwargs: dict = field(default_factory=dict)


# -- where each height sample was taken ---------------------------------------------------------
def raster_samples(scan) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, x, y) of every pixel of a RasterScanData, shaped like its height (module
    docstring's convention)."""
    rows, columns = np.asarray(scan.height).shape
    fast_is_x = scan.scan_angle_deg == 0.0
    n_fast = columns if fast_is_x else rows
    dt = scan.line_period / (2 * n_fast)
    r, c = np.meshgrid(np.arange(rows), np.arange(columns), indexing="ij")
    line, k = (r, c) if fast_is_x else (c, r)
    t = scan.start_time + np.asarray(scan.line_start_times, float)[line] + (k + 1) * dt
    x = scan.origin_x + (c + 0.5) * scan.pixel_size_x
    y = scan.origin_y + (r + 0.5) * scan.pixel_size_y
    return t, x, y


def add_height(data, dz: Callable):
    """A copy of a raster or scan line with dz(t, x, y) (m) added to every height sample."""
    if hasattr(data, "line_start_times"):
        t, x, y = raster_samples(data)
        height = (np.asarray(data.height, float) + dz(t, x, y)).astype(np.float32)
        return dataclasses.replace(data, height=height)
    t = data.start_time + np.asarray(data.times, float)
    height = np.asarray(data.height, float) + dz(t, np.asarray(data.x), np.asarray(data.y))
    return dataclasses.replace(data, height=height)


def shift_lines(data, offsets: np.ndarray):
    """A copy of a raster (or scan line) whose every line is resampled `offsets[line]` (m)
    further along its fast axis (a line's own direction): h'(s) = h(s + offset), linear
    interpolation, the end samples held."""
    if hasattr(data, "line_start_times"):
        height = np.asarray(data.height, float)
        fast_is_x = data.scan_angle_deg == 0.0
        lines = height if fast_is_x else height.T
        pixel = data.pixel_size_x if fast_is_x else data.pixel_size_y
        s = (np.arange(lines.shape[1]) + 0.5) * pixel
        shifted = np.array([np.interp(s + d, s, row) for row, d in zip(lines, offsets)])
        out = shifted if fast_is_x else shifted.T
        return dataclasses.replace(data, height=out.astype(np.float32))
    s = np.hypot(np.asarray(data.x) - data.x[0], np.asarray(data.y) - data.y[0])
    height = np.interp(s + offsets[0], s, np.asarray(data.height, float))
    return dataclasses.replace(data, height=height)


def add_torsion(trace, dtheta: Callable):
    """A copy of a force trace with dtheta(t, vertical_deflection) (rad) added to its
    lateral torsion."""
    t = trace.start_time + np.asarray(trace.times, float)
    torsion = np.asarray(trace.lateral_torsion, float) + dtheta(
        t, np.asarray(trace.vertical_deflection, float)
    )
    return dataclasses.replace(trace, lateral_torsion=torsion)


def jitter_offsets(seed: int, index: int, lines: int, sigma: float) -> np.ndarray:
    """The per-line offsets (m) of operation `index`: normal, sd sigma, reproducible."""
    return np.random.default_rng([seed, index, 7919]).normal(0.0, sigma, lines)


def _lines_of(data) -> int:
    if hasattr(data, "line_start_times"):
        return len(data.line_start_times)
    return 1


# -- per-operation rewrites -----------------------------------------------------------------------
def _heights(dz: Callable) -> Callable:
    def rewrite(operations: list) -> list:
        for op in operations:
            if op.kind in ("raster", "scan_line") and op.data is not None:
                op.data = add_height(op.data, dz)
        return operations

    return rewrite


def _torsions(dtheta: Callable) -> Callable:
    def rewrite(operations: list) -> list:
        for op in operations:
            if op.kind in ("push", "indent") and op.data is not None:
                op.data = add_torsion(op.data, dtheta)
        return operations

    return rewrite


def _jitter(seed: int, sigma: float) -> Callable:
    def rewrite(operations: list) -> list:
        for op in operations:
            if op.kind in ("raster", "scan_line") and op.data is not None:
                offsets = jitter_offsets(seed, op.index, _lines_of(op.data), sigma)
                op.data = shift_lines(op.data, offsets)
        return operations

    return rewrite


def _session_span(operations: list) -> tuple[float, float]:
    return operations[0].start_time, max(op.end_time for op in operations)


def _debris(height: float, fraction: float) -> Callable:
    def rewrite(operations: list) -> list:
        t0, t1 = _session_span(operations)
        when = t0 + fraction * (t1 - t0)
        return _heights(lambda t, x, y: height * (t >= when))(operations)

    return rewrite


# -- the simulator extension: a scanner with a periodic x nonlinearity ---------------------------
class _NonlinearScanner:
    """The simulator's LateralScanner, its true x displaced by a sin(2 pi (x - centre_x) / L):
    the tube's x sensitivity ripples with position (a nonlinearity no library term has)."""

    def __init__(self, scanner, amplitude: float, period: float):
        self._scanner, self.amplitude, self.period = scanner, amplitude, period

    def __getattr__(self, name):
        return getattr(self._scanner, name)

    def apply(self, cmd_x, cmd_y, dt):
        x, y = self._scanner.apply(cmd_x, cmd_y, dt)
        return x + x_ripple(x, self._scanner.centre[0], self.amplitude, self.period), y


def x_ripple(x, centre: float, amplitude: float, period: float):
    """The nonlinear scanner's extra x displacement (m) at true x."""
    return amplitude * np.sin(2 * np.pi * (np.asarray(x) - centre) / period)


def nonlinear_scanner_afm():
    """A SimulatedAfm subclass with the scanner's x ripple (built lazily: core imports)."""
    from afm_core.sim.instrument import SimulatedAfm

    class NonlinearScannerAfm(SimulatedAfm):
        def __init__(self, config=None, *, amplitude: float, period: float):
            super().__init__(config)
            self.scanner = _NonlinearScanner(self.scanner, amplitude, period)

    return NonlinearScannerAfm


# -- the closed forms (dz(t, x, y) in m) ----------------------------------------------------------
def sine_in_time(amplitude: float, frequency: float, phase: float) -> Callable:
    def dz(t, x, y):
        return amplitude * np.sin(2 * np.pi * frequency * np.asarray(t) + phase)

    return dz


def settling(level: float, time_constant: float) -> Callable:
    def dz(t, x, y):
        return level * (1 - np.exp(-np.asarray(t) / time_constant))

    return dz


def fringes_in_x(amplitude: float, period: float, phase: float) -> Callable:
    def dz(t, x, y):
        return amplitude * np.sin(2 * np.pi * np.asarray(x) / period + phase)

    return dz


# -- the catalogue --------------------------------------------------------------------------------
# Accepted words. A describer is free in its wording; what must come through is the signal,
# the form and, where a form exists in both, whether it lives in time or in space.
HEIGHT = ("height", "topograph", "z ", "z-", "z sensor")
TORSION = ("torsion", "lateral force", "friction signal", "lateral signal")
POSITION = ("position", "lateral", "x ", "along the scan", "fast axis", "shift")
IN_TIME = ("time", "hz", "frequency", "temporal", "clock")
IN_SPACE = ("along x", "in x", "space", "spatial", "position", "wavelength", "across the sample")
SIGNATURES = {
    "mains_pickup": Signature(
        ("height",),
        "periodic in time (50 Hz), in every height measurement alike",
        (HEIGHT, ("periodic", "oscillat", "sinus", "hz", "frequency"), IN_TIME),
        ({"kind": ("z",), "time": ("periodic",)}, {"kind": ("noise",)}),
    ),
    "thermal_bending": Signature(
        ("height",),
        "the substrate's absolute level moves slowly in time (exponential settling), the same "
        "everywhere on the sample",
        (HEIGHT, ("slow", "trend", "settl", "exponential", "level", "offset", "drift in z")),
        ({"kind": ("z",), "time": CHANGING_IN_TIME},),
    ),
    "debris_step": Signature(
        ("height",),
        "a step in time in the absolute height of every measurement (the tip picked up debris)",
        (HEIGHT, ("step", "jump", "sudden", "change point")),
        ({"kind": ("z",), "time": ("step",)},),
    ),
    "interference_fringes": Signature(
        ("height",),
        "periodic along x in space (fixed to the scanner frame), not in time",
        (HEIGHT, ("periodic", "fringe", "sinus", "wavelength"), IN_SPACE),
        ({"kind": ("z",), "space": ("periodic in x",)},),
    ),
    "torsion_crosstalk": Signature(
        ("torsion",),
        "an offset proportional to the vertical deflection at the same moment, whatever the "
        "sliding direction",
        (TORSION, ("deflection", "proportional", "correlat", "crosstalk", "offset")),
        (
            {"kind": ("torsion",), "time": ("constant",)},
            {"kind": ("torsion",), "relation": "deflection"},
        ),
    ),
    "torsion_drift": Signature(
        ("torsion",),
        "an offset growing linearly in time, whatever the sliding direction",
        (TORSION, ("linear", "trend", "grow", "drift", "time")),
        ({"kind": ("torsion",), "time": ("linear trend",)},),
    ),
    "line_jitter": Signature(
        ("lateral position",),
        "random shift of each line along its fast axis, independent from line to line",
        (POSITION + HEIGHT, ("random", "jitter", "per line", "each line", "line to line")),
        ({"kind": ("lateral",), "time": ("none", "random walk")}, {"kind": ("noise",)}),
    ),
    "x_nonlinearity": Signature(
        ("lateral position",),
        "periodic displacement along x with position in x (the scanner's x sensitivity "
        "ripples), the same in every image",
        (POSITION, ("periodic", "nonlinear", "sinus", "ripple", "distort"), IN_SPACE),
        ({"kind": ("lateral",), "space": ("periodic in x",)},),
    ),
    "particle_heights": Signature(
        ("height",),
        "each particle's apparent height differs from the model's by its own amount, constant "
        "in time; the substrate unchanged",
        (HEIGHT + ("particle",), ("particle", "per particle", "each particle", "object")),
        ({"kind": ("z",), "particles_differ": True},),
    ),
}
NAMES = tuple(SIGNATURES)


def make_injection(name: str, seed: int, model=None) -> Injection:
    """The effect `name` (one of NAMES) with magnitudes drawn from `seed`. `model`: the model's
    SimConfig (needed by particle_heights, whose truth sample is the model's re-sized)."""
    if name not in SIGNATURES:
        raise ValueError(f"injection={name!r}: expected one of {list(NAMES)}")
    rng = np.random.default_rng([seed, 104729])
    sign = 1.0 if rng.random() < 0.5 else -1.0
    signature = SIGNATURES[name]
    if name == "mains_pickup":
        p = {
            "amplitude": rng.uniform(0.3, 0.6) * NM,
            "frequency": 50.0,
            "phase": rng.uniform(0, 6.3),
        }
        dz = sine_in_time(p["amplitude"], p["frequency"], p["phase"])
        return Injection(name, signature, p, rewrite=_heights(dz))
    if name == "thermal_bending":
        p = {"level": sign * rng.uniform(2.0, 5.0) * NM, "time_constant": rng.uniform(200, 600)}
        dz = settling(p["level"], p["time_constant"])
        return Injection(name, signature, p, rewrite=_heights(dz))
    if name == "debris_step":
        p = {"height": rng.uniform(1.5, 3.0) * NM, "at_fraction": rng.uniform(0.3, 0.7)}
        return Injection(name, signature, p, rewrite=_debris(p["height"], p["at_fraction"]))
    if name == "interference_fringes":
        p = {
            "amplitude": rng.uniform(0.4, 0.8) * NM,
            "period": rng.uniform(1.2e-6, 2.5e-6),
            "phase": rng.uniform(0, 6.3),
        }
        dz = fringes_in_x(p["amplitude"], p["period"], p["phase"])
        return Injection(name, signature, p, rewrite=_heights(dz))
    if name == "torsion_crosstalk":
        # 20-50 rad/m: the 50 nm contact-mode deflection adds 10-25 % of the substrate
        # friction's torsion (1e-5 rad with the default contact)
        p = {"rad_per_m": sign * rng.uniform(20.0, 50.0)}
        return Injection(name, signature, p, rewrite=_torsions(lambda t, d: p["rad_per_m"] * d))
    if name == "torsion_drift":
        p = {"rad_per_s": sign * rng.uniform(1e-9, 3e-9)}
        return Injection(name, signature, p, rewrite=_torsions(lambda t, d: p["rad_per_s"] * t))
    if name == "line_jitter":
        p = {"sigma": rng.uniform(3.0, 6.0) * NM, "seed": int(seed)}
        return Injection(name, signature, p, rewrite=_jitter(p["seed"], p["sigma"]))
    if name == "x_nonlinearity":
        p = {"amplitude": rng.uniform(5.0, 12.0) * NM, "period": rng.uniform(1.0e-6, 3.0e-6)}
        return Injection(
            name, signature, p, simulator=nonlinear_scanner_afm(), simulator_kwargs=dict(p)
        )
    # particle_heights: the truth's spheres re-sized, each by its own factor (model: as it says)
    if model is None:
        raise ValueError("particle_heights: needs the model's config (its sample's spheres)")
    spheres = [dict(s) for s in model.sample.spheres]
    factors = np.clip(1.0 + rng.normal(0.0, 0.05, len(spheres)), 0.9, 1.1)
    for sphere, factor in zip(spheres, factors):
        sphere["radius"] = float(sphere["radius"]) * float(factor)
    p = {"radius_factors": factors.tolist()}
    return Injection(name, signature, p, truth_overrides={"sample": {"spheres": spheres}})


# -- rewriting a recording ----------------------------------------------------------------------
def first_command_stamp_ns(path) -> int:
    """The header stamp of the recording's first TipCommand (the rewrite keeps its epoch)."""
    from afm_core.recording import RecordingReader
    from afm_core.sim2real.session import TIP_COMMAND

    with RecordingReader(path) as reader:
        for _topic, _log, message in reader.messages([TIP_COMMAND]):
            return int(message.header.stamp.sec) * 1_000_000_000 + int(
                message.header.stamp.nanosec
            )
    raise ValueError(f"{path}: no {TIP_COMMAND} message to take the epoch from")


def rewrite_recording(source, target, rewrite: Callable | None) -> int:
    """Read `source` as the diagnosis does, apply `rewrite` (operations -> operations; None:
    unchanged) and write `target` as the driver would have published it (no ground truth).
    Returns the number of operations."""
    from afm_core.sim2real.session_reader import read_operations
    from afm_core.sim2real.session_writer import SessionWriter

    epoch = first_command_stamp_ns(source)
    with read_operations(source) as stream:
        operations = list(stream)
    if rewrite is not None:
        operations = rewrite(operations)
    with SessionWriter(target, epoch_ns=epoch, truth=False) as writer:
        for op in operations:
            writer.write_operation(op)
    return len(operations)
