"""The sample: a substrate and the nano-objects on it, as a height function."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Sphere:
    """A particle resting on the substrate (centre at height = radius)."""
    id: int
    x: float
    y: float
    radius: float

    def height(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        d2 = (xs - self.x) ** 2 + (ys - self.y) ** 2
        inside = d2 < self.radius**2
        return np.where(inside, self.radius + np.sqrt(np.where(inside, self.radius**2 - d2, 0.0)), 0.0)


@dataclass
class Sample:
    spheres: list[Sphere] = field(default_factory=list)

    def height(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """Topography (m) at sample-frame coordinates; substrate at 0."""
        z = np.zeros(np.broadcast(xs, ys).shape)
        for sphere in self.spheres:
            z = np.maximum(z, sphere.height(xs, ys))
        return z
