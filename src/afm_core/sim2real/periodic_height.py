"""The periodic height signal in time that no feature sees (height_spectrum.py), as a signature
and a generic term: detected on the samples' spectrum, fitted on one fold of time blocks as the
simulator's `time_sine` on the height, and checked on the other fold, re-simulated."""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from afm_core.sim.config import merge
from afm_core.sim.generic_terms import GenericTerm
from afm_core.sim2real.height_spectrum import (
    Residual,
    collect_heights,
    detect,
    fit_sine,
    heldout_chi2,
)
from afm_core.sim2real.protocol import replay
from afm_core.sim2real.signature import Signature

GROUP = "height.samples"
WORDS = "the height samples, sample by sample in time"
FORM = "periodic in time (on the samples)"


def _nominal_heights(sess, config) -> dict:
    sess.replays += 1
    out: dict = {}
    for op in replay(sess.ops, config, drift=sess.drift).operations:
        collect_heights(op, out)
    return out


def periodic_height(sess, alpha: float, say=lambda m: None):
    """(Signature, generic fit dict) of a height signal periodic in time that passes
    height_spectrum.detect at `alpha` in both folds of the session's time blocks; None without
    one (or without height samples)."""
    recorded = getattr(sess, "height_samples", None)
    if not recorded:
        return None
    res = Residual(recorded, _nominal_heights(sess, sess.base))
    if res.t.size < 100:
        return None
    found = detect(res, alpha)
    if found is None:
        return None
    train = found["train"]
    say(f"a periodic height signal at {found['frequency']:.4g} Hz on the samples")
    fit = fit_sine(res, found["candidates"], train, found["resolution"])
    f = fit["frequency"]
    term = GenericTerm(
        "height", "time_sine", fit["amplitude"], (("period", 1 / f), ("t0", fit["t0"]))
    )
    config = merge(sess.base, {"generic_terms": list(sess.base.generic_terms) + [term.as_dict()]})
    after = Residual(recorded, _nominal_heights(sess, config), res.scales)
    skip = found["spectrum"].excluded_ops(f)
    if after.t.size != res.t.size:  # an operation lost its samples in the re-simulation
        return None
    before_chi2, after_chi2 = heldout_chi2(
        res, after.unclipped, ~train, f, found["floor_test"], skip
    )
    excess = before_chi2 - 2.0
    share = (before_chi2 - after_chi2) / excess if excess > 0 else float("nan")
    variance = 1 - float(np.var(after.unclipped[~train]) / np.var(res.unclipped[~train]))
    heldout = {
        "chi2_before": before_chi2,
        "chi2_after": after_chi2,
        "dof": 2,
        "excess_reduction": share,
        "within_noise": bool(after_chi2 <= stats.chi2.ppf(0.95, 2)),
        "variance_removed": variance,
        "measured_on": "the held-out fold's height samples at the fitted frequency",
    }
    generic = {
        "fitted": True,
        "signal": "height",
        "form": FORM,
        # the amplitude's sigma for noise at the floor: robust noise x sqrt(2 / samples fitted)
        "terms": [dict(term.as_dict(), sigma=_noise(res) * math.sqrt(2 / fit["samples"]))],
        "delta_chi2": float("nan"),
        "parameters": 3,
        "p": found["false_alarm"],
        "heldout": heldout,
        "acts_on": [GROUP],
        "replays": 2,
        "searched": {},
    }
    return _signature(found, fit, res, heldout), generic


def _signature(found: dict, fit: dict, res: Residual, heldout: dict) -> Signature:
    f, amplitude = fit["frequency"], fit["amplitude"]
    noise = _noise(res)
    row = {"group": GROUP, "words": WORDS, "kind": "z", "n": int(res.t.size)}
    za, zb = found["z"]
    return Signature(
        signals=[dict(row, chi2=float("nan"), excess=float("nan"), share=1.0)],
        kind="z",
        groups=[GROUP],
        time={
            "form": "periodic",
            "params": {"frequency": f, "period": 1 / f, "amplitude": amplitude},
            "primary": True,
            "bic": {},
            "all": {},
        },
        space={"form": "uniform", "primary": False},
        size={"rms": amplitude / math.sqrt(2), "amplitude": amplitude, "noise_sigma": noise},
        sentences=[
            f"The unexplained residual is a z signal the features do not show (it is faster "
            f"than any feature's sampling); it lives in {WORDS}.",
            f"In time it is periodic at {f:.4f} Hz, amplitude {amplitude * 1e9:.3g} nm "
            f"(the samples' robust noise {noise * 1e9:.3g} nm), in both halves of the session: "
            f"its spectral peak is {za:.0f} and {zb:.0f} times the spectrum's floor, against "
            f"{found['thresholds'][0]:.0f} and {found['thresholds'][1]:.0f} for a false alarm "
            f"over {found['independent_frequencies']:.3g} independent frequencies.",
            f"Held out: a sine in time on the height, fitted on one fold and re-simulated, "
            f"removes {heldout['excess_reduction']:.0%} of the other fold's excess at that "
            f"frequency (chi2 {heldout['chi2_before']:.1f} -> {heldout['chi2_after']:.1f}, 2 "
            f"dof) and {heldout['variance_removed']:.0%} of its prepared residual variance.",
        ],
    )


def _noise(res: Residual) -> float:
    """The samples' robust noise (m): the median over the operations of their own."""
    return float(np.median(list(res.scales.values())))
