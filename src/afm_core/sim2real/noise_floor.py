"""The noise floor of a feature that is itself a noise statistic: its modelled sigma cannot be
below the sampling precision of the statistic at the level the instrument measured.

The noise model takes each feature's white variance from re-simulations with the sensor noise
on (noise_model.pooled_white). A signal the simulator draws without noise (the torsion: the
model has no torsion noise, so a push's torsion fluctuation `push.fluct` is the same in every
replica) gets the pool's relative floor only (1e-3 of its size): 1.2e-15 rad for a fluctuation
of 1.2e-12 rad, which no instrument resolves. Any measured signal has noise, and an rms of n
samples whose level is s is known to s / sqrt(2 (n - 1)) (the chi distribution's spread) at
best, whatever makes the level: so the floor is that spread at the larger of the recorded and
the modelled level (the recorded one is what this instrument showed; the model's, what the
re-simulation will be compared with). It removes nothing the model already has (the floor is
added to its variance, which is much larger wherever the replicas scatter) and it keeps an
effect that adds a few nrad of torsion noise from reading as a million noise sigmas.
"""

from __future__ import annotations

import numpy as np

# rms features whose conditions carry their sample count (features.py)
RMS_GROUPS = ("push.fluct",)


def statistic_variance(table, recorded: np.ndarray, nominal: np.ndarray) -> np.ndarray:
    """(N,) variance (SI^2) to add to each feature's white noise: the sampling variance of an
    rms feature of n samples at max(|recorded|, |nominal|); 0 for the other features."""
    out = np.zeros(len(table.groups))
    recorded, nominal = np.asarray(recorded, float), np.asarray(nominal, float)
    for i in np.flatnonzero(np.isin(table.groups, RMS_GROUPS)):
        n = table.conditions[i].get("samples")
        level = np.nanmax(np.abs([recorded[i], nominal[i], 0.0]))
        if n and n > 1 and np.isfinite(level):
            out[i] = level**2 / (2.0 * (n - 1))
    return out
