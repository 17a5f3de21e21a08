"""The unexplained residual's relation to another signal measured at the same moment.

The features average a push's torsion over segments and whole pushes; a torsion residual that
follows the vertical deflection sample by sample (one channel of the detector leaking into the
other, a mounting that couples bending into twist) shows there only as an offset and a larger
fluctuation, which other causes give too. At the samples it is unambiguous: the torsion the
model does not reproduce (recorded less the nominal re-simulation, sample by sample: the same
commands, the same clock) moves with the deflection recorded at that sample. Both are taken as
first differences, so what changes slowly along a push (the friction, the contact history the
re-simulation does not reproduce) drops out and the sample-to-sample part remains, where the
deflection's own noise is a known independent probe: a residual that tracks it sample by
sample is proportional to the measured deflection, with the slope k = sum(dr dd) / sum(dd^2)
(rad per m). Its significance is Spearman's rank test on the pooled differences (first
differences of white noise are correlated at lag one only, which leaves the test's level nearly
unchanged at thousands of samples).

A session whose pushes all meet particles (normal work) has every push torsion feature left out
(exclusions.py: the contact history), so no feature sees the torsion at all; the relation at the
samples is then the only evidence, and `unseen_signature` reports it (at the stricter level of a
"not explained" verdict, results.UNEXPLAINED_P) with what the session cannot tell.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from afm_core.sim2real.force_samples import force_differences
from afm_core.sim2real.protocol import replay
from afm_core.sim2real.signature import Signature

DEFLECTION = "the vertical deflection measured at the same moment"
MIN_SAMPLES = 50  # fewer differences than this say nothing about a sample-level relation


def sample_relation(recorded: dict, nominal: dict, alpha: float) -> dict | None:
    """{covariate, r, p, coefficient (rad/m), units, n} of the torsion residual (recorded less
    nominal) against the recorded deflection, first differences (force_differences of each,
    by operation index) pooled over the traces whose samples align; None when too few samples
    or p >= alpha."""
    dr, dd = [], []
    for index, (d_torsion, d_deflection) in recorded.items():
        nom = nominal.get(index)
        if nom is None or nom[0].size != d_torsion.size:
            continue
        dr.append(d_torsion - nom[0])
        dd.append(d_deflection)
    if not dr:
        return None
    dr, dd = np.concatenate(dr), np.concatenate(dd)
    ok = np.isfinite(dr) & np.isfinite(dd)
    dr, dd = dr[ok], dd[ok]
    if dr.size < MIN_SAMPLES or np.ptp(dd) == 0 or np.ptp(dr) == 0:
        return None
    # ranks: a push meeting a particle at another moment than in the model puts a few large
    # steps in the residual that would swamp a linear correlation (the slope, a sum over all
    # samples, keeps its value: those steps do not go with the deflection's noise)
    r, p = stats.spearmanr(dd, dr)
    if not math.isfinite(p) or p >= alpha:
        return None
    k = float(np.sum(dr * dd) / np.sum(dd * dd))
    return {
        "covariate": DEFLECTION,
        "r": float(r),
        "p": float(p),
        "coefficient": k,
        "units": "rad per m",
        "n": int(dr.size),
        "samples": True,
    }


def deflection_relation(sess, alpha: float) -> dict | None:
    """sample_relation of the recorded session `sess` (reference.ReferenceSession, its
    `force_differences`) against its nominal re-simulation (one replay); None when it has no
    force traces."""
    recorded = getattr(sess, "force_differences", None)
    if not recorded:
        return None
    sess.replays += 1
    nominal = {}
    for op in replay(sess.ops, sess.base, drift=sess.drift).operations:
        nominal.update(force_differences(op))
    return sample_relation(recorded, nominal, alpha)


def unseen_signature(sess, alpha: float) -> Signature | None:
    """The signature of a torsion residual that follows the deflection sample by sample
    (deflection_relation at `alpha`) in a session none of whose features it reaches: a torsion
    signal, its relation, and that this session cannot tell what it does to the features; None
    without such a relation."""
    rel = deflection_relation(sess, alpha)
    if rel is None:
        return None
    pushes = int(np.isin(sess.table.groups, ("push.torsion", "push.fluct")).sum())
    seen = (
        f"{pushes} push torsion features"
        if pushes
        else "no push torsion feature: those of pushes that meet a particle are left out, for "
        "their contact history"
    )
    sign = "rises" if rel["r"] > 0 else "falls"
    words = "the pushes' torsion, sample by sample"
    row = {"group": "push.samples", "words": words, "kind": "torsion", "n": rel["n"]}
    return Signature(
        signals=[dict(row, chi2=float("nan"), excess=float("nan"), share=1.0)],
        kind="torsion",
        groups=["push.samples"],
        relations=[rel],
        sentences=[
            f"The unexplained residual is a torsion signal the features do not show, the session "
            f"having {seen}; it lives in {words}.",
            f"Sample by sample it {sign} with {rel['covariate']}: proportional to it, "
            f"{rel['coefficient']:.3g} {rel['units']} (rank correlation {rel['r']:.2f} over "
            f"{rel['n']} samples, p = {rel['p']:.2g}).",
            "This session cannot tell what it does to the features; the diagnostic protocol's "
            "pushes on the bare substrate measure it.",
        ],
    )
