"""A named term against a simpler one that predicts the held-out blocks as well
(simpler_term.py): the scanner map's closed form (an antisymmetric coupling is a rotation to
first order, a one-sided one is not), and the rule on fakes of the earlier stages."""

import math
from types import SimpleNamespace

import numpy as np
import pytest
from sim2real_decisions import accepted_results, diagnosis_of

from afm_core.pzt import LateralScanner, ScannerParams
from afm_core.sim.config import merge
from afm_core.sim2real import simpler_term
from afm_core.sim2real.candidates import library
from afm_core.sim2real.heldout import significant_gain
from afm_core.sim2real.protocol import session_config
from afm_core.sim2real.results import NAMED
from afm_core.sim2real.verdict import Decision

N = 40  # features of the fake session
DOF = 55


def _matrix(c_xy, c_yx, deg):
    params = ScannerParams(coupling_x_to_y=c_xy, coupling_y_to_x=c_yx, deflection_deg=deg)
    return LateralScanner._mixing_matrix(params)


@pytest.mark.parametrize("delta_deg", [0.5, -0.8, 1.0])
def test_an_antisymmetric_coupling_is_a_rotation_to_first_order(delta_deg):
    """R(t0 + d) M(c) = R(t0) M(c + (d, -d)) + O(d^2, d c): what a session without a second-order
    feature cannot tell apart; a one-sided coupling of the same size differs at first order."""
    c, t0 = 0.01, 0.746
    d = math.radians(delta_deg)
    rotated = _matrix(c, c, t0 + delta_deg)
    antisymmetric = _matrix(c + d, c - d, t0)
    one_sided = _matrix(c + 2 * d, c, t0)
    second_order = d * d + 2 * abs(d) * c
    assert np.abs(rotated - antisymmetric).max() <= second_order
    assert np.abs(rotated - one_sided).max() >= abs(d) - second_order


def _check(after, before=2600.0):
    return {
        "chi2_before": before,
        "chi2_after": after,
        "dof": DOF,
        "reduction": 1 - after / before,
        "excess_reduction": (before - after) / (before - DOF),
        "train_theta": [1.43],
        "test": np.arange(N) % 2 == 1,
    }


def _stage(monkeypatch, simpler_after):
    """(sess, evidence, terms, noise_first, config, decision naming coupling) with the simpler
    term's held-out check giving `simpler_after`."""
    config = merge(session_config(), {"seed": 3})
    lib = {c.name: c for c in library()}
    names = ["coupling", "rotation"]
    terms = {n: (lib[n], lib[n].nominal(config), np.zeros((N, lib[n].size))) for n in names}
    results = accepted_results(lib, names, config, 0.01, bic_gain=39000.0)
    evidence = SimpleNamespace(
        overall=lambda: {"chi2": 39000.0, "dof": N - 1, "p": 0.0, "variance_factor": 1},
        results=results,
        accepted=results,
        weighting=SimpleNamespace(noise=SimpleNamespace(cov=np.eye(N)), white=lambda a: a),
        P=np.ones((N, 1)),
        folds=[np.arange(N) % 2 == 0, np.arange(N) % 2 == 1],
        variance_factor=1.0,
    )
    monkeypatch.setattr(simpler_term, "heldout_check", lambda *a, **k: _check(simpler_after))
    monkeypatch.setattr(
        simpler_term, "refine", lambda *a, **k: (np.array([1.437]), np.eye(1) * 1e-6, None)
    )
    monkeypatch.setattr(simpler_term, "reported_sigma", lambda *a, **k: np.array([0.004]))
    parameters = {
        "scanner.coupling_x_to_y": {"value": 0.0219, "sigma": 1e-4, "nominal": 0.01},
        "scanner.coupling_y_to_x": {"value": -0.0023, "sigma": 1e-4, "nominal": 0.01},
    }
    for p in parameters.values():
        p["candidate"] = "coupling"
    decision = Decision(NAMED, ["coupling"], parameters, {"scanner": {}}, _check(27.2), [], "")
    sess = SimpleNamespace(r=np.zeros(N))
    return sess, evidence, terms, SimpleNamespace(result=None, design=None), config, decision


def _prefer(stage):
    sess, evidence, terms, noise_first, config, decision = stage
    return simpler_term.prefer_simpler(
        sess, evidence, config, terms, noise_first, decision, 2, lambda m: None
    )


def test_a_simpler_term_as_good_on_the_held_out_blocks_is_named_and_both_are_said(monkeypatch):
    """The closed-loop work session's figures: a rotation of 0.69 deg fitted as coupling left
    the held-out blocks at 27.2 for 55 dof, the rotation alone at 27.7: the coupling's second
    parameter gains nothing beyond noise, so the rotation is named and the verdict says the
    session cannot tell it from the coupling."""
    stage = _stage(monkeypatch, 27.7)
    decision = _prefer(stage)
    assert decision.verdict == NAMED and decision.chosen == ["rotation"]
    assert "cannot tell" in decision.note and "coupling" in decision.note
    assert decision.parameters["scanner.deflection_deg"]["value"] == pytest.approx(1.437)
    evidence, config = stage[1], stage[4]
    diagnosis = diagnosis_of(decision, evidence, config, N)
    summary = diagnosis.summary()
    assert "rotation" in summary and "coupling" in summary and "cannot tell" in summary


def test_a_simpler_term_worse_beyond_the_bound_leaves_the_named_term(monkeypatch):
    """A one-sided coupling: the rotation cannot take it, its held-out chi^2 stays far above
    the coupling's (beyond what one more parameter gains from noise): coupling stays named."""
    bound = significant_gain(DOF, 1, 2)
    stage = _stage(monkeypatch, 27.2 + 1.01 * bound)
    decision = _prefer(stage)
    assert decision.chosen == ["coupling"] and decision.note == ""
    stage = _stage(monkeypatch, 27.2 + 0.99 * bound)
    assert _prefer(stage).chosen == ["rotation"]
