"""Sim-to-real diagnosis: where a recording deviates from the nominal simulation, which physics
is missing, its fitted parameters, and the improvement on held-out operations.

Method (all SI):

1. **Features** of every operation (features.py), recorded and re-simulated, compared key by
   key.
2. **Reference at the recorded geometry.** Drift and the random walk of the tip position move
   the particles by up to microns over a session; a re-simulation with the model's mean drift
   would cross them elsewhere (other widths, heights), or miss them. So the recorded positions
   are turned into the drift trajectory D(t) that puts the particles where the recording saw
   them: a replay without imaging gives, per measurement, where the model's scanner truly was
   (hysteresis, creep, coupling, rotation), so D = true scanner position - the particle's
   configured position (stage A). The reference is the deterministic re-simulation (drift
   wander, positioning noise and sensor noise off) with that drift, plus the mean
   noise-induced bias of nonlinear features (from re-simulations with sensor noise). Shape
   features (widths, heights) are then compared at the recorded geometry.
   Position features are linear in the drift: replays with D shifted by 10 nm in x and in y
   give each feature's sensitivity J (2-vector), and the position residual against the
   model's own mean drift D0 is r = recorded - reference + J (D(t) - D0(t)): exactly what a
   replay with the mean drift would give, without its lost lines.
3. **Noise model** (generalised least squares): Cov(r) = white (per feature, from K sensor-noise
   re-simulations at the same geometry, pooled per feature group, x (1 + 1/K) for the
   reference's own noise) + J-projected thermal-drift wander (Ornstein-Uhlenbeck velocity,
   spread s_v, correlation time tau: Cov(D(t), D(s)) = s_v^2 tau^2 [2 min(t,s)/tau - 1 + e^-t/tau
   + e^-s/tau - e^-|t-s|/tau]) + the J-projected persistent random walk of free moves (each
   adds a d + b per axis) + for background-curvature features the substrate roughness (the
   walk moves large images by more than its correlation length) and the sensor noise from
   the noise model itself (white in closed form, 1/f drawn as the simulator draws it: two
   replicas cannot tell a curvature's variance). Nuisance: a constant offset per axis
   (J-projected).
3b. **Sensor noise first.** Only a noise term moves the noise statistics (line-offset and
   pixel-to-pixel noise of images, `raster.streak`, `raster.pixel_noise`), and every other
   feature's noise model depends on it: the white- and coloured-noise candidates are tested on
   those statistics alone (same threshold and held-out rule), fitted by re-simulation with the
   replicas' seeds (only the noise level differs); the one with the larger BIC gain is named,
   and the replicas are redrawn at its fitted level before the other candidates are judged (a
   noisier instrument's images must not pass for a scanner bow or a blunter tip). The z gain
   the particle heights show is taken out of the statistics first (a gain scales the
   roughness too), and their covariance has a part common to each group's blocks from other
   realizations of the substrate's roughness (the recording's sample is its own).
4. **Candidates** (candidates.py) = config keys; design columns = d features / d value by
   re-simulation at the same drift trajectory (closed form for drift, z gain and bow; zero on
   shape features for terms that only move the tip). Evidence per candidate: GLS chi^2
   improvement over the nuisance-only model, scaled by the residual variance factor when the
   data are noisier than modelled, tested against chi^2(p) at the Bonferroni level
   alpha / (number of candidates) (alpha = 0.05: the false "missing physics" rate on null
   recordings, from theory), ranked by BIC (chi^2 improvement - p ln N), and accepted only if
   the fit also improves chi^2 on held-out blocks (2-fold: each kind of operation split in time
   order into n_blocks chunks, alternate chunks held out, nuisance refitted on the held-out
   part). The leaders are compared re-simulated at their refined values. A second term only if
   it passes the same tests on top of the first. One candidate's form comes from the data:
   friction changed in one patch of the sample (regions.py finds the rectangle from the
   slides' torsion); its four edges count as parameters (p = 5) and the held-out check
   searches the patch again on the training blocks alone.
5. The chosen term(s) are refined by re-simulation (chord / Gauss-Newton steps), the
   uncertainty is the GLS covariance, and the updated configuration is merged and dumped.
6. **Held-out demonstration**: fit on one fold only, re-simulate the whole session with that
   fit, residuals on the other fold before and after.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time as _time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.polynomial import chebyshev
from scipy import linalg, stats

from afm_core.sim.config import SimConfig, load_config, merge
from afm_core.sim.imaging import pink_noise
from afm_core.sim2real import regions
from afm_core.sim2real.candidates import (
    Candidate,
    FrictionRegion,
    available,
    has_key,
    library,
    merge_overrides,
    select,
)
from afm_core.sim2real.features import (
    POSITION_GROUPS,
    SEGMENT,
    STREAK_MIN_LINES,
    Feature,
    FeatureExtractor,
    extract_features,
    raster_noise_statistics,
)
from afm_core.sim2real.protocol import TrajectoryDrift, deterministic, replay

ALPHA = 0.05  # family-wise false "missing physics" rate on null recordings
UNEXPLAINED_P = 1e-3  # overall chi^2 p below which a residual no term explains is not called noise
MIN_MATCHED_FRACTION = 0.7  # of the recorded features the reference simulation must reproduce
SHIFT = 10e-9  # m, drift shift of the sensitivity replays
POSITION_PRECISION = 2e-9  # m, how well a measured position pins the drift trajectory
LOST_FEATURE_RETRIES = (
    2  # quarterings of a sensitivity step that made the re-simulation lose features
)
LINEAR_REACH = 2.0  # steps: how far a term's derivative column is trusted to extrapolate
COLLINEAR = 1e-9  # |R_jj| of a unit-norm column below which it repeats the others
REGION_MIN_STEP = (
    0.05  # smallest change of a friction region's factor its design column is taken over
)
SHAPE_GROUPS = ("line.width", "line.peak", "line.asym", "raster.height", "raster.half_width")
HEIGHT_GROUPS = ("line.peak", "raster.height")
BOW_GROUPS = ("raster.bow_xx", "raster.bow_yy", "raster.bow_xy")
PUSH_GROUPS = ("push.torsion", "push.fluct")
REALIZATIONS = (
    6  # other substrates and noise draws the noise statistics' common part is taken from
)
REALIZATION_NOISE_SEED = 3000  # their first noise seed (the replicas' are 1000, 1001, ...)
NOISE_LEVELS = 5  # re-simulated levels a noise term's statistics curve is fitted through
NOISE_WIDENINGS = 3  # times that curve's range may grow towards a level beyond it
NOISE_PROFILE_POINTS = 2001  # levels its chi^2 profile is evaluated on
NOISE_ZOOM = 4.0  # sigmas either side of the level the curve is fitted again through
NOISE_GROUPS = (
    "raster.streak",
    "raster.pixel_noise",
)  # noise statistics: move only with the sensor noise


class ConfigMismatchError(ValueError):
    """The configuration does not describe the recorded session (other sample, other area)."""


class NoFeaturesError(ValueError):
    """The recording has nothing the diagnosis can compare (no scan lines, rasters or pushes)."""


# -- feature tables ---------------------------------------------------------------------------


@dataclass
class Table:
    keys: list
    groups: np.ndarray
    time: np.ndarray
    xy: np.ndarray  # (N, 2)
    u: np.ndarray  # (N, 2)
    conditions: list
    op_index: np.ndarray


def _by_key(features: list[Feature]) -> dict:
    return {f.key: f for f in features}


def _values(features: dict, keys) -> np.ndarray:
    return np.array([features[k].value if k in features else np.nan for k in keys])


def _table(keys, rec: dict) -> Table:
    fs = [rec[k] for k in keys]
    return Table(
        keys=list(keys),
        groups=np.array([f.group for f in fs]),
        time=np.array([f.time for f in fs]),
        xy=np.array([(f.x, f.y) for f in fs]),
        u=np.array([f.u for f in fs], float),
        conditions=[f.conditions for f in fs],
        op_index=np.array([k[0] for k in keys]),
    )


# -- noise model --------------------------------------------------------------------------------


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
    common: np.ndarray | None = (
        None  # its part shared across groups: drift wander, positioning walk
    )

    def overdispersed(self, factors: dict, groups: np.ndarray) -> None:
        """Scale each group's own part by its overdispersion factor (variance). The shared
        part is physics with configured sizes (drift spread, walk slope) and one pattern over
        all groups: scaling it group by group would bend that pattern and let a constant drift
        velocity, which the wander makes, pass for missing physics."""
        scale = np.sqrt(np.array([factors.get(g, 1.0) for g in groups]))
        common = self.common if self.common is not None else np.zeros_like(self.cov)
        self.cov = (self.cov - common) * np.outer(scale, scale) + common
        self.white = self.white * scale**2


def _pooled_white(
    values: np.ndarray, groups: np.ndarray, shrink: float, reference: np.ndarray | None = None
):
    """Per-feature variance from K replicas (K, N): per feature, shrunk towards its group's pool."""
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
            else 1e-3 * float(np.sqrt(np.nanmean(size[sel] ** 2))) + 1e-15
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
) -> NoiseModel:
    """sensor: (K, N) features of re-simulations with only the sensor noise on (at the recorded
    geometry); J: (N, 2) sensitivity of every feature to a drift offset; moves: (time, distance)
    of the free moves. White part from `sensor`; drift wander and positioning walk analytic,
    projected through J; roughness on background-curvature features; for shape features
    (J_shape: their sensitivity to the tip-particle geometry), how far the recorded geometry may
    be from the reference's (mismatch: per feature and axis, the id of the position observation
    the drift trajectory follows there and the variance of the walk and wander since)."""
    white, pools = _pooled_white(sensor, table.groups, shrink, reference)
    analytic = _bow_sensor_variance(table, config.noise)
    white = np.where(
        np.isfinite(analytic), analytic * (1.0 + 1.0 / max(sensor.shape[0], 1)), white
    )
    white = white + _bow_roughness_variance(table, config.sample.roughness_sigma)
    if extra_white is not None:
        white = white + extra_white
    group_sigma = {g: math.sqrt(v) for g, v in pools.items()}
    cov = np.diag(white)
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
    position alike), through each feature's sensitivity J (default: its direction u)."""
    cols = np.array(J if J is not None else table.u, float).copy()
    if J is None:
        cols[~np.isin(table.groups, POSITION_GROUPS)] = 0.0
    return cols[:, np.abs(cols).sum(axis=0) > 0]


# -- GLS ---------------------------------------------------------------------------------------


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


# -- result ------------------------------------------------------------------------------------


@dataclass
class CandidateResult:
    name: str
    words: str
    keys: list
    units: list
    size: int
    estimate: np.ndarray = None  # config values (linearised fit, all data)
    sigma: np.ndarray = None
    delta_chi2: float = 0.0  # over the nuisance-only model, scaled
    statistic_threshold: float = 0.0
    bic_gain: float = 0.0
    heldout_gain: float = 0.0  # chi^2 improvement on held-out blocks
    significant: bool = False
    accepted: bool = False
    note: str = ""


@dataclass
class Diagnosis:
    n_features: int
    groups: dict  # group -> {n, chi2, dof, p}
    overall: dict  # chi2, dof, p, variance factor
    where: list  # deviations by condition, most significant first
    change_points: list
    candidates: list  # CandidateResult, best first
    chosen: list  # names of the chosen terms ([] = no missing physics)
    parameters: dict  # key -> {value, sigma, nominal}
    overrides: dict  # nested config overrides of the fitted terms
    updated_config: SimConfig | None
    heldout: dict  # before/after on held-out operations
    missing_candidates: list
    timings: dict
    residuals: dict = field(default_factory=dict)  # arrays for plots
    message: str = ""
    drift: dict = field(default_factory=dict)  # the recorded drift trajectory (times, offsets)
    not_considered: list = field(default_factory=list)  # library terms left out by the caller

    @property
    def missing_physics(self) -> bool:
        return bool(self.chosen)

    def summary(self) -> str:
        if not self.chosen:
            fit = f"chi2 {self.overall['chi2']:.1f} for {self.overall['dof']} dof, p = {self.overall['p']:.3g}"
            if self.overall["p"] < UNEXPLAINED_P:
                among = (
                    f"of those considered ({len(self.not_considered)} library terms left out)"
                    if self.not_considered
                    else "in the library"
                )
                return (
                    f"no candidate {among} explains the residual, which exceeds the noise model ({fit}): "
                    "physics the library lacks or a noise model too optimistic (see where it deviates)"
                )
            return f"no missing physics: residuals consistent with the noise model ({fit})"
        parts = []
        for name in self.chosen:
            c = next(c for c in self.candidates if c.name == name)
            values = ", ".join(
                f"{k.split('.')[-1]} = {v['value']:.4g} +- {v['sigma']:.2g} (model {v['nominal']:.4g}"
                f"{'; ' + UNRESOLVED if unresolved(v) else ''})"
                for k, v in self.parameters.items()
                if v.get("candidate") == name
            )
            parts.append(f"{c.words}: {values}")
        return "missing physics: " + "; ".join(parts)


UNRESOLVED = "within 2 sigma of the model: this session cannot tell"


def unresolved(parameter: dict) -> bool:
    """Whether a fitted parameter of a named term is within 2 sigma of the model's value (one
    component of a drift whose other one is clear, say: left for the lab to judge, not news)."""
    return abs(parameter["value"] - parameter["nominal"]) < 2 * parameter["sigma"]


# -- the recorded drift trajectory ----------------------------------------------------------------


def nominal_drift(config: SimConfig, t: np.ndarray) -> np.ndarray:
    """(N, 2) drift offset of the model's deterministic drift (mean velocity and ramp) at t."""
    t = np.asarray(t, float)
    d = config.drift
    if not d.enabled:
        return np.zeros(t.shape + (2,))
    v = np.array([d.mean_velocity_x, d.mean_velocity_y])
    a = np.array([d.acceleration_x, d.acceleration_y])
    return v * t[..., None] + 0.5 * a * (t**2)[..., None]


class ScannerMap:
    """The model's scanner along every recorded position measurement: a replay without imaging
    gives, for each scan line and raster, where the scanner truly was at each commanded sample
    (hysteresis, creep, coupling, rotation). A particle at sample position P with drift offset
    D is measured where the true path passes P + D, so the map predicts every position
    feature for any drift (`predict`), exactly also where a re-simulation would miss the
    particle, and tells which configured particle each measurement saw and what drift offset
    it implies (`observations`: stage A of the drift trajectory)."""

    def __init__(self, ops, f_rec: dict, config: SimConfig, anchors: np.ndarray):
        by_index = {op.index: op for op in ops}
        drives: dict = {}
        self.moves = replay(ops, deterministic(config), imaging=False, drives=drives).moves
        self.anchors = anchors
        self.items: dict = {}
        self.obs = [[], []]
        feats = sorted(
            (f for f in f_rec.values() if f.group in POSITION_GROUPS), key=lambda f: f.time
        )
        last = [None, None]
        per_raster: dict = {}
        for f in feats:
            op = by_index.get(f.key[0])
            if op is None:
                continue
            axis = 0 if abs(f.u[0]) >= abs(f.u[1]) else 1
            if op.kind == "scan_line":
                indices = (op.index, op.index + 1) if f.group == "line.pos" else (op.index,)
                paths = [self._line_path(drives.get(i), f.u) for i in indices]
                if any(p is None for p in paths):
                    continue
                item = {"kind": "line", "axis": axis, "paths": paths}
            elif op.kind == "raster":
                grid = self._raster_grid(drives.get(op.index), op.request)
                if grid is None:
                    continue
                item = {"kind": "raster", "axis": axis, "grid": grid}
            else:
                continue
            # where the model's scanner truly was when it measured the particle
            true_point = self._true_at(item, np.array([f.x, f.y]))
            if f.group.startswith("raster.") and f.conditions.get("particle", "") != "":
                j = int(f.conditions["particle"])
            else:
                guess = true_point - np.array(
                    [
                        self._current(config, last, 0, f.time),
                        self._current(config, last, 1, f.time),
                    ]
                )
                j = int(np.argmin(np.hypot(*(anchors - guess).T)))
            item["anchor"] = j
            self.items[f.key] = item
            value = float(true_point[axis] - anchors[j, axis])
            if op.kind == "raster":
                # a raster's particles give one offset per axis (their mean): a drift trajectory is
                # a function of time, and particles in the same lines differ by distortion, not drift
                per_raster.setdefault((op.index, axis), []).append((f.time, value, f.key))
                continue
            self.obs[axis].append((f.time, value, [f.key]))
            last[axis] = value
        for (_, axis), values in per_raster.items():
            self.obs[axis].append(
                (
                    float(np.mean([v[0] for v in values])),
                    float(np.mean([v[1] for v in values])),
                    [v[2] for v in values],
                )
            )

    def refined(self, f_rec: dict, f_ref: dict) -> list:
        """Stage B: the observations corrected by what the imaged reference at their drift
        still differs from the recording (the imaging's own offsets: tip, creep during the
        line), through each feature's sensitivity."""
        out = [[], []]
        for axis in (0, 1):
            for t, value, keys in self.obs[axis]:
                corrections = []
                for key in keys:
                    if key in f_ref and key in self.items:
                        gain = self.sensitivity([key], [np.zeros(2)])[0, axis]
                        if abs(gain) > 0.2:
                            corrections.append((f_rec[key].value - f_ref[key].value) / gain)
                out[axis].append(
                    (t, value + (float(np.mean(corrections)) if corrections else 0.0), keys)
                )
        return out

    @staticmethod
    def _current(config, last, axis, t):
        if last[axis] is None:
            return float(nominal_drift(config, np.array([t]))[0, axis])
        return last[axis]

    @staticmethod
    def _line_path(drive_calls, u):
        """(commanded coordinate along |u| sorted, true x, true y, |u|) of a line's own drive."""
        if not drive_calls:
            return None
        _, cx, cy, tx, ty = drive_calls[-1]
        if cx.size < 3:
            return None
        axis_u = np.abs(np.asarray(u, float))
        c = cx * axis_u[0] + cy * axis_u[1]
        order = np.argsort(c)
        if np.ptp(c) == 0:
            return None
        return c[order], tx[order], ty[order], cx[order], cy[order], axis_u

    @staticmethod
    def _raster_grid(drive_calls, request):
        """Commanded and true positions of a raster's trace samples, (lines, pixels) each."""
        from afm_core.sim.instrument import LINES_PER_CHUNK

        if not drive_calls or request is None:
            return None
        n_lines, n_fast = request.lines, request.pixels_per_line
        calls = drive_calls[-int(math.ceil(n_lines / LINES_PER_CHUNK)) :]
        cx = np.concatenate([c[1] for c in calls])
        if cx.size != n_lines * 2 * n_fast or n_lines < 3 or n_fast < 3:
            return None
        arrays = [
            np.concatenate([c[k] for c in calls]).reshape(n_lines, 2 * n_fast)[:, :n_fast]
            for k in (1, 2, 3, 4)
        ]
        return arrays

    @staticmethod
    def _true_at(item, point) -> np.ndarray:
        """The true scanner position at a commanded point of the measurement."""
        if item["kind"] == "line":
            out = []
            for c, tx, ty, cx, cy, axis_u in item["paths"]:
                q = point @ axis_u
                out.append(
                    [np.interp(q, c, tx - cx) + point[0], np.interp(q, c, ty - cy) + point[1]]
                )
            return np.mean(out, axis=0)
        cx, cy, tx, ty = item["grid"]
        k, j = np.unravel_index(
            int(np.argmin((cx - point[0]) ** 2 + (cy - point[1]) ** 2)), cx.shape
        )
        return point + np.array([tx[k, j] - cx[k, j], ty[k, j] - cy[k, j]])

    @staticmethod
    def _line_predict(path, q):
        """Commanded coordinate along |u| where the line's true path passes closest to q."""
        c, tx, ty, _, _, _ = path
        tangent = np.array([tx[-1] - tx[0], ty[-1] - ty[0]])
        tangent /= max(float(np.hypot(*tangent)), 1e-30)
        f = (tx - q[0]) * tangent[0] + (ty - q[1]) * tangent[1]  # increasing along c
        slope = (f[-1] - f[0]) / (c[-1] - c[0])
        if f[0] > 0:
            return float(c[0] - f[0] / slope)
        if f[-1] < 0:
            return float(c[-1] - f[-1] / slope)
        return float(np.interp(0.0, f, c))

    @staticmethod
    def _raster_predict(grid, q):
        cx, cy, tx, ty = grid
        n_lines, n_fast = cx.shape
        k, j = np.unravel_index(int(np.argmin((tx - q[0]) ** 2 + (ty - q[1]) ** 2)), cx.shape)
        j0, j1 = max(0, j - 1), min(n_fast - 1, j + 1)
        k0, k1 = max(0, k - 1), min(n_lines - 1, k + 1)
        C = np.array(
            [
                [cx[k, j1] - cx[k, j0], cx[k1, j] - cx[k0, j]],
                [cy[k, j1] - cy[k, j0], cy[k1, j] - cy[k0, j]],
            ]
        )
        T = np.array(
            [
                [tx[k, j1] - tx[k, j0], tx[k1, j] - tx[k0, j]],
                [ty[k, j1] - ty[k, j0], ty[k1, j] - ty[k0, j]],
            ]
        )
        G = T @ np.linalg.inv(C)
        return np.array([cx[k, j], cy[k, j]]) + np.linalg.solve(
            G, q - np.array([tx[k, j], ty[k, j]])
        )

    def predict(self, key, offset) -> float:
        """The feature's predicted value (commanded coordinate, m) for a drift offset (2,)."""
        item = self.items[key]
        q = self.anchors[item["anchor"]] + np.asarray(offset, float)
        if item["kind"] == "line":
            return float(np.mean([self._line_predict(p, q) for p in item["paths"]]))
        return float(self._raster_predict(item["grid"], q)[item["axis"]])

    def predict_all(self, keys, offsets) -> np.ndarray:
        return np.array(
            [self.predict(k, d) if k in self.items else np.nan for k, d in zip(keys, offsets)]
        )

    def sensitivity(self, keys, offsets, eps: float = 1e-9) -> np.ndarray:
        """(N, 2): d feature / d drift offset (NaN rows for features without a map)."""
        base = self.predict_all(keys, offsets)
        out = []
        for axis in (0, 1):
            step = np.zeros(2)
            step[axis] = eps
            out.append((self.predict_all(keys, np.asarray(offsets) + step) - base) / eps)
        return np.stack(out, axis=1)


def drift_trajectory(
    obs, config: SimConfig, t_end: float, moves=(), step: float = 0.5
) -> TrajectoryDrift:
    """D(t) per axis, on a grid of `step` s: a cubic in time fitted to the observations (the
    smooth drift) plus the residual of the observation expected to be closest to D(t): the one
    with the least positioning-walk variance (moves) between, plus the drift's wander over the
    time between (0.1 nm/s); the model's drift where an axis has no observation."""
    grid = np.arange(0.0, max(t_end, step) + step, step)
    out = nominal_drift(config, grid)
    s = config.scanner
    if moves and s.positioning_noise_enabled:
        move_t = np.array([m[0] for m in moves])
        var = (
            s.positioning_noise_slope * np.array([m[1] for m in moves])
            + s.positioning_noise_offset
        )
        order = np.argsort(move_t)
        move_t, cum = move_t[order], np.concatenate([[0.0], np.cumsum(var[order])])
        walk = lambda t: cum[np.searchsorted(move_t, t, side="right")]  # noqa: E731
    else:
        walk = lambda t: np.zeros(np.shape(t))  # noqa: E731
    wander = (0.1e-9) ** 2
    choice = np.full((grid.size, 2), -1)
    mismatch = np.full((grid.size, 2), np.inf)
    for axis in (0, 1):
        if not obs[axis]:
            continue
        t = np.array([o[0] for o in obs[axis]])
        d = np.array([o[1] for o in obs[axis]])
        order = np.argsort(t)
        t, d = t[order], d[order]
        degree = int(min(3, max(0, np.unique(np.round(t)).size - 1)))
        scale = max(float(np.ptp(t)), 1.0)
        coef = np.polyfit((t - t[0]) / scale, d, degree) if degree > 0 else np.array([d.mean()])
        smooth = lambda x: np.polyval(coef, (np.clip(x, t[0], t[-1]) - t[0]) / scale)  # noqa: E731
        resid = d - smooth(t)
        cost = (
            np.abs(walk(grid)[:, None] - walk(t)[None, :])
            + wander * (grid[:, None] - t[None, :]) ** 2
        )
        best = np.argmin(cost, axis=1)
        out[:, axis] = smooth(grid) + resid[best]
        choice[:, axis] = np.searchsorted(np.sort(t), t[best])  # an id of the observation used
        mismatch[:, axis] = cost[np.arange(grid.size), best] + POSITION_PRECISION**2
    trajectory = TrajectoryDrift(grid, out)
    trajectory.choice, trajectory.mismatch = choice, mismatch
    return trajectory


def geometry_mismatch(trajectory: TrajectoryDrift, t: np.ndarray):
    """Per time and axis: (id of the observation the trajectory follows there, variance of how
    far the true offset may be from it)."""
    k = np.clip(
        np.round(np.asarray(t, float) / (trajectory.times[1] - trajectory.times[0])).astype(int),
        0,
        trajectory.times.size - 1,
    )
    return trajectory.choice[k], trajectory.mismatch[k]


# -- the analysis ---------------------------------------------------------------------------


def _fold_blocks(table: Table, ops, n_blocks: int) -> np.ndarray:
    """Block number per feature: per family of operations (scan lines, small rasters, large
    rasters, pushes), the operations that gave features are split in time order into n_blocks
    chunks, so every family has data in every fold."""
    family = np.array(
        [
            "push"
            if g.startswith("push")
            else "bow"
            if g in BOW_GROUPS
            else "raster"
            if g.startswith("raster")
            else "line"
            for g in table.groups
        ]
    )
    op_time = {op.index: op.start_time for op in ops}
    blocks = np.zeros(len(table.keys), int)
    for fam in np.unique(family):
        sel = family == fam
        indices = sorted(set(table.op_index[sel].tolist()), key=lambda i: op_time[i])
        chunk = {i: min(n_blocks - 1, k * n_blocks // len(indices)) for k, i in enumerate(indices)}
        blocks[sel] = [chunk[i] for i in table.op_index[sel]]
    return blocks


class _Session:
    """Everything the fits re-use: the recording, the reference, the drift trajectory, the
    scanner map, and re-simulation of a parameter set."""

    def __init__(
        self,
        ops,
        config,
        keys,
        f_rec,
        anchors,
        drift,
        J,
        bias,
        reference,
        table,
        scanner_map,
        mapped,
        noise_seeds=(),
    ):
        self.ops, self.config, self.keys = ops, config, keys
        self.base = deterministic(config)
        self.noise_seeds = list(noise_seeds)
        self._noise_runs: dict = {}
        self.noise_reference: dict = {}  # the sensor-noise overrides the reference was made with
        self.f_rec, self.anchors, self.drift, self.J = f_rec, anchors, drift, J
        self.bias, self.reference, self.table = bias, reference, table
        self.map, self.mapped = scanner_map, mapped
        self.d_rec = drift.offset(table.time)
        self.d_nom = nominal_drift(config, table.time)
        self.geo_rec = np.where(mapped, scanner_map.predict_all(keys, self.d_rec), np.nan)
        self.geo_model = scanner_map.predict_all(keys, np.where(mapped[:, None], self.d_nom, 0.0))
        self.recorded = _values(f_rec, keys)
        self.shape = np.isin(table.groups, SHAPE_GROUPS)
        self.push = np.isin(table.groups, PUSH_GROUPS)
        self.noisy = np.isin(table.groups, NOISE_GROUPS)
        self.replays = 0
        self.set_reference(reference, bias, {})
        self.r_before = self.r  # against the nominal model (a fitted noise level changes self.r)

    def set_reference(
        self, reference: np.ndarray, bias: np.ndarray, noise_overrides: dict
    ) -> None:
        """Judge the fits against another reference (replicas with a fitted noise level); the
        noise statistics against their own replicas (`noise_features`)."""
        self.noise_reference = noise_overrides
        if self.noisy.any() and self.noise_seeds:
            statistics = self.noise_features(noise_overrides)
            reference = np.where(self.noisy & np.isfinite(statistics), statistics, reference)
        self.reference, self.bias = reference, bias
        self.r = self.recorded - reference + self.shift()

    def shift(self, extra: np.ndarray | None = None) -> np.ndarray:
        """What moving the drift from the recorded trajectory to the model's (plus `extra`,
        (N, 2)) changes: the scanner map where it has the feature, J (linear) elsewhere."""
        target = self.d_nom if extra is None else self.d_nom + extra
        linear = np.einsum("ij,ij->i", self.J, self.d_rec - target)
        if not self.mapped.any():
            return linear
        at_target = (
            self.geo_model
            if extra is None
            else self.map.predict_all(self.keys, np.where(self.mapped[:, None], target, 0.0))
        )
        exact = self.geo_rec - np.where(self.mapped, at_target, np.nan)
        return np.where(self.mapped, exact, linear)

    def mapped_change(self, config) -> np.ndarray:
        """How `config`'s scanner moves the mapped position features from the model's (at the
        model's drift; 0 elsewhere), from its scanner map: no imaging, no pixel rounding."""
        offsets = np.where(self.mapped[:, None], self.d_nom, 0.0)
        self.replays += 1
        moved = ScannerMap(self.ops, self.f_rec, config, self.anchors).predict_all(
            self.keys, offsets
        )
        return np.where(self.mapped, np.nan_to_num(moved - self.geo_model), 0.0)

    def features(self, config, imaging=True) -> np.ndarray:
        self.replays += 1
        rep = replay(self.ops, config, drift=self.drift, imaging=imaging)
        return _values(_by_key(extract_features(rep.operations, self.anchors)), self.keys)

    def noise_replicas(self, overrides: dict, rasters_only: bool = False) -> np.ndarray:
        """(K, N) features of the sensor-noise re-simulations with the noise replicas' seeds and
        `overrides` (so only what the overrides change differs between two calls with the same
        `rasters_only`; rasters_only: scan lines are not imaged, which is all the noise
        statistics need, at a third of the cost, with the model's positioning noise)."""
        memo = (repr(overrides), rasters_only)
        if memo not in self._noise_runs:
            config = merge(
                self._statistics_config()
                if rasters_only
                else deterministic(self.config, sensor_noise=True),
                overrides,
            )
            self._noise_runs[memo] = np.array(
                [self._noisy_run(config, seed, rasters_only) for seed in self.noise_seeds]
            )
        return self._noise_runs[memo]

    def _statistics_config(self) -> SimConfig:
        """The config the noise statistics are re-simulated with: the sensor noise and the
        positioning noise on. Each scan line's start jitters, and on a rough, tilted substrate
        that moves the line's mean height: without it the streaks' reference was 0.033 nm where
        the recording, with 1/f noise 40 times under the model's, showed 0.036, and a 1/f level
        of 0.077 nm was fitted for it. (The other features' replicas leave it out: their
        positioning walk is analytic.)"""
        return merge(
            deterministic(self.config, sensor_noise=True),
            {
                "scanner": {
                    "positioning_noise_enabled": self.config.scanner.positioning_noise_enabled
                }
            },
        )

    def _noisy_run(self, config, noise_seed: int, rasters_only: bool) -> np.ndarray:
        self.replays += 1
        rep = replay(
            self.ops,
            config,
            noise_seed=noise_seed,
            drift=self.drift,
            imaging="rasters" if rasters_only else True,
        )
        return _values(_by_key(extract_features(rep.operations, self.anchors)), self.keys)

    def realization_offsets(self, realizations: int, overrides: dict) -> np.ndarray:
        """(realizations, N): how far the noise statistics (at the noise level `overrides`) of
        other realizations of the substrate's roughness and of the noise (the sample's seed and
        the noise seed changed) lie from their replicas' mean. The recording's roughness and
        noise are its own realizations."""
        memo = ("realizations", repr(overrides), realizations)
        if memo not in self._noise_runs:
            config = merge(self._statistics_config(), overrides)
            mean = self.noise_features(overrides)
            offsets = [
                self._noisy_run(
                    merge(config, {"seed": int(config.seed) + 1 + k}),
                    REALIZATION_NOISE_SEED + k,
                    True,
                )
                - mean
                for k in range(realizations)
            ]
            self._noise_runs[memo] = np.where(self.noisy, np.nan_to_num(np.array(offsets)), 0.0)
        return self._noise_runs[memo]

    def noise_features(self, overrides: dict) -> np.ndarray:
        """Mean noise statistics of the raster-only `noise_replicas`."""
        return np.mean(self.noise_replicas(overrides, rasters_only=True), axis=0)  # (lines: NaN)

    def noise_features_along(self, cand: Candidate, levels) -> np.ndarray:
        """(len(levels), N): the noise statistics of `noise_features` (NaN on the other features)
        with the sensor-noise term `cand` at each level.
        The simulator adds that noise to the rasters in proportion to its level, from draws that
        do not depend on it, so each seed's rasters at any level are those at 0 plus level / u
        times their change at u (within 5e-14 m of a re-simulation's, the float32 images'
        rounding): two re-simulations per seed for any number of levels, not one per level."""
        memo = ("along", cand.name)
        if memo not in self._noise_runs:
            unit = max(float(cand.nominal(self.config)[0]), 1e-10)
            self._noise_runs[memo] = (
                unit,
                [
                    [
                        self._rasters(
                            merge(self._statistics_config(), cand.overrides(self.config, [level])),
                            seed,
                        )
                        for level in (0.0, unit)
                    ]
                    for seed in self.noise_seeds
                ],
            )
        unit, runs = self._noise_runs[memo]
        out = np.empty((len(levels), len(self.keys)))
        for i, level in enumerate(levels):
            out[i] = np.mean(
                [
                    self._noise_statistics_between(at_zero, at_unit, float(level) / unit)
                    for at_zero, at_unit in runs
                ],
                axis=0,
            )
        return out

    def _rasters(self, config, noise_seed: int) -> list:
        """The raster operations of a raster-only re-simulation."""
        self.replays += 1
        rep = replay(self.ops, config, noise_seed=noise_seed, drift=self.drift, imaging="rasters")
        return [op for op in rep.operations if op.kind == "raster" and op.data is not None]

    def _noise_statistics_between(
        self, at_zero: list, at_unit: list, fraction: float
    ) -> np.ndarray:
        """(N,): the noise statistics of the rasters at_zero + fraction (at_unit - at_zero) (only
        the heights move; NaN on every other feature)."""
        features = []
        for zero, unit in zip(at_zero, at_unit):
            low, high = zero.data.height.astype(float), unit.data.height.astype(float)
            height = (low + fraction * (high - low)).astype(zero.data.height.dtype)
            features += raster_noise_statistics(
                dataclasses.replace(zero, data=dataclasses.replace(zero.data, height=height))
            )
        return _values(_by_key(features), self.keys)

    def drift_extra(self, terms) -> np.ndarray | None:
        """The drift offsets (N, 2) the drift terms at theta add to the model's."""
        extra = np.zeros((len(self.keys), 2))
        found = False
        t = self.table.time
        for (cand, theta0, _), part in terms:
            if cand.analytic == "drift_velocity":
                extra += (cand.clip(part) - theta0)[None, :] * t[:, None]
                found = True
            elif cand.analytic == "drift_ramp":
                extra += 0.5 * (cand.clip(part) - theta0)[None, :] * (t**2)[:, None]
                found = True
        return extra if found else None

    def residual(self, terms, theta) -> np.ndarray:
        """Residual (recorded - model) with the terms at theta, re-simulated where needed."""
        sizes = [t[0].size for t in terms]
        parts = np.split(np.asarray(theta, float), np.cumsum(sizes)[:-1])
        pairs = list(zip(terms, parts))
        simulated = [(t, p) for t, p in pairs if not t[0].analytic]
        drifts = [(t, p) for t, p in pairs if t[0].analytic in ("drift_velocity", "drift_ramp")]
        noises = [(t, p) for t, p in pairs if t[0].analytic == "sensor_noise"]
        linear = [
            (t, p)
            for t, p in pairs
            if t[0].analytic
            and t[0].analytic not in ("drift_velocity", "drift_ramp", "sensor_noise")
        ]
        extra = self.drift_extra(drifts)
        r = self.r.copy()
        if extra is not None:
            # drift: exactly through the scanner map (positions are where the drift puts them)
            r = self.recorded - self.reference + self.shift(extra)
            r = np.where(
                np.isfinite(r),
                r,
                self.r - sum(cols @ (cand.clip(p) - t0) for (cand, t0, cols), p in drifts),
            )
        if simulated:
            overrides = {}
            for (cand, _, _), part in simulated:
                overrides = merge_overrides(overrides, cand.overrides(self.config, part))
            imaging = any(c.imaging for (c, _, _), _ in simulated)
            sim = self.features(merge(self.base, overrides), imaging=imaging)
            resim = r + (self.reference - (sim + self.bias))
            keep = np.isfinite(resim) & ~self.noisy
            if not imaging:
                keep &= self.push
            if all(c.geometric for (c, _, _), _ in simulated):
                keep &= ~self.shape
            # a feature the re-simulation loses (a line now missing its particle): its linear prediction
            lin = r - sum(cols @ (p - theta0) for (_, theta0, cols), p in simulated)
            r = np.where(keep, resim, lin)
        for (cand, theta0, cols), part in linear:
            r = r - cols @ (cand.clip(part) - theta0)
        if noises:
            overrides = {}
            for (cand, _, _), part in noises:
                overrides = merge_overrides(overrides, cand.overrides(self.config, part))
            resim = r + self.noise_features(self.noise_reference) - self.noise_features(overrides)
            r = np.where(self.noisy & np.isfinite(resim), resim, r)
        return r


def diagnose(
    recorded_ops,
    config: SimConfig,
    *,
    sensor_replicas: int = 2,
    candidates: list | None = None,
    n_blocks: int = 6,
    refine_iterations: int = 2,
    heldout_resimulation: bool = True,
    progress: Callable[[str], None] | None = None,
    replicas: int | None = None,
) -> Diagnosis:
    """The four answers for a recorded session (a list of Operations) against `config`.
    (`replicas` is accepted for compatibility and ignored: the noise is modelled at the recorded
    geometry from `sensor_replicas` re-simulations and the analytic drift and walk terms.)"""
    say = progress or (lambda message: None)
    t_start = _time.perf_counter()
    timings = {}
    anchors = np.array([(s["x"], s["y"]) for s in config.sample.spheres], float).reshape(-1, 2)
    # one pass over the recording: its measurements become features and are let go (a
    # recording is never held whole); re-simulations need the commands only
    extractor, ops = FeatureExtractor(anchors), []
    for op in recorded_ops:
        extractor.add(op)
        ops.append(dataclasses.replace(op, data=None))
    if not ops:
        raise NoFeaturesError("the session holds no commands the simulator can re-run")
    f_rec = _by_key(extractor.finish())
    if not f_rec:
        raise NoFeaturesError(
            "no scan line, raster or push in the recording gave a feature (no particle crossed?)"
        )
    base = deterministic(config)
    t_end = (
        max(op.start_time + (op.duration if np.isfinite(op.duration) else 0.0) for op in ops) + 1.0
    )

    say("drift trajectory of the recording")
    scanner_map = ScannerMap(ops, f_rec, config, anchors)
    drift = drift_trajectory(scanner_map.obs, config, t_end, scanner_map.moves)
    say("reference re-simulation at the recorded geometry")
    nominal = replay(ops, base, drift=drift)
    f_nom = _by_key(extract_features(nominal.operations, anchors))
    # stage B: the imaged reference's own offsets corrected, once
    drift = drift_trajectory(scanner_map.refined(f_rec, f_nom), config, t_end, scanner_map.moves)
    nominal = replay(ops, base, drift=drift)
    nominal_seen: dict = {}
    f_nom = _by_key(extract_features(nominal.operations, anchors, nominal_seen))
    # a drift trajectory can put the config's particles under the recorded lines one at a time
    # (one sphere fitted, by jumps of micrometres, to where six were seen), but not into the
    # images of them all: the images must show as many particles as the recording's
    seen_rec, seen_nom = (
        sum(seen.get(k, 0) for k in extractor.particles_seen)
        for seen in (extractor.particles_seen, nominal_seen)
    )
    if min(seen_rec, seen_nom) < MIN_MATCHED_FRACTION * max(seen_rec, seen_nom):
        raise ConfigMismatchError(
            f"the configuration does not match the recording: the recording's {len(extractor.particles_seen)} images "
            f"show {seen_rec} particles, the simulation of the same images with this config {seen_nom} (each must be at "
            f"least {MIN_MATCHED_FRACTION:.0%} of the other). Check the sample (particle positions, seed) and the "
            "scanner area in the config."
        )
    matched = [k for k in f_rec if k in f_nom]
    # whether the particles are where the config says (noise statistics are there on any sample)
    on_sample = {k for k, f in f_rec.items() if f.group not in NOISE_GROUPS}
    sim_on_sample = {k for k, f in f_nom.items() if f.group not in NOISE_GROUPS}
    both = on_sample & sim_on_sample
    if len(both) < MIN_MATCHED_FRACTION * len(on_sample) or len(both) < MIN_MATCHED_FRACTION * len(
        sim_on_sample
    ):
        lost_rec = sorted({k[0] for k in on_sample if k not in f_nom})[:10]
        lost_sim = sorted({k[0] for k in sim_on_sample if k not in f_rec})[:10]
        raise ConfigMismatchError(
            f"the configuration does not match the recording: of {len(on_sample)} recorded features of the sample "
            f"only {len(both)} are reproduced by the simulation ({len(sim_on_sample)} simulated). Operations where the "
            f"recording saw a particle and the simulation did not: {lost_rec}; the reverse: {lost_sim}. "
            "Check the sample (particle positions, seed) and the scanner area in the config."
        )
    say("drift sensitivities")
    shifted = []
    for axis in (0, 1):
        delta = np.zeros(2)
        delta[axis] = SHIFT
        shifted.append(
            _by_key(
                extract_features(replay(ops, base, drift=drift.shifted(delta)).operations, anchors)
            )
        )
    say(f"noise replicas ({sensor_replicas} sensor-only)")
    sensor_cfg = deterministic(config, sensor_noise=True)
    reps_s = [
        _by_key(
            extract_features(
                replay(ops, sensor_cfg, noise_seed=1000 + k, drift=drift).operations, anchors
            )
        )
        for k in range(sensor_replicas)
    ]
    keys = [k for k in matched if all(k in r for r in reps_s) and all(k in s for s in shifted)]
    timings["reference"] = _time.perf_counter() - t_start

    table = _table(keys, f_rec)
    nom = _values(f_nom, keys)
    J = np.stack([(_values(s, keys) - nom) / SHIFT for s in shifted], axis=1)
    J[np.abs(J) < 1e-3] = 0.0
    # positions: the scanner map's sensitivity (a replay's 10 nm shift also sees the pixel grid)
    d_rec = drift.offset(table.time)
    mapped = np.array([k in scanner_map.items for k in keys]) & np.isin(
        table.groups, POSITION_GROUPS
    )
    J_map = scanner_map.sensitivity(keys, d_rec)
    # how far the imaged positions depart from the scanner map's straight response over the
    # 10 nm shifts (the simulator renders coarse images on a fixed grid: a particle's centre
    # moves in small jumps): a geometry a few nm off the recorded one scrambles that much, so
    # it is noise, pooled per group
    J_rep = J.copy()
    expected = np.where(mapped[:, None], J_map, 0.0)
    rounding = mapped | (table.groups == "line.dir")
    nonlinear = np.zeros(len(keys))
    if rounding.any():
        dev2 = np.nansum(((J_rep - expected) * SHIFT) ** 2, axis=1) / 2
        for group in np.unique(table.groups[rounding]):
            sel = rounding & (table.groups == group)
            nonlinear[sel] = float(np.nanmean(dev2[sel]))
    J[mapped] = J_map[mapped]
    # features measured at the recorded geometry: their sensitivity to it (how far the
    # reference's geometry may be off enters their noise)
    J_shape = np.where(np.isin(table.groups, SHAPE_GROUPS + ("line.dir",))[:, None], J_rep, 0.0)
    # only positions move with the drift (a shape, a difference, a torsion: at the recorded
    # geometry; their replay "sensitivity" is rounding of the sampled profiles)
    J[~np.isin(table.groups, POSITION_GROUPS)] = 0.0
    rep_s = np.array([_values(r, keys) for r in reps_s])
    bias = np.nan_to_num(np.nanmean(rep_s - nom, axis=0))
    sess = _Session(
        ops,
        config,
        keys,
        f_rec,
        anchors,
        drift,
        J,
        bias,
        nom + bias,
        table,
        scanner_map,
        mapped,
        noise_seeds=[1000 + k for k in range(sensor_replicas)],
    )
    n = len(keys)
    blocks = _fold_blocks(table, ops, n_blocks)
    folds = [blocks % 2 == 0, blocks % 2 == 1]
    cands, missing = available(config, candidates)
    m = max(1, len(cands) + 1)  # the library and the searched friction region

    # the sensor noise first: only its terms move the noise statistics, and every other
    # feature's noise model depends on it, so a noise level found here is put into the
    # replicas the rest of the diagnosis is judged against
    t0 = _time.perf_counter()
    noise_design, noise_result, noise_config = None, None, config
    noise_terms = []  # (design triple, result, curve) of every sensor-noise term
    noise_cands = [c for c in cands if c.analytic == "sensor_noise"]
    # a z gain scales the substrate's roughness, and with it the noise statistics (a gain of
    # 1.2 raised the pixel noise by 4 %, and white noise was named for it): the gain the
    # particle heights show is taken out of the noise statistics before a noise term is judged
    gain_cand = next((c for c in cands if c.analytic == "height_gain"), None)
    gain_on_noise = np.zeros(n)
    if noise_cands and not sess.noisy.any():
        missing += [
            f"{c.name} (the recording has no image with {STREAK_MIN_LINES} lines or more)"
            for c in noise_cands
        ]
    elif noise_cands:
        gain = _height_gain(sess, gain_cand, rep_s, nom, m) if gain_cand is not None else None
        if gain is not None:
            gain_on_noise = _gain_on_noise_statistics(sess, gain_cand, gain)
            sess.r = sess.r - gain_on_noise
        noise_designs = []
        for cand in noise_cands:
            say(f"sensitivity: {cand.name}")
            theta0 = cand.nominal(config)
            noise_designs.append((cand, theta0, _noise_columns(sess, cand, theta0)))
        noise_cov = _noise_statistics_covariance(sess, {}, nom, [d[2] for d in noise_designs])
        noise_terms = [_noise_term(sess, d, noise_cov, folds, m) for d in noise_designs]
    # one noise level is fitted: the term the statistics favour (white noise raises the
    # line-offset noise a little too, so a grainier instrument can also pass the coloured
    # noise's test, with less evidence)
    best = max(
        [t for t in noise_terms if t[1].accepted], key=lambda t: t[1].bic_gain, default=None
    )
    if best is not None:
        noise_design, noise_result, curve = best
        cand = noise_design[0]
        # its sigma is the statistics' spread at the fitted level, not at the model's (1/f noise
        # 7.5 x the model's: +-0.010 nm with the model's spread, 0.06 with its own), and its
        # level is read off the curve fitted again around it (1.609 nm on the curve through
        # 0 .. 5 nm, 1.58 on one through the level +-4 sigma: the truth was 1.5)
        level_residual = np.zeros(n)
        level_residual[sess.noisy] = curve.residual(sess, noise_result.estimate)[:, 0]
        level_cov = _noise_statistics_covariance(
            sess, cand.overrides(config, noise_result.estimate), nom, [], residual=level_residual
        )
        level_white = Whitener(level_cov)
        level, sigma, _ = curve.zoom(sess, cand, level_white).profile(sess, level_white)
        noise_result.estimate, noise_result.sigma = np.array([level]), np.array([sigma])
        say(f"noise replicas at the fitted {cand.name}")
        fitted = cand.overrides(config, noise_result.estimate)
        noise_config = merge(config, fitted)
        rep_s = sess.noise_replicas(fitted)
        bias = np.nan_to_num(np.nanmean(rep_s - nom, axis=0))
        sess.set_reference(nom + bias, bias, fitted)
    else:
        sess.r = sess.r + gain_on_noise  # the gain's term explains it, with the heights
    for _, res, _ in noise_terms:
        if res.accepted and res is not noise_result:
            res.accepted = False
            res.note = f"explains the noise statistics less well than {noise_design[0].name}"
    cands = [c for c in cands if c.analytic != "sensor_noise"]
    timings["noise"] = _time.perf_counter() - t0
    r = sess.r
    noise = build_noise_model(
        noise_config,
        table,
        rep_s,
        J,
        nominal.moves,
        reference=nom,
        J_shape=J_shape,
        mismatch=geometry_mismatch(drift, table.time),
        extra_white=nonlinear,
    )
    P = nuisance_columns(table, J)

    # sensitivities
    t0 = _time.perf_counter()
    design = {}
    height = np.isin(table.groups, HEIGHT_GROUPS + BOW_GROUPS)
    white_model = Whitener(noise.cov)  # for choosing trial steps (before overdispersion)
    for cand in cands:
        theta0 = cand.nominal(config)
        if cand.analytic == "drift_velocity":
            cols = J * table.time[:, None]
        elif cand.analytic == "drift_ramp":
            cols = J * 0.5 * (table.time**2)[:, None]
        elif cand.analytic == "height_gain":
            on_noise = _gain_on_noise_statistics(sess, cand, theta0 + cand.steps) / cand.steps[0]
            cols = (np.where(height, (nom + bias) / max(theta0[0], 1e-12), 0.0) + on_noise)[
                :, None
            ]
        elif cand.analytic == "bow":
            gain = config.noise.height_gain
            cols = np.where(np.isin(table.groups, ("raster.bow_xx", "raster.bow_yy")), gain, 0.0)[
                :, None
            ]
        else:
            say(f"sensitivity: {cand.name}")
            cols = _simulated_columns(sess, cand, theta0, base, nom, white_model, P)
            if isinstance(cols, str):
                missing.append(f"{cand.name} ({cols})")
                continue
        design[cand.name] = (cand, theta0, np.asarray(cols, float))
    # a term's derivative column is taken one step from the model's value; a fit many steps
    # beyond extrapolates it (a 25 ms latency, fitted from a 3 ms step, moves particles out of the
    # rasters: its linear evidence was half coupling's, and it was never re-simulated): there
    # the column becomes the secant to the fit
    pw_model = white_model(P) if P.size else np.zeros((n, 0))
    rw_model = white_model(sess.r)
    _, chi2_model, _ = gls(rw_model, pw_model)
    for name, (cand, theta0, cols) in design.items():
        if cand.analytic or cand.search_range:
            continue
        coef, chi2, _ = gls(rw_model, np.hstack([pw_model, white_model(cols)]))
        estimate = cand.clip(theta0 + coef[P.shape[1] :])
        beyond = np.abs(estimate - theta0) > LINEAR_REACH * np.asarray(cand.steps)
        if beyond.any() and chi2_model - chi2 > float(stats.chi2.isf(ALPHA / m, cand.complexity)):
            say(f"sensitivity: {cand.name} at its fit")
            design[name] = (
                cand,
                theta0,
                _columns_at_estimate(sess, cand, theta0, base, nom, cols, estimate, beyond),
            )
    region, region_columns = _friction_region(design, config, table, sess.r, d_rec, noise)
    if region is not None:
        say(f"sensitivity: {region.name}")
        cols = _simulated_columns(sess, region, region.nominal(config), base, nom)
        if isinstance(cols, str):
            missing.append(f"{region.name} ({cols})")
        else:
            design[region.name] = (region, region.nominal(config), cols)
    timings["sensitivities"] = _time.perf_counter() - t0

    # overdispersion per feature group (quasi-likelihood): a group the noise model describes
    # too optimistically (here: how the few-nm mismatch of the reference's geometry acts on
    # direction differences, which the 10 nm sensitivities only partly tell) must not pass its
    # excess to a candidate; the factors are taken after the best single candidate's fit, so a
    # real effect is not mistaken for noise
    group_factors = _group_overdispersion(
        r, P, [c[2] for c in design.values()], noise.cov, table.groups
    )
    noise_model = dataclasses.replace(
        noise
    )  # before overdispersion: a second term's test takes its own
    noise.overdispersed(group_factors, table.groups)

    # evidence
    weighting = _Weighting.of(noise, folds)
    white, fold_whiteners = weighting.white, weighting.folds
    rw, pw = white(r), white(P) if P.size else np.zeros((n, 0))
    _, chi2_0, _ = gls(rw, pw)
    dof0 = n - pw.shape[1]

    def fit(cols_list):
        cols = np.hstack(cols_list) if cols_list else np.zeros((n, 0))
        coef, chi2, cov = gls(rw, np.hstack([pw, white(cols)]) if cols.size else pw)
        return coef[P.shape[1] :], chi2, cov[P.shape[1] :, P.shape[1] :]

    singles = {name: fit([cols]) for name, (cand, theta0, cols) in design.items()}
    best_chi2 = min([c[1] for c in singles.values()] + [chi2_0])
    best_p = max([design[nm][0].size for nm, c in singles.items() if c[1] == best_chi2] + [0])
    variance_factor = max(1.0, best_chi2 / max(1, dof0 - best_p))
    results = []
    for name, (cand, theta0, cols) in design.items():
        coef, chi2, cov = singles[name]
        delta = (chi2_0 - chi2) / variance_factor
        threshold = float(stats.chi2.isf(ALPHA / m, cand.complexity))
        res = CandidateResult(
            name,
            cand.words,
            cand.keys,
            cand.units,
            cand.size,
            estimate=theta0 + coef,
            sigma=np.sqrt(np.abs(np.diag(cov)) * variance_factor),
            delta_chi2=delta,
            statistic_threshold=threshold,
            bic_gain=delta - cand.complexity * math.log(n),
        )
        res.significant = delta > threshold and _can_act(cand, theta0, theta0 + coef)
        if delta > threshold and not res.significant:
            res.note = "its fit lies outside the term's physical range (e.g. a negative wear rate)"
        if res.significant:
            # a searched region is searched again on the training blocks alone
            res.heldout_gain = _cv_gain_on(
                r, region_columns if cand is region else cols, P, folds, fold_whiteners
            )
            res.accepted = res.heldout_gain > 0
            if not res.accepted:
                res.note = "fits the session but does not predict held-out blocks"
        results.append(res)
    results.sort(key=lambda c: (not c.accepted, -c.bic_gain))
    accepted = [c for c in results if c.accepted]
    if noise_terms:  # a noise term is chosen before the others when accepted (see above)
        results += [res for _, res, _ in noise_terms]
        results.sort(key=lambda c: (not c.accepted, c is not noise_result, -c.bic_gain))

    def resim_chi2(residual):
        return gls(white(residual), pw)[1]

    # the leaders are compared by re-simulation at their refined values (the linearised
    # comparison favours whichever term is more linear when they are confounded)
    chosen, refined = [], {}
    t0 = _time.perf_counter()
    for res in accepted[:3]:
        if (
            accepted[0].bic_gain - res.bic_gain > 0.5 * max(accepted[0].bic_gain, 1.0)
            and res is not accepted[0]
        ):
            continue  # far behind the leader: not worth the re-simulations
        say(f"re-simulating the fit of {res.name}")
        theta, cov, resid = _refine(
            sess, [design[res.name]], white, P, refine_iterations, variance_factor
        )
        refined[res.name] = (theta, resid, resim_chi2(resid), _sigma(cov))
        res.note = (res.note + f" re-simulated chi2 {refined[res.name][2]:.1f}").strip()
    if refined:
        scores = {
            name: (chi2_0 - v[2]) / variance_factor - design[name][0].complexity * math.log(n)
            for name, v in refined.items()
        }
        chosen = [max(scores, key=scores.get)]
        final_theta, final_r, _, final_sigma = refined[chosen[0]]
        leader = design[chosen[0]]
        final_sigma = _reported_sigma(white, P, leader[2], final_r, final_sigma, variance_factor)
        if leader[0].size == 1 and not leader[0].analytic:
            say(f"chi2 profile of {chosen[0]}")
            final_sigma = _profile_sigma(
                sess,
                leader,
                final_theta,
                final_sigma,
                resim_chi2(final_r),
                resim_chi2,
                variance_factor,
            )
        if leader[0] is region:
            final_sigma = np.maximum(
                final_sigma, _region_jackknife_sigma(region_columns, sess.r, P, noise.cov, blocks)
            )
    timings["compare"] = _time.perf_counter() - t0

    # a second term on top of the first, tested on the re-simulated residual of the first
    checked = {}  # chosen terms -> their held-out check, made for a second term
    if chosen:
        first = design[chosen[0]]
        theta1, r1, _, _ = refined[chosen[0]]
        second, alone = _second_term(
            sess,
            design,
            results,
            first,
            theta1,
            r1,
            weighting,
            P,
            folds,
            region,
            region_columns,
            refine_iterations,
            heldout_resimulation,
            dof0,
            variance_factor,
            say,
        )
        if alone is not None:
            checked[tuple(chosen)] = alone
        if second is None:
            # the overdispersion again, under the first term: the factors above were taken with
            # the first effect's excess in the residual, and a second effect's features carried
            # it (a 1.7 x friction left x->y coupling's raster y positions 422 x overdispersed, a
            # creep twice the model's a blunter tip's line widths 880 x), so its evidence was
            # divided away. The factors only come down (a group the first term's refit leaves
            # with more excess shows that fit's own error); a term named on them must explain
            # half the held-out excess the first leaves (a 25 ms latency's pushes, released,
            # let x/y coupling take 23 % of it)
            others = [cols for name, (_, _, cols) in design.items() if name != chosen[0]]
            factors = _group_overdispersion(
                r1, np.hstack([P, first[2]]), others, noise_model.cov, table.groups
            )
            factors = {g: min(f, group_factors.get(g, f)) for g, f in factors.items()}
            if any(f < group_factors.get(g, 1.0) for g, f in factors.items()):
                released = dataclasses.replace(noise_model)
                released.overdispersed(factors, table.groups)
                second, _ = _second_term(
                    sess,
                    design,
                    results,
                    first,
                    theta1,
                    r1,
                    _Weighting.of(released, folds),
                    P,
                    folds,
                    region,
                    region_columns,
                    refine_iterations,
                    heldout_resimulation,
                    dof0,
                    None,
                    say,
                    released=True,
                )
        if second is not None:
            chosen.append(second.name)
            final_theta, final_sigma = second.theta, second.sigma
            if second.heldout is not None:
                checked[tuple(chosen)] = second.heldout

    # where: the nominal model's residual after the nuisance fit, by condition
    r_seen = sess.r_before
    coef_p, _, _ = gls(white(r_seen), pw)
    e = r_seen - P @ coef_p
    where, change_points, group_stats = _where(table, e, noise.cov, variance_factor=1.0)
    p_overall = float(stats.chi2.sf(chi2_0, dof0))

    # refine the chosen terms by re-simulation and write the config
    t0 = _time.perf_counter()
    parameters, overrides, updated = {}, {}, None
    if chosen:
        theta, sigma = final_theta, final_sigma
        offset = 0
        for name in chosen:
            cand, theta0, _ = design[name]
            part = theta[offset : offset + cand.size]
            overrides = merge_overrides(overrides, cand.overrides(config, part))
            for j, key in enumerate(cand.keys):
                parameters[key] = {
                    "value": float(theta[offset + j]),
                    "sigma": float(sigma[offset + j]),
                    "nominal": float(theta0[j]),
                    "candidate": name,
                }
            offset += cand.size
    if noise_result is not None and noise_result.accepted:
        cand, theta0, _ = noise_design
        design[cand.name] = noise_design
        chosen = [cand.name] + chosen
        overrides = merge_overrides(cand.overrides(config, noise_result.estimate), overrides)
        for j, key in enumerate(cand.keys):
            parameters[key] = {
                "value": float(noise_result.estimate[j]),
                "sigma": float(noise_result.sigma[j]),
                "nominal": float(theta0[j]),
                "candidate": cand.name,
            }
    if chosen:
        updated = merge(config, overrides)
    timings["fit"] = _time.perf_counter() - t0

    # held-out: fit on one fold, re-simulate, compare on the other
    t0 = _time.perf_counter()
    heldout = {}
    if chosen and heldout_resimulation:
        say("held-out check")
        start = np.array(
            [parameters[key]["value"] for name in chosen for key in design[name][0].keys]
        )
        heldout = checked.get(tuple(chosen)) or _heldout(
            sess, [design[c] for c in chosen], noise, P, folds[0], refine_iterations, start
        )
    elif not chosen:
        test = folds[1]
        w_te = Whitener(noise.cov[np.ix_(test, test)])
        _, chi2_te, _ = gls(w_te(r[test]), w_te(P[test]))
        heldout = {
            "chi2_before": chi2_te,
            "chi2_after": chi2_te,
            "dof": int(test.sum() - P.shape[1]),
            "reduction": 0.0,
            "excess_reduction": 0.0,
        }
    timings["heldout"] = _time.perf_counter() - t0
    timings["total"] = _time.perf_counter() - t_start
    timings["replays"] = float(sess.replays + 5 + sensor_replicas)

    return Diagnosis(
        n_features=n,
        groups=group_stats,
        overall={
            "chi2": chi2_0,
            "dof": dof0,
            "p": p_overall,
            "variance_factor": variance_factor,
            "group_factors": group_factors,
        },
        where=where,
        change_points=change_points,
        candidates=results,
        chosen=chosen,
        parameters=parameters,
        overrides=overrides,
        updated_config=updated,
        heldout=heldout,
        missing_candidates=missing,
        timings=timings,
        not_considered=_left_out(candidates),
        residuals={
            "table": table,
            "r": r_seen,
            "e": e,
            "sigma": np.sqrt(np.diag(noise.cov)),
            "folds": folds,
            "after": heldout.get("r_after"),
        },
        drift={
            "times": drift.times,
            "offsets": drift.offsets,
            "nominal": nominal_drift(config, drift.times),
        },
    )


class _Weighting(NamedTuple):
    """A noise model with its whitening of the whole session and of each fold's (train, test) blocks."""

    noise: NoiseModel
    white: Whitener
    folds: list

    @classmethod
    def of(cls, noise: NoiseModel, folds: list) -> _Weighting:
        return cls(
            noise,
            Whitener(noise.cov),
            [
                (Whitener(noise.cov[np.ix_(tr, tr)]), Whitener(noise.cov[np.ix_(~tr, ~tr)]))
                for tr in folds
            ],
        )


class _SecondTerm(NamedTuple):
    name: str
    theta: np.ndarray  # both terms' parameters
    sigma: np.ndarray
    heldout: dict | None  # the pair's held-out check


RELEASED_EXCESS_REDUCTION = (
    0.5  # of the first term's held-out excess, for a term named on released factors
)


def _second_term(
    sess: _Session,
    design: dict,
    results: list,
    first: tuple,
    theta1: np.ndarray,
    r1: np.ndarray,
    weighting: _Weighting,
    P: np.ndarray,
    folds: list,
    region,
    region_columns,
    iterations: int,
    heldout_resimulation: bool,
    dof0: int,
    variance_factor: float | None,
    say: Callable[[str], None],
    released: bool = False,
):
    """The best second term on the first's re-simulated residual r1, judged with `weighting`:
    (_SecondTerm or None, the first term's held-out check alone or None). `released`: the noise's
    group factors were taken again under the first term; then any library term may be second
    (not only those significant on their own), the first alone must misfit the held-out blocks
    (chi^2 beyond its 1 - ALPHA quantile) and the pair take RELEASED_EXCESS_REDUCTION of that
    excess."""
    n = len(r1)
    first_cand, _, first_cols = first
    noise, white, fold_whiteners = weighting
    pw = white(P) if P.size else np.zeros((n, 0))
    r1w = white(r1)
    _, chi2_1lin, _ = gls(r1w, np.hstack([pw, white(first_cols)]))
    factor1 = max(1.0, chi2_1lin / max(1, dof0 - first_cand.size))
    variance_factor = factor1 if variance_factor is None else variance_factor
    where = " (group overdispersion taken again under the first term)" if released else ""
    best = None
    for res in results:
        if (
            res.name == first_cand.name
            or res.name not in design
            or not (res.significant or released)
        ):
            continue
        cand, theta0, cols = design[res.name]
        coef_2, chi2_2, _ = gls(r1w, np.hstack([pw, white(first_cols), white(cols)]))
        delta = (chi2_1lin - chi2_2) / factor1
        if delta > res.statistic_threshold and _can_act(
            cand, theta0, theta0 + coef_2[-cand.size :]
        ):
            both = (
                (lambda train, c=first_cols: _with_region(c, region_columns(train)))
                if cand is region
                else np.hstack([first_cols, cols])
            )
            gain = _cv_gain_on(r1, both, P, folds, fold_whiteners) - _cv_gain_on(
                r1, first_cols, P, folds, fold_whiteners
            )
            score = delta - cand.complexity * math.log(n)
            if gain > 0 and (best is None or score > best[1]):
                best = (res, score, delta)
    if best is None:
        return None, None
    second_res, _, delta = best
    second = design[second_res.name]
    say(f"refining {first_cand.name}, {second_res.name}{where}")
    joint_theta, joint_cov, joint_r = _refine(
        sess,
        [first, second],
        white,
        P,
        iterations,
        variance_factor,
        start=np.concatenate([theta1, second[1]]),
    )
    # the test above is linear, on the first term's residual; a term whose joint re-simulated fit
    # lies within its threshold of the model only soaked up what the first term's refinement had
    # left. It is judged with the sigma it would be reported with (a z gain of 1.001 +- 0.0007 was
    # named on top of a hysteresis asymmetry: the model-based sigma, narrower where the features
    # scatter more than the noise model says, had passed it)
    joint_sigma = _reported_sigma(
        white, P, np.hstack([first_cols, second[2]]), joint_r, _sigma(joint_cov), variance_factor
    )
    widen = joint_sigma / np.maximum(_sigma(joint_cov), 1e-300)
    part = slice(first_cand.size, None)
    change = joint_theta[part] - second[1]
    wald = float(
        change @ np.linalg.pinv((joint_cov * np.outer(widen, widen))[part, part]) @ change
    )
    if wald <= second_res.statistic_threshold:
        second_res.note += (
            f" second to {first_cand.name} in the linear test{where}, but its joint re-simulated "
            f"fit is within its threshold of the model (Wald chi2 {wald:.1f})"
        )
        return None, None
    pair = alone = None
    if heldout_resimulation:
        # the held-out gain above is linear, on the first term's residual; re-simulated, a second
        # term can soak up what the first leaves where its columns are blind (the shapes of a
        # scanner term's particles: a sharper tip on top of a wider hysteresis loop doubled the
        # held-out residual). It must predict the held-out blocks better than the first alone.
        say(f"held-out check of {first_cand.name}, {second_res.name}")
        pair = _heldout(sess, [first, second], noise, P, folds[0], iterations, joint_theta)
        alone = _heldout(sess, [first], noise, P, folds[0], iterations, theta1)
        excess = alone["chi2_after"] - alone["dof"]
        needed = RELEASED_EXCESS_REDUCTION * max(excess, 0.0) if released else 0.0
        # released factors are for a first term that leaves the held-out blocks beyond their noise
        # (a z gain of 0.9991 was named on top of a 3.8 ms latency that already fit them)
        misfit = alone["chi2_after"] > float(stats.chi2.isf(ALPHA, alone["dof"])) or not released
        if not (misfit and alone["chi2_after"] - pair["chi2_after"] > needed):
            why = (
                "the held-out blocks fit worse with it"
                if pair["chi2_after"] >= alone["chi2_after"]
                else f"{first_cand.name} alone fits the held-out blocks within their noise"
                if not misfit
                else f"it takes too little of the held-out excess {first_cand.name} leaves"
            )
            second_res.note += (
                f" second to {first_cand.name}{where}, but {why} (chi2 {pair['chi2_after']:.1f} "
                f"with it, {alone['chi2_after']:.1f} without, {alone['dof']} dof)"
            )
            return None, None if released else alone
    if released or not second_res.accepted:
        second_res.note += (
            f" named second to {first_cand.name}{where}: delta chi2 {delta:.1f} on its residual"
        )
    second_res.accepted = True
    return _SecondTerm(
        second_res.name, joint_theta, joint_sigma, pair
    ), None if released else alone


def _can_act(cand: Candidate, theta0: np.ndarray, estimate: np.ndarray) -> bool:
    """Whether the estimate, held to the term's physical range, still changes the model (a
    tip that sharpens while sliding clips to no wear at all)."""
    return bool(np.any(cand.clip(estimate) != theta0))


def _left_out(candidates) -> list[str]:
    """Names of the library terms a caller's candidate list leaves out (None: the library)."""
    given = {c.name for c in (library() if candidates is None else candidates)}
    return [c.name for c in library() if c.name not in given]


def _group_overdispersion(r, P, columns, cov, groups, min_size: int = 5) -> dict:
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


def _refine(
    sess: _Session,
    terms,
    white,
    P,
    iterations,
    variance_factor,
    mask: np.ndarray | None = None,
    start: np.ndarray | None = None,
):
    """Gauss-Newton iterations theta += (J^T W J)^-1 J^T W r(theta), r by re-simulation, J the
    design columns (a one-parameter simulated term: the secant, below). Returns (theta, its
    covariance scaled by variance_factor, residual at theta)."""
    n = len(sess.keys)
    mask = np.ones(n, bool) if mask is None else mask
    cols = np.hstack([t[2] for t in terms])
    theta0 = np.concatenate([t[1] for t in terms])
    xw = np.hstack([white(P[mask]) if P.size else np.zeros((mask.sum(), 0)), white(cols[mask])])
    coef, _, cov = gls(white(sess.r[mask]), xw)
    cov_theta = np.nan_to_num(cov[P.shape[1] :, P.shape[1] :])
    theta = _clip_all(terms, theta0 + coef[P.shape[1] :] if start is None else start)
    linear = all(t[0].analytic in ("height_gain", "bow") for t in terms)
    residual = sess.residual(terms, theta)
    # a one-parameter simulated term: its column is the secant through the two re-simulated
    # points nearest the current estimate (the secant method), not the one taken at the model's
    # value: where the features bend, the chord iterations with that fixed column creep towards
    # the fit (a tip asymmetry of 0.27 stopped at 0.29 after two) and its slope sets sigma. So
    # is a noise level: noise statistics add in quadrature, flat near zero (1/f noise of 0.019
    # nm fitted as 0.045 along the slope at the model's 0.2)
    term = terms[0][0]
    noise_level = term.analytic == "sensor_noise"
    by_secant = len(terms) == 1 and term.size == 1 and (not term.analytic or noise_level)
    bends = by_secant and (bool(term.search_range) or noise_level)
    # (the session's residual is at the model's values, except a noise level's: the reference
    # may already carry a fitted one; a noise term always comes first)
    at_model = sess.residual(terms, theta0) if noise_level else sess.r
    points = [(theta0.copy(), at_model), (theta.copy(), residual)]
    for _ in range(0 if linear else (max(iterations, 4) if bends else iterations)):
        if by_secant:
            other = min(points[:-1], key=lambda p: float(np.abs(p[0] - theta).sum()))
            if np.all(other[0] != theta):
                secant = ((other[1] - residual) / float((theta - other[0])[0]))[:, None]
                xw = np.hstack([xw[:, : P.shape[1]], white(np.nan_to_num(secant)[mask])])
        step, _, step_cov = gls(white(residual[mask]), xw)
        theta_new = _clip_all(terms, theta + step[P.shape[1] :])
        if by_secant:  # the local slope sets the uncertainty
            cov_theta = np.nan_to_num(step_cov[P.shape[1] :, P.shape[1] :])
        if np.all(np.abs(theta_new - theta) <= 0.05 * np.maximum(_sigma(cov_theta), 1e-30)):
            break
        theta = theta_new
        residual = sess.residual(terms, theta)
        points.append((theta.copy(), residual))
    return theta, cov_theta * variance_factor, residual


def _sigma(cov: np.ndarray) -> np.ndarray:
    return np.sqrt(np.maximum(np.diag(cov), 0.0))


def _reported_sigma(white, P, cols, residual, sigma, variance_factor: float = 1.0) -> np.ndarray:
    """The fitted parameters' sigma, widened where the residual left in the features that
    inform them is larger than the noise model says (the sandwich, or Huber-White, estimate
    on the whitened problem: what the features actually scatter by, weighted by how much each
    tells the parameter). The noise model has a precision floor where the simulation has no
    noise (torsion): a friction patch's edges a few nm off leave a residual there far beyond
    that floor, and the model-based sigma was 20 times smaller than the factor's error. Never
    narrower than the model's (`sigma`, which carries `variance_factor` already)."""
    xw = white(np.nan_to_num(cols))
    ew = white(np.nan_to_num(residual))
    if P.size:
        q, _ = np.linalg.qr(white(P))
        xw = xw - q @ (q.T @ xw)
        ew = ew - q @ (q.T @ ew)
    bread = np.linalg.pinv(xw.T @ xw)
    robust = bread @ (xw.T @ (xw * (ew**2)[:, None])) @ bread
    with np.errstate(invalid="ignore", divide="ignore"):
        widen = np.sqrt(np.where(np.diag(bread) > 0, np.diag(robust) / np.diag(bread), 1.0))
    widen = np.nan_to_num(widen, nan=1.0) / math.sqrt(max(variance_factor, 1.0))
    return np.asarray(sigma, float) * np.maximum(1.0, widen)


def _profile_sigma(
    sess: _Session,
    term,
    theta: np.ndarray,
    sigma: np.ndarray,
    centre: float,
    chi2_of,
    variance_factor: float,
    target: float = 25.0,
    widen: float = 3.0,
    tries: int = 4,
) -> np.ndarray:
    """A one-parameter simulated term's sigma from the re-simulated chi^2 over a bracket that
    the sigma so far says should raise it by `target` (5 sigma either side): its curvature
    there, the bracket widened while the chi^2 rises by less than half that. The secant's
    local slope is the uncertainty only where the features follow the parameter smoothly: a
    stick-slip's slips come and go with the friction ratio, the chi^2 jumps by 5 within a
    slope-sigma of 6e-6, and 1.29954 +- 0.000007 was reported for a ratio of 1.3. `centre`:
    the chi^2 at theta. Never narrower than sigma; sigma when a bracket leaves the term's
    physical range."""
    cand = term[0]
    half = math.sqrt(target) * float(sigma[0])
    best = np.asarray(sigma, float)
    for _ in range(tries):
        sides = [theta + sign * half for sign in (-1.0, 1.0)]
        if half <= 0 or any(np.any(cand.clip(side) != side) for side in sides):
            break
        rise = 0.5 * sum(chi2_of(sess.residual([term], side)) for side in sides) - centre
        # (a bracket too flat for its sigma gives only a lower bound: widened, and tried again)
        best = np.maximum(best, half / math.sqrt(max(rise, 1.0) / max(variance_factor, 1.0)))
        if rise >= 0.5 * target:
            break
        half *= widen
    return best


def _region_jackknife_sigma(
    region_columns, r: np.ndarray, P: np.ndarray, cov: np.ndarray, blocks: np.ndarray
):
    """The friction patch's factor's spread over the session with one time block left out at a
    time, the patch searched again each time (the delete-one jackknife). The factor's own
    sigma takes the patch's edges as known, but they are found in the same torsion: an edge a
    few tens of nm off over 250 nm segments shifts the factor more than the torsion's noise
    does (0.4225 +- 0.0006 against 0.413). Zero when fewer than three searches find a patch."""
    estimates = []
    for block in np.unique(blocks):
        train = blocks != block
        column = region_columns(train)
        if column is None:
            continue
        white = Whitener(cov[np.ix_(train, train)])
        coef, _, _ = gls(white(r[train]), white(np.hstack([P[train], column[train]])))
        estimates.append(float(coef[-1]))
    if len(estimates) < 3:
        return np.zeros(1)
    return np.array([math.sqrt(len(estimates) - 1) * float(np.std(estimates))])


def _with_region(first: np.ndarray, region: np.ndarray | None) -> np.ndarray:
    """The first term's columns and the region's (none found on these training blocks: a
    zero column, so the fold counts as predicting nothing more)."""
    return np.hstack([first, np.zeros((len(first), 1)) if region is None else region])


def _cv_gain_on(r, cols, P, folds, fold_whiteners) -> float:
    """chi^2 improvement on held-out blocks (2 folds) of fitting `cols` on the other blocks.
    cols: an (N, p) array, or a function of the training mask giving one (a term whose form
    is searched from the data is searched on the training blocks only; None: nothing found,
    no gain on that fold)."""
    gain = 0.0
    for train, (w_tr, w_te) in zip(folds, fold_whiteners):
        test = ~train
        if train.sum() < 5 or test.sum() < 5:
            continue
        fold_cols = cols(train) if callable(cols) else cols
        if fold_cols is None:
            continue
        coef, _, _ = gls(w_tr(r[train]), np.hstack([w_tr(P[train]), w_tr(fold_cols[train])]))
        theta = coef[P.shape[1] :]
        pte = w_te(P[test])
        _, before, _ = gls(w_te(r[test]), pte)
        _, after, _ = gls(w_te(r[test] - fold_cols[test] @ theta), pte)
        gain += before - after
    return gain


def _feature_change(sess: _Session, cand: Candidate, base: SimConfig, nom: np.ndarray, theta):
    """(how the features the term acts on move from `nom` with its parameters at theta, by
    re-simulation; which of them the re-simulation loses)."""
    sim = sess.features(cand.apply(base, theta), imaging=cand.imaging)
    # noise statistics move with the sensor noise only: what a re-simulation without it says
    # of them is how the pixel grid falls on the roughness, not physics
    col = np.where(sess.noisy, 0.0, np.nan_to_num(sim - nom))
    lost = np.isnan(sim) & np.isfinite(nom) & ~sess.noisy
    if not cand.imaging:
        col[~sess.push] = 0.0
        lost &= sess.push
    if cand.geometric:
        col[sess.shape] = 0.0
        lost &= ~sess.shape
    return col, lost


def _columns_at_estimate(
    sess: _Session,
    cand: Candidate,
    theta0: np.ndarray,
    base: SimConfig,
    nom: np.ndarray,
    cols: np.ndarray,
    estimate: np.ndarray,
    beyond: np.ndarray,
) -> np.ndarray:
    """The derivative columns `cols`, those of the parameters marked `beyond` (their estimate
    lies beyond LINEAR_REACH steps) replaced by the secants from the model's values to
    `estimate`, parameter by parameter (a feature the re-simulation there loses keeps its
    derivative: what `_Session.residual` predicts for it too)."""
    cols = cols.copy()
    for j in np.flatnonzero(beyond):
        delta = float(estimate[j] - theta0[j])
        theta = theta0.copy()
        theta[j] = estimate[j]
        try:
            change, lost = _feature_change(sess, cand, base, nom, theta)
        except ValueError:  # the estimate is invalid for this config
            continue
        cols[:, j] = np.where(lost, cols[:, j], change / delta)
    return cols


def _simulated_columns(
    sess: _Session,
    cand: Candidate,
    theta0: np.ndarray,
    base: SimConfig,
    nom: np.ndarray,
    white: Whitener | None = None,
    P: np.ndarray | None = None,
):
    """Design columns d features / d parameter by re-simulation at the recorded geometry
    (one replay per parameter, stepped by the candidate's step), or a message saying why not.
    A candidate with a search range gets the secant to the step in it that leaves the least
    chi^2 (whitened by `white`, after the nuisance columns P; `_profile_minimum`)."""

    change = functools.partial(_feature_change, sess, cand, base, nom)

    def secant(j, step):
        """The column of parameter j by a step small enough that the re-simulation keeps every
        feature: a feature it loses (a particle shifted out of a raster) has no change to
        measure, and a zero there would claim the effect leaves it alone."""
        for attempt in range(LOST_FEATURE_RETRIES + 1):
            theta = theta0.copy()
            theta[j] += step
            col, lost = change(theta)
            if not lost.any() or attempt == LOST_FEATURE_RETRIES:
                return col / step
            step /= 4.0

    if cand.search_range and white is not None:
        # a scanner term is searched on the positions the scanner map predicts (a replay without
        # imaging, a fraction of the cost), the chosen step then re-simulated in full
        on_map = cand.geometric and sess.mapped.any()
        step = _profile_minimum(
            lambda s: (
                sess.mapped_change(cand.apply(base, theta0 + s))
                if on_map
                else change(theta0 + s)[0]
            ),
            cand.search_range,
            sess.r,
            white,
            P,
        )
        if step is None:
            return "not evaluated: the term's search range is invalid for this config"
        # a step too small to measure the bend by (a best fit at the model's value)
        step = math.copysign(max(abs(step), cand.steps[0]), step)
        return (change(theta0 + step)[0] / step)[:, None]
    cols = []
    for j in range(cand.size):
        try:
            cols.append(secant(j, cand.steps[j]))
        except ValueError as exc:  # the stepped value is invalid for this config
            return f"not evaluated: {exc}"
    return np.array(cols).T


PROFILE_NODES = 9  # Chebyshev nodes of a searched term's interpolant
PROFILE_POINTS = 201  # where the interpolated chi^2 profile is evaluated


def _profile_minimum(change_at, search_range, r, white, P) -> float | None:
    """The step in [lowest, highest] = search_range at which the features' change
    (`change_at(step)`, (N,)) best fits the residual r (least GLS chi^2 after the nuisance
    columns P), or None when fewer than three nodes are valid.

    The features bend with such a term, and its chi^2 has two basins (see
    Candidate.search_range). A few trial steps picked the wrong one: against an asymmetry error
    of 0.2, -0.1 fitted better than 0.3, and the secant from it converged on the mirror (-0.127).
    So the whole range is searched, on a Chebyshev interpolant of the change through
    PROFILE_NODES re-simulations: smooth, because a monotone feed-forward moves no reversal of
    the commands (interpolated and re-simulated chi^2 agreed within 1 % across +-0.4)."""
    lowest, highest = search_range

    def step_at(node):  # the Chebyshev variable in [-1, 1] -> the step
        return lowest + (node + 1.0) * (highest - lowest) / 2.0

    nodes = np.cos(np.pi * (np.arange(PROFILE_NODES) + 0.5) / PROFILE_NODES)  # in (-1, 1)
    valid, changes = [], []
    for node in nodes:
        try:
            changes.append(change_at(float(step_at(node))))
        except ValueError:  # this step leaves the parameter's valid range here
            continue
        valid.append(node)
    if len(valid) < 3:
        return None
    coef = chebyshev.chebfit(np.array(valid), np.array(changes), len(valid) - 1)  # (degree + 1, N)
    fine = np.linspace(min(valid), max(valid), PROFILE_POINTS)  # never extrapolated
    # the whitening is linear: whiten the coefficients, then evaluate (N, PROFILE_POINTS)
    residuals = white(r)[:, None] - white(coef.T) @ chebyshev.chebvander(fine, len(valid) - 1).T
    if P is not None and P.size:
        q, _ = np.linalg.qr(white(P))
        residuals = residuals - q @ (q.T @ residuals)
    best = int(np.argmin(np.sum(residuals**2, axis=0)))
    return float(step_at(fine[best]))


def _noise_columns(sess: _Session, cand: Candidate, theta0: np.ndarray) -> np.ndarray:
    """Design columns of a sensor-noise term at the model's noise: its noise statistics
    re-simulated with the noise replicas' seeds at each stepped value and at the model's."""
    cols = []
    for j in range(cand.size):
        theta = theta0.copy()
        theta[j] += cand.steps[j]
        sim = sess.noise_features(cand.overrides(sess.config, theta))
        cols.append(
            np.where(
                sess.noisy, np.nan_to_num((sim - sess.noise_features({})) / cand.steps[j]), 0.0
            )
        )
    return np.array(cols).T


def _noise_statistics_covariance(
    sess: _Session, level: dict, nom: np.ndarray, columns: list, residual: np.ndarray | None = None
) -> np.ndarray:
    """Covariance of the noise statistics at the noise level `level` (overrides): their
    replicas' spread, times each group's overdispersion in `residual` (the session's by
    default) after the best single fit of `columns`, plus a part common to each group's
    blocks: how far other realizations of the substrate's roughness and of the noise move the
    group's mean, beyond what the blocks' own spread puts on it.

    The replicas share the reference's sample, so they cannot show how the recording's own
    roughness differs. Scattered over the blocks (left unscaled, it pulled a coloured-noise fit
    off by a fifth) the overdispersion takes it; in common (the recording's whole substrate a
    little rougher at the pixel scale than the reference's: +1.4 % in one session with a
    three-fold friction) only the common part does, and without it white noise was named. The
    noise has a common part too: the 1/f generator scales each image's draw to its level, so a
    draw heavy in slow wander is light in fast noise in every block (at 1.5 nm the pixel noise's
    mean over 16 blocks varied by 2.9 % from draw to draw, where independent blocks give 1.3 %;
    fitted without it, 1.576 +- 0.022 nm against 1.5)."""
    replicas = sess.noise_replicas(level, rasters_only=True)
    noisy = sess.noisy
    groups = sess.table.groups[noisy]
    variance, _ = _pooled_white(replicas[:, noisy], groups, 4.0, nom[noisy])
    residual = sess.r if residual is None else residual
    factors = _group_overdispersion(
        residual[noisy],
        np.zeros((int(noisy.sum()), 0)),
        [c[noisy] for c in columns],
        np.diag(variance),
        groups,
    )
    cov = np.diag(variance * np.array([factors.get(g, 1.0) for g in groups]))
    offsets = sess.realization_offsets(REALIZATIONS, level)[:, noisy]
    for group in np.unique(groups):
        sel = groups == group
        independent = float(np.mean(variance[sel])) / int(sel.sum())
        cov[np.ix_(sel, sel)] += max(
            float(np.mean(np.mean(offsets[:, sel], axis=1) ** 2)) - independent, 0.0
        )
    return cov


class _SingleTermTest(NamedTuple):
    coef: np.ndarray
    cov: np.ndarray
    delta: float  # chi^2 gain over no term, divided by the overdispersion after the fit
    factor: float  # that overdispersion (>= 1)
    threshold: float  # the Bonferroni threshold over the library's m terms


def _single_term_test(rw: np.ndarray, xw: np.ndarray, cand: Candidate, m: int) -> _SingleTermTest:
    """One term's whitened columns fitted to a whitened residual with no nuisance columns (features
    the rest of the diagnosis does not fit: noise statistics, heights): its evidence against none."""
    _, chi2_0, _ = gls(rw, np.zeros((len(rw), 0)))
    coef, chi2, cov = gls(rw, xw)
    factor = max(
        1.0, chi2 / max(1, len(rw) - cand.size)
    )  # features noisier than their replicas say
    return _SingleTermTest(
        coef,
        cov,
        (chi2_0 - chi2) / factor,
        factor,
        float(stats.chi2.isf(ALPHA / m, cand.complexity)),
    )


def _height_gain(sess: _Session, cand: Candidate, replicas: np.ndarray, nom: np.ndarray, m: int):
    """The z gain the particle heights alone show (GLS with their replicas' spread, scaled by
    their overdispersion), or None when they show none beyond the Bonferroni threshold."""
    rows = np.isin(sess.table.groups, HEIGHT_GROUPS) & np.isfinite(sess.r)
    if rows.sum() < 2:
        return None
    theta0 = cand.nominal(sess.config)
    variance, _ = _pooled_white(replicas[:, rows], sess.table.groups[rows], 4.0, nom[rows])
    white = Whitener(np.diag(variance))
    test = _single_term_test(
        white(sess.r[rows]),
        white((sess.reference[rows] / max(theta0[0], 1e-12))[:, None]),
        cand,
        m,
    )
    return cand.clip(theta0 + test.coef) if test.delta > test.threshold else None


def _gain_on_noise_statistics(sess: _Session, cand: Candidate, gain: np.ndarray) -> np.ndarray:
    """How a z gain of `gain` changes the noise statistics (0 on other features), re-simulated
    with the noise replicas' seeds at the reference's noise level."""
    at_gain = sess.noise_features(
        merge_overrides(sess.noise_reference, cand.overrides(sess.config, gain))
    )
    return np.where(
        sess.noisy, np.nan_to_num(at_gain - sess.noise_features(sess.noise_reference)), 0.0
    )


def _noise_term(sess: _Session, design: tuple, statistics_cov: np.ndarray, folds: list, m: int):
    """Evidence and fit of a sensor-noise term (its (candidate, nominal, columns) design triple)
    on the noise statistics alone (no other term moves them): GLS with their covariance, the
    Bonferroni threshold, held-out blocks, and the level from its chi^2 profile. Returns the
    design triple, its CandidateResult (estimate, sigma and evidence: the profile's) and its
    _NoiseCurve (None when it is not accepted)."""
    noisy = sess.noisy
    cand, theta0, cols = design
    white = Whitener(statistics_cov)
    none = np.zeros((int(noisy.sum()), 0))
    r = sess.r[noisy]
    test = _single_term_test(white(r), white(cols[noisy]), cand, m)
    factor = test.factor
    res = CandidateResult(
        cand.name,
        cand.words,
        cand.keys,
        cand.units,
        cand.size,
        estimate=theta0 + test.coef,
        sigma=np.sqrt(np.abs(np.diag(test.cov)) * factor),
        delta_chi2=test.delta,
        statistic_threshold=test.threshold,
        bic_gain=test.delta - cand.complexity * math.log(max(len(r), 2)),
    )
    res.significant = test.delta > res.statistic_threshold
    if res.significant:
        sub_folds = [f[noisy] for f in folds]
        whiteners = [
            (Whitener(statistics_cov[np.ix_(f, f)]), Whitener(statistics_cov[np.ix_(~f, ~f)]))
            for f in sub_folds
        ]
        res.heldout_gain = _cv_gain_on(r, cols[noisy], none, sub_folds, whiteners)
        res.accepted = res.heldout_gain > 0
        if not res.accepted:
            res.note = "fits the session but does not predict held-out blocks"
    if not res.accepted:
        return design, res, None
    # the evidence is the fit's, not the derivative's: noise levels add in quadrature, so a line
    # through the model's value misses a large change (1/f noise 7.5 x the model's fitted to
    # chi^2 85 along it, 6.5 at its value) and a white noise, straighter there, passed for it
    curve, (level, sigma, chi2_level) = _NoiseCurve.fit(
        sess, cand, float(cand.clip(res.estimate)[0]), white
    )
    res.estimate, res.sigma = np.array([level]), np.array([sigma])
    res.delta_chi2 = (float(np.sum(white(r) ** 2)) - chi2_level) / max(
        1.0, chi2_level / max(1, len(r) - cand.size)
    )
    res.bic_gain = res.delta_chi2 - cand.complexity * math.log(max(len(r), 2))
    return design, res, curve


class _NoiseCurve(NamedTuple):
    """The noise statistics as smooth functions of a noise term's level s: per feature,
    statistic^2 = a + b (s / high)^2, fitted through re-simulations (with the noise replicas'
    seeds) at NOISE_LEVELS levels spread evenly in variance over [low, high]. The statistics
    are robust spreads of noises that add in quadrature: over 0 .. 2.4 nm of 1/f noise the
    curve passes within 0.2 of the replicas' sigma of the re-simulations; over 0 .. 5 nm the
    pixel noise bends 1.7 % away from it, hence `zoom`. The recording is compared with the
    curve, not with re-simulations one by one: their jitter had secant iterations wander
    between 0.03 and 0.06 nm around a flat minimum at 0.005."""

    low: float
    high: float
    a: np.ndarray
    b: np.ndarray

    @classmethod
    def through(cls, sess: _Session, cand: Candidate, low: float, high: float) -> _NoiseCurve:
        levels = np.sqrt(np.linspace(low**2, high**2, NOISE_LEVELS))
        stats = sess.noise_features_along(cand, levels)[:, sess.noisy]
        # per feature, least squares in the squares' relative error (the lowest levels as
        # closely as the highest)
        x = np.stack([np.ones(NOISE_LEVELS), (levels / high) ** 2], axis=1)
        y = np.nan_to_num(stats) ** 2
        w = 1.0 / np.maximum(y, 1e-300) ** 2
        normal = np.einsum("ki,kj,kn->nij", x, x, w)
        a, b = np.linalg.solve(normal, np.einsum("ki,kn->ni", x, w * y)[..., None])[..., 0].T
        return cls(low, high, a, b)

    @classmethod
    def fit(cls, sess: _Session, cand: Candidate, around: float, white: Whitener):
        """Through 0 .. 1.5 x max(the model's level, `around`), widened while the chi^2 profile's
        minimum (whitened by `white`) lies beyond. Returns the curve and that profile."""
        high = 1.5 * max(float(cand.nominal(sess.config)[0]), around, 1e-15)
        for _ in range(NOISE_WIDENINGS + 1):
            curve = cls.through(sess, cand, 0.0, high)
            profile = curve.profile(sess, white)
            if profile[0] <= high:
                break
            high = 1.5 * profile[0]
        return curve, profile

    def zoom(self, sess: _Session, cand: Candidate, white: Whitener) -> _NoiseCurve:
        """The curve again through NOISE_ZOOM sigmas either side of its profile's minimum."""
        level, sigma, _ = self.profile(sess, white)
        half = max(NOISE_ZOOM * sigma, 1e-3 * level, 1e-15)
        return self.through(sess, cand, max(0.0, level - half), level + half)

    def levels(self) -> np.ndarray:
        """Where the profile is evaluated: from 0 to 4 x the top over a curve from 0, one width
        either side of a zoomed one."""
        width = self.high - self.low
        low, high = (
            (0.0, 4.0 * self.high)
            if self.low == 0.0
            else (max(0.0, self.low - width), self.high + width)
        )
        return np.linspace(low, high, NOISE_PROFILE_POINTS)

    def statistics(self, levels) -> np.ndarray:
        """(len(levels), noisy features)."""
        levels = np.atleast_1d(np.asarray(levels, float))
        return np.sqrt(
            np.maximum(self.a[None, :] + self.b[None, :] * (levels[:, None] / self.high) ** 2, 0.0)
        )

    def residual(self, sess: _Session, levels) -> np.ndarray:
        """(noisy features, len(levels)): the recording's statistics (less what a fitted z gain
        adds to them) minus the curve's."""
        target = (sess.r + sess.reference)[sess.noisy]
        return target[:, None] - self.statistics(levels).T

    def profile(self, sess: _Session, white: Whitener):
        """(level, sigma, chi^2 at the level) on levels(). sigma: half the width of the levels
        whose chi^2 lies within the overdispersion left at the minimum of it (near 0 the
        interval is lopsided; half its width is what one number can say)."""
        grid = self.levels()
        chi2 = np.sum(white(self.residual(sess, grid)) ** 2, axis=0)
        best = int(np.argmin(chi2))
        factor = max(1.0, chi2[best] / max(1, int(sess.noisy.sum()) - 1))
        outside = np.flatnonzero(chi2 > chi2[best] + factor)
        low = grid[outside[outside < best].max() + 1] if (outside < best).any() else grid[0]
        high = grid[outside[outside > best].min() - 1] if (outside > best).any() else grid[-1]
        return float(grid[best]), 0.5 * float(high - low), float(chi2[best])


def _friction_region(
    design: dict,
    config: SimConfig,
    table: Table,
    r: np.ndarray,
    d_rec: np.ndarray,
    noise: NoiseModel,
):
    """The friction-region candidate at the rectangle where the slides' torsion residual
    follows the friction's effect best (sim2real.regions: searched between segment centres,
    then its edges moved continuously), or None; and the function the held-out check uses to
    search the region again on the training blocks alone (training mask -> column or None),
    with the linear column effect x overlap (the torsion is linear in mu: the global
    friction's sensitivity gives the effect)."""
    if "friction" not in design or not has_key(config, "contact.friction_regions"):
        return None, lambda train: None
    _, mu, friction_cols = design["friction"]
    torsion = table.groups == "push.torsion"
    effect = np.where(torsion, mu[0] * friction_cols[:, 0], 0.0)  # d torsion / d (region's scale)
    points = regions.sample_points(table.xy, d_rec)
    axes = [c.get("axis", "x") for c in table.conditions]
    lengths = np.array([c.get("segment_length", SEGMENT) for c in table.conditions])

    def search(mask):
        sel = np.flatnonzero(torsion & mask)
        found = regions.best_region(
            points[sel],
            effect[sel],
            r[sel],
            noise.cov[np.ix_(sel, sel)],
            slides=table.op_index[sel],
        )
        if found is None:
            return None
        return regions.refine_region(
            points[sel],
            [axes[i] for i in sel],
            lengths[sel],
            effect[sel],
            r[sel],
            noise.cov[np.ix_(sel, sel)],
            found[0],
        )

    def fold_column(train):
        found = search(train)
        return (
            None
            if found is None
            else (effect * regions.overlap(points, axes, lengths, found[0]))[:, None]
        )

    found = search(np.ones(len(r), bool))
    if found is None:
        return None, fold_column
    bounds, _, change = found
    # the design column is the secant to the factor the torsion says (regions' doc)
    step = change if abs(change) >= REGION_MIN_STEP else math.copysign(REGION_MIN_STEP, change)
    return FrictionRegion.at(bounds, step=max(step, -0.95)), fold_column


def _clip_all(terms, theta):
    sizes = [t[0].size for t in terms]
    return np.concatenate(
        [
            cand.clip(part)
            for (cand, _, _), part in zip(terms, np.split(theta, np.cumsum(sizes)[:-1]))
        ]
    )


def _heldout(sess: _Session, terms, noise, P, train, iterations, start):
    test = ~train
    w_tr = Whitener(noise.cov[np.ix_(train, train)])
    # fit on the training blocks only (their own whitening), re-simulate the whole session
    theta, _, r_after = _refine(sess, terms, w_tr, P, iterations, 1.0, mask=train, start=start)
    w_te = Whitener(noise.cov[np.ix_(test, test)])
    pte = w_te(P[test])
    _, before, _ = gls(w_te(sess.r_before[test]), pte)
    _, after, _ = gls(w_te(r_after[test]), pte)
    dof = int(test.sum() - P.shape[1])
    excess_before = before - dof
    return {
        "chi2_before": before,
        "chi2_after": after,
        "dof": dof,
        "reduction": 1 - after / before if before > 0 else 0.0,
        "excess_reduction": (before - after) / excess_before
        if excess_before > 0
        else float("nan"),
        "train_theta": theta.tolist(),
        "r_after": r_after,
        "test": test,
    }


# -- where ----------------------------------------------------------------------------------------


def _bins(table: Table):
    """(label, mask) of condition bins per group."""
    out = []
    conds = table.conditions
    for group in np.unique(table.groups):
        g = table.groups == group
        out.append((f"{group}", g))

        def add(label, values, edges=None):
            values = np.array(values, dtype=object)
            if edges is not None:
                numeric = np.array([float(v) if v is not None else np.nan for v in values])
                for lo, hi in zip(edges[:-1], edges[1:]):
                    sel = g & (numeric >= lo) & (numeric < hi)
                    if sel.sum() >= 3:
                        out.append((f"{group} | {label} in [{lo:g}, {hi:g})", sel))
            else:
                for v in sorted({str(x) for x in values[g]}):
                    sel = g & (values.astype(str) == v)
                    if 3 <= sel.sum() < g.sum():
                        out.append((f"{group} | {label} = {v}", sel))

        add("axis", [c.get("axis") for c in conds])
        add("scan direction", [c.get("scan_sign") for c in conds])
        add("dwell after move (s)", [c.get("dwell", np.nan) for c in conds], [0, 1, 5, 20, np.inf])
        add(
            "last move (um)",
            [c.get("move_distance", np.nan) * 1e6 for c in conds],
            [0, 1, 2, np.inf],
        )
        add(
            "contact slid before (um)",
            [c.get("contact_slid", np.nan) * 1e6 for c in conds],
            [0, 0.5, 4, 8, np.inf],
        )
        add("raster angle", [c.get("angle") for c in conds])
        add("frame up", [c.get("up") for c in conds])
        add("particle", [c.get("particle") for c in conds])
        add(
            "time (s)",
            table.time,
            np.round(np.quantile(table.time[g], [0, 0.25, 0.5, 0.75, 1]) + [0, 0, 0, 0, 1e-6], 1)
            if g.any()
            else None,
        )
        add(
            "x (um)",
            table.xy[:, 0] * 1e6,
            np.round(np.quantile(table.xy[g, 0] * 1e6, [0, 0.33, 0.67, 1]) + [0, 0, 0, 1e-9], 3)
            if g.any()
            else None,
        )
        add(
            "y (um)",
            table.xy[:, 1] * 1e6,
            np.round(np.quantile(table.xy[g, 1] * 1e6, [0, 0.33, 0.67, 1]) + [0, 0, 0, 1e-9], 3)
            if g.any()
            else None,
        )
    return out


def _where(table: Table, e: np.ndarray, cov: np.ndarray, variance_factor: float = 1.0):
    bins = _bins(table)
    rows = []
    group_stats = {}
    for label, sel in bins:
        idx = np.flatnonzero(sel)
        c = cov[np.ix_(idx, idx)] * variance_factor
        mean = float(e[idx].mean())
        sd = float(math.sqrt(max(np.ones(idx.size) @ c @ np.ones(idx.size), 1e-300)) / idx.size)
        try:
            chi2 = float(e[idx] @ np.linalg.solve(c, e[idx]))
        except np.linalg.LinAlgError:
            chi2 = float("nan")
        row = {
            "where": label,
            "n": int(idx.size),
            "mean": mean,
            "sd": sd,
            "z": mean / sd,
            "chi2": chi2,
            "p_chi2": float(stats.chi2.sf(chi2, idx.size)),
            "p_mean": float(2 * stats.norm.sf(abs(mean / sd))),
        }
        rows.append(row)
        if "|" not in label:
            group_stats[label] = {
                "n": int(idx.size),
                "chi2": chi2,
                "dof": int(idx.size),
                "p": row["p_chi2"],
                "rms_residual": float(np.sqrt(np.mean(e[idx] ** 2))),
                "noise_sigma": float(np.sqrt(np.mean(np.diag(c)))),
            }
    m = max(1, len(rows))
    for row in rows:
        row["p_mean_bonferroni"] = min(1.0, row["p_mean"] * m)
        row["p_chi2_bonferroni"] = min(1.0, row["p_chi2"] * m)
    rows.sort(key=lambda row: min(row["p_mean"], row["p_chi2"]))
    change = []
    for group in np.unique(table.groups):
        idx = np.flatnonzero(table.groups == group)
        if idx.size < 8:
            continue
        idx = idx[np.argsort(table.time[idx])]
        z = e[idx] / np.sqrt(np.diag(cov)[idx])
        z = z - z.mean()
        cusum = np.cumsum(z) / math.sqrt(idx.size)
        k = int(np.argmax(np.abs(cusum[:-1])))
        stat = float(abs(cusum[k]))
        # Kolmogorov limit of the Brownian bridge maximum
        p = float(
            min(
                1.0,
                2
                * sum((-1) ** (j - 1) * math.exp(-2 * j * j * stat * stat) for j in range(1, 50)),
            )
        )
        change.append(
            {
                "group": group,
                "time": float(table.time[idx[k]]),
                "statistic": stat,
                "p": p,
                "mean_before": float(e[idx[: k + 1]].mean()),
                "mean_after": float(e[idx[k + 1 :]].mean()),
            }
        )
    change.sort(key=lambda c: c["p"])
    return rows, change, group_stats


# -- entry point ------------------------------------------------------------------------------------


def run_sim2real(
    recording_path,
    config_path,
    report_dir,
    progress=None,
    missing_data: str = "error",
    effects=None,
    **kw,
) -> Diagnosis:
    """Read a recording (MCAP), diagnose it against the simulator config, write the report and
    the updated config into report_dir. Raises ValueError subclasses with clear messages.
    missing_data="skip" leaves out commands whose measurement is not in the file (a snapshot
    of a recording still being written ends mid-operation); "error" refuses them. `effects`:
    names of library terms to consider (candidates.select), None or empty: all of them."""
    from afm_core.sim2real.report import write_report

    recording_path = Path(recording_path)
    if not recording_path.is_file():
        raise FileNotFoundError(f"recording {str(recording_path)!r} does not exist")
    candidates = select(effects)  # before the reading: a misspelt effect costs nothing
    config = load_config(config_path) if config_path is not None else load_config()
    try:
        from afm_core.sim2real.session import read_operations
    except ImportError as exc:  # pragma: no cover - the session reader is part of the package
        raise RuntimeError(
            f"the recording reader (afm_core.sim2real.session) is not available: {exc}"
        ) from exc
    with read_operations(recording_path, missing_data=missing_data) as operations:
        try:
            diagnosis = diagnose(
                operations, config, progress=progress, candidates=candidates, **kw
            )
        except NoFeaturesError as exc:
            raise NoFeaturesError(f"recording {str(recording_path)!r}: {exc}") from exc
    write_report(diagnosis, Path(report_dir), config=config, recording=str(recording_path))
    return diagnosis
