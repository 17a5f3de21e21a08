"""The generic term's held-out check where the term reaches (generic_reach.py): a group whose
overdispersion factor the noise model needs for its own reasons, and which the term does not
move, neither loses its factor nor counts in the held-out excess the term is judged on."""

from types import SimpleNamespace

import numpy as np

from afm_core.sim2real.generic_reach import (
    REACH,
    group_reach,
    heldout_where,
    reached_groups,
)
from afm_core.sim2real.heldout import heldout_chi2
from afm_core.sim2real.noise_model import NoiseModel

RNG = np.random.default_rng(29)
N_A, N_B = 40, 80  # features of the effect's group and of an untouched, overdispersed one
SIGMA_A, SIGMA_B, FACTOR_B = 0.2e-9, 0.5e-9, 4.75


def _case():
    """Group A carries a sinusoid of 3 sigma amplitude in x (the effect); group B carries its
    own noise, FACTOR_B times the modelled variance, which the sinusoid's column moves by
    0.15 sigma at one feature (ACTS's 0.1 sigma would take it as acted on) and nowhere else."""
    groups = np.array(["A"] * N_A + ["B"] * N_B)
    x = np.concatenate([np.linspace(0.0, 5e-6, N_A), np.zeros(N_B)])
    sigma = np.concatenate([np.full(N_A, SIGMA_A), np.full(N_B, SIGMA_B)])
    col = np.where(groups == "A", np.sin(2 * np.pi * x / 1.8e-6), 0.0)
    col[N_A] = 0.15 * SIGMA_B / (3 * SIGMA_A)  # per unit amplitude: 0.15 sigma at the fit's
    signal = 3 * SIGMA_A * col
    noise_b = np.sqrt(FACTOR_B) * SIGMA_B * RNG.standard_normal(N_B)
    r0 = signal + np.concatenate([np.zeros(N_A), noise_b])
    cov = np.diag(sigma**2)
    noise = NoiseModel(white=sigma**2, cov=cov, group_sigma={"A": SIGMA_A, "B": SIGMA_B})
    P = np.zeros((N_A + N_B, 0))
    evidence = SimpleNamespace(unscaled=noise, group_factors={"B": FACTOR_B}, P=P)
    sess = SimpleNamespace(table=SimpleNamespace(groups=groups))
    return sess, evidence, r0, col[:, None], signal, sigma


def test_group_reach_is_the_change_in_sigmas_squared():
    sess, _, _, col, signal, sigma = _case()
    reach = group_reach(sess.table.groups, signal, sigma)
    a = sess.table.groups == "A"
    assert np.isclose(reach["A"], np.sum((signal[a] / SIGMA_A) ** 2))
    assert np.isclose(reach["B"], (signal[N_A] / SIGMA_B) ** 2)
    lost = signal.copy()
    lost[5] = np.nan  # a lost feature counts nothing
    assert np.isclose(
        group_reach(sess.table.groups, lost, sigma)["A"], reach["A"] - (signal[5] / SIGMA_A) ** 2
    )


def test_an_untouched_overdispersed_group_is_not_reached():
    sess, evidence, r0, col, _, _ = _case()
    reached, reach = reached_groups(sess, evidence, r0, col)
    assert reached == {"A"}
    assert reach["A"] > 100 * REACH and reach["B"] < REACH


def test_share_on_the_reached_groups_against_the_closed_form():
    """The exact effect removed: in the reached group (identity whitening, no nuisance) the
    chi^2 before is sum((signal/sigma)^2), after 0, so the share is before / (before - dof);
    over the whole session with B's factor dropped (the old check) B's own excess,
    (FACTOR_B - 1) x its features, joins the denominator and the share falls below half."""
    sess, evidence, r0, _, signal, _ = _case()
    test = np.ones(N_A + N_B, bool)
    r_after = r0 - signal
    where = sess.table.groups == "A"
    noise = evidence.unscaled  # B keeps no factor here: the old check's noise model
    check = heldout_where(noise, evidence.P, test, where, r0, r_after)
    before = float(np.sum((signal[where] / SIGMA_A) ** 2))
    assert np.isclose(check["chi2_before"], before, rtol=1e-6)
    assert np.isclose(check["chi2_after"], 0.0, atol=1e-6)
    assert check["dof"] == N_A
    assert np.isclose(check["excess_reduction"], before / (before - N_A), rtol=1e-6)
    whole = heldout_chi2(noise, evidence.P, test, r0, r_after)
    assert whole["excess_reduction"] < 0.5 < check["excess_reduction"]


def test_nuisance_columns_count_only_where_they_act():
    """A nuisance column that is zero on the reached groups takes no dof there; one that acts
    there takes one (a constant offset on A: the before is the spread about A's mean)."""
    sess, evidence, r0, _, signal, _ = _case()
    test = np.ones(N_A + N_B, bool)
    where = sess.table.groups == "A"
    P = np.stack([where.astype(float), (~where).astype(float)], 1)
    check = heldout_where(evidence.unscaled, P, test, where, r0, r0 - signal)
    z = signal[where] / SIGMA_A
    assert check["dof"] == N_A - 1
    assert np.isclose(check["chi2_before"], np.sum((z - z.mean()) ** 2), rtol=1e-6)
