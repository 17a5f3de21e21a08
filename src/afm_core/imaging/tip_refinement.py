"""Blind tip refinement at one denoising threshold (Villarrubia 1997; book 4.2), the engine of
afm_core.imaging.tip_estimation. Tip and image conventions: afm_core.physics.tip_morphology
(t(u) <= 0, apex 0 at the centre; i = max_u s(x + u) + t(u)).

Blind estimation (Villarrubia 1997; book eqs. 4.32-4.38) in this convention. With the apex
over x' the tip touches the surface at some x'+c: s(x'+c) = i(x') - t(c) (the tip's surface
at x+u is i(x) - t(u) high). With the apex over any x the tip stays above that point,
i(x) >= s(x'+c) + t(x'+c-x); with w = x'+c-x this is, for all w,

    t(w) <= i(x' + c - w) - i(x') + t(c)

(the image is a union of translates of the tip's reflection lying under it, eq. 4.31). The
contact c is unknown, so the bound is the largest over the contacts still possible with the
current estimate, those that keep the apex under the image (eq. 4.33, the bound at w = 0):
i(x') - i(x' + c) <= t(c). Starting from the flat upper bound T_0 = 0 the update

    T_{k+1}(w) = min( T_k(w),  N_TH + min_x' max_{c: i(x') - i(x'+c) <= T_k(c)}
                                         [ i(x' + c - w) - i(x') + T_k(c) ] )

is iterated (in place, point by point, as Villarrubia does) until nothing changes. N_TH is
the denoising threshold: a point refines the tip only where its bound is lower than the
current one by more than N_TH, and then only down to bound + N_TH (Villarrubia's `thresh`,
Fig. 4.14). N_TH = 0 is the exact noiseless algorithm (the limit is an upper bound of the
true tip); a huge N_TH never refines and leaves the blunt flat start.

Gwyddion (libprocess/tip.c, morph_lib.c) runs the same refinement in integer heights (step =
image range / 10000) with the same threshold semantics; both use the points near the image
edges as its use_edges (its default) does, which sharpens the estimate by ~3 % (points up to
one tip half-width from the edge refine the tip pixels whose admissible contacts all lie in
the image; the tip stays an upper bound). Its tip fields are apex-up (t + const, apex = max);
its dilation and erosion rotate the field by 180 deg into Villarrubia's P before use, but its
blind estimate returns P itself (shifted to min 0), i.e. our t rotated by 180 deg (as read
from the source: check against the asymmetric characterizer tip).

Speed-ups (book 4.2); (a) and (c) do not change the limit:
  (a) feature points: prominent local maxima that Douglas-Peucker simplification of the scan
      lines keeps as peaks in both directions ("type 1" points) refine the tip first, until
      they no longer change it; only then are all image points used;
  (b) tip radius: if the tip pre-estimated on the feature points has its troughs (lowest
      points along the four half-axes, book Fig. 4.9) inside the requested window, the full
      passes work only on the window they enclose and the rest keeps its pre-estimate (the
      book's choice of tip size; on the characterizer the troughs are at the edge: no effect);
  (c) per-pass and per-point early stops: a point x' can refine the tip only if
      dilate(min(erode(I, T) + N_TH, I), T)(x') < I(x') (a sound form of Villarrubia's
      opening test that stays exact with N_TH > 0; its erosion is kept while the tip does
      not change, and its erosion and dilation run over the whole image only for the tip's
      highest pixels, TipRefiner.candidates); within a point, the tip pixels w that
      the apex contact or the contact c = w (when admissible) already bound by T(w) - N_TH
      are dropped, and the remaining contacts are processed in chunks, dropping the pixels
      whose running bound reaches T - N_TH and stopping as soon as none is left (Fig. 4.12).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy import ndimage

_REL_EPS = 1e-9  # relative (to the image's height range) tolerance for "no change"


def _threads() -> int:
    """Threads for the whole-image morphology of the candidate test: OMP_NUM_THREADS if set
    (the benchmarks set 1 to compare single-threaded with Gwyddion), else the machine's CPUs.
    numpy's ufuncs release the GIL, so row bands run in parallel."""
    try:
        return max(1, int(os.environ.get("OMP_NUM_THREADS", "")))
    except ValueError:
        return os.cpu_count() or 1


# Below this many pixel-times-tip-pixel operations the bands' overhead outweighs the gain.
_PARALLEL_WORK = 20_000_000


def _in_bands(valid_op, a: np.ndarray, tip: np.ndarray) -> np.ndarray:
    """valid_op(a, tip) computed on row bands of its output in parallel (each band reads the
    rows of `a` its tip footprints cover: the result is identical)."""
    k = tip.shape[0]
    rows = a.shape[0] - (k - 1)
    threads = min(_threads(), max(rows // (2 * k), 1))
    if threads < 2 or rows * (a.shape[1] - k + 1) * k * k < _PARALLEL_WORK:
        return valid_op(a, tip)
    edges = np.linspace(0, rows, threads + 1).astype(int)
    with ThreadPoolExecutor(threads) as pool:
        parts = pool.map(
            lambda r: valid_op(a[r[0] : r[1] + k - 1], tip), zip(edges[:-1], edges[1:])
        )
        return np.concatenate(list(parts))


# Output rows per block of the whole-image morphology: a block's running result and temporary
# stay in the cache while all tip pixels pass over it (about 20 % faster than whole arrays).
_BLOCK_ROWS = 128
# The candidate test's erosion and dilation: whole-image stages of this share of the tip's
# pixels (highest first) until at most _GATHER_SHARE of the points can still change; those get
# the other pixels by gathering (dilation on the characteriser: 20 % of the pixels leave 0-3 %
# of the points), as one index matrix up to _GATHER_TERMS terms, else pixel by pixel. On the
# 512x512 bench images with a 41x41 tip the erosion took as long at a share of 2 % as at 5 %
# on the spheres and 20 % longer on the characteriser; at 10 % twice as long on the spheres.
_STAGE_SHARE = 0.05
_GATHER_SHARE = 0.05
_GATHER_TERMS = 1 << 21
# refine_point's first block of contacts x pixels: most candidate points are ruled out within
# it (every pixel's running bound reaches T - N_TH), so a smaller first block saves work; the
# blocks then double (the result does not depend on the blocking).
_FIRST_TERMS = 16384


def _erode_pixels(a: np.ndarray, tip: np.ndarray, pixels: np.ndarray | None = None) -> np.ndarray:
    """min_u a(y-u) - t(u) for the y whose whole tip footprint lies inside `a` (no padding),
    over all tip pixels u or only the flat indices `pixels` of the tip."""
    k = tip.shape[0]
    h = k // 2
    ny, nx = a.shape[0] - 2 * h, a.shape[1] - 2 * h
    out = np.full((ny, nx), np.inf, dtype=a.dtype)
    tmp = np.empty((min(ny, _BLOCK_ROWS), nx), dtype=a.dtype)
    pixels = np.arange(k * k) if pixels is None else pixels
    for r0 in range(0, ny, _BLOCK_ROWS):
        r1 = min(r0 + _BLOCK_ROWS, ny)
        o, t = out[r0:r1], tmp[: r1 - r0]
        for p in pixels:
            i, j = divmod(int(p), k)
            np.subtract(
                a[2 * h - i + r0 : 2 * h - i + r1, 2 * h - j : 2 * h - j + nx], tip[i, j], out=t
            )
            np.minimum(o, t, out=o)
    return out


def _in_stages(tip: np.ndarray, run, extreme, still_open):
    """The staged whole-image morphology of the candidate test: the tip's pixels, highest
    first (they bound most), `run(pixels)` over the whole image _STAGE_SHARE of them at a
    time, the parts combined by `extreme` (np.minimum or np.maximum), until all have run or
    at most _GATHER_SHARE of the points are `still_open(result, pixels not yet run)` (a
    boolean mask). Returns (result, the pixels not yet run, that mask)."""
    k = tip.shape[0]
    pixels = np.argsort(-tip.ravel(), kind="stable")
    stage = max(1, int(np.ceil(_STAGE_SHARE * k * k)))
    out = None
    done = 0
    while True:
        part = run(pixels[done : done + stage])
        done = min(done + stage, pixels.size)
        out = part if out is None else extreme(out, part, out=out)
        open_ = still_open(out, pixels[done:])
        if done >= pixels.size or open_.sum() <= _GATHER_SHARE * open_.size:
            return out, pixels[done:], open_


def _erode_valid(a: np.ndarray, tip: np.ndarray) -> np.ndarray:
    """_erode_pixels over all tip pixels, bit for bit, with less work (_in_stages): the
    points that the remaining pixels could still lower gather them. A pixel u can lower the
    running minimum m(y) only if m(y) > min(a) - t(u): an estimate's low outer pixels
    (bounded only by the image's height range) matter at the highest points alone (on a
    512x512 spheres image with a 41x41 tip, 20 % of the pixels left 0.3 % of the points)."""
    k = tip.shape[0]
    h = k // 2
    floor = float(np.min(a, where=np.isfinite(a), initial=np.inf))
    if not np.isfinite(floor):
        return _erode_pixels(a, tip)
    flat_tip = tip.ravel()

    def still_open(out, rest):
        if not rest.size:
            return np.zeros(out.shape, bool)
        # the float32 terms of the remaining pixels are >= floor - t_next (rounding is
        # monotone); the margin covers the float64 subtraction's own rounding
        t_next = float(flat_tip[rest[0]])
        limit = (floor - t_next) - 4 * np.finfo(float).eps * (abs(floor) + abs(t_next))
        return out > np.float64(limit)  # compared in float64, not rounded to float32

    out, rest, open_ = _in_stages(tip, lambda p: _erode_pixels(a, tip, p), np.minimum, still_open)
    py, px = np.nonzero(open_)
    if py.size:
        shifts = -((rest // k) * a.shape[1] + rest % k)
        base = (py + 2 * h) * a.shape[1] + (px + 2 * h)
        # a - t is a + (-t) bit for bit (IEEE subtraction is the addition of the negation)
        out[py, px] = _gather(np.minimum, a.ravel(), base, shifts, -flat_tip[rest], out[py, px])
    return out


def _gather(extreme, flat: np.ndarray, base: np.ndarray, shifts, values, best: np.ndarray):
    """best combined by `extreme` (np.minimum or np.maximum) with flat[base + s] + v over the
    pairs (s, v) of shifts and values: the whole-image stages' float32 terms at a few points.
    Small problems as one index matrix; large ones one pixel at a time (no index matrix)."""
    if base.size * len(shifts) <= _GATHER_TERMS:
        terms = flat[base[:, None] + shifts[None, :]] + values[None, :]
        return extreme(best, extreme.reduce(terms, axis=1), out=best)
    term = np.empty_like(best)
    for shift, value in zip(shifts, values):
        np.add(flat[base + shift], value, out=term)
        extreme(best, term, out=best)
    return best


def _dilate_valid(a: np.ndarray, tip: np.ndarray, pixels: np.ndarray | None = None) -> np.ndarray:
    """max_u a(x+u) + t(u) for the x whose whole tip footprint lies inside `a` (no padding),
    over all tip pixels u or only the flat indices `pixels` of the tip."""
    k = tip.shape[0]
    ny, nx = a.shape[0] - (k - 1), a.shape[1] - (k - 1)
    out = np.full((ny, nx), -np.inf, dtype=a.dtype)
    tmp = np.empty((min(ny, _BLOCK_ROWS), nx), dtype=a.dtype)
    pixels = np.arange(k * k) if pixels is None else pixels
    for r0 in range(0, ny, _BLOCK_ROWS):
        r1 = min(r0 + _BLOCK_ROWS, ny)
        o, t = out[r0:r1], tmp[: r1 - r0]
        for p in pixels:
            i, j = divmod(int(p), k)
            np.add(a[i + r0 : i + r1, j : j + nx], tip[i, j], out=t)
            np.maximum(o, t, out=o)
    return out


# --------------------------------------------------------------------------------------------
# The per-point update


class TipRefiner:
    """Holds the image, the flat offsets of the tip domain and the current tip bound.

    The image is padded by a tip half-width with +inf, which is Gwyddion's use_edges: points
    within two half-widths of the edge refine the tip pixels whose every admissible contact
    lies in the image. A contact whose apex would fall outside counts as admissible (+inf is
    above any apex), and a bound through a pixel outside is +inf (no update), so the bound
    stays an upper bound of the tip."""

    def __init__(self, image: np.ndarray, tip_size: int):
        if tip_size < 1 or tip_size % 2 == 0:
            raise ValueError(f"tip_size={tip_size}: must be odd and >= 1")
        self.image = np.ascontiguousarray(image, dtype=float)
        self.k = tip_size
        self.h = tip_size // 2
        if min(self.image.shape) < 4 * self.h + 1:
            raise ValueError(f"image {self.image.shape} too small for a {tip_size}x{tip_size} tip")
        padded = np.pad(self.image, self.h, constant_values=np.inf)
        self.ny, self.nx = padded.shape
        self.flat = padded.ravel()
        span = float(self.image.max() - self.image.min())
        self.eps = _REL_EPS * max(span, np.finfo(float).tiny)
        a, b = np.mgrid[-self.h : self.h + 1, -self.h : self.h + 1]
        self.off = (a * self.nx + b).ravel()  # flat image offset of each tip pixel
        self.centre = (self.k * self.k) // 2
        self.image32 = (padded - float(self.image.mean())).astype(np.float32)
        self.test_eps = 1e-6 * max(span, np.finfo(float).tiny)
        self._eroded = None  # (float32 tip bytes, its erosion) of the last candidate test
        self._windows: dict = {}  # refiners of centred sub-windows (refine_tip's speed-up b)

    def window(self, size: int) -> TipRefiner:
        """The refiner of the same image with a centred size x size tip window, kept so that
        its cached erosion serves the next threshold too."""
        if size not in self._windows:
            self._windows[size] = TipRefiner(self.image, size)
        return self._windows[size]

    def interior(self) -> np.ndarray:
        """Image points (image coordinates) a whole tip half-width from the edge: the apex there
        has every tip pixel over the image."""
        m = np.zeros(self.image.shape, bool)
        m[self.h : self.image.shape[0] - self.h, self.h : self.image.shape[1] - self.h] = True
        return m

    def flat_index(self, rows, cols) -> np.ndarray:
        """Flat (padded) indices of image points (row, col)."""
        return (np.asarray(rows) + self.h) * self.nx + (np.asarray(cols) + self.h)

    def refine_point(
        self, g: int, tf: np.ndarray, th: float, order: np.ndarray, early: bool = True
    ) -> bool:
        """Refine the flat tip bound `tf` in place at image point g (flat index). True if
        changed."""
        flat, off, eps = self.flat, self.off, self.eps
        i0 = flat[g]
        m = flat[g - off] - i0  # contact c = 0 (the apex): i(x'-w) - i(x')
        low = np.flatnonzero(m + th < tf - eps)  # tip pixels this point may still lower
        if low.size == 0:
            return False
        if early:
            # contact c = w, when allowed, bounds t(w) by T(w) itself: no update there
            low = low[flat[g + off[low]] - i0 + tf[low] < -eps]
            if low.size == 0:
                return False
        ml = m[low]
        tc = tf[order]
        valid = flat[g + off[order]] - i0 + tc >= -eps  # eq. 4.33: the apex stays under the image
        vc = order[valid]
        if vc.size:
            tv = tc[valid] - i0
            offc = g + off[vc]
            n = vc.size
            # small problems in one go (numpy call overhead dominates), big ones in chunks
            chunk = (
                n
                if (not early or n * low.size <= _FIRST_TERMS)
                else max(16, _FIRST_TERMS // low.size)
            )
            start = 0
            while start < n:
                stop = min(start + chunk, n)
                vals = flat[offc[start:stop, None] - off[low][None, :]] + tv[start:stop, None]
                ml = np.maximum(ml, vals.max(axis=0))
                if early:
                    keep = ml + th < tf[low] - eps
                    if not keep.all():
                        low, ml = low[keep], ml[keep]
                        if low.size == 0:
                            return False  # the point cannot update the bound (Fig. 4.12)
                    chunk = min(chunk * 2, max(512, 65536 // max(low.size, 1)))
                start = stop
        new = ml + th
        lower = new < tf[low] - eps
        if not lower.any():
            return False
        tf[low[lower]] = new[lower]
        return True

    def contact_order(self, tf: np.ndarray) -> np.ndarray:
        """Contacts other than the apex, highest tip points first (they bound most)."""
        order = np.argsort(-tf, kind="stable")
        return order[order != self.centre]

    def candidates(self, tip: np.ndarray, th: float, mask: np.ndarray) -> np.ndarray:
        """Flat indices of the interior points of `mask` that may refine `tip`, largest excess
        first (Villarrubia's opening test in a form that stays exact for th > 0).

        x' cannot refine if some contact c keeps the apex under the image and has
        r(x'+c) + T(c) + th >= i(x') with r = erode(I, T): then every bound through c is
        >= T - th. One erosion and one dilation give max_c [min(r(x'+c) + th, i(x'+c)) + T(c)].
        Computed in float32 on the valid region only; a point counts as unable to refine when
        its excess is below a tolerance (1e-6 of the image's height range) far above the
        float32 rounding, i.e. refinements smaller than that are not looked for.

        The same numbers, computed with less work (`_reach`): the erosion is kept for the
        next call with the same tip (a threshold sweep's next rung starts from this one's
        converged tip), and the dilation runs over the whole image only for the tip's highest
        pixels; the points still above the tolerance then get the exact maximum over the
        rest. Every term is the same float32 sum, and max/min are exact, so the selection and
        its order are identical to the whole-image computation."""
        h = self.h
        ny0, nx0 = self.image.shape
        img = self.image32
        t32 = tip.astype(np.float32)
        key = t32.tobytes()
        if self._eroded is None or self._eroded[0] != key:
            # every image point, from its pixels in the image
            self._eroded = (key, _in_bands(_erode_valid, img, t32))
        r = self._eroded[1]
        q = np.minimum(r + np.float32(th), img[h : h + ny0, h : h + nx0] + np.float32(self.eps))
        # x' in [h, n-h) of the image
        py, px, excess = self._reach(
            q, t32, img[2 * h : ny0, 2 * h : nx0], mask[h : ny0 - h, h : nx0 - h]
        )
        order = np.argsort(-excess, kind="stable")
        return (py[order] + 2 * h) * self.nx + (px[order] + 2 * h)

    def _reach(self, q: np.ndarray, t32: np.ndarray, top: np.ndarray, mask: np.ndarray):
        """(rows, columns, excess) of the points of `mask` whose excess top - reach exceeds
        the tolerance, reach = max_c q(x+c) + T(c) (row-major order, as np.nonzero).
        Stages of the tip's highest pixels (_STAGE_SHARE of them each) run over the whole
        image while more than _GATHER_SHARE of the points are still above the tolerance (a
        partial maximum is a lower bound of reach: a point below the tolerance stays below);
        the remaining pixels are then gathered at those points only."""
        k = self.k
        reach, rest, sel = _in_stages(
            t32,
            lambda p: _in_bands(lambda a, t: _dilate_valid(a, t, p), q, t32),
            np.maximum,
            lambda reach, _: (top - reach > self.test_eps) & mask,
        )
        py, px = np.nonzero(sel)
        best = reach[py, px]
        if rest.size and py.size:
            shifts = (rest // k) * q.shape[1] + rest % k
            best = _gather(
                np.maximum, q.ravel(), py * q.shape[1] + px, shifts, t32.ravel()[rest], best
            )
        excess = top[py, px] - best
        keep = excess > self.test_eps
        return py[keep], px[keep], excess[keep]

    def run_points(self, points: np.ndarray, tf: np.ndarray, th: float, max_passes: int) -> int:
        """Refine at a fixed list of points until a pass changes nothing. Returns passes."""
        passes = 0
        while passes < max_passes:
            passes += 1
            order = self.contact_order(tf)
            changed = 0
            for g in points:
                changed += self.refine_point(int(g), tf, th, order)
            if not changed:
                break
        return passes

    def run_full(
        self, tip: np.ndarray, th: float, max_passes: int, mask: np.ndarray
    ) -> tuple[int, bool]:
        """Full passes over all (masked) image points, with the candidate test, until a pass
        changes nothing. Returns (passes, converged)."""
        tf = tip.ravel()
        passes = 0
        while passes < max_passes:
            passes += 1
            points = self.candidates(tip, th, mask)
            order = self.contact_order(tf)
            changed = 0
            for g in points:
                changed += self.refine_point(int(g), tf, th, order)
            if not changed:
                return passes, True
        return passes, False


# --------------------------------------------------------------------------------------------
# Feature points (speed-up a) and the tip radius pre-estimate (speed-up b)


def douglas_peucker(values: np.ndarray, tolerance: float) -> np.ndarray:
    """Indices kept by Douglas-Peucker simplification of a sampled curve (vertical distance
    to the chord, so that heights and positions need no common scale)."""
    n = len(values)
    if n <= 2:
        return np.arange(n)
    keep = np.zeros(n, bool)
    keep[0] = keep[-1] = True
    stack = [(0, n - 1)]
    while stack:
        a, b = stack.pop()
        if b - a < 2:
            continue
        xs = np.arange(a + 1, b)
        chord = values[a] + (values[b] - values[a]) * (xs - a) / (b - a)
        dev = np.abs(values[a + 1 : b] - chord)
        j = int(np.argmax(dev))
        if dev[j] > tolerance:
            m = a + 1 + j
            keep[m] = True
            stack.append((a, m))
            stack.append((m, b))
    return np.flatnonzero(keep)


def _dp_peak(line: np.ndarray, centre: int, tolerance: float) -> bool:
    """Whether the sample `centre` of `line` is a vertex of the Douglas-Peucker polyline that
    is higher than both neighbouring vertices (a peak of the simplified scan line)."""
    kept = douglas_peucker(line, tolerance)
    pos = np.searchsorted(kept, centre)
    if pos >= len(kept) or kept[pos] != centre or pos == 0 or pos == len(kept) - 1:
        return False
    return line[centre] > line[kept[pos - 1]] and line[centre] > line[kept[pos + 1]]


def feature_points(
    image: np.ndarray, tip_size: int, noise: float | None = None, mask: np.ndarray | None = None
) -> np.ndarray:
    """(row, col) of "type 1" feature points: local maxima enclosed by closed contours.

    Candidates are local maxima of their (tip_size/5)-neighbourhood whose height above the
    lowest point of the tip window around them exceeds a few contour steps (a few noise
    sigmas) -- closed contours surround them; each is kept if Douglas-Peucker simplification
    of its row and of its column (tolerance: the contour step) keeps it as a peak."""
    image = np.asarray(image, float)
    if noise is None:
        noise = estimate_noise(image)
    span = float(image.max() - image.min())
    step = max(3.0 * noise, 1e-3 * span, np.finfo(float).tiny)
    h = tip_size // 2
    delta = max(tip_size // 10, 1)
    local_max = image >= ndimage.maximum_filter(image, size=2 * delta + 1, mode="nearest")
    floor = ndimage.minimum_filter(image, size=tip_size, mode="nearest")
    cand = local_max & (image - floor > 3.0 * step)
    if mask is not None:
        cand &= mask
    out = []
    for y, x in zip(*np.nonzero(cand)):
        lo_x, hi_x = max(0, x - 2 * h), min(image.shape[1], x + 2 * h + 1)
        lo_y, hi_y = max(0, y - 2 * h), min(image.shape[0], y + 2 * h + 1)
        if _dp_peak(image[y, lo_x:hi_x], x - lo_x, step) and _dp_peak(
            image[lo_y:hi_y, x], y - lo_y, step
        ):
            out.append((y, x))
    pts = np.array(out, dtype=int).reshape(-1, 2)
    # strongest features first: they constrain the tip most
    return (
        pts[np.argsort(-(image - floor)[pts[:, 0], pts[:, 1]], kind="stable")] if len(pts) else pts
    )


def estimate_noise(image: np.ndarray) -> float:
    """Robust white-noise sigma: MAD of the second differences along rows (smooth tip-shaped
    slopes cancel; sharp features are outliers), for N(0, s^2) noise var(d2) = 6 s^2."""
    d2 = (
        np.asarray(image, float)[:, 2:]
        - 2 * np.asarray(image, float)[:, 1:-1]
        + np.asarray(image, float)[:, :-2]
    )
    d2 = d2.ravel()
    mad = np.median(np.abs(d2 - np.median(d2)))
    return float(1.4826 * mad / np.sqrt(6.0))


# --------------------------------------------------------------------------------------------
# Estimation at one threshold


def refine_tip(
    est: TipRefiner,
    th: float,
    max_passes: int,
    start: np.ndarray | None,
    features: np.ndarray | None,
    window: int,
) -> tuple[np.ndarray, int, bool]:
    """One blind estimate at threshold th from `start` (None: the flat upper bound 0; else
    any upper bound of the result, e.g. the estimate at a higher threshold). The feature
    points refine first (speed-up a); the full passes then work on the centred
    `window` x `window` part of the tip (speed-up b; the rest keeps its pre-estimate).
    Returns (tip, passes, converged)."""
    k, h = est.k, est.h
    tip = np.zeros((k, k)) if start is None else np.array(start, float)
    tf = tip.ravel()
    passes = 0
    interior = est.interior()
    if features is not None and len(features):
        inside = interior[features[:, 0], features[:, 1]]
        pts = est.flat_index(features[inside, 0], features[inside, 1])
        passes += est.run_points(pts, tf, th, 1000)
    if window < k:
        sub = est.window(window)
        lo = h - window // 2
        inner = np.ascontiguousarray(tip[lo : lo + window, lo : lo + window])
        p, converged = sub.run_full(inner, th, max_passes, interior)
        tip[lo : lo + window, lo : lo + window] = inner
    else:
        p, converged = est.run_full(tip, th, max_passes, interior)
    tip[h, h] = 0.0
    return tip, passes + p, converged


def work_window(est: TipRefiner, features: np.ndarray | None, th: float) -> int:
    """Speed-up (b): the tip window the full passes need, from the troughs of the tip
    pre-estimated on the feature points (the whole window unless the troughs lie inside)."""
    if features is None or not len(features):
        return est.k
    pre = np.zeros((est.k, est.k))
    interior = est.interior()
    inside = interior[features[:, 0], features[:, 1]]
    est.run_points(est.flat_index(features[inside, 0], features[inside, 1]), pre.ravel(), th, 50)
    h = est.h
    arms = [pre[h, h::-1], pre[h, h:], pre[h::-1, h], pre[h:, h]]  # Vxl, Vxr, Vyf, Vyb
    r = max(int(np.argmin(arm)) for arm in arms) + 1  # all four troughs inside, with a margin
    return 2 * r + 1 if r < h else est.k
