"""An unexplained verdict that one sub-test raised stands only if its generic fit holds on the
other fold (replication.py)."""

import pytest
from scipy import stats

from afm_core.sim2real.evidence import ALPHA
from afm_core.sim2real.replication import heldout_confirms

QUIET = {"p": 0.9}  # the whole residual within its noise


def fitted(before, after, k=2, dof=50):
    return {
        "fitted": True,
        "form": "periodic in x",
        "parameters": k,
        "heldout": {"chi2_before": before, "chi2_after": after, "dof": dof},
    }


@pytest.mark.parametrize("k", [1, 2, 3])
def test_the_bound_is_chi2_k_at_alpha(k):
    bound = stats.chi2.isf(ALPHA, k)
    assert heldout_confirms(QUIET, fitted(60.0, 60.0 - bound - 0.01, k))[0]
    stands, why = heldout_confirms(QUIET, fitted(60.0, 60.0 - bound + 0.01, k))
    assert not stands and f"{bound:.1f}" in why


def test_a_fit_that_removes_nothing_or_made_it_worse_is_a_hint():
    assert not heldout_confirms(QUIET, fitted(52.0, 52.0))[0]
    worse = {"fitted": False, "reason": "the generic step fitted on one fold made it worse"}
    stands, why = heldout_confirms(QUIET, worse)
    assert not stands and "did not hold" in why


def test_what_cannot_be_checked_keeps_its_verdict():
    assert heldout_confirms(QUIET, {})[0]
    assert heldout_confirms(QUIET, {"fitted": False, "reason": "no feature sees it"})[0]
    nan = fitted(float("nan"), 3.0)
    assert heldout_confirms(QUIET, nan)[0]


def test_a_residual_beyond_its_noise_as_a_whole_needs_no_replication():
    assert heldout_confirms({"p": 1e-6}, fitted(52.0, 52.0))[0]
