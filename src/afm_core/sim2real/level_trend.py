"""A slow change in time of the absolute substrate levels, tested as such.

The absolute levels (`features_absolute`: each scan line's and each block of an image's
substrate, relative to the session's first) are one quantity measured again and again: the
substrate's level under the tip. What moves it (a cantilever bending as it settles in
temperature, a z sensor's creep) is slow against the operations, so it shows as a smooth change
of that series in time. Read through the omnibus chi^2 of the group, such a change is diluted:
in a session of normal work (a few images, a localization's lines, pushes; about 20 level
features over 300 s) a settling of 0.7 nm against a noise of 0.13 nm gave chi^2 40 for 16
(p = 8e-4), under the per-group limit, and the verdict was "no missing physics". The same
residual is 30 chi^2 of a trend.

So the levels are also tested for the form the physics gives them: Legendre polynomials in time
of degrees 1..SMOOTH_DEGREE (signature.py's "smooth"; the constant is the levels' own nuisance
offset, their unknown zero), fitted by GLS with the noise model's full covariance of the level
features (what is correlated between them stays correlated), the chi^2 they remove tested
against chi^2 with as many dof as they have independent columns.
"""

from __future__ import annotations

import numpy as np
from scipy import linalg, stats

from afm_core.sim2real.features_absolute import LEVEL_GROUPS
from afm_core.sim2real.signature import MIN_FEATURES, SMOOTH_DEGREE


def _whiten(cov: np.ndarray):
    """x -> L^-1 x with L the Cholesky factor of cov (scaled to unit diagonal for conditioning)."""
    scale = np.sqrt(np.diag(cov))
    corr = cov / np.outer(scale, scale)
    chol = linalg.cholesky(corr + 1e-10 * np.eye(len(scale)), lower=True)
    return lambda a: linalg.solve_triangular(
        chol, (a.T / scale).T if a.ndim == 2 else a / scale, lower=True
    )


def _projected(a: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """a (vector or columns) without its least-squares part in the span of basis' columns."""
    if basis.shape[1] == 0:
        return a
    q, _ = np.linalg.qr(basis)
    return a - q @ (q.T @ a)


def level_trend(table, r, cov, nuisance, factors=None, degree: int = SMOOTH_DEGREE) -> dict:
    """{chi2, dof, p, n} of a smooth change in time of the absolute levels in the residual r
    (N), with noise covariance cov (N, N) and the nuisance columns (N, k) fitted with it (the
    levels' offset among them); {} when the session has fewer than MIN_FEATURES + degree level
    features or they span no time. factors: the diagnosis' overdispersion per group; a level
    group whose noise it scaled up scales the trend's chi^2 down alike (the factor may stand
    for noise the model lacks)."""
    r = np.asarray(r, float)
    sel = np.isin(table.groups, LEVEL_GROUPS) & np.isfinite(r)
    n = int(sel.sum())
    if degree < 1:
        raise ValueError(f"degree: {degree} must be >= 1 (degree 0 is the levels' own offset)")
    if n < MIN_FEATURES + degree:
        return {}
    t = np.asarray(table.time, float)[sel]
    span = float(t.max() - t.min())
    if span <= 0:
        return {}
    x = 2 * (t - t.min()) / span - 1
    trend = np.polynomial.legendre.legvander(x, degree)[:, 1:]
    white = _whiten(np.asarray(cov, float)[np.ix_(sel, sel)])
    nuis = np.asarray(nuisance, float)[sel]
    nuis = nuis[:, np.abs(nuis).sum(axis=0) > 0]
    wn = white(nuis) if nuis.shape[1] else np.zeros((n, 0))
    wy = _projected(white(r[sel]), wn)
    wx = _projected(white(trend), wn)
    s = np.linalg.svd(wx, compute_uv=False)
    dof = int(np.sum(s > 1e-9 * max(float(s.max()), 1e-300)))
    if dof == 0:
        return {}
    coef, *_ = np.linalg.lstsq(wx, wy, rcond=None)
    factor = max([1.0] + [float((factors or {}).get(g, 1.0)) for g in LEVEL_GROUPS])
    chi2 = float(np.sum((wx @ coef) ** 2)) / factor
    p = float(stats.chi2.sf(chi2, dof))
    return {"chi2": chi2, "dof": dof, "p": p, "n": n, "span": span}


def trend_sentence(trend: dict, form: str) -> str:
    """The trend test's result in words, for the signature it made describable (form: the
    signature's form in time); a linear trend says what the session's span cannot tell."""
    words = (
        f"The absolute substrate levels change smoothly in time beyond their noise (a trend of "
        f"degree <= {trend['dof']} over {trend['n']} levels removes chi2 {trend['chi2']:.1f} "
        f"for {trend['dof']} dof, p = {trend['p']:.2g}), which the chi2 of all the features "
        "dilutes."
    )
    if form == "linear trend":
        # a settling slower than the session and a steady drift of z agree within its span
        words += (
            f" Over the {trend['span']:.0f} s the levels span they change linearly: this "
            "session cannot tell whether the change goes on or settles, nor at what level "
            "(a longer session, or the protocol, can)."
        )
    return words
