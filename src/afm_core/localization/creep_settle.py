"""Waiting for creep to settle before an image (issue 36): how long, and why.

After a long move the piezo creeps on for minutes (book eq. 5.29-5.31: a few % of the step
over time constants up to ~50 s). An image taken meanwhile is stretched along its slow axis
by the creep of those minutes, which the pair's drift compensation (a constant velocity)
cannot remove, and the landmarks land where the tip no longer is: on the default simulated
scanner a 40 um move put the map ~100 nm off, and the first local line missed. A lab waits;
this says for how long, from the calibrated creep model driven by every command the
instrument executed (`CreepSettler.observe`): the wait before a scan is the shortest hold
after which the creep still to come is within `creep_settle_tolerance` on both axes.

`settle_before(instrument, settler, x, y, ...)` moves the tip to a scan's start (as the scan's
own approach would), holds for the wait and says what it did (`Settling`); the driver node
calls it before every image.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from afm_core.localization.calibration.model import Calibration
from afm_core.localization.motion import MotionModel
from afm_core.parameters import Parameter

CREEP_SETTLE_TOLERANCE = Parameter(
    "creep_settle_tolerance",
    5e-9,
    "Before an image the driver waits until the calibrated creep still to come is within this "
    "on both axes (the map's own error, book Fig. 7.10: 5 nm); 0 disables the wait.",
    unit="m",
    minimum=0.0,
)
MAX_CREEP_WAIT = Parameter(
    "max_creep_wait",
    600.0,
    "Longest wait for creep before an image; a longer one is cut here and said so.",
    unit="s",
    minimum=0.0,
)
HOLD_SLICE = 1.0  # s: a wait is held in slices this long, so a cancel is seen within one
SEARCH_RESOLUTION = 0.5  # s: the wait is found to this resolution (bisection)


@dataclass(frozen=True)
class Settling:
    """What settle_before did: the wait (s), the creep still to come before and after it (m,
    the larger axis), and whether the wait was cut short (max_creep_wait, or a cancel)."""

    seconds: float
    to_come_before: float
    to_come_after: float
    cut: bool = False

    def describe(self) -> str:
        if self.seconds <= 0:
            return ""
        text = (
            f"waited {self.seconds:.0f} s for piezo creep to settle "
            f"({self.to_come_before * 1e9:.0f} nm still to come, "
            f"{self.to_come_after * 1e9:.1f} nm after the wait)"
        )
        return text + (" - cut at max_creep_wait" if self.cut else "")


class CreepSettler:
    """The calibrated creep model driven by every command the instrument executes."""

    def __init__(self, calibration: Calibration, command, time: float):
        self.model = MotionModel(calibration, command, time)

    @property
    def enabled(self) -> bool:
        return self.model.has_creep

    def observe(self, start, end, start_time: float, end_time: float) -> None:
        """A command the instrument executed: hold until it starts, jump to its start if it
        began elsewhere, ramp to its end over its duration (a raster as its net ramp: its
        back-and-forth lines add little creep of their own)."""
        if end_time <= self.model.time:
            return  # already accounted for (reported twice, or settle_before's own approach)
        if start_time > self.model.time:
            self.model.hold(start_time - self.model.time)
        if tuple(map(float, start)) != self.model.command:
            self.model.move(float(start[0]), float(start[1]), 0.0)
        self.model.move(float(end[0]), float(end[1]), max(0.0, end_time - self.model.time))

    def hold_until(self, time: float) -> None:
        if time > self.model.time:
            self.model.hold(time - self.model.time)

    def wait_needed(self, tolerance: float, max_wait: float) -> Settling:
        """The shortest hold from now after which the creep still to come is within
        `tolerance` (m) per axis; at most max_wait (s)."""
        before = float(np.max(np.abs(self.model.creep_to_come())))
        if tolerance <= 0 or before <= tolerance or not self.enabled:
            return Settling(0.0, before, before)

        def to_come_after(seconds: float) -> float:
            trial = self.model.copy()
            trial.hold(seconds)
            return float(np.max(np.abs(trial.creep_to_come())))

        # creep decays monotonically under a hold: double, then bisect
        high = 1.0
        while high < max_wait and to_come_after(high) > tolerance:
            high *= 2.0
        if high >= max_wait and to_come_after(max_wait) > tolerance:
            return Settling(max_wait, before, to_come_after(max_wait), cut=True)
        low = 0.0
        while high - low > SEARCH_RESOLUTION:
            mid = 0.5 * (low + high)
            low, high = (mid, high) if to_come_after(mid) > tolerance else (low, mid)
        return Settling(high, before, to_come_after(high))


def settle_before(
    instrument,
    settler: CreepSettler,
    x: float,
    y: float,
    speed: float,
    tolerance: float,
    max_wait: float,
    on_move: Callable[[tuple, tuple, float, float], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    on_hold: Callable[[], None] | None = None,
) -> Settling:
    """Move to (x, y) at `speed` (reported to on_move(start, end, start_time, duration)), then
    hold there as long as the creep model asks (`CreepSettler.wait_needed`), in slices
    (on_hold after each, should_stop before each). The instrument needs `hold(seconds)` (the
    simulator's; the DAQ instrument waits in wall time)."""
    if not (math.isfinite(tolerance) and tolerance >= 0):
        raise ValueError(f"creep_settle_tolerance={tolerance}: must be finite and >= 0 (m)")
    if not (math.isfinite(max_wait) and max_wait >= 0):
        raise ValueError(f"max_creep_wait={max_wait}: must be finite and >= 0 (s)")
    start, start_time = instrument.commanded_position(), float(instrument.time)
    if (float(x), float(y)) != tuple(start):
        instrument.move_tip(float(x), float(y), speed)
        duration = float(instrument.time) - start_time
        settler.observe(start, (x, y), start_time, start_time + duration)
        if on_move is not None:
            on_move(tuple(start), (float(x), float(y)), start_time, duration)
    settler.hold_until(float(instrument.time))
    settling = settler.wait_needed(tolerance, max_wait)
    waited = 0.0
    while waited < settling.seconds:
        if should_stop is not None and should_stop():
            break
        piece = min(HOLD_SLICE, settling.seconds - waited)
        instrument.hold(piece)
        waited += piece
        if on_hold is not None:
            on_hold()
    settler.hold_until(float(instrument.time))
    if waited < settling.seconds:
        return Settling(waited, settling.to_come_before, settling.to_come_after, cut=True)
    return settling
