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


def dilate(surface: np.ndarray, tip: np.ndarray) -> np.ndarray:
    """Image height where the tip apex sits over each pixel: i(x) = max_u s(x+u) + t(u).

    `tip` holds t(u) <= 0 with the apex at the centre. scipy's grey_dilation computes
    max_u s(x-u) + b(u), so the tip is passed reflected.
    """
    return ndimage.grey_dilation(surface, structure=tip[::-1, ::-1], mode="nearest")


def erode(image: np.ndarray, tip: np.ndarray) -> np.ndarray:
    """Reconstruction r(y) = min_u i(y-u) - t(u) (edges clamped), the adjoint of `dilate`.

    scipy's grey_erosion computes min_v f(y+v) - b(v); with v = -u the structure is the
    reflected tip."""
    return ndimage.grey_erosion(image, structure=tip[::-1, ::-1], mode="nearest")
