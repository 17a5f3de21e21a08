"""How much a free tip move adds to the tip's position uncertainty.

The book measures the motion error variance growing linearly with the distance moved
(Fig. 7.6e, Fig. 7.20b: sigma^2 = a d + b) and, for planning, splits the slope by axis
(section 6.1: moving along x grows the x variance with slope K_h1 and the y variance with
K_h2; moving along y grows y with K_v1 and x with K_v2). This is the one noise model shared
by the Kalman filter (prediction) and the planner (predicted covariance at each waypoint).
Drift that the motion model's mean does not remove is no noise of a move but a velocity
that persists for minutes: the filter carries it as state (`TipFilter` drift_sigma).
All values SI: slopes in m^2 per m moved, offsets in m^2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MotionNoise:
    k_h1: float  # m^2/m: x variance per metre moved along x
    k_h2: float  # m^2/m: y variance per metre moved along x
    k_v1: float  # m^2/m: y variance per metre moved along y
    k_v2: float  # m^2/m: x variance per metre moved along y
    offset_x: float = 0.0  # m^2 added by any move (settling), x
    offset_y: float = 0.0  # m^2, y

    def __post_init__(self):
        for name in ("k_h1", "k_h2", "k_v1", "k_v2", "offset_x", "offset_y"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"motion noise {name}={value}: must be finite and >= 0")

    @classmethod
    def isotropic(
        cls, slope: float, offset: float = 0.0, cross_fraction: float = 0.0
    ) -> MotionNoise:
        """sigma^2 = slope d + offset on the moving axis; cross_fraction of the slope on the
        other."""
        return cls(slope, cross_fraction * slope, slope, cross_fraction * slope, offset, offset)

    @classmethod
    def book(cls) -> MotionNoise:
        """Fig. 7.20b: a = 0.0701 nm^2/nm, b = 0.4345 nm^2 (1 um range); 10 % cross-axis growth
        (the book's 'slightly')."""
        return cls.isotropic(0.0701e-9, 0.4345e-18, cross_fraction=0.1)

    def added_covariance(self, dx: float, dy: float) -> np.ndarray:
        """2x2 covariance (m^2) a move by (dx, dy) m adds; zero for no move."""
        ax, ay = abs(float(dx)), abs(float(dy))
        moved = ax > 0 or ay > 0
        var_x = self.k_h1 * ax + self.k_v2 * ay + (self.offset_x if moved else 0.0)
        var_y = self.k_h2 * ax + self.k_v1 * ay + (self.offset_y if moved else 0.0)
        return np.diag([var_x, var_y])

    def predict(self, covariance, dx: float, dy: float) -> np.ndarray:
        """Covariance after the move: the prior plus what the move adds."""
        return np.asarray(covariance, dtype=float) + self.added_covariance(dx, dy)
