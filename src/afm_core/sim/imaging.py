"""Imaging: the tip's apex height over the sample is the grey dilation of the surface by
the tip (book eq. 4.26/4.28), sampled where the tip truly is when each pixel is taken."""
from __future__ import annotations

import numpy as np
from scipy import ndimage


def dilate(surface: np.ndarray, tip: np.ndarray) -> np.ndarray:
    """Image height where the tip apex sits over each pixel: i(x) = max_u s(x+u) + t(u).

    `tip` holds t(u) <= 0 with the apex at the centre. scipy's grey_dilation computes
    max_u s(x-u) + b(u), so the tip is passed reflected.
    """
    return ndimage.grey_dilation(surface, structure=tip[::-1, ::-1], mode="nearest")


class DilatedField:
    """The dilated surface on a regular grid over a region, interpolated anywhere in it.

    Dilating once per scan and then sampling at each pixel's true (hysteresis- and
    drift-displaced) position is exact up to the grid spacing, because the surface does not
    change during a scan."""

    def __init__(self, height_function, tip_grid: np.ndarray, x0: float, y0: float, nx: int, ny: int,
                 pixel: float):
        half = tip_grid.shape[0] // 2
        xs = x0 + (np.arange(-half, nx + half)) * pixel
        ys = y0 + (np.arange(-half, ny + half)) * pixel
        surface = height_function(*np.meshgrid(xs, ys))
        self.values = dilate(surface, tip_grid)[half:half + ny, half:half + nx]
        self.x0, self.y0, self.pixel = x0, y0, pixel

    def at(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        coords = np.stack([(np.asarray(ys) - self.y0) / self.pixel, (np.asarray(xs) - self.x0) / self.pixel])
        return ndimage.map_coordinates(self.values, coords.reshape(2, -1), order=1,
                                       mode="nearest").reshape(np.shape(xs))


def dilated_heights_at(sample, tip_grid: np.ndarray, pixel: float, xs: np.ndarray, ys: np.ndarray,
                       chunk_elements: int = 2_000_000) -> np.ndarray:
    """i(q) = max_u s(q+u) + t(u) at scattered points q (local scan lines), from the definition.

    The surface is the objects on a base (roughness and pits): i = max(base dilated,
    objects dilated). The base varies by at most base_span, so only tip offsets with
    t(u) >= -base_span can win there; objects are tested only where they are near. Points go
    in chunks of at most chunk_elements (point, tip offset) pairs: a fine tip grid has tens of
    thousands of offsets, and the temporaries must stay tens of MB."""
    half = tip_grid.shape[0] // 2
    offsets = np.arange(-half, half + 1) * pixel
    ox, oy = np.meshgrid(offsets, offsets)
    ox, oy, t = ox.ravel(), oy.ravel(), tip_grid.ravel()
    near_apex = t >= -sample.base_span()
    xs, ys = np.ravel(xs), np.ravel(ys)
    reach = half * pixel
    objects = sample.objects_near(xs.min() - reach, xs.max() + reach, ys.min() - reach, ys.max() + reach) \
        if xs.size else []
    out = np.empty(xs.shape)
    chunk = max(1, chunk_elements // ox.size)
    for start in range(0, xs.size, chunk):
        qx, qy = xs[start:start + chunk, None], ys[start:start + chunk, None]
        base = sample.base_height(qx + ox[near_apex], qy + oy[near_apex]) + t[near_apex]
        out[start:start + chunk] = np.max(base, axis=1)
        if objects:
            tops = sample.object_height(qx + ox, qy + oy, objects) + t
            out[start:start + chunk] = np.maximum(out[start:start + chunk], np.max(tops, axis=1))
    return out


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
