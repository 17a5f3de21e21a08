"""Blind tip estimation and image reconstruction (book ch. 4, SPEC 2; Villarrubia 1994/1997).

Conventions (the project's; afm_core.physics.tip_morphology): a tip is a square odd-sized grid
t(u) <= 0 with its apex at the centre pixel, t(0) = 0, u = (row, column) offset from the apex.
Imaging is grey dilation i(x) = max_u [ s(x + u) + t(u) ] (`dilate`), reconstruction its
adjoint erosion r(y) = min_u [ i(y - u) - t(u) ] (`erode`), the tightest surface under the
tip everywhere, so that erode(dilate(s, t), t) >= s, with equality wherever the tip touches s.
(Villarrubia's and Gwyddion's P is the reflected tip: P(d) = t(-d), i = s (+) P.)

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

Automatic threshold (book 4.3.2). `estimate_tip(..., threshold="book")` applies the book's
rule: sweep N_TH upwards, the critical threshold is the first whose tip top has several
apexes, the choice the local maximum of the change rate of the area between successive
estimates nearest to it. On the simulated characterizer (blunt 10 nm apex, 1.6 nm pixels,
0.3 nm noise) this fails: the top splits where the background noise stops collapsing the
estimate into a needle (~2.2 nm, 7 sigma), and the area rate peaks right there (error 6-9 nm),
while the error minimum lies about twice higher (~4.4 nm, error ~1.1 nm), where the flank
cuts made by feature tops that noise displaced by a pixel (their only admissible contact is
then the apex) are balanced by the blunting. The default "auto" keeps the book's sweep
(warm-started downwards: exact, since the limit is the same from any upper bound) and
records its data, but chooses the threshold whose estimate is closest, over its top `depth`,
to the feature-consensus tip: the median over the feature points of their apex-contact
bounds, which a minority of displaced tops does not pull down. This lands within ~4 % of the
best fixed threshold's error on the characterizer (seeds 0-7, noise 0.1-1 nm).

Gwyddion (libprocess/tip.c, morph_lib.c) runs the same refinement in integer heights (step =
image range / 10000) with the same threshold semantics; both use the points near the image
edges as its use_edges (its default) does, which sharpens the estimate by ~3 % (points up to
one tip half-width from the edge refine the tip pixels whose admissible contacts all lie in
the image; the tip stays an upper bound). Its tip fields are apex-up (t + const, apex = max); its dilation and erosion
rotate the field by 180 deg into Villarrubia's P before use, but its blind estimate returns
P itself (shifted to min 0), i.e. our t rotated by 180 deg (as read from the source: check
against the asymmetric characterizer tip).

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
      opening test that stays exact with N_TH > 0); within a point, the tip pixels w that
      the apex contact or the contact c = w (when admissible) already bound by T(w) - N_TH
      are dropped, and the remaining contacts are processed in chunks, dropping the pixels
      whose running bound reaches T - N_TH and stopping as soon as none is left (Fig. 4.12).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from afm_core.physics.tip_morphology import erode

_REL_EPS = 1e-9  # relative (to the image's height range) tolerance for "no change"


@dataclass
class TipEstimate:
    tip: np.ndarray  # (n, n) heights, m, apex 0 at centre, <= 0 elsewhere
    threshold: float  # m, the denoising threshold used
    iterations: int  # passes over the image (feature passes + full passes)
    seconds: float
    sweep: list = field(
        default_factory=list
    )  # [(threshold, rms_change, apex_count, area_change)] for auto
    critical_threshold: float | None = (
        None  # auto/book: lowest swept threshold whose top has several apexes
    )
    noise: float | None = None  # auto: the image noise estimate used to size the sweep
    feature_points: int = 0
    window: int = 0  # tip window the full passes worked on (speed-up b)
    scores: dict = field(
        default_factory=dict
    )  # auto: threshold -> RMS difference from the consensus tip


def _erode_valid(a: np.ndarray, tip: np.ndarray) -> np.ndarray:
    """min_u a(y-u) - t(u) for the y whose whole tip footprint lies inside `a` (no padding)."""
    k = tip.shape[0]
    h = k // 2
    ny, nx = a.shape[0] - 2 * h, a.shape[1] - 2 * h
    out = np.full((ny, nx), np.inf, dtype=a.dtype)
    tmp = np.empty_like(out)
    for i in range(k):
        for j in range(k):
            np.subtract(
                a[2 * h - i : 2 * h - i + ny, 2 * h - j : 2 * h - j + nx], tip[i, j], out=tmp
            )
            np.minimum(out, tmp, out=out)
    return out


def _dilate_valid(a: np.ndarray, tip: np.ndarray) -> np.ndarray:
    """max_u a(x+u) + t(u) for the x whose whole tip footprint lies inside `a` (no padding)."""
    k = tip.shape[0]
    ny, nx = a.shape[0] - (k - 1), a.shape[1] - (k - 1)
    out = np.full((ny, nx), -np.inf, dtype=a.dtype)
    tmp = np.empty_like(out)
    for i in range(k):
        for j in range(k):
            np.add(a[i : i + ny, j : j + nx], tip[i, j], out=tmp)
            np.maximum(out, tmp, out=out)
    return out


# --------------------------------------------------------------------------------------------
# The per-point update


class _Estimator:
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
        """Refine the flat tip bound `tf` in place at image point g (flat index). True if changed."""
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
            chunk = n if (not early or n * low.size <= 65536) else max(16, 65536 // low.size)
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
        float32 rounding, i.e. refinements smaller than that are not looked for."""
        h, nx = self.h, self.nx
        ny0, nx0 = self.image.shape
        img = self.image32
        t32 = tip.astype(np.float32)
        r = _erode_valid(img, t32)  # every image point, from its pixels in the image
        q = np.minimum(r + np.float32(th), img[h : h + ny0, h : h + nx0] + np.float32(self.eps))
        reach = _dilate_valid(q, t32)  # x' in [h, n-h) of the image
        excess = img[2 * h : ny0, 2 * h : nx0] - reach
        sel = (excess > self.test_eps) & mask[h : ny0 - h, h : nx0 - h]
        py, px = np.nonzero(sel)
        order = np.argsort(-excess[py, px], kind="stable")
        return (py[order] + 2 * h) * nx + (px[order] + 2 * h)

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


def _estimate_fixed(
    est: _Estimator,
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
        sub = _Estimator(est.image, window)
        lo = h - window // 2
        inner = np.ascontiguousarray(tip[lo : lo + window, lo : lo + window])
        p, converged = sub.run_full(inner, th, max_passes, interior)
        tip[lo : lo + window, lo : lo + window] = inner
    else:
        p, converged = est.run_full(tip, th, max_passes, interior)
    tip[h, h] = 0.0
    return tip, passes + p, converged


def _work_window(est: _Estimator, features: np.ndarray | None, th: float) -> int:
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


# --------------------------------------------------------------------------------------------
# The automatic threshold


def feature_consensus_tip(image: np.ndarray, features: np.ndarray, tip_size: int) -> np.ndarray:
    """The median over the feature points x_j of their apex-contact bounds
    i(x_j - w) - i(x_j): the tip that a typical sharp feature images. Unlike the blind
    estimate's minimum it is not an upper bound, but it is not pulled down by the few
    features whose top is noise-displaced (the blind estimate's main error), so it serves
    as the reference that the automatic threshold matches."""
    image = np.asarray(image, float)
    h = tip_size // 2
    ny, nx = image.shape
    pts = [
        (y, x)
        for y, x in np.asarray(features).reshape(-1, 2)
        if h <= y < ny - h and h <= x < nx - h
    ]
    if not pts:
        return np.zeros((tip_size, tip_size))
    bounds = np.stack(
        [image[y - h : y + h + 1, x - h : x + h + 1][::-1, ::-1] - image[y, x] for y, x in pts]
    )
    return np.median(bounds, axis=0)


def apex_count(tip: np.ndarray, band: float) -> int:
    """Number of highest points on the tip top (book 4.3.2): the local maxima (8-neighbour,
    non-strict) within `band` of the apex height; a flat top of m pixels counts m."""
    top = tip >= tip.max() - band
    peaks = tip >= ndimage.maximum_filter(tip, size=3, mode="constant", cval=-np.inf)
    return int((top & peaks).sum())


def _book_choice(
    ths: np.ndarray, counts: np.ndarray, rates: np.ndarray
) -> tuple[float | None, float | None]:
    """Book 4.3.2 literally: the critical threshold is the first (sweeping upwards) whose
    tip top has several apexes; the choice is the local maximum of the area change rate
    nearest to it (rate k: between thresholds k-1 and k). (None, None) if no split."""
    multi = np.flatnonzero(counts > 1)
    if multi.size == 0:
        return None, None
    ic = int(multi[0])
    peaks = [
        j
        for j in range(1, len(ths))
        if rates[j] >= rates[j - 1] and (j + 1 >= len(ths) or rates[j] >= rates[j + 1])
    ]
    if not peaks:
        return float(ths[ic]), float(ths[ic])
    j = min(peaks, key=lambda j: (abs(j - ic), -rates[j]))
    return float(ths[j]), float(ths[ic])


def _sweep_table(tips: dict, pixel_size: float, band: float) -> list:
    """[(threshold, rms_change, apex_count, area_change)] in increasing threshold; the changes
    are from the next lower computed threshold (rms in m; area_change: volume between the
    successive tips per unit threshold, m^3/m)."""
    out = []
    prev = prev_th = None
    for th in sorted(tips):
        tip = tips[th]
        if prev is None:
            rms = area = 0.0
        else:
            diff = tip - prev
            rms = float(np.sqrt(np.mean(diff**2)))
            area = float(np.abs(diff).sum() * pixel_size**2 / (th - prev_th))
        out.append((float(th), rms, apex_count(tip, band), area))
        prev, prev_th = tip, th
    return out


def estimate_tip(
    image: np.ndarray,
    tip_size: int,
    threshold: float | str = "auto",
    pixel_size: float = 1.0,
    max_iterations: int = 50,
    *,
    depth: float = 20e-9,
    noise: float | None = None,
    thresholds=None,
    use_features: bool = True,
    limit_radius: bool = True,
    start: np.ndarray | None = None,
) -> TipEstimate:
    """Blind tip estimate (tip_size x tip_size, odd) from `image` (heights, m; pixel_size only
    scales the reported area changes).

    threshold: the denoising threshold N_TH (m); "auto" (the default) or "book" to choose it.
    Both sweep N_TH and record, per threshold, the change from the previous estimate, the
    number of apexes on the tip's top and the area change rate (book 4.3.2), warm-starting
    each estimate from the one at the next higher threshold (the limit does not depend on
    the start as long as it is an upper bound of it, so this is exact and fast).

    "book": the book's rule on a uniform sweep 0, s, 2s, ... (s = sigma/2, sigma the image
    noise estimate, or the given `thresholds`): the critical threshold is where the top goes
    from one apex to several, the choice the local maximum of the area change rate nearest to
    it.
    "auto": the threshold whose estimate best matches (RMS over its top `depth`, m) the
    feature-consensus tip (`feature_consensus_tip`): a coarse descent from 20 sigma (doubled while the minimum is at the top) in
    2 sigma steps with one pass per threshold (each starting from the estimate above it),
    then converged estimates at the coarse minimum and at +-sigma, +-sigma/2 around the best;
    the choice is the best converged one. The sweep lists every threshold tried (the coarse
    ones after one pass). See the module notes for why this and not the book's rule.

    start (fixed threshold only): an upper bound of the result to start from instead of the
    flat 0, e.g. the estimate at a higher threshold; the result is the same, only faster."""
    t_start = time.perf_counter()
    image = np.asarray(image, float)
    est = _Estimator(image, tip_size)
    if not isinstance(threshold, str):
        th = float(threshold)
        if th < 0:
            raise ValueError(f"threshold={th}: must be >= 0")
        if start is not None:
            start = np.minimum(np.asarray(start, float), 0.0)
            if start.shape != (est.k, est.k):
                raise ValueError(f"start: shape {start.shape}, expected {(est.k, est.k)}")
        features = (
            feature_points(image, tip_size, noise) if use_features and start is None else None
        )
        window = _work_window(est, features, th) if limit_radius else est.k
        tip, passes, _ = _estimate_fixed(est, th, max_iterations, start, features, window)
        return TipEstimate(
            tip,
            th,
            passes,
            time.perf_counter() - t_start,
            [],
            feature_points=0 if features is None else len(features),
            window=window,
        )
    if threshold not in ("auto", "book"):
        raise ValueError(f"threshold={threshold!r}: a number (m), 'auto' or 'book'")
    sigma = estimate_noise(image) if noise is None else float(noise)
    features = feature_points(image, tip_size, sigma) if use_features else None
    if (
        sigma <= 1e-6 * max(float(image.max() - image.min()), np.finfo(float).tiny)
        and thresholds is None
    ):
        # noiseless: the exact algorithm (N_TH = 0) is the answer
        window = _work_window(est, features, 0.0) if limit_radius else est.k
        tip, passes, _ = _estimate_fixed(est, 0.0, max_iterations, None, features, window)
        return TipEstimate(
            tip,
            0.0,
            passes,
            time.perf_counter() - t_start,
            _sweep_table({0.0: tip}, pixel_size, est.eps),
            noise=sigma,
            feature_points=0 if features is None else len(features),
            window=window,
        )
    band = 0.05 * sigma if sigma > 0 else est.eps
    tips: dict = {}
    converged: dict = {}
    passes = [0]
    window = _work_window(est, features, 0.0) if limit_radius else est.k

    def run(th: float, cap: int = max_iterations) -> np.ndarray:
        """The estimate at th: converged (cap = max_iterations) or after `cap` passes, warm
        started from itself or from the estimate at the next higher threshold."""
        th = float(th)
        if th in tips and (converged[th] or cap < max_iterations):
            return tips[th]
        above = [t for t in tips if t > th]
        start = tips[th] if th in tips else (tips[min(above)] if above else None)
        tip, p, done = _estimate_fixed(
            est, th, cap, start, features if start is None else None, window
        )
        tips[th], converged[th] = tip, done or cap >= max_iterations
        passes[0] += p
        return tip

    if threshold == "book":
        ths = (
            np.sort(np.asarray(thresholds, float))
            if thresholds is not None
            else np.arange(0, 41) * (sigma / 2)
        )
        for th in ths[::-1]:
            run(th)
        sweep = _sweep_table(tips, pixel_size, band)
        chosen, critical = _book_choice(
            np.array([s[0] for s in sweep]),
            np.array([s[2] for s in sweep]),
            np.array([s[3] for s in sweep]),
        )
        if chosen is None:
            chosen = float(ths[int(np.argmax([s[3] for s in sweep]))])
        return TipEstimate(
            tips[chosen],
            chosen,
            passes[0],
            time.perf_counter() - t_start,
            sweep,
            critical_threshold=critical,
            noise=sigma,
            feature_points=0 if features is None else len(features),
            window=window,
        )

    reference = feature_consensus_tip(
        image,
        features if features is not None else feature_points(image, tip_size, sigma),
        tip_size,
    )
    region = reference >= -depth
    scores: dict = {}

    def score(th: float, cap: int = max_iterations) -> float:
        th = float(th)
        tip = run(th, cap)
        scores[th] = float(np.sqrt(np.mean((tip - reference)[region] ** 2)))
        return scores[th]

    if thresholds is not None:
        for th in np.sort(np.asarray(thresholds, float))[::-1]:
            score(th)
    else:
        # coarse: one pass per threshold (each from the estimate above it, an upper bound),
        # downwards from 20 sigma in 2 sigma steps, until well past the minimum
        span = float(image.max() - image.min())
        coarse, top = 2.0 * sigma, 20.0 * sigma
        while True:
            best = None
            for j in range(int(round(top / coarse)), 0, -1):
                th = j * coarse
                q = score(th, cap=1)
                if best is None or q < scores[best]:
                    best = th
                if th < best - 1.5 * coarse and q > 1.2 * scores[best]:
                    break
            if best < top - 0.5 * coarse or top > span:
                break
            top *= 2.0  # the minimum is at the top: look higher
        # fine: converged estimates at the coarse minimum, then +-sigma and +-sigma/2 around
        # the best converged one (one pass is not enough to rank close thresholds at high noise)
        score(best)
        for step in (sigma, 0.5 * sigma):
            best = min((t for t in scores if converged[t]), key=lambda t: (scores[t], -t))
            for th in (best + step, best - step):
                if th > 0:
                    score(th)
        best = min((t for t in scores if converged[t]), key=lambda t: (scores[t], -t))
    chosen = min(scores, key=lambda t: (scores[t], -t)) if thresholds is not None else best
    sweep = _sweep_table(tips, pixel_size, band)
    counts = [s[2] for s in sweep]
    critical = next((s[0] for s in sweep if s[2] > 1), None) if counts and counts[0] <= 1 else None
    return TipEstimate(
        tips[chosen],
        chosen,
        passes[0],
        time.perf_counter() - t_start,
        sweep,
        critical_threshold=critical,
        noise=sigma,
        feature_points=0 if features is None else len(features),
        window=window,
        scores=dict(sorted(scores.items())),
    )


def estimate_tip_plain(
    image: np.ndarray, tip_size: int, threshold: float = 0.0, max_iterations: int = 50
) -> TipEstimate:
    """Villarrubia's original algorithm, without the speed-ups: every interior point, every
    contact allowed by eq. 4.33 and every tip pixel, pass after pass until no change. The
    reference the fast estimate must agree with (slow: use small images)."""
    t_start = time.perf_counter()
    est = _Estimator(np.asarray(image, float), tip_size)
    tip = np.zeros((est.k, est.k))
    tf = tip.ravel()
    flat, off, eps, th = est.flat, est.off, est.eps, float(threshold)
    points = est.flat_index(*np.nonzero(est.interior()))
    passes = 0
    while passes < max_iterations:
        passes += 1
        changed = 0
        for g in points:
            i0 = flat[g]
            valid = np.flatnonzero(flat[g + off] - i0 + tf >= -eps)
            bound = (
                flat[(g + off[valid])[:, None] - off[None, :]] + (tf[valid] - i0)[:, None]
            ).max(axis=0)
            lower = bound + th < tf - eps
            if lower.any():
                tf[lower] = bound[lower] + th
                changed += 1
        if not changed:
            break
    return TipEstimate(tip, th, passes, time.perf_counter() - t_start, [], window=est.k)


# --------------------------------------------------------------------------------------------
# Certainty map and error


def certainty_map(
    image: np.ndarray, tip: np.ndarray, tolerance: float | None = None
) -> np.ndarray:
    """Villarrubia's certainty map: True at the points y of the reconstruction
    r = erode(image, tip) that the tip, with its apex at some image point x, touches there and
    nowhere else (i(x) - t(u) = r(x+u) for the single u = y - x; with t <= 0 the tip's
    surface at x+u is i(x) - t(u) above the apex). The tip at x touches the
    true surface somewhere, and r >= s, so a single touch of r is that touch: r(y) = s(y).
    Only apexes x at least two tip half-widths from the edge are used, so that every r the
    tip can touch is computed from the image alone (touches beyond the edge are unseen)."""
    image = np.asarray(image, float)
    tip = np.asarray(tip, float)
    ny, nx = image.shape
    k = tip.shape[0]
    h = k // 2
    out = np.zeros(image.shape, bool)
    if ny <= 4 * h or nx <= 4 * h:
        return out
    r = erode(image, tip)
    if tolerance is None:
        tolerance = 1e-9 * max(float(image.max() - image.min()), np.finfo(float).tiny)
    ix = image[2 * h : ny - 2 * h, 2 * h : nx - 2 * h]
    my, mx = ix.shape
    count = np.zeros(ix.shape, np.int32)
    where = np.zeros(ix.shape, np.int32)
    for a in range(k):
        for b in range(k):
            rs = r[h + a : h + a + my, h + b : h + b + mx]  # r(x + u), u = (a - h, b - h)
            touch = np.abs(ix - tip[a, b] - rs) <= tolerance  # tip surface at x+u: i(x) - t(u)
            count += touch
            where[touch] = a * k + b
    single = count == 1
    cy, cx = np.nonzero(single)
    u = where[single]
    out[cy + h + u // k, cx + h + u % k] = True
    return out


def tip_error(estimate, true_tip: np.ndarray, depth: float) -> float:
    """RMS difference (m) between an estimated and the true tip over the top `depth` of the
    true tip (where true_tip >= -depth), both centred on their apex (height 0), compared on
    their common window."""
    est = np.asarray(estimate.tip if isinstance(estimate, TipEstimate) else estimate, float)
    true = np.asarray(true_tip, float)
    k = min(est.shape[0], true.shape[0])
    ce, ct = est.shape[0] // 2, true.shape[0] // 2
    e = est[ce - k // 2 : ce + k // 2 + 1, ce - k // 2 : ce + k // 2 + 1] - est[ce, ce]
    t = true[ct - k // 2 : ct + k // 2 + 1, ct - k // 2 : ct + k // 2 + 1] - true[ct, ct]
    sel = t >= -depth
    return float(np.sqrt(np.mean((e[sel] - t[sel]) ** 2)))
