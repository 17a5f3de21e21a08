"""The sample world: a rough substrate and the objects on it, as a height function.

Objects live in the sample-fixed task frame (afm_task). Spheres and rods/tubes move when
pushed (afm_core.physics.pushing mutates their poses); electrodes never move; pits are dents
the tip punched. Heights in metres above the mean substrate plane.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Sphere:
    """A particle resting on the substrate (centre at height = radius)."""

    id: int
    x: float
    y: float
    radius: float
    kind: str = "sphere"

    def height(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        return self._cap((xs - self.x) ** 2 + (ys - self.y) ** 2)

    def _cap(self, d2: np.ndarray) -> np.ndarray:
        """The sphere's top at squared distance d2 from its centre (-inf off it)."""
        inside = d2 < self.radius**2
        return np.where(
            inside, self.radius + np.sqrt(np.where(inside, self.radius**2 - d2, 0.0)), -np.inf
        )

    def height_bound(self, x_lo, x_hi, y_lo, y_hi) -> np.ndarray:
        """The highest `height` over each rectangle [x_lo, x_hi] x [y_lo, y_hi], an upper
        bound of what `height` computes at any point in it: the same operations at the
        rectangle's point nearest the centre, and rounding is monotone (a point farther out
        rounds to a d2 no smaller)."""
        dx = np.maximum(np.maximum(x_lo - self.x, self.x - x_hi), 0.0)
        dy = np.maximum(np.maximum(y_lo - self.y, self.y - y_hi), 0.0)
        return self._cap(dx**2 + dy**2)

    def bounds(self) -> tuple[float, float, float, float]:
        return (
            self.x - self.radius,
            self.x + self.radius,
            self.y - self.radius,
            self.y + self.radius,
        )

    def top(self) -> float:
        """Its highest point above the mean substrate plane (m)."""
        return 2 * self.radius


def distance_to_segment(a, b, xs, ys) -> np.ndarray:
    """Distance (m) from the points (xs, ys) to the segment a-b ((2,) m each; a point if a = b)."""
    ab = np.asarray(b, float) - np.asarray(a, float)
    t = np.clip(((xs - a[0]) * ab[0] + (ys - a[1]) * ab[1]) / max(float(ab @ ab), 1e-30), 0.0, 1.0)
    return np.hypot(xs - (a[0] + t * ab[0]), ys - (a[1] + t * ab[1]))


@dataclass
class Rod:
    """A rod or nanotube lying on the substrate: a capsule (cylinder with round ends) of
    `radius` whose axis, at height `radius`, runs `length` long through (x, y) at `angle`."""

    id: int
    x: float
    y: float
    angle: float  # rad, axis direction from +x
    length: float  # m, end to end of the axis segment
    radius: float
    kind: str = "rod"  # "rod" or "tube"

    def endpoints(self) -> tuple[np.ndarray, np.ndarray]:
        half = 0.5 * self.length * np.array([np.cos(self.angle), np.sin(self.angle)])
        centre = np.array([self.x, self.y])
        return centre - half, centre + half

    def distance_to_axis(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        return distance_to_segment(*self.endpoints(), xs, ys)

    def height(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        d = self.distance_to_axis(xs, ys)
        inside = d < self.radius
        return np.where(
            inside, self.radius + np.sqrt(np.where(inside, self.radius**2 - d**2, 0.0)), -np.inf
        )

    def bounds(self) -> tuple[float, float, float, float]:
        a, b = self.endpoints()
        r = self.radius
        return min(a[0], b[0]) - r, max(a[0], b[0]) + r, min(a[1], b[1]) - r, max(a[1], b[1]) + r

    def top(self) -> float:
        return 2 * self.radius


@dataclass
class Electrode:
    """A fixed rectangular metal pad (axis-aligned) of uniform height."""

    id: int
    x0: float
    y0: float
    x1: float
    y1: float
    thickness: float
    kind: str = "electrode"

    def height(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        inside = (xs >= self.x0) & (xs <= self.x1) & (ys >= self.y0) & (ys <= self.y1)
        return np.where(inside, self.thickness, -np.inf)

    def bounds(self) -> tuple[float, float, float, float]:
        return self.x0, self.x1, self.y0, self.y1

    def top(self) -> float:
        return self.thickness


@dataclass
class Pit:
    """An indentation: a paraboloid dent of the tip's apex shape, `depth` deep, `radius` wide."""

    id: int
    x: float
    y: float
    radius: float
    depth: float
    kind: str = "pit"

    def depression(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        r2 = ((xs - self.x) ** 2 + (ys - self.y) ** 2) / self.radius**2
        return np.where(r2 < 1.0, -self.depth * (1.0 - r2), 0.0)

    def bounds(self) -> tuple[float, float, float, float]:
        return (
            self.x - self.radius,
            self.x + self.radius,
            self.y - self.radius,
            self.y + self.radius,
        )


class Roughness:
    """A stationary Gaussian random surface (rms `sigma`, correlation length `correlation`),
    as a periodic tile made once from the seed and interpolated anywhere."""

    def __init__(self, sigma: float, correlation: float, seed: int, tile_pixels: int = 512):
        self.sigma = float(sigma)
        self.pixel = correlation / 4.0 if correlation > 0 else 1e-9
        self.tile = np.zeros((tile_pixels, tile_pixels))
        if sigma > 0 and correlation > 0:
            rng = np.random.default_rng(seed)
            k = np.fft.fftfreq(tile_pixels, d=self.pixel) * 2 * np.pi
            kx, ky = np.meshgrid(k, k)
            spectrum = np.exp(-(kx**2 + ky**2) * correlation**2 / 8.0)  # Gaussian correlation
            field_ = np.fft.ifft2(
                np.fft.fft2(rng.normal(size=self.tile.shape)) * np.sqrt(spectrum)
            ).real
            self.tile = field_ / field_.std() * sigma

    def height(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        if self.sigma == 0:
            return np.zeros(np.broadcast(xs, ys).shape)
        from scipy.ndimage import map_coordinates

        coords = np.stack([np.asarray(ys) / self.pixel, np.asarray(xs) / self.pixel])
        return map_coordinates(
            self.tile, coords.reshape(2, -1), order=1, mode="grid-wrap"
        ).reshape(coords.shape[1:])


@dataclass
class Sample:
    spheres: list[Sphere] = field(default_factory=list)
    rods: list[Rod] = field(default_factory=list)
    electrodes: list[Electrode] = field(default_factory=list)
    pits: list[Pit] = field(default_factory=list)
    roughness: Roughness | None = None

    @property
    def movable(self) -> list:
        return [*self.spheres, *self.rods]

    def objects(self) -> list:
        return [*self.spheres, *self.rods, *self.electrodes, *self.pits]

    def next_id(self) -> int:
        return 1 + max((o.id for o in self.objects()), default=-1)

    def height(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """Topography (m) at sample-frame coordinates: the objects on the base."""
        xs, ys = np.broadcast_arrays(np.asarray(xs, dtype=float), np.asarray(ys, dtype=float))
        z = self.base_height(xs, ys)
        if xs.size == 0:
            return z
        return np.maximum(
            z,
            self.object_height(xs, ys, self.objects_near(xs.min(), xs.max(), ys.min(), ys.max())),
        )

    def base_height(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """The substrate: roughness and pits, without the objects lying on it."""
        z = (
            self.roughness.height(xs, ys)
            if self.roughness is not None
            else np.zeros(np.broadcast(xs, ys).shape)
        )
        if self.pits and np.size(xs):
            x_lo, x_hi, y_lo, y_hi = np.min(xs), np.max(xs), np.min(ys), np.max(ys)
            for pit in self.pits:  # calibration punches dozens: only those in reach count
                b = pit.bounds()
                if not (b[1] < x_lo or b[0] > x_hi or b[3] < y_lo or b[2] > y_hi):
                    z = z + pit.depression(xs, ys)
        return z

    def base_top(self) -> float:
        """An upper bound of base_height anywhere (m): the roughness tile's highest node (its
        linear interpolation stays within the nodes, here with a margin far above round-off),
        pits only lower it."""
        if self.roughness is None or self.roughness.sigma == 0:
            return 0.0
        tile = self.roughness.tile
        return float(tile.max()) + 1e-9 * float(np.abs(tile).max())

    def base_span(self) -> float:
        """An upper bound of max - min of base_height anywhere (m): the roughness's span plus
        the deepest stack of overlapping pits."""
        span = float(np.ptp(self.roughness.tile)) if self.roughness is not None else 0.0
        deepest = 0.0
        for pit in self.pits:
            deepest = max(
                deepest,
                sum(
                    other.depth
                    for other in self.pits
                    if math.hypot(other.x - pit.x, other.y - pit.y) < other.radius + pit.radius
                ),
            )
        return span + deepest

    def objects_near(self, x_lo: float, x_hi: float, y_lo: float, y_hi: float) -> list:
        out = []
        for obj in [*self.electrodes, *self.rods, *self.spheres]:
            b = obj.bounds()
            if not (b[1] < x_lo or b[0] > x_hi or b[3] < y_lo or b[2] > y_hi):
                out.append(obj)
        return out

    @staticmethod
    def object_height(xs: np.ndarray, ys: np.ndarray, objects: list) -> np.ndarray:
        """Top of the given objects (-inf where there are none)."""
        z = np.full(np.broadcast(xs, ys).shape, -np.inf)
        for obj in objects:
            z = np.maximum(z, obj.height(xs, ys))
        return z
