"""Design columns of the candidate terms (candidates.py: each a set of config keys).

A term's columns are d features / d value by re-simulation at the same drift trajectory
(closed form for drift, z gain and bow; zero on shape features and absolute substrate levels
for terms that only move the tip; the noise statistics move with the sensor noise only). A
term whose linear fit lies many steps beyond the model's value gets the secant to that fit
instead (`_columns_at_estimate`); a term whose features bend with it (a search range) the
secant to the step the whole range searched says (`_profile_minimum`). The friction-region
candidate (region_candidate.py) is added at the patch the torsion residual shows.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from numpy.polynomial import chebyshev
from scipy import stats

from afm_core.sim.config import SimConfig
from afm_core.sim2real.candidates import Candidate, FrictionRegion
from afm_core.sim2real.evidence import ALPHA
from afm_core.sim2real.feature_table import BOW_GROUPS, HEIGHT_GROUPS
from afm_core.sim2real.noise_model import NoiseModel, Whitener, gls
from afm_core.sim2real.noise_term import gain_on_noise_statistics
from afm_core.sim2real.reference import ReferenceSession
from afm_core.sim2real.region_candidate import friction_region

# quarterings of a sensitivity step that made the re-simulation lose features
LOST_FEATURE_RETRIES = 2
LINEAR_REACH = 2.0  # steps: how far a term's derivative column is trusted to extrapolate
PROFILE_NODES = 9  # Chebyshev nodes of a searched term's interpolant
PROFILE_POINTS = 201  # where the interpolated chi^2 profile is evaluated


def _feature_change(
    sess: ReferenceSession, cand: Candidate, base: SimConfig, nom: np.ndarray, theta
):
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
        col[sess.at_geometry] = 0.0
        lost &= ~sess.at_geometry
    return col, lost


def _columns_at_estimate(
    sess: ReferenceSession,
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
    derivative: what `ReferenceSession.residual` predicts for it too)."""
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
    sess: ReferenceSession,
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


class Design(NamedTuple):
    """The candidate terms' design columns."""

    terms: dict  # name -> (candidate, nominal values, columns (N, p))
    region: FrictionRegion | None  # the friction-region candidate at the patch found, if any
    region_columns: Callable  # training mask -> its column with the patch searched there


def design_columns(
    sess: ReferenceSession,
    cands: list,
    noise: NoiseModel,
    P: np.ndarray,
    m: int,
    missing: list,
    say: Callable[[str], None],
) -> Design:
    """The design of `cands` and of the friction-region candidate; a term whose columns cannot
    be evaluated is named in `missing` instead."""
    config, table = sess.config, sess.table
    design = {}
    white_model = Whitener(noise.cov)  # for choosing trial steps (before overdispersion)
    for cand in cands:
        theta0 = cand.nominal(config)
        if cand.analytic in ("drift_velocity", "drift_ramp", "height_gain", "bow"):
            cols = _closed_form_columns(sess, cand, theta0)
        else:
            say(f"sensitivity: {cand.name}")
            cols = _simulated_columns(sess, cand, theta0, sess.base, sess.nominal, white_model, P)
            if isinstance(cols, str):
                missing.append(f"{cand.name} ({cols})")
                continue
        design[cand.name] = (cand, theta0, np.asarray(cols, float))
    _secants_at_estimates(sess, design, white_model, P, m, say)
    region, region_columns = friction_region(design, config, table, sess.r, sess.d_rec, noise)
    if region is not None:
        say(f"sensitivity: {region.name}")
        cols = _simulated_columns(sess, region, region.nominal(config), sess.base, sess.nominal)
        if isinstance(cols, str):
            missing.append(f"{region.name} ({cols})")
        else:
            design[region.name] = (region, region.nominal(config), cols)
    return Design(design, region, region_columns)


def _closed_form_columns(sess: ReferenceSession, cand: Candidate, theta0: np.ndarray):
    """The columns of a drift velocity or ramp (through J), a z gain (the heights and the
    noise statistics it scales) or a scanner bow."""
    table = sess.table
    if cand.analytic == "drift_velocity":
        return sess.J * table.time[:, None]
    if cand.analytic == "drift_ramp":
        return sess.J * 0.5 * (table.time**2)[:, None]
    if cand.analytic == "height_gain":
        height = np.isin(table.groups, HEIGHT_GROUPS + BOW_GROUPS)
        on_noise = gain_on_noise_statistics(sess, cand, theta0 + cand.steps) / cand.steps[0]
        return (
            np.where(height, (sess.nominal + sess.bias) / max(theta0[0], 1e-12), 0.0) + on_noise
        )[:, None]
    gain = sess.config.noise.height_gain
    return np.where(np.isin(table.groups, ("raster.bow_xx", "raster.bow_yy")), gain, 0.0)[:, None]


def _secants_at_estimates(sess, design: dict, white_model: Whitener, P, m: int, say) -> None:
    """A term's derivative column is taken one step from the model's value; a fit many steps
    beyond extrapolates it (a 25 ms latency, fitted from a 3 ms step, moves particles out of
    the rasters: its linear evidence was half coupling's, and it was never re-simulated):
    there the column becomes the secant to the fit (in `design`, in place)."""
    n = len(sess.keys)
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
                _columns_at_estimate(
                    sess, cand, theta0, sess.base, sess.nominal, cols, estimate, beyond
                ),
            )
