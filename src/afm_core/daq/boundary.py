"""The one seam between the DAQ backend and the card: synchronised AO ramps with AI reads.

Everything above it (calibration, paths, validation, images) is plain numpy and is tested
against `FakeDaq`; everything below it (`NidaqmxBoundary`) is the thin vendor layer that
can only be exercised on the real platform.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np


class DaqUnavailable(RuntimeError):
    """The DAQ cannot be used here: package, driver/runtime or device missing."""


class DaqBoundary(Protocol):
    """What the backend needs from a DAQ card, in volts, rows = channels in configure order."""

    def configure(
        self,
        ao_channels: list[str],
        ai_channels: list[str],
        sample_rate: float,
        ao_range: tuple[float, float],
        ai_range: tuple[float, float],
    ) -> None:
        """Set up the channels once; `sample_rate` (Hz) clocks both AO and AI."""

    def write_read(self, ao_samples: np.ndarray) -> np.ndarray:
        """Output (n_ao, n) volts on the sample clock and return the (n_ai, n) volts acquired
        on the same clock edges; blocks until the ramp is done and the outputs then hold
        the last sample."""

    def write_static(self, volts: np.ndarray) -> None:
        """Hold these (n_ao,) levels now (software-timed)."""

    def close(self) -> None: ...


Respond = Callable[[np.ndarray], np.ndarray]  # (n_ao, n) volts written -> (n_ai, n) volts read


class FakeDaq:
    """A DAQ card in memory: records every written sample and answers from `respond`.

    `clock` advances by n / sample_rate per `write_read`, as the hardware-timed ramp would,
    so passing `clock=fake.clock` to the instrument gives exact, repeatable timings.
    Writing outside the configured AO range raises, as the real driver does.
    """

    def __init__(self, respond: Respond | None = None):
        self.respond = respond
        self.ao_channels: list[str] = []
        self.ai_channels: list[str] = []
        self.sample_rate = 0.0
        self.ao_range = (-10.0, 10.0)
        self.ai_range = (-10.0, 10.0)
        self.writes: list[tuple[str, np.ndarray]] = []  # ("ramp" | "static", (n_ao, n) volts)
        self.now = 0.0  # s, simulated time
        self.closed = False

    def configure(self, ao_channels, ai_channels, sample_rate, ao_range, ai_range) -> None:
        self.ao_channels, self.ai_channels = list(ao_channels), list(ai_channels)
        self.sample_rate = float(sample_rate)
        self.ao_range, self.ai_range = tuple(ao_range), tuple(ai_range)

    def _check(self, volts: np.ndarray) -> np.ndarray:
        if self.closed:
            raise RuntimeError("FakeDaq: closed")
        if not self.ao_channels:
            raise RuntimeError("FakeDaq: write before configure")
        volts = np.array(volts, dtype=float)
        if volts.shape[0] != len(self.ao_channels):
            raise ValueError(
                f"FakeDaq: {volts.shape[0]} AO rows for {len(self.ao_channels)} channels"
            )
        if (
            not np.all(np.isfinite(volts))
            or volts.min() < self.ao_range[0]
            or volts.max() > self.ao_range[1]
        ):
            raise ValueError(f"FakeDaq: AO samples outside the configured range {self.ao_range} V")
        return volts

    def write_read(self, ao_samples: np.ndarray) -> np.ndarray:
        volts = self._check(ao_samples)
        if volts.ndim != 2 or volts.shape[1] < 1:
            raise ValueError("FakeDaq: write_read needs (n_ao, n) samples")
        self.writes.append(("ramp", volts))
        self.now += volts.shape[1] / self.sample_rate
        if self.respond is None:
            return np.zeros((len(self.ai_channels), volts.shape[1]))
        readings = np.asarray(self.respond(volts), dtype=float)
        if readings.shape != (len(self.ai_channels), volts.shape[1]):
            raise ValueError(
                f"FakeDaq: respond returned {readings.shape}, expected "
                f"{(len(self.ai_channels), volts.shape[1])}"
            )
        return np.clip(readings, *self.ai_range)  # an ADC saturates at its range

    def write_static(self, volts: np.ndarray) -> None:
        volts = self._check(np.asarray(volts, dtype=float).reshape(-1, 1))
        self.writes.append(("static", volts))

    def close(self) -> None:
        self.closed = True

    def clock(self) -> float:
        return self.now

    @property
    def samples(self) -> np.ndarray:
        """Every AO sample written so far, ramps and static holds, in order: (n_ao, total)."""
        if not self.writes:
            return np.zeros((len(self.ao_channels), 0))
        return np.concatenate([v for _, v in self.writes], axis=1)

    @property
    def last_levels(self) -> np.ndarray:
        """The AO levels the outputs hold now."""
        return self.writes[-1][1][:, -1]
