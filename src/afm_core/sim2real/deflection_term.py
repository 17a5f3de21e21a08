"""The generic term of a torsion residual that follows the deflection sample by sample
(signal_relations.py), fitted and checked where the features cannot see it: at the samples.

In a normal-work session every push meets a particle, so every push torsion feature is left out
(exclusions.py: the contact history) and no feature-level held-out check can judge the term. The
samples can, as the height samples judge a periodic height signal (periodic_height.py): the
pushes are split into two folds of alternate pushes (each spanning the session), the slope k of
the simulator's `deflection_proportional` on the torsion is fitted on one fold's first
differences, the session is re-simulated with that term, and the other fold's torsion residual is
compared before and after.

The term acts on the deflection as measured; the re-simulation's measured deflection carries
another realisation of the sensor noise than the recording's, and first differences are mostly
that noise. So the re-simulated torsion is read with the term evaluated on the recording's own
deflection (re-simulated torsion - k x simulated deflection + k x recorded deflection): the
simulator's term, applied to the input it was defined on.

The noise level. The simulator draws the torsion without noise, so no modelled sigma exists for
the torsion residual's differences (noise_floor.py meets the same gap for the push fluctuation).
The floor is taken from the recording: the robust step noise (1.4826 x median absolute value) of
the residual the fitted term leaves on the *training* fold, no finer than the relative precision
noise_model gives a signal simulated without noise (1e-3 of the residual's step size before the
term: a recording as noiseless as the model would otherwise make the floor a rounding error),
and the held-out fold's chi^2 is the sum of its squared residual differences over that floor
squared. Only every other difference
enters (non-overlapping pairs of samples), so white noise gives independent terms and chi^2 with
as many dof as terms. Steps beyond CONTACT_SIGMAS floors before and after alike (a push meeting a
particle at another moment than in the model: the contact history the re-simulation does not
reproduce) are left out of both sums, with their count stated: a robust-fit rule (8 of the
term's own robust residual), so the share is that of the samples the contact history leaves; when
those are fewer than the steps left out, the session cannot size the term and says so. Without
the rule the contact steps (1e-6 rad against the effect's 5e-9) carry nearly all the held-out
variance and no share is informative either way.

Comparability: the share removed, (before - after) / (before - dof), is the same ratio as the
feature-level checks', but judged against an empirical floor (what the fitted term leaves on the
other fold), not a modelled one: it says how much of the sample-to-sample torsion beyond that
floor the term removes on pushes it was not fitted on, not what the term does to the features,
which this session cannot tell (they are all left out).
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from afm_core.sim.config import merge
from afm_core.sim.generic_terms import GenericTerm
from afm_core.sim2real.force_samples import force_differences
from afm_core.sim2real.heldout import heldout_summary
from afm_core.sim2real.noise_model import RELATIVE_PRECISION
from afm_core.sim2real.protocol import replay

FORM = "proportional to the deflection measured at the same moment (on the samples)"
GROUP = "push.samples"
CONTACT_SIGMAS = 8.0  # a step this many floors beyond, before and after the fit: a contact event
MIN_PUSHES = 2  # one per fold at least


def robust_sd(x: np.ndarray) -> float:
    """1.4826 x the median absolute value: the sd of zero-mean Gaussian noise, unmoved by a few
    contact steps."""
    return float(1.4826 * np.median(np.abs(x))) if x.size else float("nan")


def folds(indices) -> tuple[list, list]:
    """(train, test) operation indices: alternate pushes in time order, so both folds span the
    session."""
    order = sorted(indices)
    return order[0::2], order[1::2]


def slope(dr: np.ndarray, dd: np.ndarray, rounds: int = 4) -> tuple[float, np.ndarray]:
    """(k, samples kept) of dr = k dd (rad per m): least squares, then again without the steps
    beyond CONTACT_SIGMAS of the residual's robust sd (contact steps a thousand times the
    effect's would otherwise set the slope), a few rounds."""
    keep = np.ones(dr.size, bool)
    k = 0.0
    for _ in range(rounds):
        den = float(np.sum(dd[keep] ** 2))
        if den <= 0:
            raise ValueError("deflection differences: all zero, the slope is undefined")
        k = float(np.sum(dr[keep] * dd[keep]) / den)
        e = dr - k * dd
        scale = robust_sd(e)
        if not scale > 0:
            break
        keep = np.abs(e) <= CONTACT_SIGMAS * scale
    return k, keep


def heldout(before: np.ndarray, after: np.ndarray, floor: float) -> dict:
    """Held-out chi^2 of the residual differences `before` and `after` the term (same samples)
    against `floor` (rad): every other difference, steps beyond CONTACT_SIGMAS floors in both
    left out; the share of the excess over the dof removed."""
    if not (np.isfinite(floor) and floor > 0):
        raise ValueError(f"floor: {floor!r}, expected a finite step noise > 0 rad")
    b, a = before[0::2] / floor, after[0::2] / floor
    contact = (np.abs(b) > CONTACT_SIGMAS) & (np.abs(a) > CONTACT_SIGMAS)
    b, a = b[~contact], a[~contact]
    dof = int(b.size)
    chi_b, chi_a = float(np.sum(b * b)), float(np.sum(a * a))
    return heldout_summary(chi_b, chi_a, dof) | {
        "within_noise": bool(chi_a <= stats.chi2.ppf(0.95, max(dof, 1))),
        "contact_steps": int(contact.sum()),
        # free of the floor's level (only the contact steps depend on it)
        "variance_removed": 1.0 - chi_a / chi_b if chi_b > 0 else float("nan"),
        "floor": floor,
    }


def _traces(sess, config) -> dict:
    sess.replays += 1
    out: dict = {}
    for op in replay(sess.ops, config, drift=sess.drift).operations:
        out.update(force_differences(op))
    return out


def _aligned(recorded: dict, *sims: dict) -> list:
    return [
        i
        for i, (dt, _) in recorded.items()
        if all(i in s and s[i][0].size == dt.size for s in sims)
    ]


def deflection_fit(sess, say=lambda m: None) -> dict:
    """The generic fit dict (generic_fit's keys) of `deflection_proportional` on the torsion,
    fitted on one fold of pushes and checked on the other at the samples; {"fitted": False,
    "reason"} when the session cannot size it."""
    recorded = getattr(sess, "force_differences", None) or {}
    nominal = _traces(sess, sess.base)
    pushes = _aligned(recorded, nominal)
    train, test = folds(pushes)
    if len(pushes) < MIN_PUSHES:
        return {"fitted": False, "reason": "fewer than two pushes with aligned samples"}

    def stack(ops, sim, k=0.0):
        # the residual differences, the term (k) read on the recording's own deflection
        r = [recorded[i][0] - sim[i][0] + k * (sim[i][1] - recorded[i][1]) for i in ops]
        return np.concatenate(r), np.concatenate([recorded[i][1] for i in ops])

    dr, dd = stack(train, nominal)
    fit = np.isfinite(dr) & np.isfinite(dd)
    k, kept = slope(dr[fit], dd[fit])
    term = GenericTerm("torsion", "deflection_proportional", k)
    say(f"generic term on the samples: torsion = {k:.3g} rad/m x deflection (one re-simulation)")
    config = merge(sess.base, {"generic_terms": list(sess.base.generic_terms) + [term.as_dict()]})
    resim = _traces(sess, config)
    if len(_aligned(recorded, nominal, resim)) != len(pushes):
        return {"fitted": False, "reason": "a push lost its samples in the re-simulation"}
    after_train, _ = stack(train, resim, k)
    # the term's own robust residual, but no finer than the precision of a signal simulated
    # without noise (noise_model's, relative to the residual's size before the term): else a
    # recording as noiseless as the model makes the floor the slope's rounding error
    size = robust_sd(dr[fit][0::2])
    left = robust_sd(after_train[0::2][np.isfinite(after_train[0::2])])
    floor = max(left, RELATIVE_PRECISION * size)
    if not (np.isfinite(floor) and floor > 0):
        return {
            "fitted": False,
            "reason": "the torsion the fitted term leaves has no step noise to judge against",
        }
    before, _ = stack(test, nominal)
    after, _ = stack(test, resim, k)
    ok = np.isfinite(before) & np.isfinite(after)
    h = heldout(before[ok], after[ok], floor)
    h["floor_from"] = (
        "the torsion step noise the term leaves on the fitting pushes"
        if left >= RELATIVE_PRECISION * size
        else f"the precision of a signal simulated without noise ({RELATIVE_PRECISION:.0e} of "
        "the steps before the term), the term leaving less on the fitting pushes"
    )
    if h["contact_steps"] > h["dof"]:
        # most held-out samples are steps the re-simulation does not reproduce: a share of the
        # rest would describe a minority of the pushes
        return {
            "fitted": False,
            "reason": f"this session cannot size it: {h['contact_steps']} of the held-out "
            f"pushes' {h['contact_steps'] + h['dof']} sample steps are contacts the "
            "re-simulation does not reproduce",
        }
    h["measured_on"] = (
        f"the held-out fold's torsion samples ({len(test)} pushes, every other first difference,"
        f" {h['contact_steps']} contact steps left out), against the step noise the term leaves "
        f"on the training fold ({floor:.3g} rad)"
    )
    # k's sigma for residual differences at the floor
    sigma = floor / np.sqrt(float(np.sum(dd[fit][kept] ** 2)))
    return {
        "fitted": True,
        "signal": "torsion",
        "form": FORM,
        "terms": [dict(term.as_dict(), sigma=float(sigma))],
        "delta_chi2": float("nan"),
        "parameters": 1,
        "p": float("nan"),
        "heldout": h,
        "acts_on": [GROUP],
        "reached": [GROUP],
        "replays": 2,
        "searched": {},
    }


def sample_sentence(generic: dict) -> str:
    """The sample-level fit and its held-out check in words, with what it cannot say."""
    h, k = generic["heldout"], generic["terms"][0]
    return (
        f"Its simplest generic model is the torsion {FORM}, {k['amplitude']:.3g} +- "
        f"{k['sigma']:.2g} rad per m of deflection, fitted on alternate pushes; re-simulated, it "
        f"removes {h['excess_reduction']:.0%} of the other pushes' sample-level excess (chi2 "
        f"{h['chi2_before']:.3g} -> {h['chi2_after']:.3g} for {h['dof']} dof, against a floor "
        f"of {h['floor']:.2g} rad, {h['floor_from']}, the simulator's torsion having no noise "
        f"of its own; {h['contact_steps']} steps beyond "
        f"{CONTACT_SIGMAS:.0f} of it before and after alike, where a push meets a particle "
        f"otherwise than in the model, left out; {h['variance_removed']:.1%} of their "
        "variance). This is measured on the samples, not the "
        "features: what the term does to the push features this session cannot tell."
    )
