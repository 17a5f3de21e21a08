"""The absolute `line.level` feature takes a line's substrate only where both its edges are on
the substrate (features_absolute.edges_on_substrate)."""

from types import SimpleNamespace

import numpy as np
import pytest

from afm_core.sim2real.features import EDGE_FRACTION, Feature
from afm_core.sim2real.features_absolute import AbsoluteLevels, edges_on_substrate

NM = 1e-9
SAMPLES = 200  # 800 nm at 4 nm, as the protocol's lines
LENGTH = 800 * NM
RADIUS = 100 * NM  # a particle of the model's size (200 nm high)


def _line(index: int, level: float, rng, particle_at=None, noise: float = 0.3 * NM):
    """A scan line along x over bare substrate at `level` with white noise; with a sphere of
    RADIUS whose centre is `particle_at` (m along the line) where the sphere stands higher."""
    x = np.linspace(0.0, LENGTH, SAMPLES)
    h = level + rng.normal(0.0, noise, SAMPLES)
    if particle_at is not None:
        cap = RADIUS + np.sqrt(np.clip(RADIUS**2 - (x - particle_at) ** 2, 0.0, None))
        h = np.where(np.abs(x - particle_at) < RADIUS, np.maximum(h, level + cap), h)
    data = SimpleNamespace(
        height=h, times=np.linspace(0.0, 1.0, SAMPLES), start_time=float(index),
        x=x, y=np.zeros(SAMPLES),
    )  # fmt: skip
    return SimpleNamespace(index=index, data=data, start=(0.0, 0.0), end=(LENGTH, 0.0))


def _edge_median(op) -> float:
    h = op.data.height
    edge = max(3, int(EDGE_FRACTION * h.size))
    return float(np.median(np.concatenate([h[:edge], h[-edge:]])))


def test_a_line_whose_last_edge_is_on_a_particle_does_not_enter_the_level():
    """Reference run at 0, then a run at 5 nm of three lines, the last ending on a particle
    (its top 30 nm inside the line's end, as null-4's lines): the level is the mean of the two
    bare lines' edge medians exactly, within the noise of 5 nm; the particle's line, had it
    entered, would have moved it by tens of nm."""
    rng = np.random.default_rng(4)
    levels = AbsoluteLevels(Feature, EDGE_FRACTION, block=8, min_lines=16)
    assert levels.run([_line(0, 0.0, rng), _line(1, 0.0, rng)], {}) == []  # the reference
    level = 5 * NM
    bare = [_line(2, level, rng), _line(3, level, rng)]
    on_particle = _line(4, level, rng, particle_at=LENGTH - 30 * NM)
    assert not edges_on_substrate(on_particle.data.height, 20)
    (feature,) = levels.run([*bare, on_particle], {})
    assert feature.conditions["lines"] == 2
    expected = np.mean([_edge_median(op) for op in bare]) - levels.reference[0]
    assert feature.value == pytest.approx(expected, abs=1e-15)
    assert abs(feature.value - level) < 0.5 * NM
    assert abs(_edge_median(on_particle) - level) > 10 * NM  # what the rule keeps out


def test_bare_lines_keep_both_edges_whatever_their_noise():
    """Lines over bare substrate pass at any noise level (the agreement scales with the edges'
    own spread): none of 200 noisy lines per level is left out."""
    rng = np.random.default_rng(5)
    for noise in (0.05 * NM, 0.3 * NM, 2 * NM):
        lines = [_line(0, 0.0, rng, noise=noise).data.height for _ in range(200)]
        assert all(edges_on_substrate(h, 20) for h in lines), noise


def test_edges_on_substrate_names_a_bad_edge():
    with pytest.raises(ValueError, match="edge"):
        edges_on_substrate(np.zeros(10), 6)
