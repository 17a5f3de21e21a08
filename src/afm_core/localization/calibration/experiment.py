"""What every calibration experiment shares: the `Experiment` it returns, and the steps on
the instrument its procedures are made of (wait with the command held, punch a pit, rescan a
box with its slow axis along a row of pits), with the checks of a site against the scanner
range.
"""

from __future__ import annotations

import time as wallclock
from dataclasses import dataclass, field

import numpy as np

from afm_core import checks
from afm_core.instrument import RasterScanData, ScanRequest, check_in_range
from afm_core.localization.calibration.pits import find_pits

MAX_LINE_RATE = 10.0  # Hz, rescans: slower than the slew limit allows keeps the tracking honest
# Within an experiment a progress line at most this often (wall clock): readable in a log,
# often enough that a run of hours never looks stuck.
PROGRESS_INTERVAL = 10.0  # s


@dataclass
class Experiment:
    parameters: dict = field(default_factory=dict)  # fitted values, SI
    data: dict = field(default_factory=dict)  # raw data for a plot, SI, lists


def range_centre(instrument) -> np.ndarray:
    """The centre of the scanner range (m): every experiment's sites are offsets from it."""
    return 0.5 * np.array([instrument.limits.range_x, instrument.limits.range_y])


# The range the experiments' default geometry was laid out on (the default simulator's and the
# book's 110 um scanner). Each default site offset, step and lane distance is that length on
# this range, times range_scale: exactly the same numbers here, the same fractions of the
# range on another scanner (a 10 um tube: a creep step of 4.5 um, not 50 um).
REFERENCE_RANGE = 110e-6  # m


def range_scale(instrument) -> float:
    """The instrument's (smaller) scanner range over REFERENCE_RANGE: what the experiments'
    default geometry is multiplied by (1.0 exactly on a 110 um scanner)."""
    limits = instrument.limits
    return min(limits.range_x, limits.range_y) / REFERENCE_RANGE


class GeometryError(ValueError):
    """An experiment's sites, lanes or step do not fit in the scanner range. Repeating the
    experiment cannot help: the message names the option to change (fit_checks says so)."""


def indent_force(instrument, force: float | None) -> float:
    """The force of a pit (N): 1 uN (or the instrument's limit, if lower) unless given."""
    limit = instrument.limits.max_indent_force
    return min(1e-6, limit) if force is None else checks.positive("force", force, "N", upper=limit)


def check_box(name: str, instrument, lo, hi, fix: str = "") -> None:
    """Every corner of the box [lo, hi] inside the scanner range (GeometryError naming `name`
    and, when given, `fix`: the options that would make it fit)."""
    try:
        check_in_range(f"{name} (lower corner)", float(lo[0]), float(lo[1]), instrument.limits)
        check_in_range(f"{name} (upper corner)", float(hi[0]), float(hi[1]), instrument.limits)
    except ValueError as exc:
        size = np.asarray(hi, float) - np.asarray(lo, float)
        limits = instrument.limits
        raise GeometryError(
            f"{exc}: the {name} ({size[0] * 1e6:.3g} x {size[1] * 1e6:.3g} um) does not fit in "
            f"this scanner's {limits.range_x * 1e6:.3g} x {limits.range_y * 1e6:.3g} um range"
            + (f"; {fix}" if fix else "")
        ) from None


def wait(instrument, seconds: float) -> None:
    """Let time pass with the command held: the instrument's hold() when it has one (the
    simulator), else the wall clock (hardware holds its last output by itself)."""
    if seconds <= 0:
        return
    hold = getattr(instrument, "hold", None)
    if hold is not None:
        hold(seconds)
    else:
        wallclock.sleep(seconds)


def punch_at(instrument, x: float, y: float, speed: float, force: float) -> float:
    """Move to (x, y) and punch a pit there; returns the moment it is punched (instrument
    clock)."""
    instrument.move_tip(x, y, speed)
    moment = float(instrument.time)
    instrument.indent(x, y, force, 0.0)
    return moment


def rescan(
    instrument, lo, hi, pixel, slow_axis: int, slow_up: bool = True, approach: float = 0.0
) -> RasterScanData:
    """A raster image of the box [lo, hi] (m) with square pixels of about `pixel` (or a pair:
    (along x, along y); coarser where the box needs more than max_pixels) and its slow
    axis along `slow_axis` (0 = x: 90 deg scan; 1 = y: 0 deg). The slow axis moves once,
    monotonically, so a row of pits along it is imaged on one branch of the (compensated)
    scanner with no fast-axis loop in between. approach > 0: the tip first goes that far
    before the start along the slow axis, so the pass is on a long monotone stretch of the
    scanner's loop (small moves after a reversal have a different gain)."""
    limits = instrument.limits
    lo = np.maximum(np.asarray(lo, float), 0.0)
    hi = np.minimum(np.asarray(hi, float), [limits.range_x, limits.range_y])
    size = hi - lo
    pixel = np.broadcast_to(np.asarray(pixel, float), (2,))
    # An instrument with fewer pixels per line than the pixel asks for (512 is common) gets
    # the finest image it can take: refusing lost every rescan-based experiment on such an
    # instrument, where a pixel of 12-17 nm instead of 10-15 nm still resolves the pits
    # (positions are in metres from the scan's own pixel size; an experiment whose pits
    # become too small for its pixel says so where it counts them).
    pixels = np.clip(np.ceil(size / pixel), 16, limits.max_pixels).astype(int)
    fast = 1 - slow_axis
    rate = min(MAX_LINE_RATE, limits.max_line_rate, 0.95 * limits.max_speed / (2.0 * size[fast]))
    if approach > 0:
        start = lo.copy() if slow_up else hi.copy()
        start[slow_axis] = (
            max(0.0, start[slow_axis] - approach)
            if slow_up
            else min(start[slow_axis] + approach, [limits.range_x, limits.range_y][slow_axis])
        )
        instrument.move_tip(float(start[0]), float(start[1]), 0.5 * limits.max_speed)
    request = ScanRequest(
        float(lo[0]),
        float(lo[1]),
        float(size[0]),
        float(size[1]),
        int(pixels[0]),
        int(pixels[1]),
        scan_angle_deg=90.0 if slow_axis == 0 else 0.0,
        slow_scan_up=slow_up,
        line_rate=rate,
    )
    return instrument.raster_scan(request)


# A probe pit is imaged this far either side of where it was punched, at this pixel: fine
# enough to count the pixels of the 40-60 nm wide pits of sharp tips (8-20 nm apex), wide
# enough for the compensation residual between the punch and the image
PROBE_REACH = 0.6e-6  # m
PROBE_PIXEL = 10e-9  # m


def probe_pit_width(instrument, x: float, y: float, force: float) -> float:
    """The width (m) of a pit punched at (x, y) as the pit detector sees it: the diameter of
    the disc as large as its pixels deeper than the detection threshold, in a fine image
    around it. It scales with the tip apex (radius ~ sqrt(2 R depth)); NaN when none is
    found. The experiments that image pits at a coarse pixel choose it from this."""
    punch_at(instrument, x, y, 0.1 * instrument.limits.max_speed, force)
    centre = np.array([x, y])
    scan = rescan(instrument, centre - PROBE_REACH, centre + PROBE_REACH, PROBE_PIXEL, 1)
    pits = find_pits(scan)
    if not pits:
        return float("nan")
    nearest = min(pits, key=lambda p: (p.x - x) ** 2 + (p.y - y) ** 2)
    area = nearest.pixels * scan.pixel_size_x * scan.pixel_size_y
    return float(2.0 * np.sqrt(area / np.pi))


class StepProgress:
    """Progress within one experiment (issue 37): "<experiment>: <what> k of n, about T s left
    (S s of instrument time)", to `progress(text)` at most every PROGRESS_INTERVAL and at the
    last step; the time left extrapolates the time per step so far. progress None: silent."""

    def __init__(self, progress, experiment: str, what: str, total: int, instrument):
        self.progress, self.experiment, self.what = progress, experiment, what
        self.total, self.instrument = max(1, int(total)), instrument
        self.wall0, self.clock0 = wallclock.perf_counter(), float(instrument.time)
        self.last = -np.inf

    def step(self, done: int) -> None:
        if self.progress is None:
            return
        now = wallclock.perf_counter()
        if done < self.total and now - self.last < PROGRESS_INTERVAL:
            return
        self.last = now
        share = (self.total - done) / max(done, 1)
        wall_left = (now - self.wall0) * share
        clock_left = (float(self.instrument.time) - self.clock0) * share
        self.progress(
            f"{self.experiment}: {self.what} {done} of {self.total}, about {wall_left:.0f} s left "
            f"({clock_left:.0f} s of instrument time)"
        )
