"""Which feature groups a generic term reaches, and its held-out check on them.

A generic term's held-out share is "how much of the held-out excess it removes". Taken over the
whole session, that excess mixes the effect's with every other group's: a group whose
overdispersion factor the noise model needs in every session (the forward/backward shift of
scan lines, 4.75 on the protocol's fringes case, as on its nulls) and which the term does not
move at all counts its whole factor as "excess" once the factor is dropped, an excess no
description of the effect can remove. On that case the truth's own fringe, re-simulated,
removed 54 % of the whole session's held-out excess and the fitted one 51 %: the figure
measured the noise model of a group the fringe never touches, not the fringe.

So the check is taken where the term reaches: the groups whose chi^2 the term, fitted on all
features on the diagnosis' noise model, moves by at least REACH (the sum over the group of its
change squared in units of the feature's modelled noise sigma). Only those groups lose their
overdispersion factor (the unexplained effect may have inflated it there; elsewhere it cannot
have: the term does not move them); the held-out chi^2 before and after, its dof and the share
of the excess are those of the reached groups' held-out features, with the nuisance columns
that act on them. The whole session's figures are kept beside them (`all_groups`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from afm_core.sim2real.heldout import heldout_chi2
from afm_core.sim2real.noise_model import Whitener, gls

# a group the term moves by less than one unit of chi^2 (one feature's expected contribution,
# below the chi^2 spread sqrt(2 n) of any group) holds no measurable part of its excess
REACH = 1.0


def group_reach(groups: np.ndarray, change: np.ndarray, sigma: np.ndarray) -> dict:
    """group -> sum over its features of (change / sigma)^2: how far the term moves its chi^2.
    change: the features' change (m, rad, ...; NaN where lost: not counted)."""
    groups = np.asarray(groups)
    z2 = np.where(
        np.isfinite(change) & (sigma > 0), (change / np.where(sigma > 0, sigma, 1)) ** 2, 0
    )
    return {str(g): float(np.sum(z2[groups == g])) for g in np.unique(groups)}


def reached_groups(sess, evidence, r0: np.ndarray, cols: np.ndarray) -> tuple[set, dict]:
    """(the groups the term reaches, group -> reach) for the basis columns `cols` fitted to r0
    with the nuisance columns on the diagnosis' own noise model (every factor kept: which
    groups lose theirs is what this decides)."""
    noise = dataclasses.replace(evidence.unscaled)
    noise.overdispersed(dict(evidence.group_factors), sess.table.groups)
    white = Whitener(noise.cov)
    P = evidence.P
    coef, _, _ = gls(white(r0), np.hstack([white(P), white(cols)]))
    change = cols @ coef[P.shape[1] :]
    sigma = np.sqrt(np.diag(evidence.unscaled.cov))
    reach = group_reach(sess.table.groups, change, sigma)
    return {g for g, v in reach.items() if v >= REACH}, reach


def heldout_where(noise, P, test, reached: np.ndarray, r_before, r_after) -> dict:
    """heldout.heldout_chi2 on the held-out features of the reached groups (`reached`: a mask
    over features), with the nuisance columns that act there; its dof counts only those."""
    mask = test & reached
    keep = np.abs(P[mask]).sum(axis=0) > 0
    if mask.sum() <= keep.sum():
        return {"chi2_before": 0.0, "chi2_after": 0.0, "dof": 0, "excess_reduction": np.nan}
    check = heldout_chi2(noise, P[:, keep], mask, r_before, r_after)
    dof = int(mask.sum() - np.linalg.matrix_rank(P[np.ix_(mask, keep)])) if keep.any() else None
    if dof is not None and dof != check["dof"]:
        excess = check["chi2_before"] - dof
        gain = check["chi2_before"] - check["chi2_after"]
        check.update(dof=dof, excess_reduction=gain / excess if excess > 0 else np.nan)
    return check
