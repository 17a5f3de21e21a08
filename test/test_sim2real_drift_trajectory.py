"""sim2real's drift trajectory (drift_trajectory.drift_trajectory) on observations that do not
cover their time span: a long image's one observation, then a push's lines minutes later (the
README's session: launch, a 256 s image, a push). The fitted drift is compared with the linear
drift the observations were drawn from."""

import numpy as np

from afm_core.sim.config import load_config
from afm_core.sim2real.drift_trajectory import _covered_degree, drift_trajectory

V = -0.2e-9  # m/s, the true drift along x
IMAGE = (10.0, 266.0)  # s: the long image; its one observation at its particles' mean time
IMAGE_OBS = 115.6


def _observations(seed: int) -> list:
    rng = np.random.default_rng(seed)
    late = np.sort(rng.uniform(323.0, 349.0, 14))  # the push's local scans and lines
    obs = [(IMAGE_OBS, V * IMAGE_OBS, [(1, "raster", 0)])]
    obs += [(t, V * t + rng.normal(0.0, 1e-9), [(2 + i, "line", 0)]) for i, t in enumerate(late)]
    return obs


def test_the_degree_needs_observations_across_the_span():
    assert _covered_degree(np.linspace(0.0, 800.0, 41)) == 3
    two_stretches = np.sort(np.r_[IMAGE_OBS, np.linspace(323.0, 349.0, 14)])
    assert _covered_degree(two_stretches) == 1
    assert _covered_degree(np.array([5.0])) == 0


def test_two_stretches_of_observations_give_a_drift_without_a_swing_between_them():
    """A cubic through one observation and a cluster 200 s later swung by ~100 nm within the
    image between them; the image's particles were then placed and stretched by that swing
    (a false "not explained" on a plain simulated session)."""
    config = load_config()
    for seed in range(5):
        obs = _observations(seed)
        trajectory = drift_trajectory([obs, []], config, 360.0, spans={1: IMAGE})
        grid, drift = trajectory.times, trajectory.offsets[:, 0]
        between = (grid > IMAGE_OBS) & (grid < 323.0)
        assert np.max(np.abs(drift[between] - V * grid[between])) < 5e-9, seed


def test_the_drift_goes_back_over_the_first_observed_image_at_the_mean_velocity():
    """Before the image's one observation the drift was held constant, so the particles imaged
    in its first minute got none of the drift they had."""
    config = load_config()
    obs = _observations(0)
    with_spans = drift_trajectory([obs, []], config, 360.0, spans={1: IMAGE})
    held = drift_trajectory([obs, []], config, 360.0)
    at = np.searchsorted(with_spans.times, 50.0)
    assert abs(with_spans.offsets[at, 0] - V * 50.0) < 3e-9
    assert abs(held.offsets[at, 0] - V * IMAGE_OBS) < 1e-12  # held without the spans
