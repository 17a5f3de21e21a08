"""Tip-surface morphology: an AFM image is the grey dilation of the surface by the tip (book
eq. 4.26/4.28), and the tightest surface under an image is its erosion (Villarrubia 1994/1997).

Conventions (the project's): a tip is a square odd-sized grid t(u) <= 0 with its apex at the
centre pixel, t(0) = 0, u = (row, column) offset from the apex. Imaging is grey dilation

    i(x) = max_u [ s(x + u) + t(u) ]                       (dilate)

and reconstruction is its adjoint erosion, the tightest surface under the tip everywhere:

    r(y) = min_u [ i(y - u) - t(u) ]                       (erode)

so that erode(dilate(s, t), t) >= s, with equality wherever the tip touches s.
(Villarrubia's and Gwyddion's P is the reflected tip: P(d) = t(-d), i = s (+) P.) Edges are
clamped (the grid is continued by its border values).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

# scipy's grey filters precompute the footprint's offsets for every border case: about
# (tip pixels)^2 indices, 2.6 GB for a 135 x 135 tip (a 100 nm scan at 1.6 nm pixels on the
# simulator). Above this many bytes of them the tip is applied by shifted slices instead.
SCIPY_OFFSET_BYTES = 64 * 2**20


def dilate(surface: np.ndarray, tip: np.ndarray) -> np.ndarray:
    """Image height where the tip apex sits over each pixel: i(x) = max_u s(x+u) + t(u).

    `tip` holds t(u) <= 0 with the apex at the centre. scipy's grey_dilation computes
    max_u s(x-u) + b(u), so the tip is passed reflected.
    """
    if _large(tip):
        return _shifted(surface, tip, np.maximum, 1.0)
    return ndimage.grey_dilation(surface, structure=tip[::-1, ::-1], mode="nearest")


def erode(image: np.ndarray, tip: np.ndarray) -> np.ndarray:
    """Reconstruction r(y) = min_u i(y-u) - t(u) (edges clamped), the adjoint of `dilate`.

    scipy's grey_erosion computes min_v f(y+v) - b(v); with v = -u the structure is the
    reflected tip."""
    if _large(tip):
        return _shifted(image, tip[::-1, ::-1], np.minimum, -1.0)
    return ndimage.grey_erosion(image, structure=tip[::-1, ::-1], mode="nearest")


def _large(tip: np.ndarray) -> bool:
    return 8 * tip.size**2 > SCIPY_OFFSET_BYTES


def _shifted(values: np.ndarray, tip: np.ndarray, pick, sign: float) -> np.ndarray:
    """max_u v(x+u) + t(u) (pick=np.maximum, sign=1) or min_u v(x+u) - t(u) (np.minimum, -1)
    over the tip's offsets u, edges clamped: the same sums as scipy's, so the same result, in
    memory of the image's size. An offset whose best case cannot beat the centre's worst is
    skipped (its sum never wins)."""
    values = np.asarray(values, dtype=np.float64)
    rows, cols = tip.shape
    half_r, half_c = rows // 2, cols // 2
    padded = np.pad(values, ((half_r, half_r), (half_c, half_c)), mode="edge")
    height, width = values.shape
    spread = float(values.max() - values.min())
    centre = sign * float(tip[half_r, half_c])
    out = values + centre
    for a, b in zip(*np.nonzero(np.isfinite(tip))):
        term = sign * float(tip[a, b])
        if sign * (term - centre) < -spread:  # never better than the centre's own value
            continue
        pick(out, padded[a : a + height, b : b + width] + term, out=out)
    return out
