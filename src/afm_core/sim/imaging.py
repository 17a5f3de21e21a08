"""Imaging: the tip's apex height over the sample is the grey dilation of the surface by
the tip (book eq. 4.26/4.28; afm_core.physics.tip_morphology), sampled where the tip truly is
when each pixel is taken."""

from __future__ import annotations

from collections import OrderedDict

import numpy as np
from scipy import ndimage

from afm_core.physics.sample import Sphere
from afm_core.physics.tip_morphology import dilate

# most grid lines per band across the slow axis: a band is dilated with a halo of the tip's
# half width on its two long sides, so the work grows by (1 + 2 half / band); 512 keeps that
# under 1.25 for tips up to 121 pixels wide, and a 4096-pixel scan's first band takes ~1 s
BAND = 512
CACHE_BYTES = 64 * 2**20  # bands kept: 3 of the widest field (4096 pixels + margin)
# tip offsets per side of a tile bounded at once (_sphere_max): 8 x 8 keeps a tile's bound
# close to its values near the apex, and the bounds' table small (27 x 27 tiles for 209)
TIP_TILE = 8


class DilatedField:
    """The dilated surface on a regular grid over a region, interpolated anywhere in it.

    Dilating once per scan and then sampling at each pixel's true (hysteresis- and
    drift-displaced) position is exact up to the grid spacing, because the surface does not
    change during a scan. The grid is dilated in bands along the fast axis (`along_x`: rows,
    for a 0 deg scan; else columns), at most BAND lines each, equal in size, each with a halo
    of the tip's half width so that it equals that part of the whole field's dilation to the
    bit, when a sample first needs them; at most CACHE_BYTES of them are kept (least recently
    used go first). A scan starts at once and can be stopped within its first lines, and its
    memory does not grow with the field (a 4096 x 4096 scan dilated whole took minutes before
    its first line and about 2 GiB)."""

    def __init__(
        self,
        height_function,
        tip_grid: np.ndarray,
        x0: float,
        y0: float,
        nx: int,
        ny: int,
        pixel: float,
        along_x: bool = True,
    ):
        self.height_function, self.tip_grid = height_function, tip_grid
        self.half = tip_grid.shape[0] // 2
        self.x0, self.y0, self.pixel = x0, y0, pixel
        self.nx, self.ny, self.along_x = nx, ny, along_x
        across = ny if along_x else nx
        self.band = -(-across // -(-across // BAND))  # equal bands of at most BAND lines
        self.bands: OrderedDict[int, np.ndarray] = OrderedDict()
        band_bytes = self.band * (nx if along_x else ny) * 8
        self.max_bands = max(2, CACHE_BYTES // band_bytes)

    @property
    def values(self) -> np.ndarray:
        """The whole dilated grid (ny, nx): for tests and small fields only."""
        return self._block(0, self.ny - 1, 0, self.nx - 1)

    def _band(self, k: int) -> np.ndarray:
        if k in self.bands:
            self.bands.move_to_end(k)
            return self.bands[k]
        half, lo = self.half, k * self.band
        if self.along_x:
            rows, cols = (lo, min(lo + self.band, self.ny)), (0, self.nx)
        else:
            rows, cols = (0, self.ny), (lo, min(lo + self.band, self.nx))
        # the same float coordinates as one grid over the whole field: x0 + i * pixel
        xs = self.x0 + np.arange(cols[0] - half, cols[1] + half) * self.pixel
        ys = self.y0 + np.arange(rows[0] - half, rows[1] + half) * self.pixel
        surface = self.height_function(*np.meshgrid(xs, ys))
        band = dilate(surface, self.tip_grid)[half : -half or None, half : -half or None]
        self.bands[k] = band
        while len(self.bands) > self.max_bands:
            self.bands.popitem(last=False)
        return band

    def _block(self, r_lo: int, r_hi: int, c_lo: int, c_hi: int) -> np.ndarray:
        """Rows r_lo..r_hi and columns c_lo..c_hi (inclusive) of the dilated grid."""
        lo, hi = (r_lo, r_hi) if self.along_x else (c_lo, c_hi)
        parts = []
        for k in range(lo // self.band, hi // self.band + 1):
            band, start = self._band(k), k * self.band
            a, b = max(lo, start) - start, min(hi, start + self.band - 1) - start
            if self.along_x:
                parts.append(band[a : b + 1, c_lo : c_hi + 1])
            else:
                parts.append(band[r_lo : r_hi + 1, a : b + 1])
        return (
            parts[0] if len(parts) == 1 else np.concatenate(parts, axis=0 if self.along_x else 1)
        )

    def at(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        shape = np.shape(xs)
        r = (np.ravel(ys) - self.y0) / self.pixel
        c = (np.ravel(xs) - self.x0) / self.pixel
        if not r.size:
            return np.empty(shape)
        # the block's edges are the grid's wherever a point lies beyond them, so mode="nearest"
        # extends the block as it would the whole grid
        r_lo, r_hi = (
            int(np.clip(v, 0, self.ny - 1)) for v in (np.floor(r.min()), np.ceil(r.max()))
        )
        c_lo, c_hi = (
            int(np.clip(v, 0, self.nx - 1)) for v in (np.floor(c.min()), np.ceil(c.max()))
        )
        block = self._block(r_lo, r_hi, c_lo, c_hi)
        # an integer shift of a coordinate below 2**52 is exact: the same weights as on the
        # whole grid
        coords = np.stack([r - r_lo, c - c_lo])
        return ndimage.map_coordinates(block, coords, order=1, mode="nearest").reshape(shape)


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
    _base_max(out, xs, ys, ox[near_apex], oy[near_apex], t[near_apex], sample, chunk_elements)
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
        if isinstance(obj, Sphere):
            _sphere_max(out, near, xs, ys, _tiles(offsets, t, can_win), obj, chunk_elements)
            continue
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


def _base_max(out: np.ndarray, xs, ys, ux, uy, ut, sample, chunk_elements: int) -> None:
    """out = max_u base(q + u) + t(u) over the offsets given, trying at each point only those
    that can beat the apex's own value there: base(q + u) <= sample.base_top(), so an offset
    with t(u) + top <= base(q) cannot win (the apex's t is 0). The values tried are the very
    ones _chunked_max computes, so the maximum is the same to the bit; off the pits, where the
    base spans the roughness alone, this leaves a fifth of the offsets within the base's span
    (base_span counts the deepest pit too)."""
    out[:] = np.maximum(out, sample.base_height(xs, ys))
    rank = np.argsort(-ut, kind="stable")  # highest t first: each point tries a prefix
    ux, uy, ut = ux[rank], uy[rank], ut[rank]
    count = np.searchsorted(-(ut + sample.base_top()), -out, side="left")
    first = np.cumsum(count) - count
    points = np.repeat(np.arange(xs.size), count)
    offset = np.arange(points.size) - np.repeat(first, count)
    for lo in range(0, points.size, max(1, chunk_elements)):
        p, u = points[lo : lo + chunk_elements], offset[lo : lo + chunk_elements]
        np.maximum.at(out, p, sample.base_height(xs[p] + ux[u], ys[p] + uy[u]) + ut[u])


def _tiles(offsets: np.ndarray, t: np.ndarray, can_win: np.ndarray) -> tuple:
    """The tip's offsets that can win, in square tiles of TIP_TILE x TIP_TILE grid offsets:
    per tile its offsets (ux, uy, t; t = -inf where an offset cannot win or pads the tile) and
    their extent and highest t, the tile's bounds."""
    n, side = offsets.size, TIP_TILE
    m = -(-n // side)
    index = np.full((m * side, m * side), -1)
    index[:n, :n] = np.arange(n * n).reshape(n, n)  # row: y offset, column: x offset
    index = index.reshape(m, side, m, side).transpose(0, 2, 1, 3).reshape(m * m, side * side)
    valid = index >= 0
    valid[valid] = can_win[index[valid]]
    keep = valid.any(axis=1)
    index, valid = np.where(valid, index, 0)[keep], valid[keep]
    ux, uy = offsets[index % n], offsets[index // n]  # the meshgrid's own values
    ut = np.where(valid, t[index], -np.inf)
    extent = (
        np.where(valid, ux, np.inf).min(axis=1),
        np.where(valid, ux, -np.inf).max(axis=1),
        np.where(valid, uy, np.inf).min(axis=1),
        np.where(valid, uy, -np.inf).max(axis=1),
    )
    return ux, uy, ut, extent, ut.max(axis=1)


def _sphere_max(
    out: np.ndarray, points: np.ndarray, xs, ys, tiles: tuple, sphere, chunk_elements: int
) -> None:
    """What _chunked_max does for a sphere, trying only the tiles of tip offsets that can win:
    a tile's bound (the sphere's highest point over the rectangle its offsets reach, plus its
    highest t; Sphere.height_bound) caps every value in it, so a tile whose bound is below the
    point's height found so far (the base's, then its best-bound tile's) cannot raise it. The
    values tried are the very ones _chunked_max computes, so the maximum is the same to the
    bit; a particle of the closed-loop sessions (100 nm under a 1 nm-pixel tip, 209 x 209
    offsets) leaves a few percent of the tiles to try."""
    ux, uy, ut, (ux_lo, ux_hi, uy_lo, uy_hi), t_max = tiles
    per_tile = ut.shape[1]
    rows = max(1, chunk_elements // (8 * t_max.size))  # the bounds' temporaries stay small
    for start in range(0, points.size, rows):
        p = points[start : start + rows]
        qx, qy = xs[p, None], ys[p, None]
        bound = sphere.height_bound(qx + ux_lo, qx + ux_hi, qy + uy_lo, qy + uy_hi) + t_max
        first = np.argmax(bound, axis=1)
        _tile_max(out, p, first, xs, ys, ux, uy, ut, sphere)
        bound[np.arange(p.size), first] = -np.inf
        pairs, tile = np.nonzero(bound > out[p, None])
        chunk = max(1, chunk_elements // per_tile)
        for lo in range(0, pairs.size, chunk):
            sl = slice(lo, lo + chunk)
            _tile_max(out, p[pairs[sl]], tile[sl], xs, ys, ux, uy, ut, sphere)


def _tile_max(out, p: np.ndarray, tile: np.ndarray, xs, ys, ux, uy, ut, sphere) -> None:
    """out[p_i] = max(out[p_i], max over tile_i's offsets of height(q + u) + t(u))."""
    values = np.max(
        sphere.height(xs[p, None] + ux[tile], ys[p, None] + uy[tile]) + ut[tile], axis=1
    )
    np.maximum.at(out, p, values)


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
    # in place, each temporary dropped when done: a 4096 x 4096 scan's 16.8 M samples peaked at
    # 830 MiB with the one-line form's temporaries, 510 MiB so (the same values, bit for bit)
    spectrum = np.fft.rfft(white)
    del white
    f = np.fft.rfftfreq(n)
    f[0] = np.inf
    np.sqrt(f, out=f)
    spectrum /= f
    del f
    shaped = np.fft.irfft(spectrum, n)
    del spectrum
    shaped /= shaped.std() or 1.0
    shaped *= sigma
    return shaped
