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

Steps, and where they are in the book (and in afm_core.imaging: offset_vector, the model and
fit of step 1-2; particle_matching, the features of step 2; drift_fit, steps 3-4;
scan_timing, the pixel times; frame_up_down, step 5; this module runs them and resamples):

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
   line times. `frame_up_down.velocity_from_up_down` is the second route (eq. 5.32-5.36).

The method attributes every difference between the two images to drift: scanner hysteresis,
creep and cross-coupling must be compensated (or negligible) first. SI units throughout (m, s);
image axes: row = y index, column = x index.
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from afm_core.imaging.drift_fit import book_line_offsets, fit_time_drift
from afm_core.imaging.drift_timing import TimingCheck, check_timing
from afm_core.imaging.offset_vector import BSplineImage, fit_region, offset_displacement, to_si
from afm_core.imaging.particle_matching import (
    feature_windows,
    find_blobs,
    global_shift,
    match_blobs,
)
from afm_core.imaging.scan_timing import (
    check_same_area,
    check_scan,
    extrapolating_interp,
    pixel_times,
)
from afm_core.instrument import RasterScanData

MIN_NCC = 0.9  # a feature match below this is not used


@dataclass
class DriftCorrection:
    # height map (m) in the scanner frame at t_ref, same grid as the 0 deg image
    corrected: np.ndarray
    velocity: tuple  # (vx, vy) m/s, slope of the per-line displacements against time
    # (rows, 2): drift displacement (dx, dy) in m of each 0 deg row relative to t_ref
    offsets: np.ndarray
    feature_offsets: list  # per feature region: (row0, col0, p vector in SI, ncc)
    seconds: float  # wall-clock time of the computation
    t_ref: float = 0.0  # s, instrument clock: the corrected map is the sample as at this moment
    # False where the map extends the data
    valid: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), bool))
    # the gap and line rate the images imply, and warnings where the assumed ones disagree
    timing: TimingCheck | None = None


def _check_pair(scan0: RasterScanData, scan90: RasterScanData, order, method) -> None:
    if order not in (1, 2):
        raise ValueError(
            f"order={order!r}: must be 1 (first-order offset vector) or 2 (second-order)"
        )
    if method not in ("time", "book"):
        raise ValueError(f"method={method!r}: must be 'time' or 'book'")
    check_scan("scan0", scan0)
    check_scan("scan90", scan90)
    if scan0.scan_angle_deg != 0.0:
        raise ValueError(
            f"scan0.scan_angle_deg={scan0.scan_angle_deg}: the reference must be the 0 deg scan"
        )
    if scan90.scan_angle_deg != 90.0:
        raise ValueError(
            f"scan90.scan_angle_deg={scan90.scan_angle_deg}: the deformation image must be the "
            f"90 deg scan"
        )
    check_same_area(scan0, scan90, "scan90")


def _fit_feature(blob, A, b, h0: np.ndarray, spline90: BSplineImage, order: int):
    """The offset vector of one feature region, from the start value of the affine map
    (A, b) of all particles: (blob, centre, fit, rows, cols), or None when unusable."""
    ny, nx = h0.shape
    r_lo, r_hi, c_lo, c_hi = blob.window
    centre = np.array([0.5 * (r_lo + r_hi - 1), 0.5 * (c_lo + c_hi - 1)])
    pred = A @ centre + b
    grad = A - np.eye(2)  # d(row', col')/d(row, col) - I
    p_start = np.array(
        [pred[1] - centre[1], pred[0] - centre[0], grad[1, 1], grad[0, 1], grad[1, 0], grad[0, 0]]
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
        return None
    rows, cols = rows[keep], cols[keep]
    g = h0[rows.astype(int), cols.astype(int)]
    fit = fit_region(g, rows, cols, centre, spline90, p_start, 1)
    if order == 2 and fit.ncc > 0:
        fit2 = fit_region(g, rows, cols, centre, spline90, fit.p, 2)
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
        return blob, centre, fit, rows, cols
    return None


def _feature_fits(h0: np.ndarray, h90: np.ndarray, order: int) -> list:
    """The feature regions of the 0 deg image matched in the 90 deg one (book 3.2.3.1): the
    particles, their start values from an affine map fitted to the matched particles, their
    offset vectors. (blob, centre, fit, rows, cols) per usable region."""
    blobs0, threshold = find_blobs(h0)
    blobs0 = feature_windows(blobs0, h0.shape)
    if not blobs0:
        raise ValueError(
            "scan0.height: no feature regions (particles above the substrate, away from the "
            "image edge) found; drift compensation needs at least one"
        )
    blobs90, _ = find_blobs(h90, threshold)
    shift = global_shift(h0, h90)
    _, A, b = match_blobs(blobs0, blobs90, shift)
    spline90 = BSplineImage(h90)
    fits = [_fit_feature(blob, A, b, h0, spline90, order) for blob in blobs0]
    fits = [fit for fit in fits if fit is not None]
    if not fits:
        raise ValueError(
            "scan0.height: no feature region could be matched in scan90 (normalised "
            f"cross-correlation >= {MIN_NCC}); are they images of the same area?"
        )
    return fits


def compensate_pair(
    scan0: RasterScanData, scan90: RasterScanData, order: int = 1, method: str = "time"
) -> DriftCorrection:
    """Reconstruct the 0 deg image free of thermal drift from a 0 deg / 90 deg pair of the same
    area (book ch. 3). `order`: 1 (6-parameter offset vector, the book's choice) or 2 (12
    parameters, eq. 3.17). `method`: "time" (drift as a smooth function of time, see the module
    doc) or "book" (eq. 3.23-3.27 literally). The result's `timing` says whether the images
    agree with the scans' times (the gap between them, the line period; drift_timing)."""
    started = _time.perf_counter()
    _check_pair(scan0, scan90, order, method)
    h0 = np.asarray(scan0.height, float)
    h90 = np.asarray(scan90.height, float)
    px, py = scan0.pixel_size_x, scan0.pixel_size_y
    ny, nx = h0.shape
    fits = _feature_fits(h0, h90, order)
    feature_offsets = [
        (float(c[0]), float(c[1]), to_si(f.p, px, py), float(f.ncc)) for _, c, f, *_ in fits
    ]
    # Reference line c: the middle line of the 0 deg scan (in time). Anchoring there keeps the
    # whole map's frame interpolated between feature regions; at the first line it would rest
    # on an extrapolation of the drift, whose error would shift every row.
    ref_line = int(np.argsort(scan0.line_start_times, kind="stable")[ny // 2])
    t_ref = float(pixel_times(scan0, ref_line, 0.5 * (nx - 1)))
    row_times = pixel_times(scan0, np.arange(ny), np.full(ny, 0.5 * (nx - 1)))

    if method == "time":
        tspline, coeffs, keep = fit_time_drift(fits, scan0, scan90, t_ref)
        # all features: the fit's outlier rejection trusted the timing this checks
        timing = check_timing(fits, scan0, scan90)
        feature_offsets = [entry for entry, used in zip(feature_offsets, keep) if used]  # outliers

        def displacement(rows, cols):
            d = tspline(coeffs, pixel_times(scan0, rows, cols))
            return d[..., 0], d[..., 1]

        offsets = tspline(coeffs, row_times)
    else:
        timing = check_timing(fits, scan0, scan90)
        offsets = book_line_offsets(fits, (ny, nx), ref_line) * np.array([px, py])

        def displacement(rows, cols):
            rows = np.asarray(rows, float)
            dx = extrapolating_interp(rows, offsets[:, 0])
            dy = extrapolating_interp(rows, offsets[:, 1])
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
        timing=timing,
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
