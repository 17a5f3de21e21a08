"""Imaging as grey-scale dilation of the surface by the tip (book eq. 4.26/4.28)."""
from __future__ import annotations

import numpy as np
from scipy import ndimage


def dilate(surface: np.ndarray, tip: np.ndarray) -> np.ndarray:
    """Image height where the tip apex sits over each pixel: i(x) = max_u s(x+u) + t(u).

    `tip` holds t(u) <= 0 with the apex at the centre. scipy's grey_dilation computes
    max_u s(x-u) + b(u), so the tip is passed reflected.
    """
    return ndimage.grey_dilation(surface, structure=tip[::-1, ::-1], mode="nearest")
