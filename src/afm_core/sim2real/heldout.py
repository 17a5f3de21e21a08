"""The held-out check: each kind of operation split in time order into n_blocks chunks, two
folds of alternate chunks (`fold_blocks`). A fit on one fold only re-simulates the whole
session, and the other fold's residuals are compared before and after (`heldout_check`); a
held-out gain counts only beyond `significant_gain`."""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from afm_core.sim2real.evidence import ALPHA
from afm_core.sim2real.feature_table import BOW_GROUPS, Table
from afm_core.sim2real.noise_model import NoiseModel, Whitener, gls
from afm_core.sim2real.reference import ReferenceSession
from afm_core.sim2real.refinement import refine


def fold_blocks(table: Table, ops, n_blocks: int) -> np.ndarray:
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


def heldout_check(
    sess: ReferenceSession,
    terms: list,
    noise: NoiseModel,
    P: np.ndarray,
    train: np.ndarray,
    iterations: int,
    start: np.ndarray,
) -> dict:
    """`terms` (design triples) fitted on the `train` blocks from `start`, the whole session
    re-simulated with that fit: chi^2 of the other blocks before and after (and the fit, its
    residual, the test mask)."""
    test = ~train
    w_tr = Whitener(noise.cov[np.ix_(train, train)])
    # fit on the training blocks only (their own whitening), re-simulate the whole session
    theta, _, r_after = refine(sess, terms, w_tr, P, iterations, 1.0, mask=train, start=start)
    check = heldout_chi2(noise, P, test, sess.r_before, r_after)
    before = check["chi2_before"]
    return {
        **check,
        "reduction": 1 - check["chi2_after"] / before if before > 0 else 0.0,
        "train_theta": theta.tolist(),
        "r_after": r_after,
        "test": test,
    }


def heldout_chi2(noise: NoiseModel, P: np.ndarray, test: np.ndarray, r_before, r_after) -> dict:
    """chi^2 of the `test` blocks before and after a fit (the nuisance refitted on them, in
    their own whitening), their dof and the share of the excess over the dof removed."""
    w_te = Whitener(noise.cov[np.ix_(test, test)])
    pte = w_te(P[test])
    _, before, _ = gls(w_te(r_before[test]), pte)
    _, after, _ = gls(w_te(r_after[test]), pte)
    return heldout_summary(before, after, int(test.sum() - P.shape[1]))


def heldout_summary(before: float, after: float, dof: int) -> dict:
    """A held-out check's chi^2 before and after, its dof and the share of the excess over the
    dof removed (NaN when there is no excess to remove)."""
    excess = before - dof
    return {
        "chi2_before": before,
        "chi2_after": after,
        "dof": dof,
        "excess_reduction": (before - after) / excess if excess > 0 else float("nan"),
    }


def significant_gain(dof: int, n_parameters: int, n_candidates: int) -> float:
    """The held-out chi^2 gain a fit of n_parameters (one set out of n_candidates considered)
    must exceed to count as evidence: the larger of
    - chi^2(n_parameters) at ALPHA / n_candidates: what a fit of pure noise gains when the two
      folds share nothing (the single-term test's family-wise rate), and
    - the held-out chi^2's own spread, sqrt(2 dof), times the one-sided normal quantile at the
      same rate. The folds do share parts of the noise (the substrate's surface under repeated
      passes, the drift's wander, the positioning walk): a fit on one fold then predicts some
      of the other's noise, and its gain is no longer chi^2(k) -- a null's z gain took 215.3 ->
      208.5 for 275 dof, 6.8 beyond chi^2(1)'s 5.0 at 5 %/2. A gain within the statistic's own
      scatter moves the held-out blocks' standing against their noise by less than one session
      differs from the next, so it is no evidence for the term whatever the folds share."""
    rate = ALPHA / max(n_candidates, 1)
    independent = float(stats.chi2.isf(rate, max(n_parameters, 1)))
    spread = float(stats.norm.isf(rate)) * math.sqrt(2.0 * max(dof, 1))
    return max(independent, spread)
