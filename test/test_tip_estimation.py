"""Blind tip estimation (book ch. 4, Villarrubia 1997) against brute force, closed forms and the
simulator's ground truth, with an asymmetric tip (blunt +x flank)."""

import time

import numpy as np
import pytest

from afm_core.imaging import tip_estimation as te
from afm_core.imaging import tip_refinement as tr
from afm_core.physics.tip_morphology import dilate, erode
from afm_core.sim.characterizer import characterizer_image, default_tip
from afm_core.sim.tip import paraboloid_cone_tip

NM = 1e-9


def crop(tip, size):
    c, h = tip.shape[0] // 2, size // 2
    return tip[c - h : c + h + 1, c - h : c + h + 1]


def brute_dilate(surface, tip):
    """i(x) = max_u s(x+u) + t(u), edges clamped, straight from the definition."""
    h = tip.shape[0] // 2
    padded = np.pad(surface, h, mode="edge")
    ny, nx = surface.shape
    out = np.full(surface.shape, -np.inf)
    for a in range(-h, h + 1):
        for b in range(-h, h + 1):
            out = np.maximum(
                out, padded[h + a : h + a + ny, h + b : h + b + nx] + tip[h + a, h + b]
            )
    return out


def brute_erode(image, tip):
    """r(y) = min_u i(y-u) - t(u), edges clamped, straight from the definition."""
    h = tip.shape[0] // 2
    padded = np.pad(image, h, mode="edge")
    ny, nx = image.shape
    out = np.full(image.shape, np.inf)
    for a in range(-h, h + 1):
        for b in range(-h, h + 1):
            out = np.minimum(
                out, padded[h - a : h - a + ny, h - b : h - b + nx] - tip[h + a, h + b]
            )
    return out


def brute_blind(image, tip_size, threshold):
    """Villarrubia's refinement from its definition, loops everywhere (tiny cases only), with
    the image edges used as Gwyddion's use_edges does: a contact whose apex falls outside the
    image is admissible (nothing there holds the apex down), and a tip pixel with an admissible
    contact that puts it outside the image is not refined from that point."""
    h = tip_size // 2
    ny, nx = image.shape
    tip = np.zeros((tip_size, tip_size))
    offsets = [(a, b) for a in range(-h, h + 1) for b in range(-h, h + 1)]

    def inside(y, x):
        return 0 <= y < ny and 0 <= x < nx

    changed = True
    while changed:
        changed = False
        for y in range(h, ny - h):
            for x in range(h, nx - h):
                i0 = image[y, x]
                contacts = [
                    (a, b)
                    for a, b in offsets
                    if not inside(y + a, x + b)
                    or i0 - image[y + a, x + b] <= tip[h + a, h + b] + 1e-9 * np.ptp(image)
                ]
                for wa, wb in offsets:
                    if not all(inside(y + a - wa, x + b - wb) for a, b in contacts):
                        continue
                    bound = max(
                        image[y + a - wa, x + b - wb] - i0 + tip[h + a, h + b] for a, b in contacts
                    )
                    if bound + threshold < tip[h + wa, h + wb] - 1e-9 * np.ptp(image):
                        tip[h + wa, h + wb] = bound + threshold
                        changed = True
    return tip


@pytest.fixture(scope="module")
def asym_tip():
    tip = paraboloid_cone_tip(10 * NM, 25, 6 * NM, 60 * NM, asymmetry=0.2, max_half_width=4)
    assert tip[4, 8] > tip[4, 0] + 1e-12  # +x flank blunter (higher) than -x
    return tip


@pytest.fixture(scope="module")
def noisy512():
    return characterizer_image(n=512, noise=0.3 * NM, seed=0)


# ---------------------------------------------------------------------------- dilation / erosion


def test_dilate_and_erode_match_their_definitions_for_an_asymmetric_tip(asym_tip):
    rng = np.random.default_rng(4)
    surface = rng.normal(scale=5 * NM, size=(40, 50))
    random_tip = -rng.uniform(0, 8 * NM, size=(7, 7))
    random_tip[3, 3] = 0.0
    for tip in (asym_tip, random_tip):
        np.testing.assert_allclose(
            dilate(surface, tip), brute_dilate(surface, tip), rtol=0, atol=1e-20
        )
        np.testing.assert_allclose(
            erode(surface, tip), brute_erode(surface, tip), rtol=0, atol=1e-20
        )
        # the float32 valid-region versions used by the candidate test agree on the interior
        h = tip.shape[0] // 2
        e32 = tr._erode_valid(surface.astype(np.float32), tip.astype(np.float32))
        np.testing.assert_allclose(e32, brute_erode(surface, tip)[h:-h, h:-h], rtol=0, atol=1e-14)


def test_erosion_is_the_adjoint_of_imaging(asym_tip):
    rng = np.random.default_rng(5)
    rough = rng.normal(scale=3 * NM, size=(60, 60))
    recon = erode(dilate(rough, asym_tip), asym_tip)
    assert np.all(recon >= rough - 1e-18)  # never below the surface
    assert np.any(recon > rough + 1 * NM)  # narrow pits are not reached
    # a smooth surface whose curvature is far below the tip's is touched everywhere: exact
    y, x = np.mgrid[0:80, 0:80] * 1.6 * NM
    smooth = 1 * NM * np.sin(2 * np.pi * x / (200 * NM)) * np.cos(2 * np.pi * y / (250 * NM))
    recon = erode(dilate(smooth, asym_tip), asym_tip)
    np.testing.assert_allclose(recon[5:-5, 5:-5], smooth[5:-5, 5:-5], rtol=0, atol=1e-21)


def test_erosion_speed_512_with_41_tip():
    rng = np.random.default_rng(6)
    image = rng.normal(scale=NM, size=(512, 512))
    tip = crop(default_tip(1.6 * NM, depth=100 * NM), 41)
    t0 = time.perf_counter()
    erode(image, tip)
    seconds = time.perf_counter() - t0
    print(f"\nerode 512x512 by 41x41: {seconds:.2f} s (Gwyddion ~0.56 s)")
    assert seconds < 3.0


def test_certainty_map_marks_points_the_reconstruction_gets_right():
    image, surface, tip = characterizer_image(n=300, noise=0.0, seed=2)
    certain = te.certainty_map(image, tip)
    recon = erode(image, tip)
    assert np.all(recon >= surface - 1e-15)
    inner = (slice(80, -80), slice(80, -80))
    assert certain[inner].mean() > 0.5  # the flat substrate and the spike tops
    np.testing.assert_allclose(recon[certain], surface[certain], rtol=0, atol=1e-15)
    assert np.any(recon[inner] > surface[inner] + 1 * NM)  # spike flanks the tip never reaches...
    assert not np.any(certain & (recon > surface + 1e-12))  # ...are never marked certain
    tops = (surface > 15 * NM) & (
        surface
        >= np.maximum.reduce([np.roll(surface, s, axis=a) for s in (-1, 1) for a in (0, 1)])
    )
    tops[:80], tops[-80:], tops[:, :80], tops[:, -80:] = False, False, False, False
    assert tops.any() and certain[tops].all()


# ---------------------------------------------------------------------------- the characterizer


def test_characterizer_is_the_dilated_spike_field_plus_noise():
    image, surface, tip = characterizer_image(n=256, noise=0.3 * NM, seed=1)
    assert tip[tip.shape[0] // 2, tip.shape[0] // 2] == 0 and tip.max() == 0
    noise = image - dilate(surface, tip)
    assert abs(noise.std() - 0.3 * NM) < 0.02 * NM and abs(noise.mean()) < 0.02 * NM
    assert 15 * NM < surface.max() <= 80 * NM and np.median(surface) == 0
    window = crop(tip, 41)
    axis_ends = np.array([window[20, 0], window[20, -1], window[0, 20], window[-1, 20]])
    assert np.all((axis_ends < -35 * NM) & (axis_ends > -60 * NM))  # the 41 window: top ~40-60 nm
    assert window[20, -1] > window[20, 0] + 5 * NM  # blunt +x flank
    assert abs(tr.estimate_noise(image) - 0.3 * NM) < 0.05 * NM


def test_feature_points_are_the_spike_tops():
    image, surface, tip = characterizer_image(n=256, noise=0.3 * NM, seed=1)
    pts = tr.feature_points(image, 21)
    assert len(pts) >= 10
    # each feature is a spike top, up to the noise-flat apex (within 3 pixels of a spike)
    from scipy import ndimage

    near_spike = ndimage.maximum_filter(surface, size=7) > 15 * NM
    assert near_spike[pts[:, 0], pts[:, 1]].all()
    kept = tr.douglas_peucker(np.array([0, 0.1, 0, 5, 10, 5, 0, -0.1, 0]), 1.0)
    assert 4 in kept and 3 not in kept and 1 not in kept


# ---------------------------------------------------------------------------- blind estimation


def test_refinement_matches_the_brute_force_definition():
    rng = np.random.default_rng(8)
    surface = np.zeros((22, 22))
    for y, x in rng.integers(3, 19, size=(4, 2)):
        surface[y, x] = rng.uniform(3, 6)
    true_tip = -np.array(
        [
            [4, 3, 2.5, 3, 5],
            [2, 1, 0.8, 1, 3],
            [1.5, 0.5, 0, 0.4, 2],
            [2.5, 1, 0.6, 1.2, 3],
            [5, 4, 3, 4, 6],
        ],
        float,
    )
    image = dilate(surface, true_tip) + rng.normal(scale=0.05, size=surface.shape)
    for th in (0.0, 0.1):
        brute = brute_blind(image, 5, th)
        plain = te.estimate_tip_plain(image, 5, th).tip
        fast = te.estimate_tip(image, 5, th).tip
        np.testing.assert_allclose(plain, brute, rtol=0, atol=1e-9)
        np.testing.assert_allclose(fast, brute, rtol=0, atol=1e-5)


def test_noiseless_estimate_is_an_upper_bound_that_converges_to_the_true_top():
    image, _, tip = characterizer_image(n=256, noise=0.0, seed=1)
    for size in (21, 41):
        est = te.estimate_tip(image, size, threshold=0.0)
        true = crop(tip, size)
        assert est.tip[size // 2, size // 2] == 0 and est.tip.max() == 0
        assert np.all(est.tip >= true - 1e-15)
        err = te.tip_error(est, tip, 20 * NM)
        print(
            f"\nnoiseless {size}x{size}: top-20 nm RMS error {err / NM:.2e} nm in "
            f"{est.seconds:.2f} s"
        )
        assert err < 0.05 * NM
    auto = te.estimate_tip(image, 41, "auto")  # no noise: ~ the exact algorithm
    assert auto.threshold < 0.01 * NM and te.tip_error(auto, tip, 20 * NM) < 0.05 * NM


def test_asymmetry_is_recovered_on_the_correct_side():
    image, _, tip = characterizer_image(n=256, noise=0.0, seed=1)
    noisy, _, _ = characterizer_image(n=256, noise=0.3 * NM, seed=1)
    true = crop(tip, 41)
    rows = slice(15, 26)
    true_gap = true[rows, 34:].mean() - true[rows, :7].mean()  # +x (blunt) minus -x flank
    assert true_gap > 3 * NM
    for img, label in ((image, "noiseless"), (noisy, "0.3 nm noise, auto")):
        est = te.estimate_tip(img, 41, threshold=0.0 if img is image else "auto")
        gap = est.tip[rows, 34:].mean() - est.tip[rows, :7].mean()
        print(
            f"\n{label}: +x minus -x flank height {gap / NM:.2f} nm (true {true_gap / NM:.2f} nm)"
        )
        assert gap > 0.5 * true_gap
        if img is image:
            assert abs(gap - true_gap) < 0.05 * true_gap
        # the mirror image of the estimate fits worse: the orientation is right
        assert te.tip_error(est.tip, tip, 40 * NM) < te.tip_error(est.tip[:, ::-1], tip, 40 * NM)


def test_noise_threshold_zero_is_too_sharp_huge_is_blunt_and_auto_is_near_the_best(noisy512):
    image, _, tip = noisy512
    size = 21
    t0 = time.perf_counter()
    auto = te.estimate_tip(image, size, "auto")
    auto_seconds = time.perf_counter() - t0
    auto_err = te.tip_error(auto, tip, 20 * NM)
    # fixed thresholds 2.5..7.5 nm, each starting from the one above (same result, faster)
    errors, start = {}, None
    for th in np.arange(7.5, 2.49, -0.25) * NM:
        est = te.estimate_tip(image, size, float(th), start=start)
        errors[float(th)] = te.tip_error(est, tip, 20 * NM)
        start = est.tip
    cold = te.estimate_tip(image, size, 4.5 * NM)
    np.testing.assert_allclose(
        cold.tip,
        te.estimate_tip(image, size, 4.5 * NM, start=te.estimate_tip(image, size, 6 * NM).tip).tip,
        rtol=0,
        atol=1e-6 * np.ptp(image),
    )
    best_th = min(errors, key=errors.get)
    zero = te.estimate_tip(image, size, 0.0)
    huge = te.estimate_tip(image, size, 1e-6)
    print(
        f"\n{size}x{size} on 512x512, 0.3 nm noise: auto {auto.threshold / NM:.2f} nm -> "
        f"{auto_err / NM:.3f} nm in {auto_seconds:.1f} s; best fixed {best_th / NM:.2f} nm -> "
        f"{errors[best_th] / NM:.3f} nm; N_TH=0 -> {te.tip_error(zero, tip, 20 * NM) / NM:.2f} "
        f"nm; huge -> {te.tip_error(huge, tip, 20 * NM) / NM:.2f} nm"
    )
    assert te.tip_error(zero, tip, 20 * NM) > 3 * errors[best_th]
    assert zero.tip.mean() < crop(tip, size).mean() - 3 * NM  # needle-sharp
    assert np.all(huge.tip == 0.0) and te.tip_error(huge, tip, 20 * NM) > 3 * errors[best_th]
    assert auto_err <= 1.10 * errors[best_th]
    assert auto.sweep and all(len(s) == 4 for s in auto.sweep)
    assert auto_seconds < 30


def test_speed_ups_give_the_plain_result_faster():
    for noise, th in ((0.0, 0.0), (0.3 * NM, 2 * NM)):
        image, _, _ = characterizer_image(n=110, noise=noise, seed=3)
        t0 = time.perf_counter()
        plain = te.estimate_tip_plain(image, 11, th)
        t1 = time.perf_counter()
        fast = te.estimate_tip(image, 11, th)
        t2 = time.perf_counter()
        bare = te.estimate_tip(image, 11, th, use_features=False, limit_radius=False)
        print(
            f"\nnoise {noise / NM:.1f} nm, N_TH {th / NM:.1f} nm: plain {t1 - t0:.2f} s, fast "
            f"{t2 - t1:.2f} s"
        )
        tol = 2e-6 * np.ptp(image)
        np.testing.assert_allclose(fast.tip, plain.tip, rtol=0, atol=tol)
        np.testing.assert_allclose(bare.tip, plain.tip, rtol=0, atol=tol)
        assert t2 - t1 < t1 - t0


def test_speed_on_the_512_characterizer(noisy512):
    image, _, tip = noisy512
    for size, limit in ((21, 3.0), (41, 15.0)):
        est = te.estimate_tip(image, size, 4.5 * NM)
        print(
            f"\n{size}x{size} at N_TH 4.5 nm: {est.seconds:.2f} s, {est.iterations} passes, "
            f"{est.feature_points} feature points, error "
            f"{te.tip_error(est, tip, 20 * NM) / NM:.3f} nm"
        )
        assert est.seconds < limit


def test_tip_error_closed_form():
    tip = crop(default_tip(1.6 * NM, depth=60 * NM), 21)
    off = tip - 1 * NM
    off[10, 10] = 0.0
    mask = tip >= -5 * NM
    expected = 1 * NM * np.sqrt((mask.sum() - 1) / mask.sum())
    assert te.tip_error(off, tip, 5 * NM) == pytest.approx(expected, rel=1e-12)
    assert te.tip_error(crop(off, 11), tip, 5 * NM) == pytest.approx(expected, rel=1e-12)
    assert (
        te.tip_error(tip, paraboloid_cone_tip(10 * NM, 25, 1.6 * NM, 60 * NM, 0.2), 5 * NM) < 1e-20
    )


def test_candidate_morphology_in_parallel_row_bands_is_identical(monkeypatch):
    from afm_core.imaging import tip_refinement as tr

    rng = np.random.default_rng(4)
    image = rng.normal(0.0, 1.0, (300, 190)).astype(np.float32)
    tip = crop(default_tip(), 41).astype(np.float32)
    single = [tr._erode_valid(image, tip), tr._dilate_valid(image, tip)]
    pools = []

    class CountingPool(tr.ThreadPoolExecutor):
        def __init__(self, workers):
            pools.append(workers)
            super().__init__(workers)

    monkeypatch.setattr(tr, "ThreadPoolExecutor", CountingPool)
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    banded = [tr._in_bands(op, image, tip) for op in (tr._erode_valid, tr._dilate_valid)]
    assert pools == [3, 3]  # the bands did run in parallel
    for one, many in zip(single, banded):
        assert np.array_equal(one, many)


@pytest.mark.parametrize("gather_terms", [tr._GATHER_TERMS, 1])  # index matrix, pixel by pixel
def test_staged_erosion_is_the_whole_erosion_bit_for_bit(monkeypatch, gather_terms):
    """The candidate test's erosion runs the tip's highest pixels over the whole image and
    gathers the rest only where they can still lower the minimum: the same float32 numbers.
    A tip whose outer pixels lie almost the image's height range below the apex (as an
    estimate's pixels bounded only by that range do) exercises the gathered completion."""
    rng = np.random.default_rng(7)
    k, h = 41, 20
    image = rng.normal(0.0, 1.0, (220, 170)).astype(np.float32)
    image[100:124, 60:84] += 30.0  # a mesa: only on it can the outer pixels lower the minimum
    a = np.pad(image, h, constant_values=np.inf)
    cone = crop(default_tip(), k) / NM
    outer = cone.copy()
    outer[np.hypot(*np.mgrid[-h : h + 1, -h : h + 1]) > 6] = -25.0
    rough = -rng.uniform(0.0, 3.0, (k, k))
    rough[h, h] = 0.0
    monkeypatch.setattr(tr, "_GATHER_TERMS", gather_terms)
    stages = []
    erode_pixels = tr._erode_pixels
    monkeypatch.setattr(
        tr, "_erode_pixels", lambda a, t, p=None: stages.append(len(p)) or erode_pixels(a, t, p)
    )
    for tip in (cone, outer, rough, np.zeros((k, k))):
        t32 = tip.astype(np.float32)
        stages.clear()
        staged = tr._erode_valid(a, t32)
        assert np.array_equal(staged, erode_pixels(a, t32)), tip[0, 0]
        if tip is outer:
            assert sum(stages) < k * k  # the rest was gathered, and it mattered:
            seen = np.argsort(-t32.ravel(), kind="stable")[: sum(stages)]
            assert not np.array_equal(erode_pixels(a, t32, seen), staged)


def test_candidate_test_with_less_work_selects_as_the_whole_image_one(monkeypatch):
    """The candidate test's staged dilation, gathered completion and kept erosion give the
    points and order of the plain whole-image float32 computation (its definition)."""
    image, _, _ = characterizer_image(n=160, noise=0.3 * NM, seed=3)
    est = tr.TipRefiner(image, 21)
    refined = te.estimate_tip(image, 21, threshold=6 * NM).tip  # a real cone
    h, ny0, nx0 = est.h, *image.shape
    mask = est.interior()
    mask[:40, :] = False  # a masked part too
    erode_valid, dilate_valid = tr._erode_valid, tr._dilate_valid

    def plain(tip, th):
        t32 = tip.astype(np.float32)
        r = erode_valid(est.image32, t32)
        top = est.image32[h : h + ny0, h : h + nx0] + np.float32(est.eps)
        reach = dilate_valid(np.minimum(r + np.float32(th), top), t32)
        excess = est.image32[2 * h : ny0, 2 * h : nx0] - reach
        py, px = np.nonzero((excess > est.test_eps) & mask[h : ny0 - h, h : nx0 - h])
        order = np.argsort(-excess[py, px], kind="stable")
        return (py[order] + 2 * h) * est.nx + (px[order] + 2 * h)

    erosions = []
    monkeypatch.setattr(tr, "_erode_valid", lambda a, t: erosions.append(1) or erode_valid(a, t))
    flat = np.zeros_like(refined)
    for tip, share in ((refined, tr._GATHER_SHARE), (flat, tr._GATHER_SHARE), (refined, 1.0)):
        # share 1: the gathered completion does all but the first stage
        monkeypatch.setattr(tr, "_GATHER_SHARE", share)
        for th in (0.0, 0.5 * NM, 1 * NM, 2 * NM):  # below the 6 nm the tip was refined at
            expected = plain(tip, th)
            assert expected.size > 0
            assert np.array_equal(est.candidates(tip, th, mask), expected), f"threshold {th}"
    # one erosion per tip, kept for the other thresholds and recomputed for a new tip
    assert len(erosions) == 3


@pytest.mark.parametrize("threshold", [-1e-9, float("nan"), float("inf")])
def test_a_threshold_that_is_not_a_finite_non_negative_number_is_refused(threshold):
    image = np.random.default_rng(0).normal(0.0, 1e-9, (48, 48))
    with pytest.raises(ValueError, match=r"threshold=.*: must be a finite number >= 0 \(m\)"):
        te.estimate_tip(image, 7, threshold=threshold, pixel_size=2e-9)
