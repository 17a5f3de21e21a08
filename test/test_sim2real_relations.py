"""A residual's relation to another signal measured at the same moment (signal_relations.py),
the generic term that models it (`deflection_proportional`), and the noise floor of a feature
that is itself a noise statistic (noise_floor.py): on synthetic traces and closed forms."""

import math
from types import SimpleNamespace

import numpy as np
import pytest
from test_sim2real_signature import contact_traces_without_and_with

from afm_core.sim.config import load_config, merge
from afm_core.sim2real.force_samples import collecting, force_differences
from afm_core.sim2real.generic_fit import PROPORTIONAL_FORM, _tracked, model_sentence
from afm_core.sim2real.noise_floor import statistic_variance
from afm_core.sim2real.signal_relations import DEFLECTION, sample_relation
from afm_core.sim2real.signature import Signature
from afm_core.sim2real.signature_text import sentences


def _push(index, torsion, deflection, kind="push"):
    data = SimpleNamespace(lateral_torsion=torsion, vertical_deflection=deflection)
    return SimpleNamespace(index=index, kind=kind, data=data)


def _session(k: float, seed: int, pushes: int = 6, n: int = 400):
    """(recorded, nominal) force_differences of `pushes` traces: the model's torsion a friction
    plateau with a slow wander of its own (what the re-simulation does not reproduce), the
    recorded deflection 50 nm plus 0.05 nm of white noise, the recorded torsion the model's
    plus another slow wander plus k x the recorded deflection."""
    rng = np.random.default_rng(seed)
    recorded, nominal = {}, {}
    u = np.linspace(0, 1, n)
    for i in range(pushes):
        model = 1e-5 + 2e-7 * np.sin(2 * math.pi * (u + rng.random()))
        deflection = 50e-9 + rng.normal(0, 0.05e-9, n)
        wander = 3e-7 * np.sin(2 * math.pi * 0.7 * (u + rng.random()))
        recorded |= force_differences(_push(i, model + wander + k * deflection, deflection))
        nominal |= force_differences(_push(i, model, 50e-9 + rng.normal(0, 0.05e-9, n)))
    return recorded, nominal


@pytest.mark.parametrize("k", [30.0, -23.6, 3.0])
def test_a_torsion_residual_proportional_to_the_deflection_is_found_with_its_slope(k):
    """The torsion the model lacks is k x the measured deflection: the relation is found, its
    slope is k (to the precision of 2400 samples of 0.05 nm noise against a slow wander)."""
    recorded, nominal = _session(k, seed=1)
    rel = sample_relation(recorded, nominal, alpha=0.05)
    assert rel is not None and rel["covariate"] == DEFLECTION
    assert rel["coefficient"] == pytest.approx(k, rel=0.02)
    assert math.copysign(1, rel["r"]) == math.copysign(1, k)
    assert rel["n"] == 6 * 399


def test_no_relation_is_reported_when_the_residual_does_not_follow_the_deflection():
    """A residual of slow wander only (the contact history): no relation in 19 of 20 seeds at
    alpha = 0.05 (a false alarm rate near alpha: at most 3 of 20 by the binomial's 98 %)."""
    found = sum(sample_relation(*_session(0.0, seed=s), alpha=0.05) is not None for s in range(20))
    assert found <= 3


def test_traces_that_do_not_align_with_the_model_are_left_out():
    recorded, nominal = _session(30.0, seed=2, pushes=1)
    nominal[0] = (nominal[0][0][:-5], nominal[0][1][:-5])
    assert sample_relation(recorded, nominal, alpha=0.05) is None


def test_only_force_traces_are_collected_as_the_operations_pass():
    ops = [
        _push(3, np.ones(10), np.zeros(10)),
        SimpleNamespace(index=4, kind="raster", data=object()),
        _push(5, np.ones(10), np.zeros(10), kind="indent"),
        SimpleNamespace(index=6, kind="push", data=None),
    ]
    kept: dict = {}
    assert list(collecting(ops, kept)) == ops
    assert sorted(kept) == [3, 5] and kept[3][0].size == 9


def test_the_deflection_proportional_term_adds_k_times_the_measured_deflection():
    """The simulator's torsion with the term, less the one without (same seed), is k times the
    deflection the trace reports at each sample (closed form)."""
    term = {"signal": "torsion", "form": "deflection_proportional", "amplitude": 30.0}
    traces = contact_traces_without_and_with(term)
    deflection = np.asarray(traces[1].vertical_deflection)
    diff = np.asarray(traces[1].lateral_torsion) - np.asarray(traces[0].lateral_torsion)
    assert np.allclose(diff, 30.0 * deflection, rtol=1e-9, atol=1e-18)
    assert np.ptp(deflection) > 0  # the measured deflection, noise included


def test_the_deflection_proportional_term_is_a_torsion_term_only():
    term = {"signal": "height", "form": "deflection_proportional", "amplitude": 1.0}
    with pytest.raises(ValueError, match=r"generic_terms\[0\].form=deflection_proportional"):
        merge(load_config(), {"generic_terms": [term]})


def test_a_torsion_signature_with_the_relation_says_it_and_is_fitted_as_proportional():
    rel = {
        "covariate": DEFLECTION,
        "r": 0.99,
        "p": 1e-30,
        "coefficient": 30.0,
        "units": "rad per m",
        "n": 2400,
        "samples": True,
    }
    row = {"group": "push.torsion", "words": "torsion while sliding", "kind": "torsion"}
    sig = Signature(
        signals=[dict(row, n=12, chi2=900.0, excess=888.0, share=1.0)],
        kind="torsion",
        groups=["push.torsion"],
        relations=[rel],
        size={"rms": 1.5e-6, "rms_sigma": 30.0, "noise_sigma": 5e-8},
    )
    words = " ".join(sentences(sig, 0.05))
    assert "proportional" in words and "deflection" in words and "30 rad per m" in words
    assert _tracked(sig) is rel
    assert _tracked(Signature(kind="z", relations=[rel])) is None
    generic = {
        "signal": "torsion",
        "form": PROPORTIONAL_FORM,
        "terms": [{"form": "deflection_proportional", "amplitude": 30.0}],
        "heldout": {"excess_reduction": 0.9},
    }
    assert "30 rad per m of deflection" in model_sentence(generic)


def test_an_rms_feature_is_never_known_better_than_its_sampling_precision():
    """The floor is the chi distribution's spread: the sd of the rms of n Gaussian samples of
    sd s is s / sqrt(2 (n - 1)) to O(1/n); s read from the trace's own steps as the features
    do (2000 draws: 3 % on the sd)."""
    n, s = 400, 1.2e-9
    rng = np.random.default_rng(0)
    draws = rng.normal(0, s, (2000, n))
    trace = 1e-5 + np.linspace(0, 2e-7, n) + draws[0]  # a slow course under the noise
    fluct = [f for f in _push_features_of(trace) if f.group == "push.fluct"][0]
    table = SimpleNamespace(
        groups=np.array(["push.fluct", "push.torsion", "push.fluct"]),
        conditions=[fluct.conditions, {}, {"samples": n}],
    )
    var = statistic_variance(table)
    rms = np.std(draws, axis=1)
    assert math.sqrt(var[0]) == pytest.approx(np.std(rms), rel=0.1)
    assert var[1] == 0.0 and var[2] == 0.0  # not an rms feature; no step noise


def test_a_noiseless_sawtooth_gets_no_floor_from_its_slips():
    """A stick-slip sawtooth without noise: its rms is deterministic, its steps' robust spread
    is the ramp's (none), so the floor stays at zero however large the fluctuation."""
    n = 400
    saw = 1e-5 + 2e-7 * ((np.arange(n) % 40) / 40.0)
    fluct = [f for f in _push_features_of(saw) if f.group == "push.fluct"][0]
    table = SimpleNamespace(groups=np.array(["push.fluct"]), conditions=[fluct.conditions])
    assert fluct.value > 5e-8
    assert statistic_variance(table)[0] < 1e-30


def _push_features_of(torsion: np.ndarray) -> list:
    """features.py's push features of one slide along x with this torsion."""
    from afm_core.sim2real.features import _push_features

    n = torsion.size
    data = SimpleNamespace(
        lateral_torsion=torsion,
        commanded_x=np.linspace(50e-6, 51e-6, n),
        commanded_y=np.full(n, 50e-6),
        times=np.arange(n) * 1e-3,
        start_time=10.0,
    )
    return _push_features(SimpleNamespace(index=1, data=data), 0.0)


def test_a_relation_no_feature_sees_is_a_torsion_signature_the_scoring_judges_right(monkeypatch):
    """A normal-work session whose push torsion features are all left out: the relation read
    at the samples is the signature (kind, relation), in the structured terms the suite's
    scoring reads (bench/sim2real_scoring.py), and it says what this session cannot tell."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    import sim2real_injections
    import sim2real_scoring

    import afm_core.sim2real.signal_relations as relations

    recorded, nominal = _session(-37.7, seed=3)
    monkeypatch.setattr(
        relations,
        "deflection_relation",
        lambda sess, alpha: sample_relation(recorded, nominal, alpha),
    )
    sess = SimpleNamespace(table=SimpleNamespace(groups=np.array(["raster.x", "line.level"])))
    sig = relations.unseen_signature(sess, 1e-3)
    assert sig.kind == "torsion" and sig.signals
    assert sig.relations[0]["coefficient"] == pytest.approx(-37.7, rel=0.02)
    assert "cannot tell" in sig.text() and "no push torsion feature" in sig.text()
    truth = sim2real_injections.SIGNATURES["torsion_crosstalk"]
    assert sim2real_scoring._structured(sig, truth.accepts) is True
    # a null: nothing follows the deflection, nothing is described
    recorded, nominal = _session(0.0, seed=4)
    assert relations.unseen_signature(sess, 1e-3) is None
