"""Force traces recorded chunk by chunk with bounded memory.

A push or an indentation records every DAQ sample; a 600 s dwell at 100 kHz would be 6e7
samples per signal (several GB with the positions), so a trace planned longer than
`max_samples` is averaged in blocks of `factor` consecutive samples as it is recorded, and
reports `sample_rate / factor`.
"""

from __future__ import annotations

import math

import numpy as np

_KEYS = ("t", "x", "y", "z", "d", "l")


class TraceRecorder:
    """Accumulates (times, x, y, z, deflection, torsion) chunks, block-averaged by `factor`."""

    def __init__(self, sample_rate: float, planned_samples: int, max_samples: int):
        self.factor = max(1, math.ceil(planned_samples / max_samples))
        self.sample_rate = sample_rate / self.factor
        self._done: dict[str, list[np.ndarray]] = {k: [] for k in _KEYS}
        self._pending: dict[str, np.ndarray] = {k: np.empty(0) for k in _KEYS}

    def add(self, **signals: np.ndarray) -> None:
        """One chunk: arrays of equal length under the keys t, x, y, z, d, l."""
        for key in _KEYS:
            self._pending[key] = np.concatenate([self._pending[key], signals[key]])
        whole = len(self._pending["t"]) // self.factor * self.factor
        if whole:
            for key in _KEYS:
                block = self._pending[key][:whole]
                self._done[key].append(block.reshape(-1, self.factor).mean(axis=1))
                self._pending[key] = self._pending[key][whole:]

    def arrays(self) -> dict[str, np.ndarray]:
        """Everything recorded; a last partial block becomes one (mean) sample."""
        out = {}
        for key in _KEYS:
            parts = list(self._done[key])
            if len(self._pending[key]):
                parts.append(np.array([self._pending[key].mean()]))
            out[key] = np.concatenate(parts) if parts else np.empty(0)
        return out
