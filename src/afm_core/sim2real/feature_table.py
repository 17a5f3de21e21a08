"""The recorded features as one table (per feature: key, group, time, position, direction,
conditions, operation) and the feature groups the diagnosis treats alike."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from afm_core.sim2real.features import Feature
from afm_core.sim2real.line_shift import LINE_SHIFT_GROUP

SHAPE_GROUPS = ("line.width", "line.peak", "line.asym", "raster.height", "raster.half_width")
HEIGHT_GROUPS = ("line.peak", "raster.height")
BOW_GROUPS = ("raster.bow_xx", "raster.bow_yy", "raster.bow_xy")
PUSH_GROUPS = ("push.torsion", "push.fluct")
# noise statistics: move only with the sensor noise
NOISE_GROUPS = ("raster.streak", "raster.pixel_noise", LINE_SHIFT_GROUP)


@dataclass
class Table:
    keys: list
    groups: np.ndarray
    time: np.ndarray
    xy: np.ndarray  # (N, 2)
    u: np.ndarray  # (N, 2)
    conditions: list
    op_index: np.ndarray


def by_key(features: list[Feature]) -> dict:
    return {f.key: f for f in features}


def values_at(features: dict, keys) -> np.ndarray:
    return np.array([features[k].value if k in features else np.nan for k in keys])


def make_table(keys, rec: dict) -> Table:
    fs = [rec[k] for k in keys]
    return Table(
        keys=list(keys),
        groups=np.array([f.group for f in fs]),
        time=np.array([f.time for f in fs]),
        xy=np.array([(f.x, f.y) for f in fs]),
        u=np.array([f.u for f in fs], float),
        conditions=[f.conditions for f in fs],
        op_index=np.array([k[0] for k in keys]),
    )
