"""Guard rails of blind tip estimation (issue 35): which tip pixels the image constrained, and
reconstructions that remove more than the tip's uncertainty allows."""

import subprocess
import sys
import warnings

import numpy as np
import pytest

from afm_core.imaging import tip_estimation as te
from afm_core.imaging import tip_guard as tg
from afm_core.imaging.files import HeightMap, load_height_map, save_height_map
from afm_core.physics.tip_morphology import dilate, erode
from afm_core.sim.characterizer import characterizer_image, default_tip

NM = 1e-9
PIXEL = 1.6e-9
NOISE = 0.3e-9
THRESHOLD = 1.5e-9  # a fixed N_TH (5 sigma): these tests are about the guard, not the choice


def crop(tip, size):
    c, h = tip.shape[0] // 2, size // 2
    return tip[c - h : c + h + 1, c - h : c + h + 1]


def distance(size):
    h = size // 2
    a, b = np.mgrid[-h : h + 1, -h : h + 1]
    return np.hypot(a, b)


def quiet(function, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tg.TipGuardWarning)
        return function(*args, **kwargs)


@pytest.fixture(scope="module")
def characterizer():
    return characterizer_image(n=192, pixel=PIXEL, noise=NOISE, seed=0)


def test_a_window_deeper_than_the_features_is_reported_and_warned_a_fitting_one_is_not(
    characterizer,
):
    image, surface, tip = characterizer
    tallest = float(surface.max())  # simulator truth: no feature reaches deeper than this
    with pytest.warns(tg.TipGuardWarning, match=r"only within \d+ px"):
        big = te.estimate_tip(image, 61, THRESHOLD, pixel_size=PIXEL)
    true = crop(tip, 61)
    c = big.constraint
    print(f"\n61x61: {c.summary(PIXEL)}\n  {big.warnings}")
    assert big.unconstrained is big.constraint.unconstrained and c.count > 0.1 * 61 * 61
    assert c.count == int(big.unconstrained.sum()) and c.share == c.count / 61**2
    assert np.all(np.isinf(big.uncertainty[big.unconstrained]))
    # a tip pixel deeper than the tallest feature is one the image could not reach: all of
    # them lie outside the supported radius, where no uncertainty is claimed
    unreachable = true < -tallest
    assert unreachable.sum() > 0 and np.all(np.isinf(big.uncertainty[unreachable]))
    assert distance(61)[unreachable].min() > c.radius
    # the supported window: all round constrained, short of the requested one
    assert c.radius < 30 and c.supported_size == 2 * c.radius + 1
    assert f"--tip-size (e.g. {c.supported_size})" in big.warnings[0]
    assert not np.any(big.unconstrained[distance(61) <= c.radius])
    # a window that fits: nothing unconstrained, no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error", tg.TipGuardWarning)
        small = te.estimate_tip(image, 21, THRESHOLD, pixel_size=PIXEL)
    assert small.warnings == [] and not small.unconstrained.any()
    assert small.constraint.radius == 10 and np.all(crop(tip, 21) > -tallest)
    # fallback uncertainty: threshold + 3 sigma of the image noise, 0 at the apex
    sigma = tg.estimate_noise(image)
    expected = np.full((21, 21), THRESHOLD + 3 * sigma)
    expected[10, 10] = 0.0
    np.testing.assert_allclose(small.uncertainty, expected, rtol=1e-12)


def test_flat_start_pixels_are_told_from_the_apex_plateau():
    tip = crop(default_tip(PIXEL, depth=60 * NM), 21)
    d = distance(21)
    band = THRESHOLD + 3 * NOISE
    # the refinement leaves at 0 the pixels whose bound lies within the threshold of 0 (the
    # plateau) and those no feature reached (here: the outer part)
    estimate = np.where(tip >= -THRESHOLD, 0.0, tip)
    estimate[d > 6] = 0.0
    c = tg.tip_constraint(estimate, THRESHOLD, NOISE)
    plateau = (tip >= -THRESHOLD) & (d <= 6)
    assert plateau.sum() > 1  # the test has a plateau beyond the apex
    np.testing.assert_array_equal(c.unconstrained, d > 6)
    assert c.at_start == int((d > 6).sum()) and c.at_floor == 0
    assert c.radius == 6 and c.supported_size == 13
    assert c.depth == pytest.approx(-estimate[np.rint(d) == 6].max())
    assert np.all(np.isfinite(c.uncertainty[~c.unconstrained]))
    np.testing.assert_array_equal(np.isinf(c.uncertainty), d > 6)
    assert "only within 6 px" in c.warnings[0]
    # the true tip itself, and its plateau version, are fully constrained
    for good in (tip, np.where(tip >= -THRESHOLD, 0.0, tip)):
        c = tg.tip_constraint(good, THRESHOLD, NOISE)
        assert c.count == 0 and c.radius == 10 and c.warnings == []
    # a flat plate: bounded within its resolution by an image taller than the threshold, but
    # shapeless; nothing but the apex is known when the threshold swallows the image's range
    plate = tg.tip_constraint(np.zeros((21, 21)), THRESHOLD, NOISE, height_range=50 * NM)
    assert plate.count == 0 and "no more than its resolution" in plate.warnings[0]
    flat = tg.tip_constraint(np.zeros((21, 21)), THRESHOLD, NOISE, height_range=THRESHOLD)
    assert flat.count == 21 * 21 - 1 and flat.radius == 0 and "nowhere" in flat.warnings[0]
    assert flat.at_floor == flat.count
    # an estimate flat within its resolution: constrained (bounded) but shapeless
    shallow = np.where(d <= 10, -0.5 * band * d / 10, -0.5 * band)
    c = tg.tip_constraint(shallow, THRESHOLD, NOISE)
    assert c.count == 0 and "no more than its resolution" in c.warnings[0]


def test_an_automatic_estimate_that_constrains_nothing_is_refused_a_fixed_one_warns():
    image, _, _ = characterizer_image(n=64, pixel=PIXEL, noise=NOISE, seed=1)
    plate = te.TipEstimate(np.zeros((21, 21)), 1e-6, 1, 0.0, noise=NOISE)
    with pytest.raises(ValueError, match=r"tip_size=21: .*radius 0 px < 1 px"):
        tg.guard_estimate(plate, image, refuse=True)
    with pytest.warns(tg.TipGuardWarning, match="nowhere around the apex"):
        tg.guard_estimate(plate, image, refuse=False)
    assert plate.unconstrained.sum() == 21 * 21 - 1 and len(plate.warnings) == 1


def tube_scene(noise, seed=0):
    """A 20 nm tube (a lying cylinder of radius 10 nm) on a flat substrate, imaged by the
    characteriser's tip, and that tip cropped to 21 x 21 px."""
    n = 96
    x = (np.arange(n) - n / 2 + 0.5) * PIXEL
    radius = 10 * NM
    profile = np.where(np.abs(x) < radius, radius + np.sqrt(np.clip(radius**2 - x**2, 0, None)), 0)
    surface = np.tile(profile, (n, 1))
    tip = crop(default_tip(PIXEL, depth=60 * NM), 21)
    image = dilate(surface, tip)
    if noise:
        image = image + np.random.default_rng(seed).normal(0, noise, image.shape)
    return surface, image, tip


def test_a_tip_with_unconstrained_outer_pixels_is_flagged_by_the_height_it_cuts():
    surface, image, true = tube_scene(NOISE)
    d = distance(21)
    blunt = true.copy()
    blunt[d > 6] = 0.0  # the outer part left at the flat start
    unc = tg.tip_constraint(blunt, THRESHOLD, NOISE).uncertainty
    with pytest.warns(tg.TipGuardWarning, match=r"removes up to [\d.]+ nm of a [\d.]+ nm feature"):
        check = tg.check_reconstruction(image, blunt, unc, noise=NOISE, pixel_size=PIXEL)
    inner = (slice(12, -12), slice(12, -12))  # away from the clamped edges
    loss = (surface - check.reconstruction)[inner]  # simulator truth: the height cut off
    crest = surface[inner] == surface.max()
    true_cut = float(loss[crest].mean())
    print(
        f"\ntube 20 nm: reconstructed crest {check.reconstruction[inner][crest].mean() / NM:.1f}"
        f" nm, true cut {true_cut / NM:.1f} nm, uncertain removal there "
        f"{check.uncertain_removal[inner][crest].mean() / NM:.1f} nm, max flagged "
        f"{check.max_removal / NM:.1f} nm; {check.warnings[0]}"
    )
    assert true_cut > 5 * NM  # the blunt tip does cut the tube
    assert check.flagged[inner][crest].all() and check.by_unconstrained[inner][crest].all()
    # the uncertain removal bounds the true cut (up to the noise) and is comparable to it
    assert np.all(check.uncertain_removal[inner] >= loss - 5 * NOISE)
    removal_at_crest = float(check.uncertain_removal[inner][crest].mean())
    assert true_cut - 3 * NOISE <= removal_at_crest <= true_cut + THRESHOLD + 6 * NOISE
    assert check.max_removal >= true_cut and 0.8 < check.height_there / surface.max() < 1.2
    assert 0.5 < check.flagged_share <= 1.0


def test_the_true_tip_is_not_flagged_and_the_upper_reconstruction_bounds_the_surface():
    surface, image, true = tube_scene(NOISE)
    unc = tg.tip_constraint(true, THRESHOLD, NOISE).uncertainty
    with warnings.catch_warnings():
        warnings.simplefilter("error", tg.TipGuardWarning)
        check = tg.check_reconstruction(image, true, unc, noise=NOISE)
    assert not check.flagged.any() and check.warnings == [] and check.location is None
    assert check.unconstrained_removal.max() == 0.0
    assert check.feature_height.max() == pytest.approx(surface.max(), abs=2 * NM)
    # closed form, noiseless: with the true tip within [t - U, t], r_upper >= r_true >= s
    clean_surface, clean, _ = tube_scene(0.0)
    exact = tg.check_reconstruction(clean, true, unc, noise=0.0)
    assert np.all(exact.upper >= clean_surface - 1e-15)
    assert np.all(exact.uncertain_removal >= 0)


def test_a_tip_with_its_base_at_0_is_moved_to_apex_0_and_an_off_centre_apex_is_refused():
    """Gwyddion's tips have their base at 0 and the apex above it; eroding with one as given
    lowers the whole reconstruction by the tip's depth without a word."""
    _, image, true = tube_scene(NOISE)
    unc = tg.tip_constraint(true, THRESHOLD, NOISE).uncertainty
    depth = -float(true.min())
    based = true + depth  # apex at +depth, base at 0
    ours = quiet(tg.check_reconstruction, image, true, unc, noise=NOISE)
    with pytest.warns(tg.TipGuardWarning, match=rf"apex was at \+{depth / NM:.3g} nm"):
        moved = tg.check_reconstruction(image, based, unc, noise=NOISE)
    np.testing.assert_allclose(moved.reconstruction, ours.reconstruction, rtol=0, atol=1e-15)
    # closed form: eroding with the tip as stored lowers everything by its depth
    np.testing.assert_allclose(erode(image, based), moved.reconstruction - depth, atol=1e-15)
    shifted = np.roll(true, 2, axis=1)  # the apex two pixels right of the centre
    with pytest.raises(ValueError, match=r"highest pixel \(row 10, column 12\)"):
        tg.check_reconstruction(image, shifted, unc, noise=NOISE)


def test_tip_files_carry_the_uncertainty_and_reconstruct_warns(tmp_path):
    surface, image, true = tube_scene(NOISE)
    blunt = true.copy()
    blunt[distance(21) > 6] = 0.0
    c = tg.tip_constraint(blunt, THRESHOLD, NOISE)
    tip_npz = tmp_path / "tip.npz"
    layers = {"uncertainty": c.uncertainty, "unconstrained": c.unconstrained}
    save_height_map(tip_npz, HeightMap(blunt, PIXEL, PIXEL, title="tip", layers=layers))
    back = load_height_map(tip_npz)
    np.testing.assert_array_equal(back.layers["uncertainty"], c.uncertainty)
    np.testing.assert_array_equal(back.layers["unconstrained"], c.unconstrained)
    scan = tmp_path / "tube.npz"
    save_height_map(scan, HeightMap(image, PIXEL, PIXEL))
    afm = [sys.executable, "-m", "afm_bringup.cli", "image", "reconstruct", str(scan)]
    for tip_file in (tip_npz, tmp_path / "tip.gwy"):
        if tip_file.suffix == ".gwy":
            save_height_map(tip_file, HeightMap(blunt, PIXEL, PIXEL, title="tip"))
        out = tmp_path / f"surface_{tip_file.suffix[1:]}.npz"
        run = subprocess.run(
            afm + ["--tip", str(tip_file), "-o", str(out)],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert run.returncode == 0, run.stderr
        assert out.exists()  # still written
        assert "warning: the tip is uncertain where it removes up to" in run.stderr
        assert ("carries no uncertainty" in run.stderr) == (tip_file.suffix == ".gwy")


def test_a_tip_too_blunt_for_the_image_is_flagged_even_where_it_claims_to_be_known():
    """A flat plate (a tip no image refined, given without uncertainty, as from a .gwy file)
    cuts 13 nm off a 20 nm tube: the fallback calls its pixels known (a plate is
    no flat start away from a drop), but the image is sharper than the plate allows (eroding
    and re-dilating it loses the tube), which the opening test flags. The true tip, whole or
    cropped to 5 x 5, is not flagged."""
    surface, image, true = tube_scene(NOISE)
    inner = (slice(12, -12), slice(12, -12))
    plate = np.zeros((21, 21))
    with pytest.warns(tg.TipGuardWarning, match="the tip cannot have taken this image"):
        check = tg.check_reconstruction(image, plate, None, pixel_size=PIXEL)
    cut = float((surface - check.reconstruction)[inner].max())
    residual = float(check.opening_residual[inner].max())
    print(f"\nplate: cut {cut / NM:.1f} nm, opening residual {residual / NM:.1f} nm")
    assert cut > 10 * NM and check.too_blunt.any() and check.flagged[check.too_blunt].all()
    assert 0.5 * cut <= residual <= cut + 5 * NOISE  # a lower bound of the cut, roughly
    assert check.by_unconstrained.sum() == 0  # the uncertainty rules alone miss it
    for good in (true, crop(true, 5)):
        with warnings.catch_warnings():
            warnings.simplefilter("error", tg.TipGuardWarning)
            ok = tg.check_reconstruction(
                image, good, tg.tip_constraint(good, 0, NOISE).uncertainty
            )
        assert not ok.too_blunt.any() and ok.opening_residual.max() < ok.opening_limit


def test_a_window_smaller_than_the_tips_reach_is_not_taken_for_a_blunt_tip():
    """Grains imaged by a chipped tip reaching beyond the 21 x 21 window: where the image was
    made by the tip's part outside the window, eroding and re-dilating with the cropped true
    tip loses more than the noise (on flanks, never on a crest), though erosion with a crop
    cuts nothing. Only residual regions holding a crest count."""
    from afm_core.sim import tip_corpus as tc

    chipped = tc.TipModel("chipped", 15e-9, 25.0, drop=4e-9)
    image, surface, true = tc.make_case(tc.Case(chipped, "grains", 2e-9, 0.1e-9, 160, 21, 324))
    with warnings.catch_warnings():
        warnings.simplefilter("error", tg.TipGuardWarning)
        check = tg.check_reconstruction(
            image, true, tg.tip_constraint(true, 0, 0.1e-9).uncertainty
        )
    assert np.all(check.reconstruction[12:-12, 12:-12] >= surface[12:-12, 12:-12] - 5e-10)
    assert check.opening_residual.max() > check.opening_limit  # the flank residual is there
    assert not check.too_blunt.any()
