"""The noise floor of a feature that is itself a noise statistic: its modelled sigma cannot be
below the sampling precision that the instrument's own noise gives it.

The noise model takes each feature's white variance from re-simulations with the sensor noise
on (noise_model.pooled_white). A signal the simulator draws without noise (the torsion: the
model has no torsion noise, so a push's torsion fluctuation `push.fluct` is the same in every
replica) gets the pool's relative floor only (1e-3 of its size): 1.2e-15 rad for a fluctuation
of 1.2e-12 rad, which no instrument resolves, so an effect adding a few nrad of torsion noise
read as a million noise sigmas. What the instrument measures is in the recorded trace itself:
its sample-to-sample changes (robust sd over sqrt(2), `step_noise` in the feature's conditions)
are its white noise s, which the trace's slow course and a few slips do not reach. An rms of n
samples carrying noise s is known to s / sqrt(2 (n - 1)) at best (exactly that when the noise
is all there is; a deterministic course on top makes it s / sqrt(n) times the noise's share),
so that variance is added to the feature's own. It changes nothing where the replicas already
scatter, and nothing where the recorded trace is as noiseless as the model's (a stick-slip
sawtooth, whose fluctuation is deterministic).
"""

from __future__ import annotations

import numpy as np

from afm_core.sim2real.line_shift import LINE_SHIFT_GROUP
from afm_core.sim2real.line_shift import statistic_variance as shift_statistic_variance

# rms features whose conditions carry their sample count and step noise (features.py)
RMS_GROUPS = ("push.fluct",)


def statistic_variance(table) -> np.ndarray:
    """(N,) variance (SI^2) to add to each feature's white noise: s^2 / (2 (n - 1)) of an rms
    feature of n samples whose recorded trace has step noise s; a line-shift statistic's own
    sampling variance (line_shift.statistic_variance); 0 for the other features."""
    out = np.zeros(len(table.groups))
    for i in np.flatnonzero(table.groups == LINE_SHIFT_GROUP):
        cond = table.conditions[i]
        out[i] = shift_statistic_variance(cond.get("statistic", 0.0), cond.get("crossings", 1))
    for i in np.flatnonzero(np.isin(table.groups, RMS_GROUPS)):
        cond = table.conditions[i]
        n, s = cond.get("samples"), cond.get("step_noise")
        if n and n > 1 and s is not None and np.isfinite(s):
            out[i] = s**2 / (2.0 * (n - 1))
    return out
