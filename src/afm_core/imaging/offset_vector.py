"""The offset vector of a feature region and its fit (book 3.2.3.1, eq. 3.7-3.22).

Offset vector (eq. 3.13-3.18): about a region centre (x0, y0), dx = x - x0, dy = y - y0,
u = p0 + p2 dx + p4 dy, v = p1 + p3 dx + p5 dy (first order, 6 parameters, the book's choice),
or plus (p6 dx^2 + p8 dy^2)/2 + p10 dx dy in u and (p7 dx^2 + p9 dy^2)/2 + p11 dx dy in v
(second order, 12 parameters, eq. 3.17).

For each region, p maximises the zero-mean normalised cross-correlation C(p) (eq. 3.19; the
means removed so that either image's substrate level does not matter) between the reference
region and the deformation image sampled at (x + u, y + v) by bicubic B-spline interpolation
(eq. 3.7-3.11, `BSplineImage`: scipy's cubic B-spline coefficients, then the 4x4 evaluation
U M Q M^T V^T and its analytic derivatives dh/dx, dh/dy). The maximisation is the Newton
iteration of eq. 3.20 on |g^ - h^(p)|^2 = 2 (1 - C(p)) (g^, h^ the normalised zero-mean
regions): gradient eq. 3.21, Hessian eq. 3.22 without its second-derivative term
(Gauss-Newton), Levenberg-damped so that no step lowers C. A round particle looks the same
rotated, so the rotation part of p is held near the start value by a weak prior (free, it
wanders and leaks into the stretch at second order).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

ROTATION_PRIOR = 0.01  # weight of the rotation prior in the Newton fit (see _RotationPrior)


def _basis(dx, dy, order: int):
    """The offset vector's terms at (dx, dy): 1, dx, dy (and dx^2/2, dy^2/2, dx dy), last axis."""
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
            f"p: {p.shape[0] if p.ndim == 1 else p.shape} parameters; the offset vector has "
            "6 or 12"
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


def cubic_weights(t):
    """Uniform cubic B-spline weights of the 4 coefficients i-1..i+2 at i + t, and their
    derivatives."""
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
    with its analytic derivatives. Matches scipy.ndimage.map_coordinates(order=3,
    mode='mirror')."""

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
        wr, dwr = cubic_weights(r - ir)
        wc, dwc = cubic_weights(c - ic)
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


@dataclass
class RegionFit:
    p: np.ndarray  # pixel units, about the window centre
    cov: np.ndarray  # covariance of p (Gauss-Newton), pixel units
    ncc: float
    converged: bool
    # (P, 2N): p (pixel units) per displacement (du, dv) of each region pixel
    projection: np.ndarray = None
    rows_def: np.ndarray = None  # where the region's pixels are in the deformation image
    cols_def: np.ndarray = None
    p_data: np.ndarray = None  # p without the rotation prior's pull: projection @ (du, dv)


class _NccProblem:
    """The reference region g at (rows, cols) against the deformation image, as a function of
    the offset vector q in scaled coordinates (the region's half-size is 1: well-conditioned)."""

    def __init__(self, g, rows, cols, centre, spline: BSplineImage, order: int):
        r0, c0 = centre
        self.rows, self.cols, self.spline = rows, cols, spline
        self.scale = max(float(np.max(np.abs(rows - r0))), float(np.max(np.abs(cols - c0))), 1.0)
        self.basis = _basis((cols - c0) / self.scale, (rows - r0) / self.scale, order)  # (N, m)
        self.m = self.basis.shape[1]
        self.powers = np.array([0, 1, 1, 2, 2, 2][: self.m], float)
        gc = g - g.mean()
        self.g_hat = gc / np.linalg.norm(gc)

    def scaled(self, p_start) -> np.ndarray:
        """q of an offset vector p in pixel units (missing second-order terms 0)."""
        q = np.zeros(2 * self.m)
        q[: len(p_start)] = p_start * np.repeat(self.scale ** self.powers[: len(p_start) // 2], 2)
        return q

    def unscale(self) -> np.ndarray:
        """Divide q by this to get p in pixel units."""
        return np.repeat(self.scale**self.powers, 2)

    def displacement(self, q):
        """(u, v) of the region's pixels."""
        return self.basis @ q[0::2], self.basis @ q[1::2]

    def residual(self, q):
        """(g^ - h^(q), d h^ / dq), or None when the sampled region is flat."""
        u, v = self.displacement(q)
        h, h_row, h_col = self.spline(self.rows + v, self.cols + u, derivatives=True)
        hc = h - h.mean()
        norm = np.linalg.norm(hc)
        if norm == 0:
            return None
        h_hat = hc / norm
        r = self.g_hat - h_hat
        dh = np.empty((len(h), 2 * self.m))
        dh[:, 0::2] = h_col[:, None] * self.basis
        dh[:, 1::2] = h_row[:, None] * self.basis
        dh -= dh.mean(axis=0)
        a = (dh - np.outer(h_hat, h_hat @ dh)) / norm  # d h^ / dq
        return r, a


class _RotationPrior:
    """A round particle looks the same rotated, so the rotation part of the mapping (p3 - p4)
    is all but free; left free it wanders off and, at second order, leaks into the stretch (a
    rotation by theta fitted as an affine map also scales by theta^2/2). A weak quadratic
    penalty keeps it at the start value (the affine fit of all particles) unless the feature
    itself fixes it: its weight is ROTATION_PRIOR times the curvature of a feature that is
    fully structured in rotation (translation curvature x region radius^2)."""

    def __init__(self, a: np.ndarray, q: np.ndarray):
        self.e = np.zeros(len(q))
        self.e[3], self.e[4] = 1.0, -1.0
        ata0 = a.T @ a
        self.weight = ROTATION_PRIOR * 0.25 * 0.5 * (ata0[0, 0] + ata0[1, 1])
        self.matrix = self.weight * np.outer(self.e, self.e)
        self.tau0 = float(self.e @ q)

    def cost(self, r, q) -> float:
        """The fit's cost: |g^ - h^|^2 plus the penalty."""
        return float(r @ r) + self.weight * (float(self.e @ q) - self.tau0) ** 2

    def pull(self, q) -> np.ndarray:
        """Half the penalty's gradient."""
        return self.weight * self.e * (float(self.e @ q) - self.tau0)


def _levenberg_marquardt(problem: _NccProblem, prior: _RotationPrior, q, r, a, max_iter: int):
    """Gauss-Newton steps on the cost, damped so that none raises it. Returns (q, r, a,
    converged)."""
    cost = prior.cost(r, q)
    lam = 1e-3
    for _ in range(max_iter):
        ata = a.T @ a + prior.matrix
        try:
            delta = np.linalg.solve(
                ata + lam * np.diag(np.diag(ata) + 1e-12), a.T @ r - prior.pull(q)
            )
        except np.linalg.LinAlgError:
            return q, r, a, False
        if np.max(np.abs(delta)) < 1e-4:  # pixels at the region's edge
            return q, r, a, True
        trial = problem.residual(q + delta)
        if trial is not None and prior.cost(trial[0], q + delta) < cost:
            q = q + delta
            r, a = trial
            new_cost = prior.cost(r, q)
            gain, cost = cost - new_cost, new_cost
            lam = max(lam / 4, 1e-9)
            if gain < 1e-4 * cost:  # converged to well below the noise
                return q, r, a, True
        else:
            lam *= 8
            if lam > 1e8:
                return q, r, a, True  # no descent left: at the optimum within rounding
    return q, r, a, False


def _linearised_fit(problem: _NccProblem, prior: _RotationPrior, q, r, a, converged) -> RegionFit:
    """The fit at q with its covariance and its linearisation. Linearised, the fit is a
    weighted least-squares projection of the true displacement field onto the offset-vector
    model, q = (a^T a + prior)^-1 (a^T M (du, dv) + prior q_start), with M (du, dv) the change
    of h^ for a per-pixel displacement. The data part is kept so that p can be predicted from a
    drift hypothesis (see afm_core.imaging.drift_fit); p_data excludes the prior part."""
    m = problem.m
    u, v = problem.displacement(q)
    rows, cols = problem.rows, problem.cols
    h, h_row, h_col = problem.spline(rows + v, cols + u, derivatives=True)
    hc = h - h.mean()
    norm = float(np.linalg.norm(hc))
    h_hat = hc / norm
    ncc = 1.0 - float(r @ r) / 2.0
    unscale = problem.unscale()
    try:
        ata_inv = np.linalg.inv(a.T @ a + prior.matrix)
    except np.linalg.LinAlgError:
        return RegionFit(q / unscale, np.diag(np.full(2 * m, np.inf)), 0.0, False)  # unusable
    dof = max(len(r) - 2 * m, 1)
    cov = ata_inv * float(r @ r) / dof / np.outer(unscale, unscale)
    pa = ata_inv @ a.T / unscale[:, None]  # (P, N): p per unit change of h^
    sens = _normalisation_adjoint(pa, h_hat, norm)
    projection = np.hstack([sens * h_col, sens * h_row])
    p_data = (q - ata_inv @ (prior.weight * prior.e * prior.tau0)) / unscale
    return RegionFit(q / unscale, cov, ncc, converged, projection, rows + v, cols + u, p_data)


def fit_region(
    g: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    centre,
    spline: BSplineImage,
    p_start: np.ndarray,
    order: int,
    max_iter: int = 60,
) -> RegionFit:
    """The offset vector (pixel units, about `centre` (row, col)) that maps the reference
    region g, at (rows, cols), best onto the deformation image `spline` (eq. 3.19-3.22), from
    p_start; order 1 (6 parameters) or 2 (12)."""
    problem = _NccProblem(g, rows, cols, centre, spline, order)
    q = problem.scaled(p_start)
    first = problem.residual(q)
    if first is None:
        m = problem.m
        return RegionFit(np.zeros(2 * m), np.diag(np.full(2 * m, np.inf)), 0.0, False)
    r, a = first
    prior = _RotationPrior(a, q)
    q, r, a, converged = _levenberg_marquardt(problem, prior, q, r, a, max_iter)
    return _linearised_fit(problem, prior, q, r, a, converged)


def _normalisation_adjoint(pa: np.ndarray, h_hat: np.ndarray, norm: float) -> np.ndarray:
    """pa @ M0 where M0 = (I - h^ h^T)(I - 1 1^T / N) / norm (the normalisation's Jacobian)."""
    x = pa - np.outer(pa @ h_hat, h_hat)
    x = x - x.mean(axis=1, keepdims=True)
    return x / norm


def si_factors(n: int, px: float, py: float) -> np.ndarray:
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


def to_si(p_px: np.ndarray, px: float, py: float) -> np.ndarray:
    """Pixel-unit offset vector (u, v in columns/rows, derivatives per pixel) to SI."""
    return p_px * si_factors(len(p_px), px, py)
