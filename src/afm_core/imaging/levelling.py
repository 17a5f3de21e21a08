"""Levelling a raw AFM height map as the field does it before any analysis: remove the sample's
tilt (plane), the line-to-line offsets of the slow axis (median line alignment) and the bow of
each fast line (polynomial rows), fitting only the background: pixels of a feature mask
(particles, pits) are left out of every fit, and subtracted from like the rest.

Rows are fast-scan lines (a `HeightMap` row at 0 deg). Fits are in pixel coordinates; the
heights keep their unit (metres).

- `level_plane(height, mask)`: least-squares plane a + b col + c row over the background.
- `level_median_rows(height, mask)`: each row minus the median of its background pixels
  (a row that is all mask keeps its overall median), the line alignment of Gwyddion's
  "align rows: median" and TopoStats.
- `level_poly_rows(height, order, mask)`: each row minus its least-squares polynomial in the
  column (order 2 = bow), over its background pixels.
- `feature_mask(height, rows)`: pixels that stand out of a levelled map's background (or of
  their row's) by more than a Gaussian false-alarm rate allows (noise from the median
  absolute deviation).
- `level(height, method, mask="auto")`: one of the above, or several in order
  ("median+plane+median"); "auto" alternates levelling and `feature_mask` until the mask settles.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.stats import norm

METHODS = ("plane", "median", "poly2")
# A background pixel is taken for a feature with this probability (two-sided, Gaussian noise):
# one in a thousand, so a 512 x 512 map loses ~260 background pixels to the mask, too few to
# move a fit, while a feature 3.3 noise sigmas high is masked.
MASK_FALSE_ALARM = 1e-3
MASK_SIGMAS = float(norm.isf(MASK_FALSE_ALARM / 2))
# MAD -> standard deviation for Gaussian noise
_MAD_TO_SIGMA = 1.0 / float(norm.ppf(0.75))
# A feature's flanks are above the background but below the threshold: the mask grows by one
# pixel so they stay out of the fit (a tip-broadened edge spans at least a pixel).
MASK_GROW_PIXELS = 1
# "auto" stops when the mask stops changing; it settles in 2-4 passes, the cap only guards
# against a mask oscillating between two states.
_AUTO_PASSES = 10


def level_plane(height, mask=None) -> np.ndarray:
    """`height` minus the least-squares plane through its background (mask False)."""
    z, background = _checked(height, mask)
    rows, cols = np.indices(z.shape)
    design = np.column_stack([np.ones(z.size), cols.ravel(), rows.ravel()]).astype(float)
    use = background.ravel()
    if np.count_nonzero(use) < 3:
        raise ValueError(
            f"mask leaves {np.count_nonzero(use)} background pixel(s); a plane needs 3"
        )
    coefficients, *_ = np.linalg.lstsq(design[use], z.ravel()[use], rcond=None)
    return z - (design @ coefficients).reshape(z.shape)


def level_median_rows(height, mask=None) -> np.ndarray:
    """Each row minus the median of its background pixels."""
    z, background = _checked(height, mask)
    offsets = np.empty(z.shape[0])
    for row in range(z.shape[0]):
        values = z[row, background[row]]
        offsets[row] = np.median(values if values.size else z[row])
    return z - offsets[:, None]


def level_poly_rows(height, order: int = 2, mask=None) -> np.ndarray:
    """Each row minus its least-squares polynomial of `order` in the column, fitted to its
    background pixels (a row with fewer than order + 1 of them is fitted whole)."""
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)) or order < 0:
        raise ValueError(f"order={order!r}: must be an integer >= 0")
    z, background = _checked(height, mask)
    if z.shape[1] <= order:
        raise ValueError(f"order={order}: rows of {z.shape[1]} pixels need order < {z.shape[1]}")
    # columns scaled to [-1, 1] keep the Vandermonde matrix well conditioned
    x = np.linspace(-1.0, 1.0, z.shape[1])
    vander = np.vander(x, order + 1)
    out = np.empty_like(z)
    for row in range(z.shape[0]):
        use = background[row] if np.count_nonzero(background[row]) > order else slice(None)
        coefficients, *_ = np.linalg.lstsq(vander[use], z[row, use], rcond=None)
        out[row] = z[row] - vander @ coefficients
    return out


def feature_mask(levelled, grow: int = MASK_GROW_PIXELS, rows: bool = False) -> np.ndarray:
    """True where a levelled map leaves its background: |z - median| > MASK_SIGMAS sigma, sigma
    from the median absolute deviation (robust to the features themselves), grown by `grow`
    pixels. `rows`: the median is each row's (for row-by-row levelling, where a feature biases
    its own rows' fits but not the row's median). A noise-free background (sigma 0) masks
    every pixel off the median."""
    z, _ = _checked(levelled, None)
    centre = np.median(z, axis=1, keepdims=True) if rows else np.median(z)
    deviation = np.abs(z - centre)
    sigma = _MAD_TO_SIGMA * np.median(deviation)
    # relative floor: float rounding of a noise-free background is not a feature
    floor = 1e-9 * max(float(np.max(deviation)), np.finfo(float).tiny)
    mask = deviation > max(MASK_SIGMAS * sigma, floor)
    if grow and mask.any():
        mask = ndimage.binary_dilation(mask, iterations=int(grow))
    return mask


def level(height, method: str = "plane", mask="auto") -> tuple[np.ndarray, np.ndarray]:
    """(levelled heights, mask used). `method`: plane, median or poly2, or several joined by
    "+" and applied in that order (e.g. "median+plane+median": line offsets, tilt, what is left);
    `mask`: "auto" (`feature_mask`, refined until it settles; each step finds its own), None
    (fit every pixel) or a boolean array of the height's shape (True = feature, left out of
    every fit). The mask returned is the last step's."""
    steps = parse_method(method)
    z, _ = _checked(height, None)
    used = np.zeros(z.shape, dtype=bool)
    for step in steps:
        z, used = _level_one(z, step, mask)
    return z, used


def parse_method(method) -> list[str]:
    """The steps of a method name ("plane", "median+plane", ...); ValueError naming it."""
    steps = method.split("+") if isinstance(method, str) else []
    if not steps or any(step not in METHODS for step in steps):
        raise ValueError(
            f"method={method!r}: expected one of {', '.join(METHODS)}, or several joined by "
            "'+' (e.g. median+plane+median)"
        )
    return steps


def _level_one(z: np.ndarray, method: str, mask) -> tuple[np.ndarray, np.ndarray]:
    function = {
        "plane": level_plane,
        "median": level_median_rows,
        "poly2": lambda z, m: level_poly_rows(z, 2, m),
    }[method]
    if mask is None:
        return function(z, None), np.zeros(z.shape, dtype=bool)
    if not (isinstance(mask, str) and mask == "auto"):
        _, background = _checked(z, mask)
        return function(z, ~background), ~background
    current = np.zeros(z.shape, dtype=bool)
    levelled = function(z, None)
    for _ in range(_AUTO_PASSES):
        new = feature_mask(levelled, rows=method != "plane")
        if new.all():  # nothing is background: leave the fit unmasked
            break
        if np.array_equal(new, current):
            break
        current = new
        levelled = function(z, current)
    return levelled, current


def _checked(height, mask) -> tuple[np.ndarray, np.ndarray]:
    z = np.asarray(height, dtype=float)
    if z.ndim != 2 or min(z.shape) < 1:
        raise ValueError(f"height: expected a non-empty 2-D array, got shape {z.shape}")
    if not np.all(np.isfinite(z)):
        raise ValueError(f"height: {np.count_nonzero(~np.isfinite(z))} NaN or infinite pixel(s)")
    if mask is None:
        return z, np.ones(z.shape, dtype=bool)
    m = np.asarray(mask)
    if m.shape != z.shape or m.dtype != bool:
        raise ValueError(
            f"mask: expected a boolean array of shape {z.shape}, got {m.dtype} {m.shape}"
        )
    return z, ~m
