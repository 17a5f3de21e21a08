"""A tip characterizer sample for blind tip estimation (book ch. 4, SPEC 2).

Blind estimation recovers only the parts of the tip that some sample feature sharper than
the tip has imaged. The characterizer is therefore a flat substrate carrying a random field
of very sharp, narrow cones ("spikes", 20-80 nm high, half-angle a few degrees), far sharper
than the tip being characterised: each spike images (a reflected copy of) the tip's top down
to the spike's height. The image is the grey dilation of the sampled surface by the tip
(`afm_core.physics.tip_morphology.dilate`) plus white noise. Heights are in metres.

With the default tip (apex radius 10 nm, half-angle 25 deg, asymmetry 0.2) and pixel
(1.6 nm), a 41x41 tip window covers the tip's top ~40-50 nm (a 21x21 window the top ~13 nm).
"""

from __future__ import annotations

import numpy as np

from afm_core.physics.tip_morphology import dilate
from afm_core.sim.tip import paraboloid_cone_tip

DEFAULT_PIXEL = 1.6e-9  # m
DEFAULT_APEX_RADIUS = 10e-9  # m
DEFAULT_HALF_ANGLE_DEG = 25.0
DEFAULT_ASYMMETRY = 0.2  # +x flank blunter (afm_core.sim.tip convention)


def default_tip(pixel: float = DEFAULT_PIXEL, depth: float = 100e-9) -> np.ndarray:
    """The characterised tip sampled at `pixel`, deep enough to image the tallest spikes."""
    return paraboloid_cone_tip(
        DEFAULT_APEX_RADIUS, DEFAULT_HALF_ANGLE_DEG, pixel, depth, asymmetry=DEFAULT_ASYMMETRY
    )


def spike_field(
    n: int,
    pixel: float,
    rng: np.random.Generator,
    count: int | None = None,
    heights: tuple[float, float] = (20e-9, 80e-9),
    half_angle_deg: float = 6.0,
) -> np.ndarray:
    """(n, n) surface: a flat substrate at 0 with `count` sharp cones at random sub-pixel
    positions, heights uniform in `heights`, cone half-angle `half_angle_deg`."""
    if count is None:
        count = max(1, int(round(n * n / 2500)))
    slope = 1.0 / np.tan(np.radians(half_angle_deg))
    surface = np.zeros((n, n))
    reach = int(np.ceil(heights[1] / slope / pixel)) + 1
    offsets = np.arange(-reach, reach + 1)
    for _ in range(count):
        cy, cx = rng.uniform(0, n, size=2)
        height = rng.uniform(*heights)
        iy, ix = int(cy), int(cx)
        rows = np.clip(iy + offsets, 0, n - 1)
        cols = np.clip(ix + offsets, 0, n - 1)
        ry = (rows[:, None] + 0.5 - cy) * pixel
        rx = (cols[None, :] + 0.5 - cx) * pixel
        cone = height - np.hypot(ry, rx) * slope
        surface[np.ix_(rows, cols)] = np.maximum(surface[np.ix_(rows, cols)], cone)
    return surface


def characterizer_image(
    n: int = 512,
    pixel: float = DEFAULT_PIXEL,
    tip: np.ndarray | None = None,
    noise: float = 0.3e-9,
    seed: int = 0,
    count: int | None = None,
    heights: tuple[float, float] = (20e-9, 80e-9),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image, surface, tip): the spike field imaged by `tip` (default `default_tip(pixel)`)
    with white noise of standard deviation `noise` (m) added to the image."""
    rng = np.random.default_rng(seed)
    if tip is None:
        tip = default_tip(pixel, depth=heights[1])
    surface = spike_field(n, pixel, rng, count=count, heights=heights)
    image = dilate(surface, tip)
    if noise > 0:
        image = image + rng.normal(0.0, noise, size=image.shape)
    return image, surface, tip
