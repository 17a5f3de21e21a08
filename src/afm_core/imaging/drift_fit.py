"""The drift between a 0 deg and a 90 deg scan from the feature regions' offset vectors (book
3.2.3.2-3.2.4): per line of the reference, its displacement relative to a reference line.

Two estimators (see afm_core.imaging.drift_compensation):
- the time model: the drift D(t) as a cubic B-spline in time fitted to all the feature p's at
  once by generalised least squares (`fit_time_drift`);
- the book's: the offset vectors over the whole reference grid from the feature p's and the
  band means of the non-feature regions, averaged per line (`book_line_offsets`).

Non-feature regions (3.2.3.2, Fig. 3.14, eq. 3.23): particles grouped in horizontal bands (a
band ends where the next particle does not overlap it vertically; split midway), a non-feature
region takes the mean p of its band's particles (each p first moved to the band centre: p
describes the mapping about its own centre). `band_partition`, `band_offset_vectors`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import sparse

from afm_core.imaging.offset_vector import (
    cubic_weights,
    offset_displacement,
    recentre,
    si_factors,
    to_si,
)
from afm_core.imaging.scan_timing import pixel_times
from afm_core.instrument import RasterScanData

KNOT_LINES = 8  # time-spline knot spacing, in line periods of the 0 deg scan
DRIFT_SIGMA_VELOCITY = 0.21e-9  # m/s, stationary spread of the drift velocity (book Fig. 7.9, v_y)
DRIFT_CORRELATION_TIME = 1800.0  # s, how long the drift velocity stays about the same
_VALUE_FLOOR = 0.15e-9  # m, model-error floor of p0, p1 (1 sigma)
_GRADIENT_FLOOR = 5e-4  # model-error floor of p2..p5 (1 sigma)
_ROTATION_SIGMA = 0.1  # rad: a round particle does not fix the rotation part of p (p3 - p4)


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


class TimeSpline:
    """Cubic B-spline in time with uniform knots: D(t) = sum_k c_k B_k(t)."""

    def __init__(self, t_start: float, t_end: float, spacing: float):
        self.t0 = t_start - spacing
        self.h = spacing
        self.n = int(math.ceil((t_end + spacing - self.t0) / spacing)) + 3

    def _weights(self, t, derivative: bool):
        x = (np.asarray(t, float) - self.t0) / self.h
        i = np.clip(np.floor(x).astype(int), 1, self.n - 3)
        w, dw = cubic_weights(x - i)
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


_NM = 1e9  # the drift is solved in nm: well-scaled normal equations


def whitened_blocks(obs: list, spline: TimeSpline, shift: float = 0.0) -> list:
    """Per feature, (whitened design, whitened data) of its (p0 .. p5) against the spline's
    coefficients (2n: Dx then Dy, in nm): the model is projection @ (D(t90 + shift) - D(t0)),
    z in nm and dimensionless gradients, whitened with the covariance's Cholesky factor."""
    unit = np.array([_NM, _NM, 1, 1, 1, 1])
    blocks = []
    for o in obs:
        psi = spline.rows(o.t90 + shift) - spline.rows(o.t0)  # (N, n), sparse
        half = o.projection.shape[1] // 2
        design = np.hstack(
            [(psi.T @ o.projection[:, :half].T).T, (psi.T @ o.projection[:, half:].T).T]
        )  # (6, 2n)
        design = design * unit[:, None] / _NM  # per nm of coefficient
        white = whitening(o.cov * np.outer(unit, unit))
        blocks.append((white @ design, white @ (o.z * unit)))
    return blocks


def whitening(cov: np.ndarray) -> np.ndarray:
    """W with W cov W^T = I (the inverse Cholesky factor; the diagonal alone if cov is not
    positive definite)."""
    try:
        return np.linalg.inv(np.linalg.cholesky(cov))
    except np.linalg.LinAlgError:
        return np.diag(1.0 / np.sqrt(np.clip(np.diag(cov), 1e-300, None)))


def velocity_prior(spline: TimeSpline) -> np.ndarray:
    """Whitened prior rows on the coefficients (nm): a random walk of the drift velocity, the
    second differences of the coefficients with the spread of the drift statistics (Fig. 7.9)."""
    n, spacing = spline.n, spline.h
    sigma_pen = _NM * math.sqrt(
        2.0 * DRIFT_SIGMA_VELOCITY**2 * spacing**3 / DRIFT_CORRELATION_TIME
    )
    pen = np.zeros((n - 2, n))
    idx = np.arange(n - 2)
    pen[idx, idx], pen[idx, idx + 1], pen[idx, idx + 2] = 1.0, -2.0, 1.0
    return np.kron(np.eye(2), pen) / sigma_pen


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
    spline = TimeSpline(t_start, t_end, spacing)
    n = spline.n
    nm = _NM
    blocks = whitened_blocks(obs, spline)
    pen = velocity_prior(spline)
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


def feature_observations(fits, scan0: RasterScanData, scan90: RasterScanData) -> list:
    """Each fitted feature's (p0 .. p5) in SI with its covariance (the fit's plus a model-error
    floor), its projection of per-pixel displacements (m) and its pixels' times in both scans."""
    px, py = scan0.pixel_size_x, scan0.pixel_size_y
    obs = []
    floor = np.diag(np.array([_VALUE_FLOOR] * 2 + [_GRADIENT_FLOOR] * 4) ** 2)
    rotation = np.array([0, 0, 0, 1.0, -1.0, 0]) / math.sqrt(2)
    floor += _ROTATION_SIGMA**2 * np.outer(rotation, rotation)
    f = si_factors(6, px, py)
    for _, _, fit, rows, cols in fits:
        n_pix = rows.size
        projection = fit.projection[:6] * f[:, None]
        projection[:, :n_pix] /= px  # du in columns = dx / px
        projection[:, n_pix:] /= py
        obs.append(
            _FeatureObs(
                z=to_si(fit.p_data, px, py)[:6],
                cov=fit.cov[:6, :6] * np.outer(f, f) + floor,
                projection=projection,
                t0=pixel_times(scan0, rows, cols),
                t90=pixel_times(scan90, fit.rows_def, fit.cols_def),
            )
        )
    return obs


def fit_time_drift(fits, scan0: RasterScanData, scan90: RasterScanData, t_ref: float):
    """The time model: D(t) fitted to the features' offset vectors (`_fit_drift`) over the
    span of both scans, knots every KNOT_LINES line periods. fits: (blob, centre, RegionFit,
    rows, cols) per feature. Returns (spline, coefficients (m), which features were kept)."""
    obs = feature_observations(fits, scan0, scan90)
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
    return _fit_drift(obs, t_ref, float(t_all.min()), float(t_all.max()), spacing)


def book_line_offsets(fits, shape, ref_line: int) -> np.ndarray:
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
