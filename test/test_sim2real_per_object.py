"""Each particle's own offset, the same in every image (sim2real/per_object.py): seen against
the noise where it is, silent where the residual is noise, a plane across the sample, or noise a
constant factor larger than modelled; described as such; the simulator's per-particle term is
what it says (closed form)."""

import numpy as np
import pytest

from afm_core.instrument import LineRequest
from afm_core.sim.config import load_config, merge
from afm_core.sim.generic_terms import parse_generic_terms
from afm_core.sim.instrument import SimulatedAfm
from afm_core.sim2real.feature_table import Table
from afm_core.sim2real.per_object import EACH_ITS_OWN, differing, object_basis, object_offsets
from afm_core.sim2real.signature import describe

ANCHORS = np.array([[0.0, 0.0], [1.5e-6, 0.2e-6], [3.1e-6, -0.1e-6], [0.3e-6, 1.6e-6],
                    [1.8e-6, 1.7e-6], [3.2e-6, 1.5e-6]])  # fmt: skip
SIGMA = 0.5e-9  # m, each line peak's noise
PASSES = 8  # runs of lines over each particle


def _lines_table(rng):
    """Line-peak features: PASSES runs over each particle, in time order, each near (within
    50 nm of) its particle's place, untagged (particle_tags gives them the nearest anchor)."""
    n = len(ANCHORS) * PASSES
    which = np.tile(np.arange(len(ANCHORS)), PASSES)
    xy = ANCHORS[which] + rng.normal(0, 50e-9, (n, 2))
    return (
        Table(
            keys=[(i, "line.peak") for i in range(n)],
            groups=np.array(["line.peak"] * n),
            time=np.arange(n) * 10.0,
            xy=xy,
            u=np.zeros((n, 2)),
            conditions=[{"axis": "x"} for _ in range(n)],
            op_index=np.arange(n),
        ),
        which,
    )


def _offsets(r, table, sigma=SIGMA):
    cov = np.diag(np.full(len(r), sigma**2))
    P = np.zeros((len(r), 0))
    return object_offsets(table, r, cov, P, ANCHORS)


def test_each_particles_own_offset_is_seen_and_recovered():
    """Offsets of a few % of a 200 nm particle (4-8 nm), each its own, under 0.5 nm noise."""
    rng = np.random.default_rng(1)
    table, which = _lines_table(rng)
    truth = rng.normal(0, 6e-9, len(ANCHORS))
    r = truth[which] + rng.normal(0, SIGMA, len(which))
    out = _offsets(r, table)
    assert differing(out) == ["line.peak"]
    got = np.array([out["line.peak"]["objects"][str(k)][0] for k in range(len(ANCHORS))])
    sigmas = np.array([out["line.peak"]["objects"][str(k)][1] for k in range(len(ANCHORS))])
    # each within 4 of its sigmas (one sigma: SIGMA / sqrt(PASSES))
    assert np.all(np.abs(got - truth) < 4 * sigmas), (got, truth, sigmas)
    assert np.all(sigmas < 2 * SIGMA / np.sqrt(PASSES))


@pytest.mark.parametrize(
    "case",
    ["noise", "plane across the sample", "noise 5x the model's", "the same for all"],
)
def test_noise_a_plane_or_a_common_offset_is_no_particle_of_its_own(case):
    """The false alarms the test must not raise: over 40 seeds at most 4 (ALPHA = 5 %, plus
    a margin for 40 draws)."""
    alarms = 0
    for seed in range(40):
        rng = np.random.default_rng(100 + seed)
        table, which = _lines_table(rng)
        noise = rng.normal(0, SIGMA * (5.0 if "5x" in case else 1.0), len(which))
        if case.startswith("plane"):
            r = 4e-3 * table.xy[:, 0] - 2e-3 * table.xy[:, 1] + noise  # up to 12 nm
        elif case.startswith("the same"):
            r = 7e-9 + noise
        else:
            r = noise
        alarms += bool(differing(_offsets(r, table)))
    assert alarms <= 4, alarms


def test_the_signature_says_each_particle_differs_the_same_in_every_image():
    rng = np.random.default_rng(2)
    table, which = _lines_table(rng)
    truth = rng.normal(0, 6e-9, len(ANCHORS))
    r = truth[which] + rng.normal(0, SIGMA, len(which))
    sigma = np.full(len(r), SIGMA)
    objects = _offsets(r, table)
    # as the diagnosis may have it: the group's noise scaled up by the effect itself
    sig = describe(table, r, sigma, factors={"line.peak": 150.0}, objects=objects)
    assert sig.kind == "z"
    assert sig.particles["line.peak"]["alike"] is False
    assert sig.space["per_object"] and sig.space["form"] == EACH_ITS_OWN
    assert "each particle differs from the model by its own amount" in sig.text()
    # without the per-particle test the same residual is described as nothing at all
    assert not describe(table, r, sigma, factors={"line.peak": 150.0}).signals


def test_the_per_particle_generic_term_scales_only_its_particles_heights():
    """disc_proportional: the heights within its radius scaled by (1 + amplitude), the rest
    untouched (same seed: the difference is the term's alone)."""
    base = load_config()
    sphere = base.sample.spheres[0]
    x0, y0 = float(sphere["x"]), float(sphere["y"])
    term = {"signal": "height", "form": "disc_proportional", "amplitude": 0.05,
            "x0": x0, "y0": y0, "radius": 0.3e-6}  # fmt: skip
    request = LineRequest(x0 - 0.6e-6, y0, x0 + 0.6e-6, y0, 400, 1e-6)
    lines = [
        SimulatedAfm(config).local_scan(request)
        for config in (base, merge(base, {"generic_terms": [term]}))
    ]
    x = np.asarray(lines[0].x, float)
    h0, h1 = (np.asarray(line.height, float) for line in lines)
    diff = h1 - h0
    assert np.max(diff) > 0.04 * np.max(h0)  # the particle's top: 5 % of its height
    assert np.max(np.abs(diff)) <= 0.05 * np.max(np.abs(h0)) + 1e-15
    far = np.abs(x - x0) > 0.35e-6  # (the scanner's true place: the commanded one give or take)
    assert np.all(diff[far] == 0.0)


def test_a_per_particle_term_needs_its_place_and_a_positive_radius():
    entry = {"signal": "height", "form": "disc_proportional", "amplitude": 0.1, "x0": 0.0}
    with pytest.raises(ValueError, match=r"generic_terms\[0\].y0: required"):
        parse_generic_terms([entry])
    with pytest.raises(ValueError, match=r"generic_terms\[0\].radius=0.0: must be > 0"):
        parse_generic_terms([entry | {"y0": 0.0, "radius": 0.0}])
    with pytest.raises(ValueError, match="only on the height signal"):
        parse_generic_terms([entry | {"y0": 0.0, "radius": 1e-7, "signal": "torsion"}])


def test_the_per_particle_basis_is_one_term_per_configured_particle():
    basis = object_basis(["0", "2", "5", ""], ANCHORS)
    assert [(t.param("x0"), t.param("y0")) for t in basis] == [
        tuple(ANCHORS[k]) for k in (0, 2, 5)
    ]
    spacing = np.min([np.hypot(*(a - b)) for i, a in enumerate(ANCHORS) for b in ANCHORS[i + 1 :]])
    assert all(t.param("radius") == pytest.approx(0.5 * spacing) for t in basis)
