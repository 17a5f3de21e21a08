"""Thermal-drift image reconstruction (book ch. 3) and frame-up/down drift velocity (5.3.3),
against the simulator's ground truth.

Acceptance (project): on simulated 0/90 deg pairs with drift in the book's range, particle aspect
ratio after correction >= 0.99 (book: 0.8710 -> 0.9794), particle centres within 2 nm RMS of
truth, drift velocity within 10 %.

Truth: a sphere at sample position s appears in the corrected map at s + D(t_ref), D the
simulator's drift offset (the map is the scanner frame at t_ref). Particles are measured here
independently of the module: region above half of each particle's height, height-weighted
centroid and second moments; aspect = sqrt(smaller / larger eigenvalue). The drift velocity
truth is the least-squares slope of D over the 0 deg scan's line times (the constant velocity
when the drift is constant).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import ndimage

from afm_core.imaging.drift_compensation import DriftCorrection, compensate_pair
from afm_core.imaging.drift_fit import band_offset_vectors, band_partition
from afm_core.imaging.frame_up_down import (
    sampled_velocity,
    up_down_observations,
    up_down_velocity,
    velocity_from_up_down,
)
from afm_core.imaging.offset_vector import BSplineImage, offset_displacement, recentre
from afm_core.imaging.scan_timing import pixel_times
from afm_core.instrument import RasterScanData, ScanRequest
from afm_core.sim.config import load_config, merge
from afm_core.sim.instrument import SimulatedAfm

ORIGIN = 20e-6  # m, scan area corner (x and y)
SIZE = 2e-6  # m, 256 x 256 pixels: 7.8 nm pixels
PIXELS = 256
LINE_RATE = 0.5  # Hz: 256 lines take 512 s, so a drift of 0.1-0.4 nm/s matters
BOOK_DRIFT = {
    "mean_velocity_x": -0.004e-9,
    "mean_velocity_y": 0.099e-9,  # Fig. 7.9
    "sigma_velocity_x": 0.027e-9,
    "sigma_velocity_y": 0.209e-9,
}


def constant_drift(vx: float, vy: float) -> dict:
    return {
        "mean_velocity_x": vx,
        "mean_velocity_y": vy,
        "sigma_velocity_x": 0.0,
        "sigma_velocity_y": 0.0,
    }


class AcceleratingDrift:
    """A drift whose velocity changes steadily (replaces the simulator's wandering one)."""

    def __init__(self, v0, a):
        self.v0, self.a = np.asarray(v0, float), np.asarray(a, float)

    def offset(self, t):
        t = np.asarray(t, float)[..., None]
        return self.v0 * t + 0.5 * self.a * t**2

    def velocity(self, t):
        return self.v0 + self.a * np.asarray(t, float)[..., None]


def random_spheres(rng, n: int, r_min=50e-9, r_max=100e-9, separation=420e-9, edge=200e-9) -> list:
    """Up to n spheres spread over the scan area, centres at least `separation` apart."""
    spheres = []
    for _ in range(20000):
        if len(spheres) == n:
            break
        x, y = ORIGIN + rng.uniform(edge, SIZE - edge, size=2)
        if all(np.hypot(x - s["x"], y - s["y"]) > separation for s in spheres):
            spheres.append(
                {"x": float(x), "y": float(y), "radius": float(rng.uniform(r_min, r_max))}
            )
    assert len(spheres) >= 10
    return spheres


def simulator(drift: dict, seed: int, spheres: list) -> SimulatedAfm:
    """Drift only: the scanner's hysteresis, creep, coupling, line deflection and positioning
    noise are off."""
    config = merge(
        load_config(),
        {
            "seed": seed,
            "scanner": {
                "hysteresis_enabled": False,
                "creep_enabled": False,
                "coupling_enabled": False,
                "deflection_enabled": False,
                "positioning_noise_enabled": False,
            },
            "drift": drift,
            "sample": {"spheres": spheres},
        },
    )
    return SimulatedAfm(config)


def scan(afm, angle=0.0, up=True, pixels=PIXELS, rate=LINE_RATE):
    return afm.raster_scan(
        ScanRequest(
            ORIGIN,
            ORIGIN,
            SIZE,
            SIZE,
            pixels,
            pixels,
            scan_angle_deg=angle,
            slow_scan_up=up,
            line_rate=rate,
        )
    )


def make_pair(drift, seed, n_spheres=14, up0=True, up90=True, custom=None):
    spheres = random_spheres(np.random.default_rng(seed), n_spheres)
    afm = simulator(drift, seed, spheres)
    if custom is not None:
        afm.drift = custom
    scan0 = scan(afm, 0.0, up0)
    scan90 = scan(afm, 90.0, up90)
    return afm, scan0, scan90, spheres


def particles(height: np.ndarray, ref: RasterScanData) -> list:
    """(x, y, aspect) of each particle fully inside the image, in scanner coordinates (m)."""
    h = np.asarray(height, float)
    rel = h - np.median(h)
    labels, _ = ndimage.label(rel > 0.1 * rel.max())
    out = []
    for index, sl in enumerate(ndimage.find_objects(labels), start=1):
        if (
            sl[0].start < 3
            or sl[1].start < 3
            or sl[0].stop > h.shape[0] - 3
            or sl[1].stop > h.shape[1] - 3
        ):
            continue
        part = np.where(labels[sl] == index, rel[sl], 0.0)
        if part.max() < 20e-9:
            continue
        w = np.clip(part - 0.5 * part.max(), 0.0, None)
        rows, cols = np.mgrid[sl[0], sl[1]]
        x = ref.origin_x + (cols + 0.5) * ref.pixel_size_x
        y = ref.origin_y + (rows + 0.5) * ref.pixel_size_y
        mx, my = (w * x).sum() / w.sum(), (w * y).sum() / w.sum()
        cxx, cyy = (w * (x - mx) ** 2).sum() / w.sum(), (w * (y - my) ** 2).sum() / w.sum()
        cxy = (w * (x - mx) * (y - my)).sum() / w.sum()
        small, large = np.linalg.eigvalsh([[cxx, cxy], [cxy, cyy]])
        out.append((mx, my, float(np.sqrt(small / large))))
    return out


def assess(afm, scan0, result: DriftCorrection, spheres) -> dict:
    truth = np.array([[s["x"], s["y"]] for s in spheres]) + afm.drift.offset(result.t_ref)

    def centre_errors(found):
        return np.array([np.min(np.hypot(truth[:, 0] - x, truth[:, 1] - y)) for x, y, _ in found])

    before, after = particles(scan0.height, scan0), particles(result.corrected, scan0)
    ny, nx = scan0.height.shape
    t = pixel_times(scan0, np.arange(ny), np.full(ny, 0.5 * (nx - 1)))
    d = afm.drift.offset(t)
    tc = t - t.mean()
    v_true = tc @ (d - d.mean(axis=0)) / (tc @ tc)
    v_err = np.linalg.norm(np.array(result.velocity) - v_true) / np.linalg.norm(v_true)
    return {
        "aspect_before": min(a for *_, a in before),
        "aspect_after": min(a for *_, a in after),
        "rms_before": float(np.sqrt(np.mean(centre_errors(before) ** 2))),
        "rms_after": float(np.sqrt(np.mean(centre_errors(after) ** 2))),
        "found": len(after),
        "velocity_error": float(v_err),
        "v_true": v_true,
    }


def check_acceptance(m: dict, n_spheres: int) -> None:
    assert m["found"] >= 0.75 * n_spheres
    assert m["aspect_before"] < 0.975, "the test case must show visible drift distortion"
    assert m["aspect_after"] >= 0.99
    assert m["rms_after"] <= 2e-9
    assert m["rms_after"] < 0.2 * m["rms_before"]
    assert m["velocity_error"] <= 0.10


# -- the acceptance cases ----------------------------------------------------------------------
@pytest.mark.parametrize(
    "vx, vy, up0, up90",
    [
        (-0.1e-9, 0.3e-9, True, True),
        (0.2e-9, -0.25e-9, False, True),
        (0.15e-9, 0.2e-9, True, False),
    ],
)
def test_constant_drift_pair_is_reconstructed(vx, vy, up0, up90):
    afm, scan0, scan90, spheres = make_pair(constant_drift(vx, vy), seed=3, up0=up0, up90=up90)
    result = compensate_pair(scan0, scan90)
    m = assess(afm, scan0, result, spheres)
    check_acceptance(m, len(spheres))
    assert result.corrected.shape == scan0.height.shape and np.all(np.isfinite(result.corrected))
    assert result.offsets.shape == (PIXELS, 2) and result.valid.shape == scan0.height.shape
    assert len(result.feature_offsets) >= 5
    for row0, col0, p, ncc in result.feature_offsets:
        assert p.shape == (6,) and ncc > 0.99 and 0 <= row0 < PIXELS and 0 <= col0 < PIXELS
    # the per-line displacements are the drift itself, relative to t_ref
    ny = PIXELS
    t = pixel_times(scan0, np.arange(ny), np.full(ny, 0.5 * (ny - 1)))
    true_offsets = afm.drift.offset(t) - afm.drift.offset(result.t_ref)
    assert np.sqrt(np.mean((result.offsets - true_offsets) ** 2)) < 1e-9


def test_particles_in_a_row_are_enough():
    """Collinear feature regions do not fix an affine start value (its fit is free across the
    row); the match must still work from the translation."""
    spheres = [
        {"x": ORIGIN + f * SIZE, "y": ORIGIN + 0.5 * SIZE, "radius": 60e-9}
        for f in (0.25, 0.5, 0.75)
    ]
    afm = simulator(constant_drift(0.2e-9, 0.3e-9), 4, spheres)
    scan0, scan90 = scan(afm, 0.0), scan(afm, 90.0)
    result = compensate_pair(scan0, scan90)
    m = assess(afm, scan0, result, spheres)
    assert m["found"] == 3 and m["aspect_after"] >= 0.99 and m["rms_after"] <= 2e-9, m


@pytest.mark.parametrize("seed", [5, 6, 8])
def test_wandering_drift_with_the_books_statistics_is_reconstructed(seed):
    afm, scan0, scan90, spheres = make_pair(BOOK_DRIFT, seed=seed)
    v = afm.drift.velocity(np.array([scan0.start_time, scan90.start_time + PIXELS / LINE_RATE]))
    assert np.ptp(v[:, 1]) > 0.01e-9, "the drift must actually change during the pair"
    m = assess(afm, scan0, compensate_pair(scan0, scan90), spheres)
    check_acceptance(m, len(spheres))


def test_second_order_offset_vector_is_at_least_as_good_when_the_drift_accelerates():
    drift = AcceleratingDrift(
        v0=[-0.2e-9, 0.3e-9], a=[3e-13, -1e-12]
    )  # vy: 0.3 -> -0.7 nm/s over the pair
    afm, scan0, scan90, spheres = make_pair({}, seed=4, custom=drift)
    first = compensate_pair(scan0, scan90, order=1)
    second = compensate_pair(scan0, scan90, order=2)
    assert all(p.shape == (12,) for _, _, p, _ in second.feature_offsets)
    m1, m2 = assess(afm, scan0, first, spheres), assess(afm, scan0, second, spheres)
    check_acceptance(m1, len(spheres))
    check_acceptance(m2, len(spheres))
    assert m2["rms_after"] <= m1["rms_after"] + 0.3e-9
    assert m2["aspect_after"] >= m1["aspect_after"] - 0.002
    assert m2["velocity_error"] <= m1["velocity_error"] + 0.01


def test_the_books_literal_line_averaging_also_corrects_a_constant_drift():
    afm, scan0, scan90, spheres = make_pair(constant_drift(-0.1e-9, 0.3e-9), seed=1)
    m = assess(afm, scan0, compensate_pair(scan0, scan90, method="book"), spheres)
    assert m["aspect_before"] < 0.95 and m["aspect_after"] >= 0.985
    assert m["rms_after"] <= 2e-9 < m["rms_before"]
    assert m["velocity_error"] <= 0.05


# -- frame up / frame down (eq. 5.32-5.36) ------------------------------------------------------
@pytest.mark.parametrize(
    "vx, vy, angle", [(0.12e-9, -0.25e-9, 0.0), (-0.05e-9, 0.3e-9, 0.0), (0.2e-9, 0.1e-9, 90.0)]
)
def test_velocity_from_frame_up_and_frame_down(vx, vy, angle):
    spheres = random_spheres(np.random.default_rng(7), 12, r_min=30e-9)
    afm = simulator(constant_drift(vx, vy), 7, spheres)
    up, down = scan(afm, angle, up=True), scan(afm, angle, up=False)
    v = np.array(velocity_from_up_down(up, down))
    truth = np.array([vx, vy])
    assert np.linalg.norm(v - truth) <= 0.1 * np.linalg.norm(truth)
    assert np.all(np.abs(v - truth) <= 0.1 * np.abs(truth) + 0.005e-9)


def test_frame_up_down_with_two_particles_is_the_books_formula():
    """Two particles, constant drift: the apparent vertical separation is d V / (V - v) frame up
    and d V / (V + v) frame down (V: line pitch / line period), so
    v = V (d_up - d_down) / (d_up + d_down)."""
    spheres = [
        {"x": ORIGIN + 0.7e-6, "y": ORIGIN + 0.6e-6, "radius": 80e-9},
        {"x": ORIGIN + 1.3e-6, "y": ORIGIN + 1.4e-6, "radius": 80e-9},
    ]
    vx, vy = 0.1e-9, 0.3e-9
    afm = simulator(constant_drift(vx, vy), 2, spheres)
    up, down = scan(afm, up=True), scan(afm, up=False)
    (xu1, yu1, _), (xu2, yu2, _) = sorted(particles(up.height, up), key=lambda p: p[1])
    (xd1, yd1, _), (xd2, yd2, _) = sorted(particles(down.height, down), key=lambda p: p[1])
    d_up, d_down = yu2 - yu1, yd2 - yd1
    speed = up.pixel_size_y / up.line_period
    assert d_up > 0.8e-6 > d_down  # stretched up, compressed down
    assert speed * (d_up - d_down) / (d_up + d_down) == pytest.approx(vy, rel=0.05)
    v = velocity_from_up_down(up, down)
    assert v[0] == pytest.approx(vx, rel=0.1) and v[1] == pytest.approx(vy, rel=0.05)


def test_a_pair_measures_the_velocity_at_its_particles_moments():
    """A drift that speeds up: the pair's velocity is the least squares over the moments the
    particles were imaged (`sampled_velocity` of the known drift; for a constant drift the
    velocity itself)."""
    v = np.array([0.1e-9, -0.2e-9])
    t_up, t_down = np.array([10.0, 50.0, 90.0]), np.array([400.0, 380.0, 300.0])
    np.testing.assert_allclose(
        sampled_velocity(lambda t: np.asarray(t)[..., None] * v, t_up, t_down), v, rtol=1e-9
    )
    spheres = random_spheres(np.random.default_rng(7), 12, r_min=30e-9)
    afm = simulator(constant_drift(0.0, 0.0), 7, spheres)
    afm.drift = AcceleratingDrift([0.05e-9, 0.1e-9], [2e-13, 4e-13])
    up, down = scan(afm, up=True), scan(afm, up=False)
    observations = up_down_observations(up, down)
    measured = np.array(velocity_from_up_down(up, down))
    assert tuple(measured) == up_down_velocity(observations)
    truth = sampled_velocity(afm.drift.offset, observations.t_up, observations.t_down)
    assert np.all(np.abs(measured - truth) <= 0.05 * np.abs(truth) + 0.005e-9)


# -- the pieces --------------------------------------------------------------------------------
def test_bicubic_bspline_sampling_matches_scipy_and_its_derivative():
    rng = np.random.default_rng(0)
    image = ndimage.gaussian_filter(rng.normal(size=(40, 50)), 2.0)
    spline = BSplineImage(image)
    rows, cols = rng.uniform(0, 39, 500), rng.uniform(0, 49, 500)
    value, d_row, d_col = spline(rows, cols, derivatives=True)
    np.testing.assert_allclose(
        value, ndimage.map_coordinates(image, [rows, cols], order=3, mode="mirror"), atol=1e-12
    )
    eps = 1e-5
    np.testing.assert_allclose(
        d_row, (spline(rows + eps, cols) - spline(rows - eps, cols)) / (2 * eps), atol=1e-8
    )
    np.testing.assert_allclose(
        d_col, (spline(rows, cols + eps) - spline(rows, cols - eps)) / (2 * eps), atol=1e-8
    )
    np.testing.assert_allclose(
        spline(*np.mgrid[0:40, 0:50].astype(float)), image, atol=1e-12
    )  # interpolates


def test_offset_vector_first_and_second_order():
    p1 = np.array([1.0, 2.0, 0.1, 0.2, 0.3, 0.4])
    u, v = offset_displacement(p1, 2.0, -1.0)
    assert (u, v) == pytest.approx((1 + 0.1 * 2 - 0.3, 2 + 0.2 * 2 - 0.4))  # eq. 3.15
    p2 = np.concatenate([p1, [0.01, 0.02, 0.03, 0.04, 0.05, 0.06]])
    u, v = offset_displacement(p2, 2.0, -1.0)
    assert u == pytest.approx(
        1 + 0.2 - 0.3 + 0.5 * 0.01 * 4 + 0.5 * 0.03 * 1 + 0.05 * -2
    )  # eq. 3.17
    assert v == pytest.approx(2 + 0.4 - 0.4 + 0.5 * 0.02 * 4 + 0.5 * 0.04 * 1 + 0.06 * -2)
    for p in (p1, p2):  # moving the centre describes the same mapping
        q = recentre(p, 3.0, 1.5)
        assert offset_displacement(q, -1.0, 2.0) == pytest.approx(offset_displacement(p, 2.0, 3.5))
    with pytest.raises(ValueError, match="p:"):
        offset_displacement(np.ones(5), 0.0, 0.0)


def test_band_partition_follows_fig_3_14():
    # particles 1-3 overlap vertically (one band), 4-5 overlap, 6 alone: three bands
    extents = [(0, 10), (5, 20), (18, 30), (40, 50), (45, 60), (70, 80)]
    bands, splits = band_partition(extents)
    assert bands == [[0, 1, 2], [3, 4], [5]]
    assert splits == pytest.approx(
        [0.5 * (24 + 45), 0.5 * (52.5 + 75)]
    )  # midway between the centres
    centres = [np.array([0.0, 0.0]), np.array([0.0, 10.0])]
    ps = [np.array([1.0, 0, 0.1, 0, 0, 0]), np.array([3.0, 0, 0.1, 0, 0, 0])]
    ((centre, p),) = band_offset_vectors(centres, ps, [[0, 1]])  # eq. 3.23, about the band centre
    assert centre == pytest.approx([0.0, 5.0]) and p[0] == pytest.approx(0.5 * (1.5 + 2.5))


# -- bad input ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_pair():
    spheres = [
        {"x": ORIGIN + 0.3e-6, "y": ORIGIN + 0.3e-6, "radius": 60e-9},
        {"x": ORIGIN + 0.7e-6, "y": ORIGIN + 0.6e-6, "radius": 60e-9},
    ]
    afm = simulator(constant_drift(0.1e-9, 0.2e-9), 1, spheres)
    request = dict(pixels=64, rate=2.0)
    return (
        scan(afm, 0.0, True, **request),
        scan(afm, 90.0, True, **request),
        scan(afm, 0.0, False, **request),
    )


def test_a_small_pair_is_accepted(small_pair):
    scan0, scan90, down = small_pair
    assert compensate_pair(scan0, scan90).corrected.shape == (64, 64)
    assert len(velocity_from_up_down(scan0, down)) == 2


def with_nan(s: RasterScanData) -> RasterScanData:
    height = np.array(s.height, copy=True)
    height[5, 7] = np.nan
    return dataclasses.replace(s, height=height)


@pytest.mark.parametrize(
    "case, field",
    [
        (lambda a, b, d: (dataclasses.replace(a, height=a.height[:, :60]), b), "height"),
        (
            lambda a, b, d: (a, dataclasses.replace(b, pixel_size_x=b.pixel_size_x * 1.1)),
            "scan90.pixel_size_x",
        ),
        (
            lambda a, b, d: (a, dataclasses.replace(b, origin_y=b.origin_y + 50e-9)),
            "scan90.origin_y",
        ),
        (lambda a, b, d: (with_nan(a), b), "scan0.height"),
        (lambda a, b, d: (a, with_nan(b)), "scan90.height"),
        (lambda a, b, d: (b, a), "scan0.scan_angle_deg"),
        (lambda a, b, d: (a, d), "scan90.scan_angle_deg"),
        (
            lambda a, b, d: (dataclasses.replace(a, height=np.zeros_like(a.height)), b),
            "scan0.height",
        ),
        (
            lambda a, b, d: (dataclasses.replace(a, line_start_times=a.line_start_times[:10]), b),
            "scan0.line_start_times",
        ),
    ],
)
def test_bad_pairs_raise_naming_the_field(small_pair, case, field):
    scan0, scan90, down = small_pair
    a, b = case(scan0, scan90, down)
    with pytest.raises(ValueError, match=field.replace(".", r"\.")):
        compensate_pair(a, b)


def test_no_features_and_bad_options_raise(small_pair):
    scan0, scan90, _ = small_pair
    flat = dataclasses.replace(
        scan0, height=np.random.default_rng(0).normal(0, 0.3e-9, scan0.height.shape)
    )
    with pytest.raises(ValueError, match=r"scan0\.height: no feature"):
        compensate_pair(flat, scan90)
    with pytest.raises(ValueError, match="order"):
        compensate_pair(scan0, scan90, order=3)
    with pytest.raises(ValueError, match="method"):
        compensate_pair(scan0, scan90, method="magic")


@pytest.mark.parametrize(
    "case, field",
    [
        (lambda u, d, t: (u, u), "scan_down.slow_scan_up"),
        (lambda u, d, t: (d, d), "scan_up.slow_scan_up"),
        (
            lambda u, d, t: (u, dataclasses.replace(t, slow_scan_up=False)),
            "scan_down.scan_angle_deg",
        ),
        (lambda u, d, t: (u, with_nan(d)), "scan_down.height"),
        (
            lambda u, d, t: (u, dataclasses.replace(d, pixel_size_y=d.pixel_size_y * 2)),
            "scan_down.pixel_size_y",
        ),
        (
            lambda u, d, t: (
                u,
                dataclasses.replace(
                    d, height=d.height[:50], line_start_times=d.line_start_times[:50]
                ),
            ),
            "scan_down.height",
        ),
        (
            lambda u, d, t: (dataclasses.replace(u, height=np.zeros_like(u.height)), d),
            "scan_up.height",
        ),
    ],
)
def test_bad_up_down_pairs_raise_naming_the_field(small_pair, case, field):
    up, turned, down = small_pair
    a, b = case(up, down, turned)
    with pytest.raises(ValueError, match=field.replace(".", r"\.")):
        velocity_from_up_down(a, b)
