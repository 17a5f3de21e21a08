"""The substrate's realization: what the model cannot know about the recorded sample.

A model describes the substrate by its roughness (rms and correlation length), never by the
recording's own surface. The shape features (a line's peak, width and asymmetry, an image's
particle height and half-width) are measured against the substrate about the particle, so the
recording's surface and the model's differ in them by an amount the sensor-noise replicas
(which keep the model's sample) never show. That difference is static: every later pass over
the same place carries the same part of it, in the training blocks and the held-out blocks
alike. Left out of the noise model, it passes for a term that changes every height a little:
a null on a new layout named a z gain of 0.9993 +- 0.0002 whose held-out chi^2 went
229.5 -> 217.7 for 275 dof (the repeated passes counted as independent evidence twice over).

So it enters the noise model as a covariance, drawn by re-simulation: SAMPLE_REALIZATIONS
deterministic replays at the recorded drift whose sample differs only in its seed (another
surface of the same roughness), each feature's departure from the reference pooled per group
(two draws per feature are too few alone) for its variance, and shared between two features of
a group (along the same axis, where the feature has one) with the Gaussian kernel of their
distance at the roughness' correlation length: the same place, the same part of the surface
(positive semi-definite, a product of kernels).
"""

from __future__ import annotations

import numpy as np

from afm_core.sim.config import SimConfig, merge
from afm_core.sim2real.feature_table import SHAPE_GROUPS, Table, by_key, values_at
from afm_core.sim2real.features import extract_features
from afm_core.sim2real.protocol import deterministic, replay

# other surfaces drawn; their seeds are the model's + SAMPLE_SEED_OFFSET + k (the noise
# statistics' realizations use + 1 + k: reference.realization_offsets)
SAMPLE_REALIZATIONS = 2
SAMPLE_SEED_OFFSET = 101


def sample_covariance(
    ops, config: SimConfig, drift, anchors, keys: list, table: Table, nominal: np.ndarray
) -> np.ndarray:
    """(N, N) covariance of the shape features from the substrate's unknown realization
    (module docstring); zeros when the session has no shape feature, the substrate has no
    roughness, or the model draws particles from its seed (another seed would move them)."""
    n = len(keys)
    shape = np.isin(table.groups, SHAPE_GROUPS)
    sample = config.sample
    if not shape.any() or sample.roughness_sigma <= 0 or sample.random_spheres > 0:
        return np.zeros((n, n))
    base = deterministic(config)
    departures = []
    for k in range(SAMPLE_REALIZATIONS):
        other = merge(base, {"seed": int(config.seed) + SAMPLE_SEED_OFFSET + k})
        rep = replay(ops, other, drift=drift)
        values = values_at(by_key(extract_features(rep.operations, anchors)), keys)
        departures.append(values - nominal)
    d = np.array(departures)
    variance = np.zeros(n)
    for group in np.unique(table.groups[shape]):
        sel = table.groups == group
        part = d[:, sel]
        part = part[np.isfinite(part)]
        if part.size:
            variance[sel] = float(np.mean(part**2))
    return shared_covariance(table, variance, sample.roughness_correlation)


def shared_covariance(table: Table, variance: np.ndarray, length: float) -> np.ndarray:
    """variance_i^(1/2) variance_j^(1/2) exp(-|xy_i - xy_j|^2 / 2 length^2) between features
    of one group with the same axis u, 0 otherwise."""
    use = np.flatnonzero(variance > 0)
    out = np.zeros((len(variance), len(variance)))
    if not use.size:
        return out
    xy, u, groups = table.xy[use], table.u[use], table.groups[use]
    distance2 = np.sum((xy[:, None, :] - xy[None, :, :]) ** 2, axis=2)
    kernel = np.exp(-distance2 / (2 * max(length, 1e-12) ** 2))
    same = (groups[:, None] == groups[None, :]) & np.all(
        np.isclose(u[:, None, :], u[None, :, :]), axis=2
    )
    sd = np.sqrt(variance[use])
    out[np.ix_(use, use)] = np.outer(sd, sd) * kernel * same
    return out
