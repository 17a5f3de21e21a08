"""The sample-level generic term of a torsion that follows the deflection (deflection_term.py):
its slope against the truth, its held-out share against the closed form, and a null's."""

from types import SimpleNamespace

import numpy as np
import pytest
from scipy import stats

from afm_core.sim.config import SimConfig
from afm_core.sim2real import deflection_term
from afm_core.sim2real.deflection_term import deflection_fit, heldout, slope

SIGMA_D = 0.05e-9  # m, the deflection's sensor noise (the simulator's default)
SIGMA_T = 2e-10  # rad, a torsion measurement noise in the "recording"


def _session(k_true: float, seed: int, pushes: int = 8, n: int = 400):
    """A fake session whose recorded torsion differences are k_true x its own deflection
    differences plus torsion noise; the simulator's traces carry another deflection noise and
    no torsion noise, and the term, given, adds k x the simulated deflection."""
    rng = np.random.default_rng(seed)
    recorded, sim_deflection = {}, {}
    for i in range(pushes):
        dd = np.diff(rng.normal(0, SIGMA_D, n + 1))
        dt = k_true * dd + np.diff(rng.normal(0, SIGMA_T, n + 1))
        recorded[i] = (dt, dd)
        sim_deflection[i] = np.diff(rng.normal(0, SIGMA_D, n + 1))

    def traces(sess, config):
        sess.replays += 1
        k = sum(t["amplitude"] for t in config.generic_terms)
        return {i: (k * d, d) for i, d in sim_deflection.items()}

    sess = SimpleNamespace(force_differences=recorded, base=SimConfig(), replays=0)
    return sess, traces


def test_slope_recovers_the_truth_and_the_sample_share_is_the_closed_forms(monkeypatch):
    k_true = -37.0
    sess, traces = _session(k_true, seed=1)
    monkeypatch.setattr(deflection_term, "_traces", traces)
    fit = deflection_fit(sess)
    assert fit["fitted"], fit
    term = fit["terms"][0]
    assert term["form"] == "deflection_proportional" and term["signal"] == "torsion"
    assert abs(term["amplitude"] - k_true) < 4 * term["sigma"]
    h = fit["heldout"]
    # closed form: differences of white noise have variance 2 s^2; before the term the held-out
    # chi^2 per dof is 1 + (k sigma_d)^2 / sigma_t^2, after it about 1
    expected = 1 + (k_true * SIGMA_D / SIGMA_T) ** 2
    assert h["chi2_before"] / h["dof"] == pytest.approx(expected, rel=0.15)
    assert h["floor"] == pytest.approx(np.sqrt(2) * SIGMA_T, rel=0.1)
    assert h["excess_reduction"] > 0.9
    assert h["within_noise"]
    # the variance removed, closed form: 1 - 1 / (chi^2 per dof before)
    assert h["variance_removed"] == pytest.approx(1 - 1 / expected, abs=0.05)
    assert sess.replays == 2


def test_no_relation_removes_nothing(monkeypatch):
    sess, traces = _session(0.0, seed=2)
    monkeypatch.setattr(deflection_term, "_traces", traces)
    fit = deflection_fit(sess)
    h = fit["heldout"]
    # no excess to remove: before and after within the noise, their difference a chi^2(1)-sized
    assert h["within_noise"]
    assert abs(h["chi2_before"] - h["chi2_after"]) < stats.chi2.ppf(0.999, 1)
    assert abs(fit["terms"][0]["amplitude"]) < 4 * fit["terms"][0]["sigma"]


def test_contact_steps_are_left_out_of_both_sums():
    rng = np.random.default_rng(3)
    noise = rng.normal(0, 1.0, 2000)
    before = noise + 3.0 * rng.normal(0, 1.0, 2000)
    after = noise.copy()
    for arr in (before, after):
        arr[[100, 500, 900]] += 50.0  # the same contact steps, unexplained before and after
    h = heldout(before, after, 1.0)
    assert h["contact_steps"] == 3 and h["dof"] == 1000 - 3
    assert h["excess_reduction"] > 0.9


def test_bad_input_names_the_field():
    with pytest.raises(ValueError, match="floor"):
        heldout(np.ones(4), np.ones(4), 0.0)
    with pytest.raises(ValueError, match="deflection"):
        slope(np.ones(4), np.zeros(4))


def test_the_slope_is_the_truth_despite_contact_steps():
    rng = np.random.default_rng(7)
    dd = rng.normal(0, SIGMA_D, 4000)
    dr = -30.0 * dd + rng.normal(0, SIGMA_T, 4000)
    steps = rng.random(4000) < 0.3
    k, kept = slope(dr + steps * rng.choice([-1e-6, 1e-6], 4000), dd)
    # the clean samples' least-squares sigma: SIGMA_T / sqrt(sum dd^2)
    assert abs(k + 30.0) < 4 * SIGMA_T / np.sqrt(np.sum(dd[~steps] ** 2))
    assert np.array_equal(kept, ~steps)


def test_too_few_pushes_says_so(monkeypatch):
    sess, traces = _session(-30.0, seed=4, pushes=1)
    monkeypatch.setattr(deflection_term, "_traces", traces)
    fit = deflection_fit(sess)
    assert not fit["fitted"] and "pushes" in fit["reason"]


def _contacts(sess, share: float, seed: int):
    """Steps of 1e-6 rad (a push meeting a particle otherwise than in the model) on a `share`
    of the recorded torsion differences, which no term reproduces."""
    rng = np.random.default_rng(seed)
    for i, (dt, dd) in sess.force_differences.items():
        contact = rng.random(dt.size) < share
        sess.force_differences[i] = (dt + contact * rng.choice([-1e-6, 1e-6], dt.size), dd)


def test_contact_steps_on_a_minority_of_samples_are_left_out_and_counted(monkeypatch):
    sess, traces = _session(-30.0, seed=5)
    _contacts(sess, 0.3, seed=6)
    monkeypatch.setattr(deflection_term, "_traces", traces)
    h = deflection_fit(sess)["heldout"]
    left = h["contact_steps"] / (h["contact_steps"] + h["dof"])
    assert left == pytest.approx(0.3, abs=0.05)
    assert h["excess_reduction"] > 0.9


def test_a_session_mostly_in_unreproduced_contact_claims_no_share(monkeypatch):
    # beyond the robust floor's breakdown (half the samples) the floor is the contacts' own:
    # the term then removes nothing measurable and the check says so
    sess, traces = _session(-30.0, seed=5)
    _contacts(sess, 0.7, seed=6)
    monkeypatch.setattr(deflection_term, "_traces", traces)
    fit = deflection_fit(sess)
    if fit["fitted"]:
        assert not fit["heldout"]["excess_reduction"] >= 0.5  # NaN: no excess over the floor
    else:
        assert "cannot size" in fit["reason"]
