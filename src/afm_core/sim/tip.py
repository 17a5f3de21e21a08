"""Tip geometry as a height grid: apex at the centre pixel, height 0, everything else < 0.

A paraboloid apex z = -r^2 / (2 R), or a spherical cap of radius R (the usual model of a
microfabricated tip; below its apex it is sharper than the paraboloid of the same R), blends
tangentially into a cone. With asymmetry a, the
cone's half-angle depends on the azimuth phi: theta(phi) = theta0 * (1 + a cos phi), so the
+x flank is blunter than the -x flank for a > 0 (real tips are rarely symmetric). Wear
blunts the apex: the radius grows in proportion to the distance slid in contact.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

APEX_SHAPES = ("paraboloid", "sphere")


@dataclass
class TipParams:
    apex_radius: float = 20e-9  # m, new tip
    half_angle_deg: float = 20.0  # deg, cone half-angle (theta0)
    asymmetry: float = 0.0  # relative half-angle change between +x and -x flanks, |a| < 1
    apex_shape: str = "paraboloid"  # "paraboloid" or "sphere" (spherical cap)
    wear_enabled: bool = False
    wear_rate: float = 1e-5  # m of apex radius gained per m slid in contact
    max_apex_radius: float = 200e-9  # m, wear stops here (a flat, worn tip)

    def validate(self) -> None:
        if not self.apex_radius > 0:
            raise ValueError(f"tip.apex_radius={self.apex_radius}: must be > 0 m")
        if not 0 < self.half_angle_deg < 90:
            raise ValueError(
                f"tip.half_angle_deg={self.half_angle_deg}: must be within (0, 90) deg"
            )
        if not abs(self.asymmetry) < 1:
            raise ValueError(f"tip.asymmetry={self.asymmetry}: must be within (-1, 1)")
        if self.half_angle_deg * (1 + abs(self.asymmetry)) >= 90:
            raise ValueError(
                f"tip.asymmetry={self.asymmetry}: makes a flank's half-angle reach 90 deg"
            )
        if self.apex_shape not in APEX_SHAPES:
            raise ValueError(
                f"tip.apex_shape={self.apex_shape!r}: must be one of {', '.join(APEX_SHAPES)}"
            )
        if self.wear_rate < 0:
            raise ValueError(f"tip.wear_rate={self.wear_rate}: must be >= 0")


def tip_reach(
    apex_radius: float,
    half_angle_deg: float,
    depth: float,
    asymmetry: float = 0.0,
    apex_shape: str = "paraboloid",
) -> float:
    """How far from the apex axis (m) the tip of `paraboloid_cone_tip` reaches at `depth` below
    the apex, on its widest flank: its grid's half width."""
    flattest = 1.0 / np.tan(np.radians(half_angle_deg * (1 + abs(asymmetry))))
    if apex_shape == "sphere":
        r_t = apex_radius * flattest / np.sqrt(1 + flattest**2)
        z_t = -(apex_radius - np.sqrt(apex_radius**2 - r_t**2))
        if depth <= -z_t:
            return float(np.sqrt(depth * (2 * apex_radius - depth)))
    else:
        r_t = apex_radius * flattest
        z_t = -(r_t**2) / (2 * apex_radius)
        if depth <= -z_t:
            return float(np.sqrt(2 * apex_radius * depth))
    return float(r_t + (depth + z_t) / flattest)


def paraboloid_cone_tip(
    apex_radius: float,
    half_angle_deg: float,
    pixel_size: float,
    depth: float,
    asymmetry: float = 0.0,
    max_half_width: int | None = None,
    apex_shape: str = "paraboloid",
) -> np.ndarray:
    """Odd-sized square height grid (m) of the tip down to `depth` below the apex; the apex a
    paraboloid or a spherical cap (`apex_shape`), blended into the cone where their slopes meet."""
    if not (apex_radius > 0 and pixel_size > 0 and depth > 0 and 0 < half_angle_deg < 90):
        raise ValueError(
            f"tip: apex_radius={apex_radius}, half_angle_deg={half_angle_deg}, "
            f"pixel_size={pixel_size}, depth={depth}: all must be > 0, angle < 90 deg"
        )
    if apex_shape not in APEX_SHAPES:
        raise ValueError(f"apex_shape={apex_shape!r}: must be one of {', '.join(APEX_SHAPES)}")
    sphere = apex_shape == "sphere"

    def tangent(slope):
        """(r, z) where the apex's slope equals the cone's: r/R (paraboloid), r/sqrt(R^2-r^2)
        (sphere)."""
        if sphere:
            r = apex_radius * slope / np.sqrt(1 + slope**2)
            return r, -(apex_radius - np.sqrt(apex_radius**2 - r**2))
        r = apex_radius * slope
        return r, -(r**2) / (2 * apex_radius)

    r_max = tip_reach(apex_radius, half_angle_deg, depth, asymmetry, apex_shape)
    half = int(np.ceil(r_max / pixel_size))
    if max_half_width is not None:
        half = min(half, max_half_width)
    offsets = np.arange(-half, half + 1) * pixel_size
    ox, oy = np.meshgrid(offsets, offsets)
    r = np.hypot(ox, oy)
    cos_phi = np.divide(ox, r, out=np.zeros_like(r), where=r > 0)
    slope = 1.0 / np.tan(np.radians(half_angle_deg) * (1 + asymmetry * cos_phi))  # cone wall dz/dr
    r_tangent, z_tangent = tangent(slope)
    if sphere:
        cap = -(apex_radius - np.sqrt(np.maximum(apex_radius**2 - r**2, 0.0)))
    else:
        cap = -(r**2) / (2 * apex_radius)
    z = np.where(r <= r_tangent, cap, z_tangent - (r - r_tangent) * slope)
    return np.maximum(z, -depth)


class Tip:
    """The simulated tip: current apex radius (wears) and its grid, cached per pixel size."""

    def __init__(self, params: TipParams):
        params.validate()
        self.params = params
        self.apex_radius = params.apex_radius
        self.contact_distance = 0.0
        self._cache: dict = {}

    def reach(self, depth: float) -> float:
        """The grid's half width at `depth` (m): how far from the apex the tip can touch."""
        return tip_reach(
            self.apex_radius,
            self.params.half_angle_deg,
            depth,
            self.params.asymmetry,
            self.params.apex_shape,
        )

    def grid(
        self, pixel_size: float, depth: float, max_half_width: int | None = None
    ) -> np.ndarray:
        key = (round(pixel_size, 15), round(depth, 12), max_half_width, self.apex_radius)
        if key not in self._cache:
            self._cache = {
                key: paraboloid_cone_tip(
                    self.apex_radius,
                    self.params.half_angle_deg,
                    pixel_size,
                    depth,
                    self.params.asymmetry,
                    max_half_width,
                    self.params.apex_shape,
                )
            }
        return self._cache[key]

    def slide(self, distance: float) -> None:
        """Account for `distance` (m) slid in contact: wear, if enabled."""
        self.contact_distance += distance
        if self.params.wear_enabled:
            self.apex_radius = min(
                self.params.max_apex_radius,
                self.params.apex_radius + self.params.wear_rate * self.contact_distance,
            )
