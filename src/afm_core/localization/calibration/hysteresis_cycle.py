"""The open-loop cycle of the hysteresis experiment (hysteresis.py): the drive as issued
against the instrument clock (`Timeline`), the cycle with its pits (`drive_cycle`) and the
feed-forward switch it needs.
"""

from __future__ import annotations

import numpy as np

from afm_core.localization.calibration.experiment import StepProgress, wait


def on_axis(axis: int, along: float, across: float) -> tuple[float, float]:
    """(x, y) of the point `along` the cycled axis and `across` on the other."""
    p = np.empty(2)
    p[axis], p[1 - axis] = along, across
    return float(p[0]), float(p[1])


def drive_cycle(
    instrument,
    axis: int,
    start,
    amplitude: float,
    step: float,
    *,
    steps_per_sweep: int,
    pit_every: int,
    branch_gap: float,
    speed: float,
    settle: float,
    force: float,
    progress: StepProgress,
) -> tuple[Timeline, list[tuple]]:
    """The open-loop cycle about start = (range centre of the cycled axis, lane): feed-forward
    off, rise to +amplitude, then the descending sweep and (`branch_gap` beside it) the
    ascending one in steps of `step`, a pit every `pit_every` steps; feed-forward back on.
    Returns the drive as issued and the pits as (branch, drive, moment)."""
    limits = instrument.limits
    middle, lane = start
    other = 1 - axis
    instrument.move_tip(*on_axis(axis, middle, lane), 0.5 * limits.max_speed)
    set_feed_forward(instrument, False)
    try:
        # Open loop a raw drive is up to half a loop width (several um) from where the
        # compensated command puts the tip: keep the other axis' drive where the switch left it
        # (the tip stays on the lane) and move only the cycled axis, to the raw centre.
        lane_drive = float(instrument.commanded_position()[other])
        instrument.move_tip(*on_axis(axis, middle, lane_drive), speed)
        wait(instrument, settle)
        timeline = Timeline(instrument)
        for k in range(1, steps_per_sweep // 2 + 1):
            timeline.move(*on_axis(axis, middle + k * step, lane_drive), speed)
        pits = []  # (branch, drive, moment)
        top, bottom = middle + amplitude, middle - amplitude
        for branch, first, sign, b in (
            ("descending", top, -1.0, lane_drive),
            ("ascending", bottom, 1.0, lane_drive + branch_gap),
        ):
            if branch == "ascending":
                # to the second lane, along the other axis only
                timeline.move(*on_axis(axis, bottom, b), speed)
            for k in range(steps_per_sweep + 1):
                drive = first + sign * k * step
                if k:
                    timeline.move(*on_axis(axis, drive, b), speed)
                if k % pit_every == 0:
                    pits.append((branch, drive, timeline.punch(force)))
                    progress.step(len(pits))
    finally:
        set_feed_forward(instrument, True)
    return timeline, pits


def drive_record(timeline: Timeline, axis: int, centre: float, half: float) -> dict:
    """The drive of `axis` as `refit_hysteresis` needs it, with the centre it cycled about and
    the half range."""
    return {
        # the drive as issued (piecewise linear between these knots), to refit or plot
        "drive_knots": {
            "time": list(timeline.times),
            "drive": [c[axis] for c in timeline.commands],
        },
        "centre": float(centre),
        "half_range": half,
    }


class Timeline:
    """The commanded position against the instrument clock, as issued: the command is held
    between calls and ramps linearly during a move, so the drive is piecewise linear in time."""

    def __init__(self, instrument):
        self.instrument = instrument
        self.times: list[float] = []
        self.commands: list[tuple[float, float]] = []
        self.mark()

    def mark(self) -> None:
        self.times.append(float(self.instrument.time))
        self.commands.append(tuple(float(c) for c in self.instrument.commanded_position()))

    def move(self, x: float, y: float, speed: float) -> None:
        self.mark()
        self.instrument.move_tip(x, y, speed)
        self.mark()

    def punch(self, force: float) -> float:
        """A pit where the tip is; returns the moment it is punched (instrument clock)."""
        self.mark()
        x, y = self.instrument.commanded_position()
        moment = float(self.instrument.time)
        self.instrument.indent(x, y, force, 0.0)
        self.mark()
        return moment

    def sampled(self, axis: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
        times = np.asarray(self.times)
        values = np.asarray(self.commands)[:, axis]
        grid = np.arange(times[0], times[-1] + dt, dt)
        return grid, np.interp(grid, times, values)


def set_feed_forward(instrument, enabled: bool) -> None:
    if not hasattr(instrument, "feed_forward_enabled"):
        raise ValueError(
            "instrument: has no feed_forward_enabled switch; the hysteresis experiment drives the "
            "piezos open loop (raw voltages) and needs it"
        )
    instrument.feed_forward_enabled = enabled
