"""The tip-estimation corpus (afm_core.sim.tip_corpus) and the automatic threshold on it
(issue 35): the corpus images by the project's convention with its own code, its tips are
what their formulas say, and the automatic threshold, chosen from the image alone, lands near
the threshold a user who knew the true tip would pick."""

import numpy as np
import pytest

from afm_core.imaging import tip_estimation as te
from afm_core.imaging.tip_refinement import estimate_noise
from afm_core.physics.tip_morphology import dilate
from afm_core.sim import tip_corpus as tc

NM = 1e-9


def test_corpus_images_by_the_projects_convention_with_its_own_code():
    # an asymmetric tip makes a flipped convention show
    tip = tc.tip_grid(tc.TipModel("tilted", 10 * NM, 22.0, tilt_deg=12.0), 2 * NM, 7)
    rng = np.random.default_rng(3)
    surface = rng.uniform(0, 30 * NM, (40, 40))
    np.testing.assert_allclose(tc.image_surface(surface, tip), dilate(surface, tip), atol=1e-18)


@pytest.mark.parametrize("kind", tc.TIP_KINDS)
def test_corpus_tips_have_their_apex_at_the_centre(kind):
    model = tc.TipModel(kind, 10 * NM, 22.0, tilt_deg=12.0, separation=14 * NM, drop=3 * NM)
    tip = tc.tip_grid(model, 2 * NM, 10)
    assert tip.shape == (21, 21) and tip[10, 10] == 0.0 and tip.max() == 0.0


def test_corpus_tip_shapes_follow_their_formulas():
    pixel, r = 2 * NM, 10 * NM
    hyper = tc.tip_grid(tc.TipModel("hyperboloid", r, 20.0), pixel, 10)
    # near the apex a hyperboloid of apex radius R is the paraboloid -x^2 / 2R
    assert hyper[10, 11] == pytest.approx(-(pixel**2) / (2 * r), rel=0.05)
    # far out it is the cone of half-angle theta: slope 1 / tan(theta)
    wide = tc.tip_grid(tc.TipModel("hyperboloid", r, 20.0), pixel, 150)
    slope = (wide[150, 300] - wide[150, 299]) / pixel
    assert slope == pytest.approx(-1 / np.tan(np.radians(20.0)), rel=0.01)
    tilted = tc.tip_grid(tc.TipModel("tilted", r, 22.0, tilt_deg=12.0), pixel, 10)
    assert tilted[10, 20] < tilted[10, 0]  # +x flank steeper (half-angle theta - tilt)
    pyramid = tc.tip_grid(tc.TipModel("pyramid", r, 35.0), pixel, 10)
    assert pyramid[20, 20] == pytest.approx(pyramid[10, 20], rel=1e-9)  # square sections
    two = tc.TipModel("double", r, 20.0, separation=14 * NM, drop=2 * NM)
    double = tc.tip_grid(two, pixel, 10)
    assert double[10, 17] == pytest.approx(-2 * NM, rel=1e-6)  # the second apex, 7 px away


def test_corpus_design_covers_every_tip_sample_pixel_and_noise():
    cases = tc.corpus_cases(n=128, seeds=(0, 1))
    assert {c.tip.kind for c in cases} == set(tc.TIP_KINDS)
    assert {c.sample for c in cases} == set(tc.SAMPLE_KINDS)
    assert sorted({round(c.pixel / NM, 6) for c in cases}) == [1, 2, 4, 6, 10]
    assert sorted({round(c.noise / NM, 6) for c in cases}) == [0.1, 0.2, 0.3, 0.5, 1.0]
    for sample in tc.SAMPLE_KINDS:  # no sample is seen at one pixel size only
        assert len({round(c.pixel / NM) for c in cases if c.sample == sample}) >= 3
    image, surface, tip = tc.make_case(cases[0])
    noise = estimate_noise(image)
    assert noise == pytest.approx(cases[0].noise, rel=0.3)
    assert tip.shape == (21, 21) and np.all(image >= surface - 6 * cases[0].noise)


def test_auto_threshold_is_near_the_best_fixed_threshold_across_the_corpus():
    """Every other case of a seed the rule was not developed on (seed 2; developed on seeds
    0 and 3) at 160 px; measured there 2026-11-27: median 1.21, worst 3.58 (the steep error
    on both sides of the best threshold: one fine rung too high or low costs 1.5-3.5x). The
    level at 256 px on seeds 0 and 1 is in bench/results/tip-corpus.md."""
    ratios = []
    for case in tc.corpus_cases(n=160, seeds=(2,))[::2]:
        image, _, tip = tc.make_case(case)
        auto = te.estimate_tip(image, case.tip_size)
        _, best = tc.best_fixed_threshold(image, tip, case.tip_size, auto.noise, refine=0)
        ratios.append(te.tip_error(auto, tip, tc.score_depth(tip)) / best)
    print("auto / best fixed:", np.round(ratios, 2))
    assert np.median(ratios) <= 1.25
    assert max(ratios) <= 3.7
