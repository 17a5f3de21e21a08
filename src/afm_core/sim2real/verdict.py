"""The naming rule and the verdict: which of the chosen terms are named, and what the diagnosis
says ("named", "partly explained", "not explained by the library", "no missing physics").

The linear tests (evidence.py, refinement.py, second_term.py) choose the terms; a term is
named only if, in addition, its fit re-simulated (fitted on one fold of time blocks, the whole
session re-simulated, heldout.heldout_check):

- finds a held-out excess to remove at all: the held-out chi^2 of the nominal model above its
  dof, what noise gives on average (a held-out chi^2 of 172 for 211 dof has nothing to name);
- gains more than noise would (heldout.significant_gain: beyond chi^2(k) and beyond the
  held-out chi^2's own spread sqrt(2 dof), each at the family-wise rate ALPHA / candidates);
- removes at least EXCESS_SHARE of that excess (excess = chi^2 - dof);
- does not make the held-out blocks worse;
- has a fitted parameter the session can tell from the model's (results.unresolved: a term
  whose every parameter is within CANNOT_TELL_SIGMAS = 2 sigma of the model is never named).

A term that passes and leaves the held-out blocks within their noise (chi^2 below the 1 - ALPHA
quantile) is "named"; one that leaves them beyond it is "partly explained", with where the
excess remains: the signals and conditions (deviations.where_by_condition on the held-out
residual after the fit) beyond their noise at Bonferroni ALPHA. When the excess lives in none of
them, the term is named: the full-covariance chi^2 also counts how the residual departs from the
modelled correlations between features (the drift's shared part), and a fit of a large effect
leaves some of that (a loop 1.3 x wider, fitted to 0.2 %, left 729 for 215 dof, its groups'
own chi^2 summing to 182); an effect the term leaves shows in the signals it acts on.

The terms are tried as a set (a sensor-noise term first, the leader, a second term); a set
that fails is tried without its last library term (the leader alone: its held-out check is
usually made already for the second term), and an accepted noise term last alone.
When none passes, nothing is named and no updated configuration is written: "not explained by
the library" when the residual exceeds the noise model, else "no missing physics". A set named
here still meets its generic rival (rival.py, run by diagnose.py): no better on the held-out
blocks than the simplest generic form of the same residual, it is "partly explained (this
session cannot tell)" and updates no configuration.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from scipy import stats

from afm_core.sim2real.candidates import merge_overrides
from afm_core.sim2real.deviations import where_by_condition
from afm_core.sim2real.evidence import ALPHA, Evidence
from afm_core.sim2real.feature_table import Table
from afm_core.sim2real.heldout import heldout_check, significant_gain
from afm_core.sim2real.noise_model import Whitener, gls
from afm_core.sim2real.reference import ReferenceSession
from afm_core.sim2real.refinement import refine, reported_sigma, sigma_of
from afm_core.sim2real.results import (
    CANNOT_TELL_SIGMAS,
    NAMED,
    NO_MISSING_PHYSICS,
    NOT_EXPLAINED,
    PARTLY_EXPLAINED,
    UNEXPLAINED_P,
    unresolved,
)

# share of the held-out excess (chi^2 - dof) a named term's re-simulated fit must remove: more
# than half, so the term is the larger part of what the model misses and not a term soaking up
# a little of another effect's signature (a term that removes less leaves most of the deviation
# to something else, and its fitted value is then as much that other effect's as its own)
EXCESS_SHARE = 0.5
# rows of "what remains where" a partly explained verdict lists
REMAINING_ROWS = 5


class Decision(NamedTuple):
    verdict: str
    chosen: list  # the named terms ([] unless named or partly explained)
    parameters: dict  # key -> {value, sigma, nominal, candidate} of the named terms
    overrides: dict  # {} unless named or partly explained
    heldout: dict  # the demonstration of the named terms, or of the last set tried
    remaining: list  # where the held-out excess remains after the named terms (partly)
    note: str  # what was tried and why nothing was named ("" when named)


class _Tried(NamedTuple):
    names: list
    theta: np.ndarray  # the library terms' parameters
    sigma: np.ndarray


def decide(
    sess: ReferenceSession,
    evidence: Evidence,
    config,
    terms: dict,
    noise_first,
    tried: list,
    checked: dict,
    iterations: int,
    resimulate: bool,
    say: Callable[[str], None],
) -> Decision:
    """The verdict on the chosen library terms (`tried`: (names, theta, sigma) sets, best
    first) and the accepted sensor-noise term (`noise_first`), by the module docstring's rule.
    `terms`: name -> design triple (the noise term's joins it); `checked`: held-out checks
    made on the way, by the library terms' names. resimulate=False (no held-out
    demonstration): the chosen terms are named on the linear tests alone."""
    noise_terms, noise_params, noise_overrides = _noise_term(config, terms, noise_first)
    notes = []
    if noise_terms and all(unresolved(p) for p in noise_params.values()):
        notes.append(f"{noise_terms[0]}: {_CANNOT_TELL}")
        noise_terms, noise_params, noise_overrides = [], {}, {}
    # last, alone: a noise level is tested on its own statistics
    sets = list(tried) + ([([], None, None)] if noise_terms else [])
    heldout = {}
    for entry in sets:
        if callable(entry):  # a set made only when reached (a runner-up's re-simulated fit)
            # only when a term failed on its own merits: with no held-out excess to remove, or
            # no re-simulation, nothing else can pass either
            failed = heldout.get("chi2_before", 0.0) > heldout.get("limit", np.inf)
            entry = entry() if resimulate and failed else None
            if entry is None:
                continue
        names, theta, sigma = entry
        parameters, overrides = _parameters(config, terms, names, theta, sigma)
        vague = [n for n in names if _cannot_tell(parameters, n)]
        if vague:
            notes.append(f"{', '.join(vague)}: {_CANNOT_TELL}")
            continue
        names = noise_terms + list(names)
        parameters = {**noise_params, **parameters}
        overrides = merge_overrides(noise_overrides, overrides)
        if not resimulate:
            return Decision(NAMED, names, parameters, overrides, {}, [], "")
        heldout = _demonstration(
            sess, evidence, terms, names, parameters, checked, iterations, say
        )
        verdict, why = judge(heldout, len(parameters), len(evidence.results))
        heldout["terms"] = list(names)
        if verdict is not None:
            remaining = where_remaining(sess, evidence, heldout) if verdict != NAMED else []
            if not remaining:  # beyond the noise in no signal or condition (module docstring)
                verdict = NAMED
            return Decision(verdict, names, parameters, overrides, heldout, remaining, "")
        notes.append(f"{', '.join(names)} not named: {why}")
        for res in evidence.results:  # the term the next set goes without
            if res.name == names[-1]:
                res.note = f"{res.note} not named: {why}".strip()
    if "chi2_after" not in heldout:  # nothing was tried
        heldout = _as_it_is(sess, evidence)
    beyond = evidence.overall()["p"] < UNEXPLAINED_P
    return Decision(
        NOT_EXPLAINED if beyond else NO_MISSING_PHYSICS, [], {}, {}, heldout, [], "; ".join(notes)
    )


_CANNOT_TELL = (
    f"every fitted parameter within {CANNOT_TELL_SIGMAS:g} sigma of the model (this session "
    "cannot tell)"
)


def judge(heldout: dict, n_parameters: int, n_candidates: int) -> tuple[str | None, str]:
    """(NAMED, PARTLY_EXPLAINED or None, why not) of a held-out demonstration of a set of terms
    with n_parameters fitted parameters, out of n_candidates considered. All must hold:
    - the held-out blocks do not fit worse with the set;
    - there is an excess to remove: the nominal model's held-out chi^2 above its dof (what noise
      gives on average); a null's z gain taking 215.3 -> 208.5 for 275 dof had none;
    - the gain is beyond noise: heldout.significant_gain (chi^2(k) at ALPHA / n_candidates and
      the held-out chi^2's own spread sqrt(2 dof) at the same rate). A small effect whose
      held-out blocks sit within the 95 % quantile is still seen when the fit takes far more
      out of them than that (a drift ramp took 235 -> 143 for 211 dof);
    - it removes EXCESS_SHARE of the excess.
    Named when the blocks are then within the noise's 1 - ALPHA quantile, else partly explained.
    """
    before, after, dof = heldout["chi2_before"], heldout["chi2_after"], heldout["dof"]
    limit = float(stats.chi2.isf(ALPHA, dof)) if dof > 0 else float("inf")
    gain_limit = significant_gain(dof, n_parameters, n_candidates)
    heldout["limit"] = limit
    heldout["gain_limit"] = gain_limit
    numbers = f"held-out chi2 {before:.1f} -> {after:.1f} for {dof} dof"
    if after > before:
        return None, f"the held-out blocks fit worse with it ({numbers})"
    excess = before - dof
    if excess <= 0:
        return None, (
            f"the held-out blocks are within what noise gives on average without it ({numbers}): "
            "nothing to remove"
        )
    if before - after <= gain_limit:
        return None, (
            f"its held-out gain is within the noise ({numbers}; a gain beyond {gain_limit:.1f} "
            "would be evidence)"
        )
    share = (before - after) / excess
    if share < EXCESS_SHARE:
        return None, (
            f"it removes {100 * share:.0f} % of the held-out excess over the noise ({numbers}; "
            f"a named term must remove {100 * EXCESS_SHARE:.0f} %)"
        )
    return (NAMED if after <= limit else PARTLY_EXPLAINED), ""


def where_remaining(sess: ReferenceSession, evidence: Evidence, heldout: dict) -> list:
    """Where the held-out blocks stay beyond the noise after the named terms: the rows of
    deviations.where_by_condition on the held-out features' residual after the fit (nuisance
    refitted on them), Bonferroni p below ALPHA, the largest chi^2 excess first."""
    test, r_after = heldout.get("test"), heldout.get("r_after")
    if test is None or r_after is None:
        return []
    keep = test & np.isfinite(r_after)
    idx = np.flatnonzero(keep)
    cov = evidence.weighting.noise.cov[np.ix_(idx, idx)]
    white = Whitener(cov)
    P = evidence.P[idx]
    coef, _, _ = gls(white(r_after[idx]), white(P) if P.size else np.zeros((idx.size, 0)))
    e = r_after[idx] - (P @ coef if P.size else 0.0)
    t = sess.table
    sub = Table(
        keys=[t.keys[i] for i in idx],
        groups=t.groups[idx],
        time=t.time[idx],
        xy=t.xy[idx],
        u=t.u[idx],
        conditions=[t.conditions[i] for i in idx],
        op_index=t.op_index[idx],
    )
    rows, _, _ = where_by_condition(sub, e, cov)
    rows = [row for row in rows if row["p_chi2_bonferroni"] < ALPHA]
    rows.sort(key=lambda row: -(row["chi2"] - row["n"]))
    return rows[:REMAINING_ROWS]


def _demonstration(sess, evidence, terms, names, parameters, checked, iterations, say) -> dict:
    """The held-out check of `names` (made on the way when it was: `checked`)."""
    if tuple(names) in checked:
        return dict(checked[tuple(names)])
    say(f"held-out check of {', '.join(names)}")
    start = np.array([parameters[key]["value"] for name in names for key in terms[name][0].keys])
    noise, P, folds = evidence.weighting.noise, evidence.P, evidence.folds
    return heldout_check(sess, [terms[n] for n in names], noise, P, folds[0], iterations, start)


def _as_it_is(sess: ReferenceSession, evidence: Evidence) -> dict:
    """The held-out fold's chi^2 of the nominal model, when no term was tried."""
    noise, P, folds = evidence.weighting.noise, evidence.P, evidence.folds
    test = folds[1]
    w_te = Whitener(noise.cov[np.ix_(test, test)])
    _, chi2_te, _ = gls(w_te(sess.r[test]), w_te(P[test]))
    return {
        "chi2_before": chi2_te,
        "chi2_after": chi2_te,
        "dof": int(test.sum() - P.shape[1]),
        "reduction": 0.0,
        "excess_reduction": 0.0,
    }


def _cannot_tell(parameters: dict, name: str) -> bool:
    own = [p for p in parameters.values() if p.get("candidate") == name]
    return bool(own) and all(unresolved(p) for p in own)


def _parameters(config, terms: dict, names, theta, sigma) -> tuple[dict, dict]:
    """(key -> {value, sigma, nominal, candidate}, nested config overrides) of library terms."""
    parameters, overrides = {}, {}
    if not names:
        return parameters, overrides
    offset = 0
    for name in names:
        cand, theta0, _ = terms[name]
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
    return parameters, overrides


def _noise_term(config, terms: dict, noise_first) -> tuple[list, dict, dict]:
    """([the accepted sensor-noise term's name] or [], its parameters, its overrides); its
    design joins `terms`."""
    result = noise_first.result
    if result is None or not result.accepted:
        return [], {}, {}
    cand, theta0, _ = noise_first.design
    terms[cand.name] = noise_first.design
    parameters = {
        key: {
            "value": float(result.estimate[j]),
            "sigma": float(result.sigma[j]),
            "nominal": float(theta0[j]),
            "candidate": cand.name,
        }
        for j, key in enumerate(cand.keys)
    }
    return [cand.name], parameters, cand.overrides(config, result.estimate)


def runner_up(sess, design, evidence: Evidence, leader: str, iterations: int, say):
    """A set to try should the leader not be named: the best other accepted single term, fitted
    by re-simulation ([name], theta, its reported sigma), or None when there is none."""

    def make():
        others = [res for res in evidence.accepted if res.name != leader]
        if not others or others[0].name not in design.terms:
            return None
        term = design.terms[others[0].name]
        say(f"re-simulating the fit of {others[0].name} (the leader was not named)")
        white, P = evidence.weighting.white, evidence.P
        theta, cov, resid = refine(sess, [term], white, P, iterations, evidence.variance_factor)
        sigma = reported_sigma(white, P, term[2], resid, sigma_of(cov), evidence.variance_factor)
        return [others[0].name], theta, sigma

    return make
