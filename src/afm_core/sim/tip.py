"""Tip geometry as a height grid: apex at the centre pixel, height 0, everything else < 0."""
from __future__ import annotations

import numpy as np


def paraboloid_cone_tip(apex_radius: float, half_angle_deg: float, pixel_size: float,
                        depth: float) -> np.ndarray:
    """A paraboloid apex z = -r^2 / (2 R) blended tangentially into a cone of the given
    half-angle, cut at `depth` below the apex. Returns an odd-sized square grid (metres)."""
    if not (apex_radius > 0 and pixel_size > 0 and depth > 0 and 0 < half_angle_deg < 90):
        raise ValueError(f"tip: apex_radius={apex_radius}, half_angle_deg={half_angle_deg}, "
                         f"pixel_size={pixel_size}, depth={depth}: all must be > 0, angle < 90 deg")
    slope = 1.0 / np.tan(np.radians(half_angle_deg))          # dz/dr of the cone wall
    r_tangent = apex_radius * slope                            # where the paraboloid's slope = cone's
    z_tangent = -r_tangent**2 / (2 * apex_radius)
    r_max = r_tangent + (depth + z_tangent) / slope if depth > -z_tangent else np.sqrt(2 * apex_radius * depth)
    half = int(np.ceil(r_max / pixel_size))
    offsets = np.arange(-half, half + 1) * pixel_size
    r = np.hypot(*np.meshgrid(offsets, offsets))
    z = np.where(r <= r_tangent, -r**2 / (2 * apex_radius), z_tangent - (r - r_tangent) * slope)
    return np.maximum(z, -depth)
