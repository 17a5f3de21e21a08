"""A named term against a simpler library term that predicts the held-out blocks as well.

Two library terms can describe the same change to first order: an x/y coupling whose two
coefficients move by +e and -e is a rotation of the scan axes by e radians (the scanner map is
R(theta) @ [[1, c_yx], [c_xy, 1]]; the rotation's own signature, a scale of cos(theta), is
second order: 7e-5 for 0.7 deg). A session that holds no feature telling the symmetric or
one-sided part of the coupling from zero cannot tell the two apart; the in-sample re-simulated
chi^2 of the term with more parameters is then lower by what those parameters take of the
noise and of the reference's non-linearities (a rotation of 0.69 deg fitted as coupling
+0.0119 / -0.0123: re-simulated chi^2 97.2 against the rotation's 110.7 for 153 features, the
held-out gains of the two linear fits equal to 0.004 %), and the leader by that chi^2 is the
term with more freedom, named with a confident fit.

The rule (general: it knows the terms only by their parameter counts): when the named set is
one library term (beside a sensor-noise term) and another accepted single term has fewer
parameters, the simpler term's fit is checked on the same held-out blocks; when it leaves them
no worse than the named term's by more than what the named term's extra parameters could gain
from noise (heldout.significant_gain for the parameter difference), the session cannot tell
the named term's extra freedom from noise: the simpler term is named (parsimony) and the
verdict says that the other fits as well and this session cannot tell them apart.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from afm_core.sim2real.evidence import Evidence
from afm_core.sim2real.heldout import heldout_check, significant_gain
from afm_core.sim2real.reference import ReferenceSession
from afm_core.sim2real.refinement import refine, reported_sigma, sigma_of
from afm_core.sim2real.results import NAMED, PARTLY_EXPLAINED
from afm_core.sim2real.verdict import Decision, decide

# how many simpler accepted terms are re-simulated at most (each costs a held-out check)
MAX_SIMPLER = 2


def simpler_alternative(
    sess: ReferenceSession,
    evidence: Evidence,
    terms: dict,
    chosen: list,
    heldout: dict,
    iterations: int,
    say: Callable[[str], None],
) -> dict | None:
    """{name, theta, heldout, bound, named, words} of the simplest accepted single term whose
    held-out check is within `bound` of the named term's (`heldout`), or None when the named set
    is not a single library term or no simpler term fits the held-out blocks as well."""
    library = [n for n in chosen if terms[n][0].analytic != "sensor_noise"]
    if len(library) != 1 or "chi2_after" not in heldout or "test" not in heldout:
        return None
    named = library[0]
    k_named = terms[named][0].complexity
    simpler = [
        res
        for res in evidence.accepted
        if res.name != named
        and res.name in terms
        and terms[res.name][0].complexity < k_named
        and not terms[res.name][0].analytic
    ]
    simpler.sort(key=lambda res: (terms[res.name][0].complexity, -res.bic_gain))
    noise, P, folds = evidence.weighting.noise, evidence.P, evidence.folds
    dof = int(heldout["dof"])
    for res in simpler[:MAX_SIMPLER]:
        k = terms[res.name][0].complexity
        bound = significant_gain(dof, k_named - k, len(evidence.results))
        say(f"held-out check of {res.name}, simpler than {named}")
        check = heldout_check(
            sess, [terms[res.name]], noise, P, folds[0], iterations, np.asarray(res.estimate)
        )
        worse = check["chi2_after"] - heldout["chi2_after"]
        say(
            f"held-out chi2 {check['chi2_after']:.1f} ({res.name}) against "
            f"{heldout['chi2_after']:.1f} ({named}); bound {bound:.1f}"
        )
        if worse <= bound:
            words = (
                f"{res.name} ({k} parameter{'s' if k > 1 else ''}) or {named} ({k_named}): "
                f"this session cannot tell them apart (held-out chi2 {check['chi2_after']:.1f} "
                f"against {heldout['chi2_after']:.1f} for {dof} dof; {named}'s extra "
                f"parameters would have to gain more than {bound:.1f}); the simpler is named"
            )
            return {
                "name": res.name,
                "theta": np.asarray(check["train_theta"], dtype=float),
                "heldout": check,
                "bound": bound,
                "named": named,
                "words": words,
            }
    return None


def prefer_simpler(
    sess: ReferenceSession,
    evidence: Evidence,
    config,
    terms: dict,
    noise_first,
    decision: Decision,
    iterations: int,
    say: Callable[[str], None],
) -> Decision:
    """`decision` with its single named library term replaced by a simpler one that predicts
    the held-out blocks as well (simpler_alternative), judged again by the same naming rule
    (verdict.decide); the verdict's note says that this session cannot tell the two apart.
    `decision` unchanged when there is no such term or the simpler one is not named."""
    if decision.verdict not in (NAMED, PARTLY_EXPLAINED):
        return decision
    alt = simpler_alternative(
        sess, evidence, terms, decision.chosen, decision.heldout, iterations, say
    )
    if alt is None:
        return decision
    term = terms[alt["name"]]
    white, P = evidence.weighting.white, evidence.P
    say(f"re-simulating the fit of {alt['name']} (simpler than {alt['named']})")
    theta, cov, resid = refine(sess, [term], white, P, iterations, evidence.variance_factor)
    sigma = reported_sigma(white, P, term[2], resid, sigma_of(cov), evidence.variance_factor)
    simpler = decide(
        sess,
        evidence,
        config,
        terms,
        noise_first,
        [([alt["name"]], theta, sigma)],
        {(alt["name"],): alt["heldout"]},
        iterations,
        True,
        say,
    )
    if simpler.verdict not in (NAMED, PARTLY_EXPLAINED):
        return decision
    for res in evidence.results:
        if res.name == alt["named"]:
            res.note = f"{res.note} {alt['words']}".strip()
    return simpler._replace(note="; ".join(filter(None, [simpler.note, alt["words"]])))
