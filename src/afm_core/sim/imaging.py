"""Imaging: the tip's apex height over the sample is the grey dilation of the surface by
the tip (book eq. 4.26/4.28; afm_core.physics.tip_morphology), sampled where the tip truly is
when each pixel is taken."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from afm_core.physics.tip_morphology import dilate


class DilatedField:
    """The dilated surface on a regular grid over a region, interpolated anywhere in it.

    Dilating once per scan and then sampling at each pixel's true (hysteresis- and
    drift-displaced) position is exact up to the grid spacing, because the surface does not
    change during a scan."""

    def __init__(
        self,
        height_function,
        tip_grid: np.ndarray,
        x0: float,
        y0: float,
        nx: int,
        ny: int,
        pixel: float,
    ):
        half = tip_grid.shape[0] // 2
        xs = x0 + (np.arange(-half, nx + half)) * pixel
        ys = y0 + (np.arange(-half, ny + half)) * pixel
        surface = height_function(*np.meshgrid(xs, ys))
        self.values = dilate(surface, tip_grid)[half : half + ny, half : half + nx]
        self.x0, self.y0, self.pixel = x0, y0, pixel

    def at(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        coords = np.stack(
            [(np.asarray(ys) - self.y0) / self.pixel, (np.asarray(xs) - self.x0) / self.pixel]
        )
        return ndimage.map_coordinates(
            self.values, coords.reshape(2, -1), order=1, mode="nearest"
        ).reshape(np.shape(xs))


def dilated_heights_at(
    sample,
    tip_grid: np.ndarray,
    pixel: float,
    xs: np.ndarray,
    ys: np.ndarray,
    chunk_elements: int = 2_000_000,
) -> np.ndarray:
    """i(q) = max_u s(q+u) + t(u) at scattered points q (local scan lines), from the definition.

    The surface is the objects on a base (roughness and pits): i = max(base dilated,
    objects dilated). Only tip offsets that can win are tried, which leaves the maximum
    exactly as over all of them: the tip's apex (t = 0) over q already gives the base's height
    there, so on the base only offsets with t(u) >= -base_span can win, and on an object only
    those with top + t(u) above the least base dilation of the points near it, and only at
    points within those offsets' reach of the object (the suite's scan lines: 180 points, a
    particle near 78 of them, 1849 tip offsets; trying them all made a session's re-simulation
    1.8 s, 1.1 s without). Points go in chunks of at most chunk_elements (point, tip offset)
    pairs, so the temporaries stay tens of MB."""
    half = tip_grid.shape[0] // 2
    offsets = np.arange(-half, half + 1) * pixel
    ox, oy = np.meshgrid(offsets, offsets)
    ox, oy, t = ox.ravel(), oy.ravel(), tip_grid.ravel()
    xs, ys = np.ravel(xs), np.ravel(ys)
    out = np.full(xs.shape, -np.inf)
    if not xs.size:
        return out
    near_apex = t >= -sample.base_span()
    _chunked_max(
        out,
        np.arange(xs.size),
        xs,
        ys,
        ox[near_apex],
        oy[near_apex],
        t[near_apex],
        sample.base_height,
        chunk_elements,
    )
    reach = half * pixel
    for obj in sample.objects_near(
        xs.min() - reach, xs.max() + reach, ys.min() - reach, ys.max() + reach
    ):
        x_lo, x_hi, y_lo, y_hi = obj.bounds()
        near = np.flatnonzero(
            (xs >= x_lo - reach)
            & (xs <= x_hi + reach)
            & (ys >= y_lo - reach)
            & (ys <= y_hi + reach)
        )
        if not near.size:
            continue
        can_win = obj.top() + t >= out[near].min()
        if not can_win.any():
            continue
        # the offsets that can win reach less far than the whole grid
        u_reach = max(float(np.abs(ox[can_win]).max()), float(np.abs(oy[can_win]).max()))
        q_x, q_y = xs[near], ys[near]
        near = near[
            (q_x >= x_lo - u_reach)
            & (q_x <= x_hi + u_reach)
            & (q_y >= y_lo - u_reach)
            & (q_y <= y_hi + u_reach)
        ]
        _chunked_max(
            out,
            near,
            xs,
            ys,
            ox[can_win],
            oy[can_win],
            t[can_win],
            lambda x, y, obj=obj: obj.height(x, y),
            chunk_elements,
        )
    return out


def _chunked_max(
    out: np.ndarray, points: np.ndarray, xs, ys, ux, uy, ut, height, chunk_elements: int
) -> None:
    """out[p] = max(out[p], max_u height(q_p + u) + t(u)) for the points p (indices)."""
    chunk = max(1, chunk_elements // max(ux.size, 1))
    for start in range(0, points.size, chunk):
        p = points[start : start + chunk]
        out[p] = np.maximum(
            out[p], np.max(height(xs[p, None] + ux, ys[p, None] + uy) + ut, axis=1)
        )


def pink_noise(n: int, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """n samples of 1/f (flicker) noise with standard deviation sigma, by shaping white noise
    in the frequency domain (power ~ 1/f, the DC term removed). The draws are taken even when
    sigma is 0, so the generator's later draws do not depend on sigma (re-simulations with a
    changed noise level share every other random number)."""
    if n == 0:
        return np.zeros(n)
    white = rng.normal(size=n)
    if sigma == 0:
        return np.zeros(n)
    spectrum = np.fft.rfft(white)
    f = np.fft.rfftfreq(n)
    f[0] = np.inf
    shaped = np.fft.irfft(spectrum / np.sqrt(f), n)
    return shaped / (shaped.std() or 1.0) * sigma
