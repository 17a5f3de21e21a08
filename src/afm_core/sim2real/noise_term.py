"""Sensor noise first: the white- and coloured-noise candidates, judged on the noise statistics.

Only a noise term moves the noise statistics (line-offset and pixel-to-pixel noise of images,
`raster.streak`, `raster.pixel_noise`), and every other feature's noise model depends on it:
the white- and coloured-noise candidates are tested on those statistics alone (same threshold
and held-out rule), fitted by re-simulation with the replicas' seeds (only the noise level
differs); the one with the larger BIC gain is named, and the replicas are redrawn at its fitted
level before the other candidates are judged (a noisier instrument's images must not pass for a
scanner bow or a blunter tip). The z gain the particle heights show is taken out of the
statistics first (a gain scales the roughness too), and their covariance has a part common to
each group's blocks from other realizations of the substrate's roughness (the recording's
sample is its own). A noise term's level is read off a smooth curve of the statistics through
re-simulations at a few levels (`_NoiseCurve`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from scipy import stats

from afm_core.sim.config import SimConfig, merge
from afm_core.sim2real.candidates import Candidate, merge_overrides
from afm_core.sim2real.evidence import ALPHA, cv_gain_on
from afm_core.sim2real.feature_table import HEIGHT_GROUPS
from afm_core.sim2real.features import STREAK_MIN_LINES
from afm_core.sim2real.line_shift import LINE_SHIFT_GROUP
from afm_core.sim2real.noise_floor import statistic_variance
from afm_core.sim2real.noise_model import Whitener, gls, group_overdispersion, pooled_white
from afm_core.sim2real.reference import ReferenceSession
from afm_core.sim2real.results import CandidateResult

# other substrates and noise draws the noise statistics' common part is taken from
REALIZATIONS = 6
NOISE_LEVELS = 5  # re-simulated levels a noise term's statistics curve is fitted through
NOISE_WIDENINGS = 3  # times that curve's range may grow towards a level beyond it
NOISE_PROFILE_POINTS = 2001  # levels its chi^2 profile is evaluated on
NOISE_ZOOM = 4.0  # sigmas either side of the level the curve is fitted again through


def _noise_columns(sess: ReferenceSession, cand: Candidate, theta0: np.ndarray) -> np.ndarray:
    """Design columns of a sensor-noise term at the model's noise: its noise statistics
    re-simulated with the noise replicas' seeds at each stepped value and at the model's."""
    cols = []
    for j in range(cand.size):
        theta = theta0.copy()
        theta[j] += cand.steps[j]
        sim = sess.noise_features(cand.overrides(sess.config, theta))
        cols.append(
            np.where(
                sess.noisy, np.nan_to_num((sim - sess.noise_features({})) / cand.steps[j]), 0.0
            )
        )
    return np.array(cols).T


def _noise_statistics_covariance(
    sess: ReferenceSession,
    level: dict,
    nom: np.ndarray,
    columns: list,
    residual: np.ndarray | None = None,
) -> np.ndarray:
    """Covariance of the noise statistics at the noise level `level` (overrides): their
    replicas' spread, times each group's overdispersion in `residual` (the session's by
    default) after the best single fit of `columns`, plus a part common to each group's
    blocks: how far other realizations of the substrate's roughness and of the noise move the
    group's mean, beyond what the blocks' own spread puts on it.

    The replicas share the reference's sample, so they cannot show how the recording's own
    roughness differs. Scattered over the blocks (left unscaled, it pulled a coloured-noise fit
    off by a fifth) the overdispersion takes it; in common (the recording's whole substrate a
    little rougher at the pixel scale than the reference's: +1.4 % in one session with a
    three-fold friction) only the common part does, and without it white noise was named. The
    noise has a common part too: the 1/f generator scales each image's draw to its level, so a
    draw heavy in slow wander is light in fast noise in every block (at 1.5 nm the pixel noise's
    mean over 16 blocks varied by 2.9 % from draw to draw, where independent blocks give 1.3 %;
    fitted without it, 1.576 +- 0.022 nm against 1.5)."""
    replicas = sess.noise_replicas(level, rasters_only=True)
    noisy = sess.noisy
    groups = sess.table.groups[noisy]
    variance, _ = pooled_white(replicas[:, noisy], groups, 4.0, nom[noisy])
    # what the replicas cannot show: a line-shift statistic's own sampling (noise_floor.py)
    variance = variance + statistic_variance(sess.table)[noisy]
    residual = sess.r if residual is None else residual
    factors = group_overdispersion(
        residual[noisy],
        np.zeros((int(noisy.sum()), 0)),
        [c[noisy] for c in columns],
        np.diag(variance),
        groups,
    )
    # the lines' own shifts keep their modelled noise (line_shift.py): a factor hides them
    factors.pop(LINE_SHIFT_GROUP, None)
    cov = np.diag(variance * np.array([factors.get(g, 1.0) for g in groups]))
    offsets = sess.realization_offsets(REALIZATIONS, level)[:, noisy]
    for group in np.unique(groups):
        sel = groups == group
        independent = float(np.mean(variance[sel])) / int(sel.sum())
        cov[np.ix_(sel, sel)] += max(
            float(np.mean(np.mean(offsets[:, sel], axis=1) ** 2)) - independent, 0.0
        )
    return cov


class _SingleTermTest(NamedTuple):
    coef: np.ndarray
    cov: np.ndarray
    delta: float  # chi^2 gain over no term, divided by the overdispersion after the fit
    factor: float  # that overdispersion (>= 1)
    threshold: float  # the Bonferroni threshold over the library's m terms


def _single_term_test(rw: np.ndarray, xw: np.ndarray, cand: Candidate, m: int) -> _SingleTermTest:
    """One term's whitened columns fitted to a whitened residual with no nuisance columns
    (features the rest of the diagnosis does not fit: noise statistics, heights): its evidence
    against none."""
    _, chi2_0, _ = gls(rw, np.zeros((len(rw), 0)))
    coef, chi2, cov = gls(rw, xw)
    factor = max(
        1.0, chi2 / max(1, len(rw) - cand.size)
    )  # features noisier than their replicas say
    return _SingleTermTest(
        coef,
        cov,
        (chi2_0 - chi2) / factor,
        factor,
        float(stats.chi2.isf(ALPHA / m, cand.complexity)),
    )


def _height_gain(
    sess: ReferenceSession, cand: Candidate, replicas: np.ndarray, nom: np.ndarray, m: int
):
    """The z gain the particle heights alone show (GLS with their replicas' spread, scaled by
    their overdispersion), or None when they show none beyond the Bonferroni threshold."""
    rows = np.isin(sess.table.groups, HEIGHT_GROUPS) & np.isfinite(sess.r)
    if rows.sum() < 2:
        return None
    theta0 = cand.nominal(sess.config)
    variance, _ = pooled_white(replicas[:, rows], sess.table.groups[rows], 4.0, nom[rows])
    white = Whitener(np.diag(variance))
    test = _single_term_test(
        white(sess.r[rows]),
        white((sess.reference[rows] / max(theta0[0], 1e-12))[:, None]),
        cand,
        m,
    )
    return cand.clip(theta0 + test.coef) if test.delta > test.threshold else None


def gain_on_noise_statistics(
    sess: ReferenceSession, cand: Candidate, gain: np.ndarray
) -> np.ndarray:
    """How a z gain of `gain` changes the noise statistics (0 on other features), re-simulated
    with the noise replicas' seeds at the reference's noise level."""
    at_gain = sess.noise_features(
        merge_overrides(sess.noise_reference, cand.overrides(sess.config, gain))
    )
    return np.where(
        sess.noisy, np.nan_to_num(at_gain - sess.noise_features(sess.noise_reference)), 0.0
    )


def _noise_term(
    sess: ReferenceSession, design: tuple, statistics_cov: np.ndarray, folds: list, m: int
):
    """Evidence and fit of a sensor-noise term (its (candidate, nominal, columns) design triple)
    on the noise statistics alone (no other term moves them): GLS with their covariance, the
    Bonferroni threshold, held-out blocks, and the level from its chi^2 profile. Returns the
    design triple, its CandidateResult (estimate, sigma and evidence: the profile's) and its
    _NoiseCurve (None when it is not accepted)."""
    noisy = sess.noisy
    cand, theta0, cols = design
    white = Whitener(statistics_cov)
    none = np.zeros((int(noisy.sum()), 0))
    r = sess.r[noisy]
    test = _single_term_test(white(r), white(cols[noisy]), cand, m)
    factor = test.factor
    res = CandidateResult(
        cand.name,
        cand.words,
        cand.keys,
        cand.units,
        cand.size,
        estimate=theta0 + test.coef,
        sigma=np.sqrt(np.abs(np.diag(test.cov)) * factor),
        delta_chi2=test.delta,
        statistic_threshold=test.threshold,
        bic_gain=test.delta - cand.complexity * math.log(max(len(r), 2)),
    )
    res.significant = test.delta > res.statistic_threshold
    if res.significant:
        sub_folds = [f[noisy] for f in folds]
        whiteners = [
            (Whitener(statistics_cov[np.ix_(f, f)]), Whitener(statistics_cov[np.ix_(~f, ~f)]))
            for f in sub_folds
        ]
        res.heldout_gain = cv_gain_on(r, cols[noisy], none, sub_folds, whiteners)
        res.accepted = res.heldout_gain > 0
        if not res.accepted:
            res.note = "fits the session but does not predict held-out blocks"
    if not res.accepted:
        return design, res, None
    # the evidence is the fit's, not the derivative's: noise levels add in quadrature, so a line
    # through the model's value misses a large change (1/f noise 7.5 x the model's fitted to
    # chi^2 85 along it, 6.5 at its value) and a white noise, straighter there, passed for it
    curve, (level, sigma, chi2_level) = _NoiseCurve.fit(
        sess, cand, float(cand.clip(res.estimate)[0]), white
    )
    res.estimate, res.sigma = np.array([level]), np.array([sigma])
    res.delta_chi2 = (float(np.sum(white(r) ** 2)) - chi2_level) / max(
        1.0, chi2_level / max(1, len(r) - cand.size)
    )
    res.bic_gain = res.delta_chi2 - cand.complexity * math.log(max(len(r), 2))
    return design, res, curve


class _NoiseCurve(NamedTuple):
    """The noise statistics as smooth functions of a noise term's level s: per feature,
    statistic^2 = a + b (s / high)^2, fitted through re-simulations (with the noise replicas'
    seeds) at NOISE_LEVELS levels spread evenly in variance over [low, high]. The statistics
    are robust spreads of noises that add in quadrature: over 0 .. 2.4 nm of 1/f noise the
    curve passes within 0.2 of the replicas' sigma of the re-simulations; over 0 .. 5 nm the
    pixel noise bends 1.7 % away from it, hence `zoom`. The recording is compared with the
    curve, not with re-simulations one by one: their jitter had secant iterations wander
    between 0.03 and 0.06 nm around a flat minimum at 0.005."""

    low: float
    high: float
    a: np.ndarray
    b: np.ndarray

    @classmethod
    def through(
        cls, sess: ReferenceSession, cand: Candidate, low: float, high: float
    ) -> _NoiseCurve:
        levels = np.sqrt(np.linspace(low**2, high**2, NOISE_LEVELS))
        stats = sess.noise_features_along(cand, levels)[:, sess.noisy]
        # per feature, least squares in the squares' relative error (the lowest levels as
        # closely as the highest)
        x = np.stack([np.ones(NOISE_LEVELS), (levels / high) ** 2], axis=1)
        y = np.nan_to_num(stats) ** 2
        w = 1.0 / np.maximum(y, 1e-300) ** 2
        normal = np.einsum("ki,kj,kn->nij", x, x, w)
        a, b = np.linalg.solve(normal, np.einsum("ki,kn->ni", x, w * y)[..., None])[..., 0].T
        return cls(low, high, a, b)

    @classmethod
    def fit(cls, sess: ReferenceSession, cand: Candidate, around: float, white: Whitener):
        """Through 0 .. 1.5 x max(the model's level, `around`), widened while the chi^2 profile's
        minimum (whitened by `white`) lies beyond. Returns the curve and that profile."""
        high = 1.5 * max(float(cand.nominal(sess.config)[0]), around, 1e-15)
        for _ in range(NOISE_WIDENINGS + 1):
            curve = cls.through(sess, cand, 0.0, high)
            profile = curve.profile(sess, white)
            if profile[0] <= high:
                break
            high = 1.5 * profile[0]
        return curve, profile

    def zoom(self, sess: ReferenceSession, cand: Candidate, white: Whitener) -> _NoiseCurve:
        """The curve again through NOISE_ZOOM sigmas either side of its profile's minimum."""
        level, sigma, _ = self.profile(sess, white)
        half = max(NOISE_ZOOM * sigma, 1e-3 * level, 1e-15)
        return self.through(sess, cand, max(0.0, level - half), level + half)

    def levels(self) -> np.ndarray:
        """Where the profile is evaluated: from 0 to 4 x the top over a curve from 0, one width
        either side of a zoomed one."""
        width = self.high - self.low
        low, high = (
            (0.0, 4.0 * self.high)
            if self.low == 0.0
            else (max(0.0, self.low - width), self.high + width)
        )
        return np.linspace(low, high, NOISE_PROFILE_POINTS)

    def statistics(self, levels) -> np.ndarray:
        """(len(levels), noisy features)."""
        levels = np.atleast_1d(np.asarray(levels, float))
        return np.sqrt(
            np.maximum(self.a[None, :] + self.b[None, :] * (levels[:, None] / self.high) ** 2, 0.0)
        )

    def residual(self, sess: ReferenceSession, levels) -> np.ndarray:
        """(noisy features, len(levels)): the recording's statistics (less what a fitted z gain
        adds to them) minus the curve's."""
        target = (sess.r + sess.reference)[sess.noisy]
        return target[:, None] - self.statistics(levels).T

    def profile(self, sess: ReferenceSession, white: Whitener):
        """(level, sigma, chi^2 at the level) on levels(). sigma: half the width of the levels
        whose chi^2 lies within the overdispersion left at the minimum of it (near 0 the
        interval is lopsided; half its width is what one number can say)."""
        grid = self.levels()
        chi2 = np.sum(white(self.residual(sess, grid)) ** 2, axis=0)
        best = int(np.argmin(chi2))
        factor = max(1.0, chi2[best] / max(1, int(sess.noisy.sum()) - 1))
        outside = np.flatnonzero(chi2 > chi2[best] + factor)
        low = grid[outside[outside < best].max() + 1] if (outside < best).any() else grid[0]
        high = grid[outside[outside > best].min() - 1] if (outside > best).any() else grid[-1]
        return float(grid[best]), 0.5 * float(high - low), float(chi2[best])


class NoiseFirst(NamedTuple):
    """What the sensor-noise stage leaves the rest of the diagnosis."""

    design: tuple | None  # the named noise term's (candidate, nominal, columns), or None
    result: CandidateResult | None  # its result (estimate: the fitted level)
    config: SimConfig  # the config at that level (the model's when none is named)
    replicas: np.ndarray  # (K, N) sensor-noise replicas at that level
    terms: list  # (design, result, curve) of every noise term tested


def sensor_noise_first(
    sess: ReferenceSession,
    cands: list,
    folds: list,
    m: int,
    missing: list,
    say: Callable[[str], None],
) -> NoiseFirst:
    """The sensor-noise candidates among `cands` tested on the noise statistics; the one named
    is fitted, and the session's reference and replicas are redrawn at its level (`missing`
    gains the noise terms a recording without long enough images cannot test)."""
    config, nom, n = sess.config, sess.nominal, len(sess.keys)
    noise_design, noise_result, noise_config = None, None, config
    rep_s = sess.replicas
    noise_terms = []  # (design triple, result, curve) of every sensor-noise term
    noise_cands = [c for c in cands if c.analytic == "sensor_noise"]
    # a z gain scales the substrate's roughness, and with it the noise statistics (a gain of
    # 1.2 raised the pixel noise by 4 %, and white noise was named for it): the gain the
    # particle heights show is taken out of the noise statistics before a noise term is judged
    gain_cand = next((c for c in cands if c.analytic == "height_gain"), None)
    gain_on_noise = np.zeros(n)
    if noise_cands and not sess.noisy.any():
        missing += [
            f"{c.name} (the recording has no image with {STREAK_MIN_LINES} lines or more)"
            for c in noise_cands
        ]
    elif noise_cands:
        gain = _height_gain(sess, gain_cand, rep_s, nom, m) if gain_cand is not None else None
        if gain is not None:
            gain_on_noise = gain_on_noise_statistics(sess, gain_cand, gain)
            sess.r = sess.r - gain_on_noise
        noise_designs = []
        for cand in noise_cands:
            say(f"sensitivity: {cand.name}")
            theta0 = cand.nominal(config)
            noise_designs.append((cand, theta0, _noise_columns(sess, cand, theta0)))
        noise_cov = _noise_statistics_covariance(sess, {}, nom, [d[2] for d in noise_designs])
        noise_terms = [_noise_term(sess, d, noise_cov, folds, m) for d in noise_designs]
    # one noise level is fitted: the term the statistics favour (white noise raises the
    # line-offset noise a little too, so a grainier instrument can also pass the coloured
    # noise's test, with less evidence)
    best = max(
        [t for t in noise_terms if t[1].accepted], key=lambda t: t[1].bic_gain, default=None
    )
    if best is not None:
        noise_design, noise_result, curve = best
        noise_config, rep_s = _fit_level(sess, noise_design[0], noise_result, curve, say)
    else:
        sess.r = sess.r + gain_on_noise  # the gain's term explains it, with the heights
    for _, res, _ in noise_terms:
        if res.accepted and res is not noise_result:
            res.accepted = False
            res.note = f"explains the noise statistics less well than {noise_design[0].name}"
    return NoiseFirst(noise_design, noise_result, noise_config, rep_s, noise_terms)


def _fit_level(
    sess: ReferenceSession,
    cand: Candidate,
    result: CandidateResult,
    curve: _NoiseCurve,
    say: Callable[[str], None],
):
    """The named noise term's level and sigma (into `result`), and the session's reference at
    that level: (the config with it, the sensor-noise replicas at it)."""
    config, nom, n = sess.config, sess.nominal, len(sess.keys)
    # its sigma is the statistics' spread at the fitted level, not at the model's (1/f noise
    # 7.5 x the model's: +-0.010 nm with the model's spread, 0.06 with its own), and its
    # level is read off the curve fitted again around it (1.609 nm on the curve through
    # 0 .. 5 nm, 1.58 on one through the level +-4 sigma: the truth was 1.5)
    level_residual = np.zeros(n)
    level_residual[sess.noisy] = curve.residual(sess, result.estimate)[:, 0]
    level_cov = _noise_statistics_covariance(
        sess, cand.overrides(config, result.estimate), nom, [], residual=level_residual
    )
    level_white = Whitener(level_cov)
    level, sigma, _ = curve.zoom(sess, cand, level_white).profile(sess, level_white)
    result.estimate, result.sigma = np.array([level]), np.array([sigma])
    say(f"noise replicas at the fitted {cand.name}")
    fitted = cand.overrides(config, result.estimate)
    noise_config = merge(config, fitted)
    rep_s = sess.noise_replicas(fitted)
    bias = np.nan_to_num(np.nanmean(rep_s - nom, axis=0))
    sess.set_reference(nom + bias, bias, fitted)
    return noise_config, rep_s
