"""Whether an unexplained residual that only one sub-test sees shows again on the held-out blocks.

When nothing is named and the whole residual is within its noise, "not explained by the library"
rests on one narrower test: a feature group beyond its own noise, a lateral displacement across
the sample, the lines' own shifts, a level trend. Each such test is run at a family-wise level,
but the tests have grown with every kind of physics the describer learnt to see, and each is a
new chance for a null session to cross its line by chance (or for a statistic whose noise the
replicas underestimate a little). Physics that is there is there in both halves of the session:
its generic form, fitted on one fold of time blocks and re-simulated, removes part of the other
fold's chi^2. A chance excursion, fitted on one fold, removes nothing from the other.

So such a verdict stands only when the generic fit's held-out check removes more than its own
estimation noise could: the drop in the held-out chi^2 beats chi^2(k) at ALPHA, k the generic
model's free amplitudes (the same bound as the generic rival's, rival.py). A description that
cannot be checked (no generic term of its form, or a session that cannot size it) keeps its
verdict; one whose fit made the held-out blocks worse, or removed nothing, is a hint and is
reported as such, with "no missing physics".
"""

from __future__ import annotations

import math

from scipy import stats

from afm_core.sim2real.evidence import ALPHA
from afm_core.sim2real.results import UNEXPLAINED_P

# reasons a generic fit gives when its held-out blocks got worse: a check that failed, not one
# that could not be made
WORSE = "worse"


def heldout_confirms(overall: dict, generic: dict) -> tuple[bool, str]:
    """(whether the unexplained verdict stands, why not in words). It stands when the whole
    residual is beyond its noise (overall p < UNEXPLAINED_P), when there is no generic fit to
    check it with, or when that fit's held-out chi^2 drop beats chi^2(k) at ALPHA."""
    if overall.get("p", 1.0) < UNEXPLAINED_P or not generic:
        return True, ""
    if not generic.get("fitted"):
        reason = str(generic.get("reason", ""))
        if WORSE in reason:
            return (
                False,
                f"its generic form, fitted on one fold, did not hold on the other: {reason}",
            )
        return True, ""
    heldout = generic.get("heldout") or {}
    before, after = heldout.get("chi2_before"), heldout.get("chi2_after")
    if before is None or after is None or not (math.isfinite(before) and math.isfinite(after)):
        return True, ""
    k = max(int(generic.get("parameters", len(generic.get("terms", [])) or 1)), 1)
    bound = float(stats.chi2.isf(ALPHA, k))
    if before - after > bound:
        return True, ""
    return False, (
        f"its generic {generic.get('form', 'form')}, fitted on one fold of time blocks, removed "
        f"{before - after:.1f} of the other fold's chi^2 ({before:.1f} -> {after:.1f} for "
        f"{heldout.get('dof', '?')} dof), within what its {k} fitted amplitude(s) remove from "
        f"noise alone ({bound:.1f} at {ALPHA:g}): a chance excursion in one sub-test, not seen "
        "again"
    )
