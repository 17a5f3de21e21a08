"""Image reconstruction under thermal drift (book ch. 3) and drift velocity from frame-up /
frame-down pairs (book 5.3.3).

Physics (the simulator's and the book's): during a raster scan the sample drifts against the
scanner by D(t). A sample point s is imaged where the scanner is at X = s + D(t(X)), t(X) being
the moment pixel X is acquired (`pixel_times`). Within one fast line the time hardly changes,
so the fast axis is nearly drift-free, but successive lines are displaced by the drift at their
own times: the image is stretched/compressed along the slow axis and sheared along the fast one.

The 0 deg image (rows in order; the book's reference g) and the 90 deg image of the same area
(columns in order; the deformation image h) see the same sample point s at
    X0 = s + D(t0(X0)),     X90 = s + D(t90(X90)),
so the mapping reference -> deformation, (x, y) -> (x + u, y + v), is, pixel by pixel,
    (u, v) = D(t90) - D(t0)                                   (the book's eq. 3.24, U = u_d - u_r)
Near a feature it is about affine: d(u, v)/dy ~ -D'(t0) * line period / pixel size (the 0 deg
lines), d(u, v)/dx ~ +D'(t90) * line period / pixel size (the 90 deg columns).

Steps, and where they are in the book:

1. Offset vector (eq. 3.13-3.18): about a region centre (x0, y0), dx = x - x0, dy = y - y0,
   u = p0 + p2 dx + p4 dy, v = p1 + p3 dx + p5 dy (first order, 6 parameters, the book's choice),
   or plus (p6 dx^2 + p8 dy^2)/2 + p10 dx dy in u and (p7 dx^2 + p9 dy^2)/2 + p11 dx dy in v
   (second order, 12 parameters, eq. 3.17). `offset_displacement`, `recentre`.
2. Feature regions (3.2.3.1): particles found by thresholding the height above the substrate;
   a region is a particle's bounding box plus a margin. For each, p maximises the zero-mean
   normalised cross-correlation C(p) (eq. 3.19; the means removed so that either image's
   substrate level does not matter) between the reference region and the deformation image
   sampled at (x + u, y + v) by bicubic B-spline interpolation (eq. 3.7-3.11, `BSplineImage`:
   scipy's cubic B-spline coefficients, then the 4x4 evaluation U M Q M^T V^T and its analytic
   derivatives dh/dx, dh/dy). The maximisation is the Newton iteration of eq. 3.20 on
   |g^ - h^(p)|^2 = 2 (1 - C(p)) (g^, h^ the normalised zero-mean regions): gradient eq. 3.21,
   Hessian eq. 3.22 without its second-derivative term (Gauss-Newton), Levenberg-damped so that
   no step lowers C. Start value ("a better initial value of p from the deformation law"): the
   particles are matched between the images and an affine map fitted to their centroids (a
   region the drift carried partly out of the 90 deg image is matched on the part inside). A
   round particle looks the same rotated, so the rotation part of p is held near the start
   value by a weak prior (free, it wanders and leaks into the stretch at second order).
3. Non-feature regions (3.2.3.2, Fig. 3.14, eq. 3.23): particles grouped in horizontal bands
   (a band ends where the next particle does not overlap it vertically; split midway), a
   non-feature region takes the mean p of its band's particles (each p first moved to the band
   centre: p describes the mapping about its own centre). `band_partition`, `band_offset_vectors`.
4. Whole-image reconstruction (3.2.4): per reference line j, its displacement relative to a
   reference line c (eq. 3.25-3.27); the reference pixels are moved by it (eq. 3.28) and
   resampled to the integer grid by B-spline interpolation. Two estimators of the displacement:
   - method="time" (default). The drift D(t) is a cubic B-spline in time (knots every
     KNOT_LINES line periods) fitted to all the feature p's at once. Linearised, the Newton fit
     is a weighted least-squares projection of the true per-pixel field D(t90) - D(t0) onto the
     offset vector, with weights it knows (its Jacobian); so each feature's (p0 .. p5) is a known
     linear function of D sampled at the region's pixel times in both images (t90 taken where
     each pixel really lands in the 90 deg image). Generalised least squares (each fit's
     covariance, a model-error floor, a random-walk prior on the drift velocity from the
     statistics of Fig. 7.9, outlier rejection). This is the book's eq. 3.24-3.27 with the
     unknowns u_d, v_d (the 90 deg displacements) solved for rather than averaged out, and the
     band means of eq. 3.23 replaced by that prior: rows between particles get an interpolated
     drift rather than a band's constant p, and a drift that changes is followed.
   - method="book": eq. 3.23-3.27 literally: (u, v) over the whole reference grid from the
     feature p's (first order, in the feature regions) and the band p's (elsewhere); the line
     displacement relative to line c is minus the change of the line mean of (u, v). It assumes
     a drift constant over both scans, and the line mean of u_d cancels only to first order (the
     90 deg point sits at column i + u, not i): an error of about (v * line period / pixel) x
     displacement, ~1 nm at 0.3 nm/s and 2 s lines, several nm when the drift changes.
   The reference line c is the middle line (in time) of the 0 deg scan and t_ref its time: the
   map's frame rests on an interpolated, not an extrapolated, drift. The corrected map is the
   height field in the scanner frame at t_ref: a sample point s appears at s + D(t_ref). Output
   pixel X takes the reference at X' = X + D(t0(X')) - D(t_ref) (fixed point, 4 iterations).
5. Drift velocity (3.3.2.2): the least-squares slope of the per-line displacements against the
   line times. `velocity_from_up_down` is the second route (eq. 5.32-5.36).

The method attributes every difference between the two images to drift: scanner hysteresis,
creep and cross-coupling must be compensated (or negligible) first. SI units throughout (m, s);
image axes: row = y index, column = x index.
"""

from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage, sparse

from afm_core.instrument import RasterScanData

KNOT_LINES = 8  # time-spline knot spacing, in line periods of the 0 deg scan
DRIFT_SIGMA_VELOCITY = 0.21e-9  # m/s, stationary spread of the drift velocity (book Fig. 7.9, v_y)
DRIFT_CORRELATION_TIME = 1800.0  # s, how long the drift velocity stays about the same
ROTATION_PRIOR = 0.01  # weight of the rotation prior in the Newton fit (see _newton_ncc)
MIN_NCC = 0.9  # a feature match below this is not used
MIN_FEATURE_PIXELS = 9  # smaller blobs above the threshold are noise
_VALUE_FLOOR = 0.15e-9  # m, model-error floor of p0, p1 (1 sigma)
_GRADIENT_FLOOR = 5e-4  # model-error floor of p2..p5 (1 sigma)
_ROTATION_SIGMA = 0.1  # rad: a round particle does not fix the rotation part of p (p3 - p4)


@dataclass
class DriftCorrection:
    corrected: (
        np.ndarray
    )  # height map (m) in the scanner frame at t_ref, same grid as the 0 deg image
    velocity: tuple  # (vx, vy) m/s, slope of the per-line displacements against time
    offsets: (
        np.ndarray
    )  # (rows, 2): drift displacement (dx, dy) in m of each 0 deg row relative to t_ref
    feature_offsets: list  # per feature region: (row0, col0, p vector in SI, ncc)
    seconds: float  # wall-clock time of the computation
    t_ref: float = 0.0  # s, instrument clock: the corrected map is the sample as at this moment
    valid: np.ndarray = field(
        default_factory=lambda: np.zeros((0, 0), bool)
    )  # False where the map extends the data


# -- the offset vector (eq. 3.15 / 3.17) ---------------------------------------------------------
def _basis(dx, dy, order: int):
    dx, dy = np.broadcast_arrays(np.asarray(dx, float), np.asarray(dy, float))
    terms = [np.ones_like(dx), dx, dy]
    if order == 2:
        terms += [0.5 * dx * dx, 0.5 * dy * dy, dx * dy]
    return np.stack(terms, axis=-1)


def offset_displacement(p, dx, dy):
    """(u, v) of the offset vector p (6 parameters: eq. 3.15/3.18; 12: eq. 3.17) at dx, dy from
    the region centre. p = (p0..p5) or (p0..p11) in consistent units (SI: m, 1, 1/m)."""
    p = np.asarray(p, float)
    if p.shape not in ((6,), (12,)):
        raise ValueError(
            f"p: {p.shape[0] if p.ndim == 1 else p.shape} parameters; the offset vector has 6 or 12"
        )
    b = _basis(dx, dy, 1 if len(p) == 6 else 2)
    return b @ p[0::2], b @ p[1::2]


def recentre(p, dx: float, dy: float):
    """The same mapping as p, expressed about a centre moved by (dx, dy)."""
    p = np.asarray(p, float).copy()
    u0, v0 = offset_displacement(p, dx, dy)
    q = p.copy()
    q[0], q[1] = u0, v0
    if len(p) == 12:  # first derivatives change with the centre: du/dx = p2 + p6 dx + p10 dy, ...
        q[2] = p[2] + p[6] * dx + p[10] * dy
        q[3] = p[3] + p[7] * dx + p[11] * dy
        q[4] = p[4] + p[8] * dy + p[10] * dx
        q[5] = p[5] + p[9] * dy + p[11] * dx
    return q


# -- bicubic B-spline sampling (eq. 3.7-3.11) -------------------------------------------------
def _cubic_weights(t):
    """Uniform cubic B-spline weights of the 4 coefficients i-1..i+2 at i + t, and their derivatives."""
    t2, t3 = t * t, t * t * t
    w = np.stack(
        [(1 - t) ** 3 / 6, (3 * t3 - 6 * t2 + 4) / 6, (-3 * t3 + 3 * t2 + 3 * t + 1) / 6, t3 / 6],
        -1,
    )
    dw = np.stack([-0.5 * (1 - t) ** 2, 1.5 * t2 - 2 * t, -1.5 * t2 + t + 0.5, 0.5 * t2], -1)
    return w, dw


class BSplineImage:
    """Bicubic B-spline interpolation of an image: the coefficient grid Q (scipy's exact cubic
    spline prefilter, mirror boundary) and the 4x4 evaluation p(u, v) = U M Q M^T V^T (eq. 3.11),
    with its analytic derivatives. Matches scipy.ndimage.map_coordinates(order=3, mode='mirror')."""

    PAD = 3

    def __init__(self, image: np.ndarray):
        image = np.asarray(image, float)
        coeffs = ndimage.spline_filter(image, order=3, mode="mirror")
        self.coeffs = np.pad(coeffs, self.PAD, mode="reflect")  # scipy 'mirror' == numpy 'reflect'
        self.shape = image.shape

    def __call__(self, rows, cols, derivatives: bool = False):
        rows, cols = np.asarray(rows, float), np.asarray(cols, float)
        ny, nx = self.shape
        r = np.clip(rows, -self.PAD + 1, ny + self.PAD - 3)
        c = np.clip(cols, -self.PAD + 1, nx + self.PAD - 3)
        ir, ic = np.floor(r).astype(int), np.floor(c).astype(int)
        wr, dwr = _cubic_weights(r - ir)
        wc, dwc = _cubic_weights(c - ic)
        offs = np.arange(-1, 3)
        idx_r = (ir[..., None] + offs + self.PAD)[..., :, None]
        idx_c = (ic[..., None] + offs + self.PAD)[..., None, :]
        q = self.coeffs[idx_r, idx_c]  # (..., 4, 4): Q
        qc = np.matmul(q, wc[..., None])[..., 0]  # Q M^T V^T
        value = np.sum(wr * qc, axis=-1)
        if not derivatives:
            return value
        d_row = np.sum(dwr * qc, axis=-1)
        d_col = np.sum(wr * np.matmul(q, dwc[..., None])[..., 0], axis=-1)
        return value, d_row, d_col


# -- acquisition times ------------------------------------------------------------------------
def _extrapolating_interp(x, fp):
    x = np.asarray(x, float)
    n = len(fp)
    i = np.clip(np.floor(x).astype(int), 0, n - 2)
    return fp[i] + (fp[i + 1] - fp[i]) * (x - i)


def pixel_times(scan: RasterScanData, rows, cols):
    """Instrument-clock time (s) at which (fractional) pixel (row, col) was acquired: the line's
    start plus the trace time to the pixel (the trace is the first half of the line period)."""
    ny, nx = np.shape(scan.height)
    rows, cols = np.broadcast_arrays(np.asarray(rows, float), np.asarray(cols, float))
    line, k, n_fast = (rows, cols, nx) if scan.scan_angle_deg == 0.0 else (cols, rows, ny)
    t_line = _extrapolating_interp(line, np.asarray(scan.line_start_times, float))
    return scan.start_time + t_line + (k + 0.5) * 0.5 * scan.line_period / n_fast


# -- input checks -----------------------------------------------------------------------------
def _check_scan(name: str, scan: RasterScanData) -> None:
    h = np.asarray(scan.height)
    if h.ndim != 2 or min(h.shape) < 16:
        raise ValueError(
            f"{name}.height: shape {h.shape}; need a 2-D image of at least 16 x 16 pixels"
        )
    bad = int(np.count_nonzero(~np.isfinite(h)))
    if bad:
        raise ValueError(
            f"{name}.height: {bad} NaN/inf pixels (incomplete scan?); drift compensation needs "
            f"a complete image"
        )
    if scan.scan_angle_deg not in (0.0, 90.0):
        raise ValueError(f"{name}.scan_angle_deg={scan.scan_angle_deg}: must be 0 or 90")
    lines = h.shape[0] if scan.scan_angle_deg == 0.0 else h.shape[1]
    times = np.asarray(scan.line_start_times, float)
    if times.shape != (lines,) or not np.all(np.isfinite(times)):
        raise ValueError(f"{name}.line_start_times: need {lines} finite times (one per line)")
    for attr in ("pixel_size_x", "pixel_size_y", "line_period"):
        value = getattr(scan, attr)
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name}.{attr}={value}: must be > 0")
    for attr in ("origin_x", "origin_y", "start_time"):
        if not math.isfinite(getattr(scan, attr)):
            raise ValueError(f"{name}.{attr}={getattr(scan, attr)}: must be finite")


def _check_same_area(a: RasterScanData, b: RasterScanData, name_b: str) -> None:
    if np.shape(a.height) != np.shape(b.height):
        raise ValueError(
            f"{name_b}.height: shape {np.shape(b.height)} differs from {np.shape(a.height)}; "
            f"both scans must have the same pixels"
        )
    for attr in ("pixel_size_x", "pixel_size_y"):
        if not math.isclose(getattr(a, attr), getattr(b, attr), rel_tol=1e-6):
            raise ValueError(
                f"{name_b}.{attr}={getattr(b, attr):.6e}: differs from {getattr(a, attr):.6e}; "
                f"both scans must cover the same area"
            )
    for attr, pix in (("origin_x", a.pixel_size_x), ("origin_y", a.pixel_size_y)):
        if abs(getattr(a, attr) - getattr(b, attr)) > 1e-3 * pix:
            raise ValueError(
                f"{name_b}.{attr}={getattr(b, attr):.6e}: differs from {getattr(a, attr):.6e}; "
                f"both scans must cover the same area"
            )


# -- features ---------------------------------------------------------------------------------
@dataclass
class _Blob:
    label_slice: tuple
    centroid: np.ndarray  # (row, col), height-weighted over the part above half height
    peak: float
    window: tuple = ()  # (r0, r1, c0, c1), half-open, region with margin


def _background(height: np.ndarray):
    bg = float(np.median(height))
    dev = np.abs(height - bg)
    noise = 1.4826 * float(np.median(dev))
    return bg, noise


def _blobs(height: np.ndarray, threshold: float | None = None) -> tuple[list, float]:
    """Particles: connected regions above the substrate by more than a threshold."""
    bg, noise = _background(height)
    rel = height - bg
    peak = float(np.max(rel))
    if threshold is None:
        threshold = max(10.0 * noise, 0.1 * peak, 1e-9)
    labels, n = ndimage.label(rel > threshold)
    blobs = []
    for index, sl in enumerate(ndimage.find_objects(labels), start=1):
        if sl is None:
            continue
        mask = labels[sl] == index
        if mask.sum() < MIN_FEATURE_PIXELS:
            continue
        part = np.where(mask, rel[sl], 0.0)
        top = float(part.max())
        if top < 2.0 * threshold:
            continue
        w = np.clip(part - 0.5 * top, 0.0, None)
        rr, cc = np.mgrid[sl[0], sl[1]]
        centroid = np.array([(w * rr).sum(), (w * cc).sum()]) / w.sum()
        blobs.append(_Blob(sl, centroid, top))
    return blobs, threshold


def _global_shift(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Integer (row, col) shift of b against a by FFT cross-correlation: b(x + s) ~ a(x)."""
    fa = np.fft.rfft2(a - a.mean())
    fb = np.fft.rfft2(b - b.mean())
    xc = np.fft.irfft2(np.conj(fa) * fb, a.shape)
    ny, nx = a.shape
    limit_r, limit_c = ny // 4, nx // 4
    rr = np.fft.fftfreq(ny, 1.0 / ny)
    cc = np.fft.fftfreq(nx, 1.0 / nx)
    allowed = (np.abs(rr)[:, None] <= limit_r) & (np.abs(cc)[None, :] <= limit_c)
    xc = np.where(allowed, xc, -np.inf)
    i, j = np.unravel_index(int(np.argmax(xc)), xc.shape)
    return np.array([rr[i], cc[j]])


def _match_blobs(src: list, dst: list, shift: np.ndarray):
    """Pairs (i, j) of blobs src[i] ~ dst[j]: translation first, then an affine fit refined twice.
    Returns the pairs and the affine (A, b) with dst ~ A src + b (in (row, col) pixels)."""
    if not src or not dst:
        return [], np.eye(2), shift
    ps = np.array([b.centroid for b in src])
    pd = np.array([b.centroid for b in dst])
    A, b = np.eye(2), shift.astype(float)
    spacing = _min_spacing(ps)
    pairs = []
    for _ in range(3):
        pred = ps @ A.T + b
        d = np.linalg.norm(pred[:, None, :] - pd[None, :, :], axis=2)
        j = np.argmin(d, axis=1)
        i_back = np.argmin(d, axis=0)
        gate = 0.4 * spacing if np.isfinite(spacing) else np.inf
        pairs = [(i, int(j[i])) for i in range(len(ps)) if i_back[j[i]] == i and d[i, j[i]] < gate]
        src_pts = np.array([ps[i] for i, _ in pairs]).reshape(-1, 2)
        if len(pairs) >= 3 and _spans_a_plane(src_pts):
            dst_pts = np.array([pd[k] for _, k in pairs])
            design = np.hstack([src_pts, np.ones((len(pairs), 1))])
            sol, *_ = np.linalg.lstsq(design, dst_pts, rcond=None)
            A, b = sol[:2].T, sol[2]
        elif pairs:
            b = np.mean([pd[k] - ps[i] for i, k in pairs], axis=0)
    return pairs, A, b


def _spans_a_plane(points: np.ndarray) -> bool:
    """Whether points fix an affine map: not (nearly) on one line, where the fit would be free
    in the direction across it."""
    singular = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return bool(singular[0] > 0 and singular[-1] > 0.1 * singular[0])


def _min_spacing(points: np.ndarray) -> float:
    if len(points) < 2:
        return np.inf
    d = np.linalg.norm(points[:, None] - points[None], axis=2)
    d[np.diag_indices(len(points))] = np.inf
    return float(d.min())


def _windows(blobs: list, shape) -> list:
    """Feature regions: each blob's bounding box plus a margin, kept if inside the image."""
    ny, nx = shape
    kept = []
    for blob in blobs:
        sr, sc = blob.label_slice
        size = max(sr.stop - sr.start, sc.stop - sc.start)
        margin = max(4, int(math.ceil(0.3 * size)))
        r0, r1, c0, c1 = sr.start - margin, sr.stop + margin, sc.start - margin, sc.stop + margin
        if r0 < 2 or c0 < 2 or r1 > ny - 2 or c1 > nx - 2:
            continue  # a particle cut by the image edge is no reliable feature
        blob.window = (r0, r1, c0, c1)
        kept.append(blob)
    return kept


# -- Newton iteration on the normalised cross-correlation (eq. 3.19-3.22) --------------------------
@dataclass
class _Fit:
    p: np.ndarray  # pixel units, about the window centre
    cov: np.ndarray  # covariance of p (Gauss-Newton), pixel units
    ncc: float
    converged: bool
    projection: np.ndarray = (
        None  # (P, 2N): p (pixel units) per displacement (du, dv) of each region pixel
    )
    rows_def: np.ndarray = None  # where the region's pixels are in the deformation image
    cols_def: np.ndarray = None
    p_data: np.ndarray = None  # p without the rotation prior's pull: projection @ (du, dv)


def _newton_ncc(
    g: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    centre,
    spline: BSplineImage,
    p_start: np.ndarray,
    order: int,
    max_iter: int = 60,
) -> _Fit:
    r0, c0 = centre
    scale = max(float(np.max(np.abs(rows - r0))), float(np.max(np.abs(cols - c0))), 1.0)
    basis = _basis((cols - c0) / scale, (rows - r0) / scale, order)  # (N, m)
    m = basis.shape[1]
    powers = np.array([0, 1, 1, 2, 2, 2][:m], float)
    gc = g - g.mean()
    g_hat = gc / np.linalg.norm(gc)
    q = np.zeros(2 * m)
    q[: len(p_start)] = p_start * np.repeat(scale ** powers[: len(p_start) // 2], 2)

    def evaluate(q, jacobian: bool):
        u, v = basis @ q[0::2], basis @ q[1::2]
        if not jacobian:
            h = spline(rows + v, cols + u)
        else:
            h, h_row, h_col = spline(rows + v, cols + u, derivatives=True)
        hc = h - h.mean()
        norm = np.linalg.norm(hc)
        if norm == 0:
            return None
        h_hat = hc / norm
        r = g_hat - h_hat
        if not jacobian:
            return r, None
        dh = np.empty((len(h), 2 * m))
        dh[:, 0::2] = h_col[:, None] * basis
        dh[:, 1::2] = h_row[:, None] * basis
        dh -= dh.mean(axis=0)
        a = (dh - np.outer(h_hat, h_hat @ dh)) / norm  # d h^ / dq
        return r, a

    res = evaluate(q, True)
    if res is None:
        return _Fit(np.zeros(2 * m), np.diag(np.full(2 * m, np.inf)), 0.0, False)
    r, a = res
    # Rotation prior: a round particle looks the same rotated, so the rotation part of the
    # mapping (p3 - p4) is all but free; left free it wanders off and, at second order, leaks
    # into the stretch (a rotation by theta fitted as an affine map also scales by theta^2/2).
    # A weak quadratic penalty keeps it at the start value (the affine fit of all particles)
    # unless the feature itself fixes it: its weight is ROTATION_PRIOR times the curvature of
    # a feature that is fully structured in rotation (translation curvature x region radius^2).
    e = np.zeros(2 * m)
    e[3], e[4] = 1.0, -1.0
    ata0 = a.T @ a
    weight = ROTATION_PRIOR * 0.25 * 0.5 * (ata0[0, 0] + ata0[1, 1])
    prior = weight * np.outer(e, e)
    tau0 = float(e @ q)

    def total(r, q):
        return float(r @ r) + weight * (float(e @ q) - tau0) ** 2

    cost = total(r, q)
    lam = 1e-3
    converged = False
    for _ in range(max_iter):
        ata = a.T @ a + prior
        try:
            delta = np.linalg.solve(
                ata + lam * np.diag(np.diag(ata) + 1e-12),
                a.T @ r - weight * e * (float(e @ q) - tau0),
            )
        except np.linalg.LinAlgError:
            break
        if np.max(np.abs(delta)) < 1e-4:  # pixels at the region's edge
            converged = True
            break
        trial = evaluate(q + delta, True)
        if trial is not None and total(trial[0], q + delta) < cost:
            q = q + delta
            r, a = trial
            new_cost = total(r, q)
            gain, cost = cost - new_cost, new_cost
            lam = max(lam / 4, 1e-9)
            if gain < 1e-4 * cost:  # converged to well below the noise
                converged = True
                break
        else:
            lam *= 8
            if lam > 1e8:
                converged = True  # no descent left: at the optimum within rounding
                break
    # Linearised, the fit is a weighted least-squares projection of the true displacement field
    # onto the offset-vector model, q = (a^T a + prior)^-1 (a^T M (du, dv) + prior q_start), with
    # M (du, dv) the change of h^ for a per-pixel displacement. The data part is kept so that p
    # can be predicted from a drift hypothesis (see _fit_drift); p_data excludes the prior part.
    u, v = basis @ q[0::2], basis @ q[1::2]
    h, h_row, h_col = spline(rows + v, cols + u, derivatives=True)
    hc = h - h.mean()
    norm = float(np.linalg.norm(hc))
    h_hat = hc / norm
    ncc = 1.0 - float(r @ r) / 2.0
    unscale = np.repeat(scale**powers, 2)
    try:
        ata_inv = np.linalg.inv(a.T @ a + prior)
    except np.linalg.LinAlgError:
        return _Fit(q / unscale, np.diag(np.full(2 * m, np.inf)), 0.0, False)  # unusable
    dof = max(len(r) - 2 * m, 1)
    cov = ata_inv * float(r @ r) / dof / np.outer(unscale, unscale)
    pa = ata_inv @ a.T / unscale[:, None]  # (P, N): p per unit change of h^
    sens = _normalisation_adjoint(pa, h_hat, norm)
    projection = np.hstack([sens * h_col, sens * h_row])
    p_data = (q - ata_inv @ (weight * e * tau0)) / unscale
    return _Fit(q / unscale, cov, ncc, converged, projection, rows + v, cols + u, p_data)


def _normalisation_adjoint(pa: np.ndarray, h_hat: np.ndarray, norm: float) -> np.ndarray:
    """pa @ M0 where M0 = (I - h^ h^T)(I - 1 1^T / N) / norm (the normalisation's Jacobian)."""
    x = pa - np.outer(pa @ h_hat, h_hat)
    x = x - x.mean(axis=1, keepdims=True)
    return x / norm


def _si_factors(n: int, px: float, py: float) -> np.ndarray:
    s = np.array(
        [
            px,
            py,  # p0 (u), p1 (v): m
            1.0,
            py / px,  # p2 du/dx, p3 dv/dx
            px / py,
            1.0,  # p4 du/dy, p5 dv/dy
            1 / px,
            py / px**2,  # p6 d2u/dx2, p7 d2v/dx2
            px / py**2,
            1 / py,  # p8 d2u/dy2, p9 d2v/dy2
            1 / py,
            1 / px,
        ]
    )  # p10 d2u/dxdy, p11 d2v/dxdy
    return s[:n]


def _to_si(p_px: np.ndarray, px: float, py: float) -> np.ndarray:
    """Pixel-unit offset vector (u, v in columns/rows, derivatives per pixel) to SI."""
    return p_px * _si_factors(len(p_px), px, py)


# -- bands (eq. 3.23, Fig. 3.14) ---------------------------------------------------------------
def band_partition(row_extents) -> tuple[list, list]:
    """Fig. 3.14: group features into horizontal bands. Features whose row extents (top, bottom)
    overlap, directly or through others, share a band. Between two bands the dividing line is
    midway between the centres of the two nearest particles across the gap. Returns (bands:
    lists of feature indices, top to bottom; splits: the dividing rows)."""
    ext = [(float(a), float(b)) for a, b in row_extents]
    order = sorted(range(len(ext)), key=lambda i: ext[i][0])
    bands, bottoms = [], []
    for i in order:
        if bands and ext[i][0] <= bottoms[-1]:
            bands[-1].append(i)
            bottoms[-1] = max(bottoms[-1], ext[i][1])
        else:
            bands.append([i])
            bottoms.append(ext[i][1])
    centre = [0.5 * (a + b) for a, b in ext]
    splits = [
        0.5 * (max(centre[i] for i in a) + min(centre[i] for i in b))
        for a, b in zip(bands[:-1], bands[1:])
    ]
    return bands, splits


def band_offset_vectors(centres, ps, bands) -> list:
    """eq. 3.23: per band, (band centre (row, col), the mean of its features' offset vectors after
    moving each to the band centre). centres in (row, col) pixels, ps in pixel units."""
    out = []
    for band in bands:
        centre = np.mean([centres[i] for i in band], axis=0)
        moved = [
            recentre(ps[i], centre[1] - centres[i][1], centre[0] - centres[i][0]) for i in band
        ]
        out.append((centre, np.mean(moved, axis=0)))
    return out


# -- the drift as a function of time ----------------------------------------------------------
class _TimeSpline:
    """Cubic B-spline in time with uniform knots: D(t) = sum_k c_k B_k(t)."""

    def __init__(self, t_start: float, t_end: float, spacing: float):
        self.t0 = t_start - spacing
        self.h = spacing
        self.n = int(math.ceil((t_end + spacing - self.t0) / spacing)) + 3

    def _weights(self, t, derivative: bool):
        x = (np.asarray(t, float) - self.t0) / self.h
        i = np.clip(np.floor(x).astype(int), 1, self.n - 3)
        w, dw = _cubic_weights(x - i)
        return i, (dw / self.h if derivative else w)

    def rows(self, t, derivative: bool = False):
        """Design rows (sparse): D(t) = rows(t) @ coeffs."""
        t = np.atleast_1d(np.asarray(t, float))
        i, w = self._weights(t, derivative)
        cols = (i[:, None] - 1 + np.arange(4)).ravel()
        return sparse.csr_matrix(
            (w.ravel(), (np.repeat(np.arange(len(t)), 4), cols)), shape=(len(t), self.n)
        )

    def __call__(self, coeffs: np.ndarray, t, derivative: bool = False) -> np.ndarray:
        """D(t) (or D'(t)) for coefficients (n, k): shape t.shape + (k,)."""
        i, w = self._weights(t, derivative)
        return sum(w[..., a, None] * coeffs[i - 1 + a] for a in range(4))


@dataclass
class _FeatureObs:
    z: np.ndarray  # (p0 .. p5) in SI
    cov: np.ndarray  # (6, 6) covariance of z, SI
    projection: np.ndarray  # (6, 2N): z per displacement (dx, dy) in m of each region pixel
    t0: np.ndarray  # (N,) when each region pixel was imaged at 0 deg
    t90: np.ndarray  # (N,) when its match was imaged at 90 deg


def _fit_drift(obs: list, t_ref: float, t_start: float, t_end: float, spacing: float):
    """Generalised least squares for D(t) = (Dx, Dy), a cubic B-spline in time, with
    D(t_ref) = 0 and a random-walk prior on the velocity (second differences of the spline
    coefficients, spread from the drift statistics of Fig. 7.9).

    Each region pixel i sees the displacement D(t90_i) - D(t0_i) between the images (eq. 3.24);
    the Newton fit projects that field onto the offset vector, so the model of each feature's
    (p0 .. p5) is projection @ (D(t90) - D(t0)): p0, p1 are essentially the displacement at the
    centre and p2 .. p5 the mean drift velocity over the region's lines, at 0 deg and at 90 deg
    (d(u, v)/dy ~ -D'(t0) * line period / pixel, d(u, v)/dx ~ D'(t90) * line period / pixel).
    Residuals are whitened with the Newton fit's covariance plus a model-error floor (round
    particles hardly fix the rotation part of p: p3 - p4 alone is uncertain, p3 + p4 is not);
    the feature with the largest chi-square is dropped while it is an outlier."""
    spline = _TimeSpline(t_start, t_end, spacing)
    n = spline.n
    nm = 1e9  # solve in nm: well-scaled normal equations
    sigma_pen = nm * math.sqrt(2.0 * DRIFT_SIGMA_VELOCITY**2 * spacing**3 / DRIFT_CORRELATION_TIME)
    unit = np.array([nm, nm, 1, 1, 1, 1])  # z in nm and dimensionless gradients
    blocks = []
    for o in obs:
        psi = spline.rows(o.t90) - spline.rows(o.t0)  # (N, n), sparse
        half = o.projection.shape[1] // 2
        design = np.hstack(
            [(psi.T @ o.projection[:, :half].T).T, (psi.T @ o.projection[:, half:].T).T]
        )  # (6, 2n)
        design = design * unit[:, None] / nm  # per nm of coefficient
        cov = o.cov * np.outer(unit, unit)
        try:
            white = np.linalg.inv(np.linalg.cholesky(cov))
        except np.linalg.LinAlgError:
            white = np.diag(1.0 / np.sqrt(np.clip(np.diag(cov), 1e-300, None)))
        blocks.append((white @ design, white @ (o.z * unit)))
    pen = np.zeros((n - 2, n))
    idx = np.arange(n - 2)
    pen[idx, idx], pen[idx, idx + 1], pen[idx, idx + 2] = 1.0, -2.0, 1.0
    pen = np.kron(np.eye(2), pen) / sigma_pen
    anchor = np.kron(np.eye(2), spline.rows(t_ref).toarray())
    keep = np.ones(len(obs), bool)
    while True:
        design = np.vstack([blocks[k][0] for k in range(len(obs)) if keep[k]] + [pen, anchor])
        rhs = np.concatenate(
            [blocks[k][1] for k in range(len(obs)) if keep[k]] + [np.zeros(len(pen) + 2)]
        )
        coeffs = np.linalg.lstsq(design, rhs, rcond=None)[0]
        chi2 = np.array(
            [
                float(np.sum((blocks[k][0] @ coeffs - blocks[k][1]) ** 2)) if keep[k] else 0.0
                for k in range(len(obs))
            ]
        )
        kept = chi2[keep]
        limit = max(50.0, 10.0 * float(np.median(kept)))
        if keep.sum() <= 2 or kept.max() <= limit:
            break
        keep[int(np.argmax(np.where(keep, chi2, -1.0)))] = False
    coeffs = coeffs.reshape(2, n).T
    coeffs -= spline(coeffs, t_ref)  # D(t_ref) = 0 exactly (the B-splines sum to 1)
    coeffs /= nm
    return spline, coeffs, keep


# -- the main entry ---------------------------------------------------------------------------
def compensate_pair(
    scan0: RasterScanData, scan90: RasterScanData, order: int = 1, method: str = "time"
) -> DriftCorrection:
    """Reconstruct the 0 deg image free of thermal drift from a 0 deg / 90 deg pair of the same
    area (book ch. 3). `order`: 1 (6-parameter offset vector, the book's choice) or 2 (12
    parameters, eq. 3.17). `method`: "time" (drift as a smooth function of time, see the module
    doc) or "book" (eq. 3.23-3.27 literally)."""
    started = _time.perf_counter()
    if order not in (1, 2):
        raise ValueError(
            f"order={order!r}: must be 1 (first-order offset vector) or 2 (second-order)"
        )
    if method not in ("time", "book"):
        raise ValueError(f"method={method!r}: must be 'time' or 'book'")
    _check_scan("scan0", scan0)
    _check_scan("scan90", scan90)
    if scan0.scan_angle_deg != 0.0:
        raise ValueError(
            f"scan0.scan_angle_deg={scan0.scan_angle_deg}: the reference must be the 0 deg scan"
        )
    if scan90.scan_angle_deg != 90.0:
        raise ValueError(
            f"scan90.scan_angle_deg={scan90.scan_angle_deg}: the deformation image must be the "
            f"90 deg scan"
        )
    _check_same_area(scan0, scan90, "scan90")

    h0 = np.asarray(scan0.height, float)
    h90 = np.asarray(scan90.height, float)
    px, py = scan0.pixel_size_x, scan0.pixel_size_y
    ny, nx = h0.shape

    # feature regions and their start values
    blobs0, threshold = _blobs(h0)
    blobs0 = _windows(blobs0, h0.shape)
    if not blobs0:
        raise ValueError(
            "scan0.height: no feature regions (particles above the substrate, away from the "
            "image edge) found; drift compensation needs at least one"
        )
    blobs90, _ = _blobs(h90, threshold)
    shift = _global_shift(h0, h90)
    _, A, b = _match_blobs(blobs0, blobs90, shift)
    spline90 = BSplineImage(h90)

    fits = []
    for blob in blobs0:
        r_lo, r_hi, c_lo, c_hi = blob.window
        centre = np.array([0.5 * (r_lo + r_hi - 1), 0.5 * (c_lo + c_hi - 1)])
        pred = A @ centre + b
        grad = A - np.eye(2)  # d(row', col')/d(row, col) - I
        p_start = np.array(
            [
                pred[1] - centre[1],
                pred[0] - centre[0],
                grad[1, 1],
                grad[0, 1],
                grad[1, 0],
                grad[0, 0],
            ]
        )
        rows, cols = np.mgrid[r_lo:r_hi, c_lo:c_hi]
        rows, cols = rows.ravel().astype(float), cols.ravel().astype(float)
        # a region the drift has partly carried out of the 90 deg image is matched on the part
        # that stays inside (3 pixels of slack for the start value's error)
        target = np.stack([rows, cols], axis=1) @ A.T + b
        keep = (
            (target[:, 0] >= 3)
            & (target[:, 0] <= ny - 4)
            & (target[:, 1] >= 3)
            & (target[:, 1] <= nx - 4)
        )
        c_pred = A @ blob.centroid + b
        if keep.mean() < 0.6 or not (0 <= c_pred[0] <= ny - 1 and 0 <= c_pred[1] <= nx - 1):
            continue
        rows, cols = rows[keep], cols[keep]
        g = h0[rows.astype(int), cols.astype(int)]
        fit = _newton_ncc(g, rows, cols, centre, spline90, p_start, 1)
        if order == 2 and fit.ncc > 0:
            fit2 = _newton_ncc(g, rows, cols, centre, spline90, fit.p, 2)
            if fit2.ncc >= fit.ncc:
                fit = fit2
        u, v = offset_displacement(fit.p, cols - centre[1], rows - centre[0])
        inside = (
            np.min(rows + v) >= 0
            and np.max(rows + v) <= ny - 1
            and np.min(cols + u) >= 0
            and np.max(cols + u) <= nx - 1
        )
        if fit.ncc >= MIN_NCC and inside and np.all(np.isfinite(fit.p)):
            fits.append((blob, centre, fit, rows, cols))
    if not fits:
        raise ValueError(
            "scan0.height: no feature region could be matched in scan90 (normalised "
            f"cross-correlation >= {MIN_NCC}); are they images of the same area?"
        )

    feature_offsets = [
        (float(c[0]), float(c[1]), _to_si(f.p, px, py), float(f.ncc)) for _, c, f, *_ in fits
    ]
    # Reference line c: the middle line of the 0 deg scan (in time). Anchoring there keeps the
    # whole map's frame interpolated between feature regions; at the first line it would rest
    # on an extrapolation of the drift, whose error would shift every row.
    ref_line = int(np.argsort(scan0.line_start_times, kind="stable")[ny // 2])
    t_ref = float(pixel_times(scan0, ref_line, 0.5 * (nx - 1)))
    row_times = pixel_times(scan0, np.arange(ny), np.full(ny, 0.5 * (nx - 1)))

    if method == "time":
        obs = []
        floor = np.diag(np.array([_VALUE_FLOOR] * 2 + [_GRADIENT_FLOOR] * 4) ** 2)
        rotation = np.array([0, 0, 0, 1.0, -1.0, 0]) / math.sqrt(2)
        floor += _ROTATION_SIGMA**2 * np.outer(rotation, rotation)
        f = _si_factors(6, px, py)
        for blob, centre, fit, rows, cols in fits:
            n_pix = rows.size
            projection = fit.projection[:6] * f[:, None]
            projection[:, :n_pix] /= px  # du in columns = dx / px
            projection[:, n_pix:] /= py
            obs.append(
                _FeatureObs(
                    z=_to_si(fit.p_data, px, py)[:6],
                    cov=fit.cov[:6, :6] * np.outer(f, f) + floor,
                    projection=projection,
                    t0=pixel_times(scan0, rows, cols),
                    t90=pixel_times(scan90, fit.rows_def, fit.cols_def),
                )
            )
        t_all = np.concatenate(
            [
                [
                    t_ref,
                    scan0.start_time + np.min(scan0.line_start_times),
                    scan0.start_time + np.max(scan0.line_start_times) + scan0.line_period,
                ]
            ]
            + [o.t0 for o in obs]
            + [o.t90 for o in obs]
        )
        spacing = KNOT_LINES * scan0.line_period
        tspline, coeffs, keep = _fit_drift(
            obs, t_ref, float(t_all.min()), float(t_all.max()), spacing
        )
        feature_offsets = [
            entry for entry, used in zip(feature_offsets, keep) if used
        ]  # outliers dropped

        def displacement(rows, cols):
            d = tspline(coeffs, pixel_times(scan0, rows, cols))
            return d[..., 0], d[..., 1]

        offsets = tspline(coeffs, row_times)
    else:
        offsets = _book_line_offsets(fits, (ny, nx), ref_line) * np.array([px, py])

        def displacement(rows, cols):
            rows = np.asarray(rows, float)
            dx = _extrapolating_interp(rows, offsets[:, 0])
            dy = _extrapolating_interp(rows, offsets[:, 1])
            return dx + 0 * np.asarray(cols, float), dy + 0 * np.asarray(cols, float)

    corrected, valid = _resample(h0, displacement, px, py)
    velocity = _slope(row_times, offsets)
    return DriftCorrection(
        corrected=corrected.astype(np.asarray(scan0.height).dtype, copy=False),
        velocity=(float(velocity[0]), float(velocity[1])),
        offsets=offsets,
        feature_offsets=feature_offsets,
        seconds=_time.perf_counter() - started,
        t_ref=t_ref,
        valid=valid,
    )


def _slope(t: np.ndarray, y: np.ndarray) -> np.ndarray:
    tc = t - t.mean()
    return (tc @ (y - y.mean(axis=0))) / (tc @ tc)


def _resample(h0: np.ndarray, displacement, px: float, py: float):
    """Corrected map C(X) = I0(X') with X' = X + D(t0(X')) - D(t_ref) (eq. 3.28 inverted), by
    fixed-point iteration, then bicubic B-spline sampling of the reference (eq. 3.11)."""
    ny, nx = h0.shape
    rows, cols = np.mgrid[0:ny, 0:nx].astype(float)
    r, c = rows.copy(), cols.copy()
    for _ in range(4):
        dx, dy = displacement(r, c)
        r, c = rows + dy / py, cols + dx / px
    corrected = ndimage.map_coordinates(h0, [r, c], order=3, mode="nearest", prefilter=True)
    valid = (r >= 0) & (r <= ny - 1) & (c >= 0) & (c <= nx - 1)
    return corrected, valid


def _book_line_offsets(fits, shape, ref_line: int) -> np.ndarray:
    """eq. 3.23-3.27: (u, v) over the whole grid from the feature p's (in their regions) and band
    means (elsewhere); the displacement of line j relative to line c (pixels) is minus the change
    of the line mean of (u, v)."""
    ny, nx = shape
    centres = [c for _, c, *_ in fits]
    ps = [
        f.p[:6] for _, _, f, *_ in fits
    ]  # first order: the band means extrapolate p over the band
    extents = [(blob.window[0], blob.window[1] - 1) for blob, *_ in fits]
    bands, splits = band_partition(extents)
    band_p = band_offset_vectors(centres, ps, bands)
    edges = [-np.inf] + list(splits) + [np.inf]
    rows = np.arange(ny, dtype=float)
    cols = np.arange(nx, dtype=float)
    U = np.zeros((ny, nx))
    V = np.zeros((ny, nx))
    for k, (centre, p) in enumerate(band_p):
        sel = (rows >= edges[k]) & (rows < edges[k + 1])
        if not sel.any():
            continue
        uu, vv = offset_displacement(p, cols[None, :] - centre[1], rows[sel, None] - centre[0])
        U[sel], V[sel] = uu, vv
    for (blob, centre, *_), p in zip(fits, ps):
        r0, r1, c0, c1 = blob.window
        rr, cc = np.mgrid[r0:r1, c0:c1]
        uu, vv = offset_displacement(p, cc - centre[1], rr - centre[0])
        U[r0:r1, c0:c1], V[r0:r1, c0:c1] = uu, vv
    mean_u, mean_v = U.mean(axis=1), V.mean(axis=1)
    return np.stack([-(mean_u - mean_u[ref_line]), -(mean_v - mean_v[ref_line])], axis=1)


# -- frame up / frame down (eq. 5.32-5.36) -----------------------------------------------------
def velocity_from_up_down(
    scan_up: RasterScanData, scan_down: RasterScanData
) -> tuple[float, float]:
    """Drift velocity (vx, vy) in m/s from a frame-up and a frame-down image of the same area at
    the same angle (book 5.3.3).

    A particle at sample position s appears at X = s + D(t), t the moment its centre is imaged.
    For two particles P1, P2 and constant drift v the apparent separations are
        d_up = d + v (t_up(P2) - t_up(P1)),   d_down = d + v (t_down(P2) - t_down(P1)),
    so v = (d_up - d_down) / (T'_u + T'_d) with T'_u, T'_d the times between imaging the two
    particles in each frame (signed; along the slow axis they have opposite signs, so the
    denominator is the sum of the two intervals: eq. 5.35; along the fast axis the same relation
    with the horizontal separations: eq. 5.36). Along the slow axis with line speed V this is the
    stretch V / (V - v) frame up and the compression V / (V + v) frame down:
    v = V (d_up - d_down) / (d_up + d_down). With more than two particles all pairs are used at
    once: X_up(k) - X_down(k) = c + v (t_up(k) - t_down(k)) by least squares (c absorbs a common
    offset between the frames, e.g. the drift between the frames or a scanner offset).

    What it measures: the least-squares slope over the particles' moments, so in a drift that
    wanders it is an average of the velocity over the stretches of the two frames where the
    particles are imaged (`sampled_velocity` gives it for a known D(t)), in the units of the
    images (their pixel size as commanded: a scanner whose small moves go farther than
    commanded makes every image, and the velocity, smaller by the same factor)."""
    return up_down_velocity(up_down_observations(scan_up, scan_down))


@dataclass
class UpDownObservations:
    """The particles matched between a frame-up and a frame-down image: their positions
    (n, 2) as (x, y) in m from the image origin, in image units (commanded pixel size), and
    the instrument-clock moments (n,) their centres were imaged (`pixel_times`)."""

    position_up: np.ndarray
    position_down: np.ndarray
    t_up: np.ndarray
    t_down: np.ndarray


def up_down_observations(scan_up: RasterScanData, scan_down: RasterScanData) -> UpDownObservations:
    """The particles of a frame-up / frame-down pair, matched (see `velocity_from_up_down`)."""
    _check_scan("scan_up", scan_up)
    _check_scan("scan_down", scan_down)
    if scan_down.scan_angle_deg != scan_up.scan_angle_deg:
        raise ValueError(
            f"scan_down.scan_angle_deg={scan_down.scan_angle_deg}: must equal "
            f"scan_up.scan_angle_deg={scan_up.scan_angle_deg}"
        )
    if not scan_up.slow_scan_up:
        raise ValueError("scan_up.slow_scan_up=False: the frame-up image must be scanned upwards")
    if scan_down.slow_scan_up:
        raise ValueError(
            "scan_down.slow_scan_up=True: the frame-down image must be scanned downwards"
        )
    _check_same_area(scan_up, scan_down, "scan_down")
    hu = np.asarray(scan_up.height, float)
    hd = np.asarray(scan_down.height, float)
    blobs_u, threshold = _blobs(hu)
    blobs_d, _ = _blobs(hd, threshold)
    blobs_u = _windows(blobs_u, hu.shape)
    blobs_d = _windows(blobs_d, hd.shape)
    if len(blobs_u) < 2:
        raise ValueError(f"scan_up.height: {len(blobs_u)} particle(s) found; need at least two")
    pairs, _, _ = _match_blobs(blobs_u, blobs_d, _global_shift(hu, hd))
    if len(pairs) < 2:
        raise ValueError(
            f"scan_down.height: only {len(pairs)} particle(s) match the frame-up image; need two"
        )
    pu = np.array([blobs_u[i].centroid for i, _ in pairs])
    pd = np.array([blobs_d[j].centroid for _, j in pairs])
    tu = pixel_times(scan_up, pu[:, 0], pu[:, 1])
    td = pixel_times(scan_down, pd[:, 0], pd[:, 1])
    if np.ptp(tu - td) <= 0:
        raise ValueError(
            "scan_up.height: the particles were imaged at the same moments; need particles on "
            "different lines"
        )
    scale = np.array([scan_up.pixel_size_x, scan_up.pixel_size_y])
    return UpDownObservations(
        position_up=pu[:, ::-1] * scale, position_down=pd[:, ::-1] * scale, t_up=tu, t_down=td
    )


def up_down_velocity(obs: UpDownObservations) -> tuple[float, float]:
    """(vx, vy) in m/s: X_up(k) - X_down(k) = c + v (t_up(k) - t_down(k)) by least squares."""
    dt = np.asarray(obs.t_up, float) - np.asarray(obs.t_down, float)
    design = np.stack([np.ones_like(dt), dt], axis=1)
    diff = np.asarray(obs.position_up, float) - np.asarray(obs.position_down, float)
    sol, *_ = np.linalg.lstsq(design, diff, rcond=None)
    return float(sol[1, 0]), float(sol[1, 1])


def sampled_velocity(offset, t_up, t_down) -> np.ndarray:
    """The velocity (vx, vy) a frame-up / frame-down pair returns for a drift offset D(t)
    (`offset(t)` -> (..., 2), m) with its particles imaged at t_up, t_down (s): the least
    squares of `up_down_velocity` applied to D(t_up) - D(t_down). For a constant velocity it is
    that velocity; for a wandering one it is the average the pair samples (weighted towards the
    stretches of the two frames where the particles are), which is the truth to compare a
    measured pair velocity with (not the mean velocity over the pair's whole span)."""
    t_up, t_down = np.asarray(t_up, float), np.asarray(t_down, float)
    return np.array(
        up_down_velocity(
            UpDownObservations(
                position_up=np.asarray(offset(t_up), float),
                position_down=np.asarray(offset(t_down), float),
                t_up=t_up,
                t_down=t_down,
            )
        )
    )
