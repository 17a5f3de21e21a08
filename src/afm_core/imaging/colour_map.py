"""A height image as 8-bit RGB for viewers that show pictures, not data (Foxglove's Image panel,
`rqt_image_view`): one fixed colour map, scaled per image, with the scale returned so it can be
said beside the picture.

The map is `afmhot` (black - red - yellow - white), the one AFM software and this project's
reports use, so the same height looks the same in the report and in a recording. Rows are
flipped so that +y is up, as the reports draw the images (`origin="lower"`): an image viewer
draws row 0 at the top.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# The scale spans these percentiles of the image's finite heights, not its extremes: one spike
# (a tip crash, a noise burst) or a deep pit would otherwise take most of the 256 levels and
# leave the particles and the substrate the same colour. 0.5 % of the pixels at each end clip.
SCALE_PERCENTILES = (0.5, 99.5)
LEVELS = 256  # 8-bit channels


@dataclass(frozen=True)
class ColourScale:
    """Heights (m) shown as the first and the last colour of the map."""

    low: float
    high: float

    def describe(self) -> str:
        return f"afmhot, {self.low * 1e9:.3f} nm (black) to {self.high * 1e9:.3f} nm (white)"


def afmhot(fraction: np.ndarray) -> np.ndarray:
    """Fractions in [0, 1] -> RGB in [0, 1] (matplotlib's afmhot, in closed form)."""
    x = np.clip(fraction, 0.0, 1.0)[..., None]
    return np.clip(2.0 * x - np.array([0.0, 0.5, 1.0]), 0.0, 1.0)


def height_scale(height: np.ndarray) -> ColourScale:
    """The image's own scale; ValueError when it has no finite height."""
    finite = np.asarray(height, float)
    finite = finite[np.isfinite(finite)]
    if finite.size == 0:
        raise ValueError("height: no finite value to scale the colour map by")
    low, high = np.percentile(finite, SCALE_PERCENTILES)
    return ColourScale(float(low), float(high))


def height_to_rgb(height: np.ndarray) -> tuple[np.ndarray, ColourScale]:
    """A 2-D height image (m, row 0 at the smallest y) -> (rows x cols x 3 uint8 with row 0 at
    the largest y, its scale). Heights that are not finite are drawn black."""
    height = np.asarray(height, float)
    if height.ndim != 2 or min(height.shape) == 0:
        raise ValueError(f"height: expected a non-empty 2-D image, got shape {height.shape}")
    scale = height_scale(height)
    span = scale.high - scale.low
    # a flat image (span 0) is drawn mid-map rather than divided by zero
    fraction = (height - scale.low) / span if span > 0 else np.full(height.shape, 0.5)
    fraction = np.where(np.isfinite(fraction), fraction, 0.0)
    rgb = np.round(afmhot(fraction) * (LEVELS - 1)).astype(np.uint8)
    return np.ascontiguousarray(rgb[::-1]), scale
