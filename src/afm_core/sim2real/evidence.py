"""Evidence for each candidate term, one at a time.

The design columns (design_columns.py) of each candidate are fitted to the residual by GLS
after the nuisance columns (noise_model.py). Evidence per candidate: the GLS chi^2 improvement
over the nuisance-only model, scaled by the residual variance factor when the data are noisier
than modelled, tested against chi^2(p) at the Bonferroni level alpha / (number of candidates)
(alpha = 0.05: the false "missing physics" rate on null recordings, from theory), ranked by BIC
(chi^2 improvement - p ln N), and accepted only if the fit also improves chi^2 on held-out
blocks (2-fold: each kind of operation split in time order into n_blocks chunks, alternate
chunks held out, nuisance refitted on the held-out part; heldout.fold_blocks). Before that,
each feature group's overdispersion (quasi-likelihood) scales its part of the noise model.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import numpy as np
from scipy import stats

from afm_core.sim2real.candidates import Candidate
from afm_core.sim2real.features_absolute import LEVEL_GROUPS, UPDOWN_GROUP
from afm_core.sim2real.line_shift import LINE_SHIFT_GROUP
from afm_core.sim2real.noise_model import NoiseModel, Weighting, gls, group_overdispersion
from afm_core.sim2real.reference import ReferenceSession
from afm_core.sim2real.results import CandidateResult

ALPHA = 0.05  # family-wise false "missing physics" rate on null recordings
# groups whose noise is modelled whole, never scaled by an overdispersion factor
UNSCALED_GROUPS = (*LEVEL_GROUPS, UPDOWN_GROUP, LINE_SHIFT_GROUP)


def can_act(cand: Candidate, theta0: np.ndarray, estimate: np.ndarray) -> bool:
    """Whether the estimate, held to the term's physical range, still changes the model (a
    tip that sharpens while sliding clips to no wear at all)."""
    return bool(np.any(cand.clip(estimate) != theta0))


def cv_gain_on(r, cols, P, folds, fold_whiteners) -> float:
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


class Evidence(NamedTuple):
    """The single-term tests of every candidate, and what later stages judge with."""

    results: list  # CandidateResult of every term (the noise terms' too), accepted ones first
    accepted: list  # the accepted library terms' results, by BIC gain
    weighting: Weighting  # the noise model with the group factors, and its whitenings
    P: np.ndarray  # the nuisance columns
    pw: np.ndarray  # whitened
    folds: list  # training masks of the held-out check's two folds
    chi2_0: float  # of the nuisance-only fit
    dof0: int
    variance_factor: float  # after the best single candidate's fit (>= 1)
    group_factors: dict  # overdispersion per feature group
    unscaled: NoiseModel  # the noise model before the group factors (a second term's own test)

    def overall(self) -> dict:
        """The nominal model's fit (after the nuisance) against the noise model."""
        return {
            "chi2": self.chi2_0,
            "dof": self.dof0,
            "p": float(stats.chi2.sf(self.chi2_0, self.dof0)),
            "variance_factor": self.variance_factor,
            "group_factors": self.group_factors,
        }


def weigh_candidates(
    sess: ReferenceSession,
    design,
    noise: NoiseModel,
    P: np.ndarray,
    folds: list,
    m: int,
    noise_terms: list,
    noise_result: CandidateResult | None,
) -> Evidence:
    """Each candidate's evidence on the session's residual (`design`: design_columns.Design;
    m: the Bonferroni count); `noise` is scaled by the group factors in place. The sensor-noise
    terms' results (`noise_terms`, tested before on the noise statistics) join the ranking,
    the accepted one first."""
    r, table, n = sess.r, sess.table, len(sess.keys)
    terms, region, region_columns = design
    # overdispersion per feature group (quasi-likelihood): a group the noise model describes
    # too optimistically (here: how the few-nm mismatch of the reference's geometry acts on
    # direction differences, which the 10 nm sensitivities only partly tell) must not pass its
    # excess to a candidate; the factors are taken after the best single candidate's fit, so a
    # real effect is not mistaken for noise
    group_factors = group_overdispersion(
        r, P, [c[2] for c in terms.values()], noise.cov, table.groups
    )
    # not the absolute levels (nor their difference by scan direction) nor the lines' own
    # shifts: their noise is modelled whole (replicas, roughness), and what moves the whole z
    # signal, one scan direction's or each line sideways shows nowhere else, so a factor would
    # hide exactly that
    group_factors = {g: f for g, f in group_factors.items() if g not in UNSCALED_GROUPS}
    # before overdispersion: a second term's test takes its own
    unscaled = dataclasses.replace(noise)
    noise.overdispersed(group_factors, table.groups)

    weighting = Weighting.of(noise, folds)
    white = weighting.white
    rw, pw = white(r), white(P) if P.size else np.zeros((n, 0))
    _, chi2_0, _ = gls(rw, pw)
    dof0 = n - pw.shape[1]
    results, variance_factor = _single_term_results(
        r, rw, pw, terms, weighting, P, chi2_0, dof0, folds, m, region, region_columns
    )
    results.sort(key=lambda c: (not c.accepted, -c.bic_gain))
    accepted = [c for c in results if c.accepted]
    if noise_terms:  # a noise term is chosen before the others when accepted (noise_term.py)
        results += [res for _, res, _ in noise_terms]
        results.sort(key=lambda c: (not c.accepted, c is not noise_result, -c.bic_gain))
    return Evidence(
        results,
        accepted,
        weighting,
        P,
        pw,
        folds,
        chi2_0,
        dof0,
        variance_factor,
        group_factors,
        unscaled,
    )


def _single_term_results(
    r, rw, pw, design, weighting, P, chi2_0, dof0, folds, m, region, region_columns
):
    """(CandidateResult per design term, the variance factor after the best single fit)."""
    n = len(r)
    white, fold_whiteners = weighting.white, weighting.folds

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
        res.significant = delta > threshold and can_act(cand, theta0, theta0 + coef)
        if delta > threshold and not res.significant:
            res.note = "its fit lies outside the term's physical range (e.g. a negative wear rate)"
        if res.significant:
            # a searched region is searched again on the training blocks alone
            res.heldout_gain = cv_gain_on(
                r, region_columns if cand is region else cols, P, folds, fold_whiteners
            )
            res.accepted = res.heldout_gain > 0
            if not res.accepted:
                res.note = "fits the session but does not predict held-out blocks"
        results.append(res)
    return results, variance_factor
