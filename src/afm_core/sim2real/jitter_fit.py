"""The noise family's generic term: a random per-line lateral offset of sd s (the simulator's
generic `line_jitter`), fitted where the residual lives in the lines' own shifts
(`raster.line_shift`, line_shift.py).

A random term has no deterministic change to fit by columns: re-simulated once, it would put
one draw of offsets into every position feature. What it changes predictably are the noise
statistics, so it is fitted as the library's sensor-noise terms are (noise_term.py): the noise
statistics re-simulated with the noise replicas' seeds at a few levels of s, each feature's
curve statistic^2 = a + b s^2 (a per-line offset and the estimate's own noise add in
quadrature) fitted through them, and s found where the curves meet the recorded statistics
(GLS chi^2 in the diagnosis' noise model, a bounded search). The held-out check is heldout.py's,
as for the other generic forms: s fitted on one fold of time blocks, the noise statistics
re-simulated at that s, chi^2 of the other fold before and after in the same noise model, the
share of its excess removed. The features it does not act on keep their residual (a random
offset moves no position feature in expectation), which is how the noise statistics' columns of
the library are zero elsewhere too.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import optimize, stats

from afm_core.sim.generic_terms import GenericTerm
from afm_core.sim2real.heldout import heldout_chi2
from afm_core.sim2real.line_shift import LINE_SHIFT_GROUP

JITTER_FORM = "random per-line lateral offset"
JITTER_LEVELS = (0.0, 0.5, 1.0, 1.6)  # levels re-simulated, in units of the statistic's size
ACTS = 0.1  # a group the term moves by this share of its noise sigma loses its factor
HELDOUT_QUANTILE = 0.95


def lives_in_line_shifts(sig) -> bool:
    """Whether the signature leads with the lines' own shifts (a z or torsion signal that
    leads is modelled by its own generic form, whatever else passes beside it)."""
    return bool(sig.signals) and sig.signals[0]["group"] == LINE_SHIFT_GROUP


def _overrides(sess, sd: float) -> dict:
    """The noise statistics' overrides at jitter sd `sd` (m), on the reference's noise level."""
    term = GenericTerm("lateral", "line_jitter", float(sd))
    earlier = list(sess.config.generic_terms)
    return {**sess.noise_reference, "generic_terms": earlier + [term.as_dict()]}


class _Curves:
    """Per noise feature, statistic^2 = a + b s^2 through the re-simulated levels."""

    def __init__(self, sess, scale: float):
        self.levels = np.array(JITTER_LEVELS) * scale
        base = sess.noise_features(sess.noise_reference)
        runs = [base] + [sess.noise_features(_overrides(sess, s)) for s in self.levels[1:]]
        stats_ = np.array(runs)[:, sess.noisy]  # (levels, noisy features)
        # in units of the scale: levels^2 in m^2 are below lstsq's cut-off
        u = np.array(JITTER_LEVELS)
        X = np.stack([np.ones_like(u), u**2], 1)
        coef, *_ = np.linalg.lstsq(X, np.nan_to_num(stats_) ** 2, rcond=None)
        self.a, self.b, self.scale = coef[0], coef[1], scale
        self.base = base[sess.noisy]

    def at(self, sd: float) -> np.ndarray:
        """The noisy features' statistics at sd (m)."""
        return np.sqrt(np.clip(self.a + self.b * (sd / self.scale) ** 2, 0.0, None))

    def change(self, sd: float) -> np.ndarray:
        return self.at(sd) - self.at(0.0)


def _chi2(noise_cov, r_noisy, curves, sd, rows) -> float:
    e = (r_noisy - curves.change(sd))[rows]
    var = np.diag(noise_cov)[rows]
    return float(np.sum(e**2 / var))


def _fit(noise_cov, r_noisy, curves, rows, upper: float) -> tuple[float, float, float]:
    """(sd, its sigma from chi^2 + 1, chi^2 at sd) on the noisy features `rows`."""
    best = optimize.minimize_scalar(
        lambda s: _chi2(noise_cov, r_noisy, curves, s, rows),
        bounds=(0.0, upper),
        method="bounded",
        options={"xatol": upper * 1e-5},
    )
    sd, chi2 = float(best.x), float(best.fun)
    grid = np.linspace(0.0, upper, 801)
    inside = grid[[_chi2(noise_cov, r_noisy, curves, s, rows) <= chi2 + 1.0 for s in grid]]
    sigma = 0.5 * float(inside.max() - inside.min()) if inside.size > 1 else upper / 800
    return sd, sigma, chi2


def line_jitter_fit(sess, evidence, r0: np.ndarray, say=lambda m: None) -> dict:
    """The generic per-line lateral offset fitted to the noise statistics of r0 (the residual
    after the named terms, if any), with its held-out check (generic_fit.generic_fit's dict)."""
    noisy = sess.noisy
    shift_rows = (sess.table.groups == LINE_SHIFT_GROUP) & np.isfinite(r0)
    if not shift_rows.any():
        return {"fitted": False, "reason": "no image shows its lines' own shifts"}
    recorded = (sess.reference + r0)[shift_rows]
    scale = max(float(np.median(np.abs(recorded))), 1e-10)
    say(f"generic term: {JITTER_FORM} ({len(JITTER_LEVELS) - 1} levels of noise statistics)")
    curves = _Curves(sess, scale)
    change = np.zeros_like(r0)
    change[noisy] = curves.change(scale)
    sigma_all = np.sqrt(np.diag(evidence.unscaled.cov))
    acted = set(np.unique(sess.table.groups[np.abs(change) >= ACTS * sigma_all]).tolist())
    noise = dataclasses.replace(evidence.unscaled)
    factors = {g: f for g, f in evidence.group_factors.items() if g not in acted}
    noise.overdispersed(factors, sess.table.groups)
    cov = noise.cov[np.ix_(noisy, noisy)]
    r_noisy = np.nan_to_num(r0[noisy])
    live = np.isfinite(r0[noisy])
    upper = float(curves.levels[-1]) * 2.0
    sd, sd_sigma, chi2_fit = _fit(cov, r_noisy, curves, live, upper)
    chi2_0 = _chi2(cov, r_noisy, curves, 0.0, live)
    train = evidence.folds[0]
    sd_train, _, _ = _fit(cov, r_noisy, curves, live & train[noisy], upper)
    # the held-out fold: the noise statistics re-simulated at the training fold's sd
    resim = sess.noise_features(_overrides(sess, sd_train))[noisy]
    moved = np.nan_to_num(resim - curves.base)
    r_after = r0.copy()
    r_after[noisy] = r0[noisy] - moved
    check = heldout_chi2(noise, evidence.P, ~train, r0, r_after)
    heldout = {
        **check,
        "within_noise": bool(
            check["chi2_after"] <= stats.chi2.ppf(HELDOUT_QUANTILE, max(check["dof"], 1))
        ),
        "train_amplitudes": [sd_train],
        "r_after": r_after,
    }
    if heldout["chi2_after"] > heldout["chi2_before"]:
        return {
            "fitted": False,
            "form": JITTER_FORM,
            "reason": (
                f"the generic {JITTER_FORM} fitted on one fold made the other fold's chi2 worse "
                f"({heldout['chi2_before']:.1f} -> {heldout['chi2_after']:.1f} for "
                f"{heldout['dof']} dof)"
            ),
        }
    term = dict(GenericTerm("lateral", "line_jitter", sd).as_dict(), sigma=sd_sigma)
    delta = max(chi2_0 - chi2_fit, 0.0)
    return {
        "fitted": True,
        "signal": "lateral",
        "form": JITTER_FORM,
        "terms": [term],
        "delta_chi2": float(delta),
        "parameters": 1,
        "p": float(stats.chi2.sf(delta, 1)),
        "heldout": heldout,
        "acts_on": sorted(acted),
        "replays": len(JITTER_LEVELS),
        "searched": {},
    }


def jitter_sentence(generic: dict) -> str:
    """The noise-family model in words."""
    term, h = generic["terms"][0], generic["heldout"]
    return (
        f"Its simplest generic model is a noise term: each scan line read at its own random "
        f"offset along its fast axis, independent from line to line, sd "
        f"{term['amplitude'] * 1e9:.3g} +- {term['sigma'] * 1e9:.2g} nm; re-simulated, it "
        f"removes {h['excess_reduction']:.0%} of the held-out excess."
    )
