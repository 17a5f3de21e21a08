"""The generic rival of a named library term: a library term is named with a confident fit only
if it explains the held-out blocks better than the simplest generic form of the same signal.

A library term and the generic family (generic_fit.py: an additive offset on the height or
torsion signal, linear, stepped, smooth or periodic in time, linear or periodic across the
sample) are two models of one residual. When the residual has a form the generic family can
take, both are fitted on the same fold of time blocks, each re-simulated, and compared on the
same held-out blocks, in the same noise model (the library's), so the blocks' own noise is
common to both and cancels from the difference. What does not cancel is each fit's estimation
noise: a fit of k free amplitudes on one fold loses about chi^2(k) on the other when the truth
lies in its span. The library term wins only when the generic form's held-out chi^2 exceeds the
library term's by more than that loss could give at ALPHA (chi^2(k_generic) at ALPHA, the
generic fit's own parameters: it is the generic model whose fit is asked to be as good). When it
does not, this session cannot tell the library term from the generic description: the verdict
is "partly explained" with both named, the residual described as no term explains it, and no
updated configuration is written. Particle positions displaced as a function of their place
have a generic form too (a displacement of the scanner's true x or y, linear or periodic in its
place: lateral.py), which faces the library's scanner terms (gain, hysteresis, coupling).

The physics this separates: a library term is a constrained model, one parameter acting on many
signals and conditions in a fixed pattern (a friction coefficient scales the torsion of every
slide by the load and contact at that moment). When its pattern is what the data show, no
generic form of one signal does as well, because a generic form lacks the constraint's reach
(other signals) or needs the shape the constraint supplies for free. When the data show only an
offset of one signal that the term's pattern happens to cover (a torsion growing in time, read
through pushes whose torsion has the same sign in both sliding directions), the generic form
takes it as well or better, and the name is no more than one description among two.

A z gain named together with a tip radius meets a second generic rival besides the
signature's form: the measured height's square (generic_fit.quadratic_height_fit), one
amplitude. A z sensor whose sensitivity changes along its range stretches a particle's top
more than its flanks; with particles of one height a gain and a sharper tip together imitate
that (an outside probe's h + h^2 / 10 um was named a gain of 1.019 and a tip radius of 19.48
+- 0.05 nm for the model's 20), and no form in time or across the sample takes it (the
residual is relative to each line's edges: an offset in time moves no particle height). Only
the pair meets it: a gain named alone is the nonlinearity's nearest library term (its mean
slope), and against a gain alone the square is one amplitude against one, which a work
session's few particles of one height cannot tell apart (a true 3 % gain then read "cannot
tell"). The linear form is no rival: it is the z gain itself. Of the rivals, the one the
library terms beat by least is the one reported.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from afm_core.sim2real.evidence import ALPHA
from afm_core.sim2real.heldout import heldout_chi2
from afm_core.sim2real.results import NAMED, PARTLY_EXPLAINED

# library terms that, named together, reshape particles as a z nonlinearity does
HEIGHT_SHAPE_TERMS = ("height_gain", "tip_radius")


def compare_rival(evidence, library_heldout: dict, generic: dict, r_before) -> dict:
    """The held-out comparison of the named library terms (their heldout_check dict) with the
    generic fit of the nominal residual (generic_fit.generic_fit's dict), on the library's
    noise model and held-out blocks. {} when there is no generic rival (its signal has no
    generic term, or no held-out check to compare with)."""
    if not generic.get("fitted") or "r_after" not in library_heldout:
        return {}
    test = library_heldout.get("test")
    r_generic = generic.get("heldout", {}).get("r_after")
    if test is None or r_generic is None:
        return {}
    noise, P = evidence.weighting.noise, evidence.P
    chi2_generic = heldout_chi2(noise, P, test, r_before, r_generic)["chi2_after"]
    chi2_library = heldout_chi2(noise, P, test, r_before, library_heldout["r_after"])["chi2_after"]
    k = int(generic["parameters"])
    bound = float(stats.chi2.isf(ALPHA, max(k, 1)))
    return {
        "form": generic["form"],
        "signal": generic["signal"],
        "parameters": k,
        "chi2_library": float(chi2_library),
        "chi2_generic": float(chi2_generic),
        "dof": int(library_heldout.get("dof", 0)),
        "bound": bound,
        # the library term explains the held-out blocks better than its generic rival could
        # by the generic fit's own estimation noise
        "library_better": bool(chi2_generic - chi2_library > bound),
        "generic_excess_reduction": float(generic["heldout"].get("excess_reduction", np.nan)),
    }


def closest_rival(rivals: list) -> dict:
    """Of several rivals' comparisons (compare_rival's dicts, {} for none), the one the library
    terms beat by least (its held-out chi^2 above theirs less its bound): any one the library
    does not beat is enough for "cannot tell". {} when there is none."""
    rivals = [r for r in rivals if r]
    if not rivals:
        return {}
    return min(rivals, key=lambda r: r["chi2_generic"] - r["chi2_library"] - r["bound"])


def ruling(verdict: str, rival: dict) -> str:
    """The verdict once the named terms met their generic rival: a named or partly explained
    set the rival is not beaten by becomes "partly explained" (this session cannot tell)."""
    if verdict in (NAMED, PARTLY_EXPLAINED) and rival and not rival["library_better"]:
        return PARTLY_EXPLAINED
    return verdict


def rival_words(rival: dict, names: list) -> str:
    """The "cannot tell" sentence of a rival the library term does not beat."""
    terms = " + ".join(names)
    return (
        f"this session cannot tell: {terms} or a generic {rival['form']} on the "
        f"{rival['signal']} signal (held-out chi2 {rival['chi2_library']:.1f} with the library "
        f"term(s), {rival['chi2_generic']:.1f} with the generic form, for {rival['dof']} dof; "
        f"a library term must do better by more than {rival['bound']:.1f}, what the generic "
        f"fit's {rival['parameters']} amplitude(s) lose to estimation noise at {ALPHA:g})"
    )
