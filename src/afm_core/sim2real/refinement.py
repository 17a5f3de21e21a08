"""The chosen terms refined by re-simulation (chord / Gauss-Newton steps; the secant for a
one-parameter simulated term), with their uncertainty: the GLS covariance, widened to what the
informative features scatter by (sandwich), and for a one-parameter simulated term to its
re-simulated chi^2 profile. The leading candidates are compared re-simulated at their refined
values: the linearised comparison favours whichever term is more linear when they are
confounded."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from afm_core.sim2real.design_columns import Design
from afm_core.sim2real.evidence import Evidence
from afm_core.sim2real.noise_model import gls
from afm_core.sim2real.reference import ReferenceSession
from afm_core.sim2real.region_candidate import region_jackknife_sigma


def refine(
    sess: ReferenceSession,
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
        if np.all(np.abs(theta_new - theta) <= 0.05 * np.maximum(sigma_of(cov_theta), 1e-30)):
            break
        theta = theta_new
        residual = sess.residual(terms, theta)
        points.append((theta.copy(), residual))
    return theta, cov_theta * variance_factor, residual


def _clip_all(terms, theta):
    sizes = [t[0].size for t in terms]
    return np.concatenate(
        [
            cand.clip(part)
            for (cand, _, _), part in zip(terms, np.split(theta, np.cumsum(sizes)[:-1]))
        ]
    )


def sigma_of(cov: np.ndarray) -> np.ndarray:
    return np.sqrt(np.maximum(np.diag(cov), 0.0))


def reported_sigma(white, P, cols, residual, sigma, variance_factor: float = 1.0) -> np.ndarray:
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


def profile_sigma(
    sess: ReferenceSession,
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


class Leader(NamedTuple):
    """The best single term, re-simulated at its refined values."""

    name: str
    theta: np.ndarray
    residual: np.ndarray  # re-simulated at theta
    sigma: np.ndarray  # as reported


def compare_leaders(
    sess: ReferenceSession,
    design: Design,
    evidence: Evidence,
    iterations: int,
    blocks: np.ndarray,
    say: Callable[[str], None],
) -> Leader | None:
    """The accepted terms near the best (up to three) refined by re-simulation and compared by
    their re-simulated BIC gain; the winner's reported sigma. None when none was accepted."""
    white, P, pw = evidence.weighting.white, evidence.P, evidence.pw
    terms, region, region_columns = design
    chi2_0, variance_factor = evidence.chi2_0, evidence.variance_factor
    accepted = evidence.accepted
    n = len(sess.keys)

    def resim_chi2(residual):
        return gls(white(residual), pw)[1]

    refined = {}
    for res in accepted[:3]:
        if (
            accepted[0].bic_gain - res.bic_gain > 0.5 * max(accepted[0].bic_gain, 1.0)
            and res is not accepted[0]
        ):
            continue  # far behind the leader: not worth the re-simulations
        say(f"re-simulating the fit of {res.name}")
        theta, cov, resid = refine(sess, [terms[res.name]], white, P, iterations, variance_factor)
        refined[res.name] = (theta, resid, resim_chi2(resid), sigma_of(cov))
        res.note = (res.note + f" re-simulated chi2 {refined[res.name][2]:.1f}").strip()
    if not refined:
        return None
    scores = {
        name: (chi2_0 - v[2]) / variance_factor - terms[name][0].complexity * math.log(n)
        for name, v in refined.items()
    }
    name = max(scores, key=scores.get)
    theta, residual, _, sigma = refined[name]
    leader = terms[name]
    sigma = reported_sigma(white, P, leader[2], residual, sigma, variance_factor)
    if leader[0].size == 1 and not leader[0].analytic:
        say(f"chi2 profile of {name}")
        sigma = profile_sigma(
            sess, leader, theta, sigma, resim_chi2(residual), resim_chi2, variance_factor
        )
    if leader[0] is region:
        sigma = np.maximum(
            sigma,
            region_jackknife_sigma(
                region_columns, sess.r, P, evidence.weighting.noise.cov, blocks
            ),
        )
    return Leader(name, theta, residual, sigma)
