"""The absolute levels' trend test (level_trend.py): a slow change of the substrate's level in
time, which the omnibus chi^2 of a normal-work session's ~20 levels dilutes."""

import numpy as np
import pytest
from scipy import stats

from afm_core.sim2real.feature_table import Table
from afm_core.sim2real.generic_fit import needs_description
from afm_core.sim2real.level_trend import level_trend, trend_sentence

NM = 1e-9


def _table(times, groups):
    n = len(times)
    return Table(
        keys=[(i, g) for i, g in enumerate(groups)],
        groups=np.array(groups),
        time=np.asarray(times, float),
        xy=np.zeros((n, 2)),
        u=np.zeros((n, 2)),
        conditions=[{} for _ in range(n)],
        op_index=np.arange(n),
    )


def _levels(n=20, span=300.0, others=5):
    """n raster levels over `span` s, then `others` features of another group."""
    times = np.r_[np.linspace(10.0, 10.0 + span, n), np.linspace(0, span, others)]
    groups = ["raster.level"] * n + ["line.pos"] * others
    table = _table(times, groups)
    offset = np.isin(table.groups, ("raster.level",)).astype(float)[:, None]
    return table, offset


def test_a_linear_change_of_the_levels_gives_its_closed_form_chi2():
    table, offset = _levels()
    sigma = 0.13 * NM
    lv = table.groups == "raster.level"
    t = table.time[lv]
    slope = 0.7 * NM / 300.0  # the settling's 0.7 nm over the session
    r = np.zeros(len(table.keys))
    r[lv] = 2.0 * NM + slope * t  # any offset: it is the levels' unknown zero
    r[~lv] = 1e-6  # another group's residual, far beyond its noise, is not a level
    cov = np.eye(len(r)) * sigma**2
    out = level_trend(table, r, cov, offset)
    # GLS of a line with an offset on white noise: chi2 = slope^2 sum (t - mean t)^2 / sigma^2
    closed = slope**2 * float(np.sum((t - t.mean()) ** 2)) / sigma**2
    assert out["chi2"] == pytest.approx(closed, rel=1e-6)
    assert out["dof"] == 3 and out["n"] == lv.sum()
    assert out["p"] == pytest.approx(stats.chi2.sf(closed, 3), rel=1e-6)
    # a level group whose noise the diagnosis scaled by 2 scales the chi^2 down by 2
    halved = level_trend(table, r, cov, offset, {"raster.level": 2.0})
    assert halved["chi2"] == pytest.approx(closed / 2, rel=1e-6)


def test_the_trend_test_holds_its_false_alarm_rate_on_correlated_noise():
    """Noise with a slow wander (a random walk of the levels, which itself looks like a trend)
    over white noise: with the covariance whitened p is uniform; read with its diagonal alone
    the same draws alarm 130 times in 400 at 5 %."""
    table, offset = _levels()
    n = len(table.keys)
    lv = table.groups == "raster.level"
    sigma = 0.13 * NM
    t = table.time
    cov = np.eye(n) * 0.2 * sigma**2
    cov += sigma**2 * np.minimum(t[:, None], t[None, :]) / 100.0 * np.outer(lv, lv)
    chol = np.linalg.cholesky(cov)
    rng = np.random.default_rng(7)
    ps = np.array(
        [level_trend(table, chol @ rng.normal(size=n), cov, offset)["p"] for _ in range(400)]
    )
    # 400 draws: 5 % at 0.05 is 20 +- 4.4
    assert 8 <= np.sum(ps < 0.05) <= 34
    assert stats.kstest(ps, "uniform").pvalue > 1e-3


def test_too_few_levels_or_no_span_tell_nothing_and_a_bad_degree_is_an_error():
    table, offset = _levels(n=5)
    r = np.zeros(len(table.keys))
    assert level_trend(table, r, np.eye(len(r)), offset) == {}
    table, offset = _levels(n=10, span=0.0)
    assert level_trend(table, np.zeros(len(table.keys)), np.eye(len(table.keys)), offset) == {}
    with pytest.raises(ValueError, match="degree: 0 must be >= 1"):
        level_trend(table, np.zeros(len(table.keys)), np.eye(len(table.keys)), offset, degree=0)


def test_a_slow_change_of_the_levels_is_described_though_its_group_chi2_is_diluted():
    """The normal-work session's settling: the level group at p = 8e-4 (under the per-group
    limit of 1e-3 over 11 groups), the whole residual quiet; its trend at p = 4e-8."""
    quiet = {"p": 0.47, "group_factors": {}}
    groups = {f"g{k}": {"p": 0.5} for k in range(10)}
    groups["raster.level"] = {"p": 8e-4}
    assert not needs_description(quiet, [], {}, groups)
    assert needs_description(quiet, [], {}, groups, {"chi2": 37.3, "dof": 3, "p": 4e-8})
    # a trend no stronger than noise keeps the verdict
    assert not needs_description(quiet, [], {}, groups, {"chi2": 3.0, "dof": 3, "p": 0.39})


def test_a_linear_change_of_the_levels_says_what_the_session_cannot_tell():
    table, offset = _levels(span=280.0)
    r = np.where(table.groups == "raster.level", 1e-12 * table.time, 0.0)
    trend = level_trend(table, r, np.eye(len(r)) * (0.13 * NM) ** 2, offset)
    assert trend["span"] == pytest.approx(280.0)
    linear = trend_sentence(trend, "linear trend")
    assert "cannot tell whether the change goes on or settles" in linear and "280 s" in linear
    assert "cannot tell" not in trend_sentence(trend, "smooth")
