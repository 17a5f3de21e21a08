"""The diagnosis' noise model and its generalised least squares.

Cov(r) of the residual r = recorded - reference is white (per feature, from K sensor-noise
re-simulations at the same geometry, pooled per feature group, x (1 + 1/K) for the reference's
own noise) + J-projected thermal-drift wander (Ornstein-Uhlenbeck velocity, spread s_v,
correlation time tau: Cov(D(t), D(s)) = s_v^2 tau^2 [2 min(t,s)/tau - 1 + e^-t/tau + e^-s/tau -
e^-|t-s|/tau]) + the J-projected persistent random walk of free moves (each adds a d + b per
axis) + for background-curvature features the substrate roughness (the walk moves large images
by more than its correlation length) and the sensor noise from the noise model itself (white in
closed form, 1/f drawn as the simulator draws it: two replicas cannot tell a curvature's
variance) + for shape features the substrate's unknown surface, shared by passes over one place
(sample_realization.py). Nuisance: a constant offset per axis (J-projected). A feature group
the model describes too optimistically is scaled by its overdispersion (`group_overdispersion`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy import linalg

from afm_core.sim.config import SimConfig
from afm_core.sim.imaging import pink_noise
from afm_core.sim2real.drift_trajectory import geometry_mismatch
from afm_core.sim2real.feature_table import BOW_GROUPS, Table
from afm_core.sim2real.features import POSITION_GROUPS
from afm_core.sim2real.features_absolute import LEVEL_GROUPS, level_variance
from afm_core.sim2real.noise_floor import statistic_variance
from afm_core.sim2real.reference import ReferenceSession

# the precision of a signal the simulation reproduces without noise, relative to its size
RELATIVE_PRECISION = 1e-3

COLLINEAR = 1e-9  # |R_jj| of a unit-norm column below which it repeats the others


def drift_covariance(t: np.ndarray, sigma: float, tau: float) -> np.ndarray:
    """Cov(D(t_i), D(t_j)) of the integral of a stationary OU velocity (spread sigma, time tau)."""
    t = np.maximum(np.asarray(t, float), 0.0)
    ti, tj = t[:, None], t[None, :]
    bracket = (
        2 * np.minimum(ti, tj) / tau
        - 1
        + np.exp(-ti / tau)
        + np.exp(-tj / tau)
        - np.exp(-np.abs(ti - tj) / tau)
    )
    return sigma**2 * tau**2 * bracket


def positioning_covariance(t: np.ndarray, moves: list, slope: float, offset: float) -> np.ndarray:
    """Per-axis covariance of the persistent positioning random walk at times t."""
    if not moves:
        return np.zeros((t.size, t.size))
    move_t = np.array([m[0] for m in moves])
    var = slope * np.array([m[1] for m in moves]) + offset
    order = np.argsort(move_t)
    cum = np.concatenate([[0.0], np.cumsum(var[order])])
    accumulated = cum[np.searchsorted(move_t[order], t, side="right")]
    return np.minimum.outer(accumulated, accumulated)


@dataclass
class NoiseModel:
    white: np.ndarray  # per-feature variance
    cov: np.ndarray  # full covariance
    group_sigma: dict  # group -> pooled white sigma
    # its part shared across groups: drift wander, positioning walk
    common: np.ndarray | None = None

    def overdispersed(self, factors: dict, groups: np.ndarray) -> None:
        """Scale each group's own part by its overdispersion factor (variance). The shared
        part is physics with configured sizes (drift spread, walk slope) and one pattern over
        all groups: scaling it group by group would bend that pattern and let a constant drift
        velocity, which the wander makes, pass for missing physics."""
        scale = np.sqrt(np.array([factors.get(g, 1.0) for g in groups]))
        common = self.common if self.common is not None else np.zeros_like(self.cov)
        self.cov = (self.cov - common) * np.outer(scale, scale) + common
        self.white = self.white * scale**2


def pooled_white(
    values: np.ndarray, groups: np.ndarray, shrink: float, reference: np.ndarray | None = None
):
    """Per-feature variance from K replicas (K, N): per feature, shrunk towards its group's
    pool."""
    count = np.isfinite(values).sum(axis=0)
    k = values.shape[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.nanmean(np.where(count >= 1, values, 0.0), axis=0)
        spread = np.where(
            count >= 2, np.nansum((values - mean) ** 2, axis=0) / np.maximum(count - 1, 1), np.nan
        )
    size = np.abs(reference) if reference is not None else np.abs(mean)
    white = np.empty(values.shape[1])
    pools = {}
    for group in np.unique(groups):
        sel = groups == group
        # a feature the simulation reproduces without noise still has a finite precision: 0.1 % of
        # its size (torsion), 0.01 nm for positions (whose size is the scanner coordinate)
        floor = (
            1e-11
            if group in POSITION_GROUPS or group == "line.dir"
            else RELATIVE_PRECISION * float(np.sqrt(np.nanmean(size[sel] ** 2))) + 1e-15
        ) ** 2
        good = sel & np.isfinite(spread)
        pooled = max(
            float(np.sum(spread[good] * (count[good] - 1)) / max(np.sum(count[good] - 1), 1)),
            floor,
        )
        dof = np.maximum(count[sel] - 1, 0)
        own = np.nan_to_num(spread[sel])
        white[sel] = np.maximum((dof * own + shrink * pooled) / (dof + shrink), floor)
        pools[group] = pooled
    return white * (1.0 + 1.0 / max(k, 1)), pools


def _bow_weights(group: str, image) -> np.ndarray:
    """The pixel weights (1/m^2 per m of height, row-major) that make a background-curvature
    feature of an image (ny, nx, px, py) out of its heights: the rows of the quadratic's least
    squares (on every pixel: a bare-substrate image)."""
    ny, nx, px, py = image
    yy, xx = np.mgrid[0:ny, 0:nx]
    x = ((xx - (nx - 1) / 2) * px).ravel() * 1e6
    y = ((yy - (ny - 1) / 2) * py).ravel() * 1e6
    A = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], 1)
    column = {"raster.bow_xx": 3, "raster.bow_yy": 5, "raster.bow_xy": 4}[group]
    factor = 2.0 if group != "raster.bow_xy" else 1.0
    return np.linalg.solve(A.T @ A, A.T)[column] * factor * 1e12


def _bow_roughness_variance(table: Table, roughness: float) -> np.ndarray:
    """Variance the substrate roughness adds to background-curvature features: pixels of a
    large image are far apart compared with the roughness correlation, and the recording's
    image sits where the walk put it, so each pixel's roughness differs from the reference's
    by an independent difference (variance 2 sigma_r^2)."""
    out = np.zeros(len(table.keys))
    for i, (group, cond) in enumerate(zip(table.groups, table.conditions)):
        if group in BOW_GROUPS and "image" in cond:
            out[i] = 2 * roughness**2 * float(np.sum(_bow_weights(group, cond["image"]) ** 2))
    return out


def _bow_sensor_variance(table: Table, noise, draws: int = 400) -> np.ndarray:
    """Variance the height sensor's noise gives background-curvature features, from the noise
    model itself rather than from a few replicas (two replicas estimate a variance to within a
    factor of several, and a curvature fitted to an image of few lines picks up much of the
    coloured noise's slow wander): white noise per pixel in closed form, 1/f noise by drawing
    it as the simulator does (one sequence over the lines in acquisition order)."""
    out = np.full(len(table.keys), np.nan)
    rng = np.random.default_rng(0)
    images: dict = {}  # one image's features share the draws
    for i, (group, cond) in enumerate(zip(table.groups, table.conditions)):
        if group in BOW_GROUPS and "image" in cond:
            images.setdefault(int(table.op_index[i]), []).append(i)
    for rows in images.values():
        cond = table.conditions[rows[0]]
        ny, nx, _, _ = cond["image"]
        weights = np.array(
            [_bow_weights(table.groups[i], cond["image"]).reshape(ny, nx) for i in rows]
        )
        if cond.get("angle", 0.0) != 0.0:  # lines are columns: the sequence runs down them
            weights = weights.transpose(0, 2, 1)
        weights = weights.reshape(len(rows), -1)
        flicker = np.array(
            [weights @ pink_noise(ny * nx, noise.height_flicker_sigma, rng) for _ in range(draws)]
        )
        out[rows] = noise.height_white_sigma**2 * np.sum(weights**2, axis=1) + np.mean(
            flicker**2, axis=0
        )
    return out


def build_noise_model(
    config: SimConfig,
    table: Table,
    sensor: np.ndarray,
    J: np.ndarray,
    moves: list,
    reference: np.ndarray | None = None,
    shrink: float = 4.0,
    J_shape: np.ndarray | None = None,
    mismatch=None,
    extra_white: np.ndarray | None = None,
    extra_cov: np.ndarray | None = None,
) -> NoiseModel:
    """sensor: (K, N) features of re-simulations with only the sensor noise on (at the recorded
    geometry); J: (N, 2) sensitivity of every feature to a drift offset; moves: (time, distance)
    of the free moves. White part from `sensor`; drift wander and positioning walk analytic,
    projected through J; roughness on background-curvature features; for shape features
    (J_shape: their sensitivity to the tip-particle geometry), how far the recorded geometry may
    be from the reference's (mismatch: per feature and axis, the id of the position observation
    the drift trajectory follows there and the variance of the walk and wander since);
    extra_cov: a covariance of the features' own (the substrate's unknown surface: static, so
    shared by passes over one place, sample_realization.py)."""
    white, pools = pooled_white(sensor, table.groups, shrink, reference)
    analytic = _bow_sensor_variance(table, config.noise)
    white = np.where(
        np.isfinite(analytic), analytic * (1.0 + 1.0 / max(sensor.shape[0], 1)), white
    )
    white = white + _bow_roughness_variance(table, config.sample.roughness_sigma)
    if extra_white is not None:
        white = white + extra_white
    group_sigma = {g: math.sqrt(v) for g, v in pools.items()}
    cov = np.diag(white)
    if extra_cov is not None:
        cov = cov + extra_cov
        white = white + np.diag(extra_cov)
    if J_shape is not None and mismatch is not None:
        ids, var = mismatch
        for axis in (0, 1):
            j = J_shape[:, axis]
            use = np.flatnonzero((j != 0) & np.isfinite(var[:, axis]))
            if not use.size:
                continue
            same = ids[use, axis][:, None] == ids[use, axis][None, :]
            sd = np.sqrt(var[use, axis])
            cov[np.ix_(use, use)] += np.outer(j[use], j[use]) * np.outer(sd, sd) * same
    common = np.zeros_like(cov)
    active = np.flatnonzero(np.abs(J).sum(axis=1) > 0)
    if active.size:
        t = table.time[active]
        Ja = J[active]
        d = config.drift
        if d.enabled:
            for axis, sigma in enumerate((d.sigma_velocity_x, d.sigma_velocity_y)):
                if sigma > 0:
                    common[np.ix_(active, active)] += np.outer(
                        Ja[:, axis], Ja[:, axis]
                    ) * drift_covariance(t, sigma, d.correlation_time)
        s = config.scanner
        if s.positioning_noise_enabled:
            walk = positioning_covariance(
                t, moves, s.positioning_noise_slope, s.positioning_noise_offset
            )
            common[np.ix_(active, active)] += (Ja @ Ja.T) * walk
    return NoiseModel(white=white, cov=cov + common, group_sigma=group_sigma, common=common)


def nuisance_columns(table: Table, J: np.ndarray | None = None) -> np.ndarray:
    """A constant offset per axis (what the drift, the walk and the start position add to every
    position alike), through each feature's sensitivity J (default: its direction u); and one on
    the absolute levels (the noise of the session's first level, which they are relative to)."""
    cols = np.array(J if J is not None else table.u, float).copy()
    if J is None:
        cols[~np.isin(table.groups, POSITION_GROUPS)] = 0.0
    levels = np.isin(table.groups, LEVEL_GROUPS).astype(float)[:, None]
    return np.hstack([cols, levels])[:, np.abs(np.hstack([cols, levels])).sum(axis=0) > 0]


class Whitener:
    def __init__(self, cov: np.ndarray):
        scale = np.sqrt(np.diag(cov))
        self.scale = scale
        corr = cov / np.outer(scale, scale)
        self.chol = linalg.cholesky(corr + 1e-10 * np.eye(len(scale)), lower=True)

    def __call__(self, a: np.ndarray) -> np.ndarray:
        a = np.asarray(a, float)
        a = a / self.scale[:, None] if a.ndim == 2 else a / self.scale
        return linalg.solve_triangular(self.chol, a, lower=True)


def gls(rw: np.ndarray, xw: np.ndarray):
    """(coefficients, chi^2, covariance of the coefficients) of the whitened problem."""
    if xw.shape[1] == 0:
        return np.zeros(0), float(rw @ rw), np.zeros((0, 0))
    # columns in their parameters' units differ by twenty orders of magnitude (a drift ramp in
    # m/s^2 beside a creep factor): judged at unit norm, only a column that repeats the
    # others is left out, never one that is merely small
    norms = np.linalg.norm(xw, axis=0)
    scale = np.where(norms > 0, norms, 1.0)
    unit = xw / scale
    _, rr = np.linalg.qr(unit)
    keep = (np.abs(np.diag(rr)) > COLLINEAR) & (norms > 0)
    coef = np.zeros(xw.shape[1])
    cov = np.full((xw.shape[1], xw.shape[1]), np.nan)
    if keep.any():
        sub = unit[:, keep]
        c, *_ = np.linalg.lstsq(sub, rw, rcond=None)
        coef[keep] = c / scale[keep]
        cov[np.ix_(keep, keep)] = np.linalg.pinv(sub.T @ sub) / np.outer(scale[keep], scale[keep])
    resid = rw - xw @ coef
    return coef, float(resid @ resid), cov


def group_overdispersion(r, P, columns, cov, groups, min_size: int = 5) -> dict:
    """Per feature group: max(1, chi^2 / n) of its residual after the nuisance and the single
    candidate that fits best (GLS on the whole, chi^2 of the group's part with its own
    covariance block)."""
    white = Whitener(cov)
    rw, pw = white(r), white(P) if P.size else np.zeros((len(r), 0))
    best = (gls(rw, pw)[1], np.zeros((len(r), 0)))
    for cols in columns:
        chi2 = gls(rw, np.hstack([pw, white(cols)]))[1]
        if chi2 < best[0]:
            best = (chi2, cols)
    X = np.hstack([P, best[1]]) if P.size else best[1]
    coef, _, _ = gls(rw, white(X)) if X.shape[1] else (np.zeros(0), 0.0, None)
    e = r - (X @ coef if X.shape[1] else 0.0)
    factors = {}
    for group in np.unique(groups):
        idx = np.flatnonzero(groups == group)
        if idx.size < min_size:
            continue
        block = cov[np.ix_(idx, idx)]
        try:
            chi2 = float(e[idx] @ np.linalg.solve(block + 1e-12 * np.diag(np.diag(block)), e[idx]))
        except np.linalg.LinAlgError:
            continue
        factors[str(group)] = max(1.0, chi2 / idx.size)
    return factors


class Weighting(NamedTuple):
    """A noise model with its whitening of the whole session and of each fold's (train, test)
    blocks."""

    noise: NoiseModel
    white: Whitener
    folds: list

    @classmethod
    def of(cls, noise: NoiseModel, folds: list) -> Weighting:
        return cls(
            noise,
            Whitener(noise.cov),
            [
                (Whitener(noise.cov[np.ix_(tr, tr)]), Whitener(noise.cov[np.ix_(~tr, ~tr)]))
                for tr in folds
            ],
        )


def session_noise_model(
    sess: ReferenceSession, config: SimConfig, replicas: np.ndarray
) -> NoiseModel:
    """The noise model of a reference.ReferenceSession's features at the sensor-noise level of
    `config`, whose sensor-noise replicas are `replicas` (K, N)."""
    return build_noise_model(
        config,
        sess.table,
        replicas,
        sess.J,
        sess.moves,
        reference=sess.nominal,
        J_shape=sess.J_shape,
        mismatch=geometry_mismatch(sess.drift, sess.table.time),
        extra_white=sess.rounding_variance
        + level_variance(sess.table, config)
        + statistic_variance(sess.table),
        extra_cov=getattr(sess, "sample_cov", None),
    )
