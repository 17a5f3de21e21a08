"""Simulated imaging against closed forms and brute force."""
import numpy as np
import pytest

from afm_core.sim.imaging import dilate
from afm_core.sim.instrument import ScanRequest, SimConfig, SimulatedAfm
from afm_core.sim.sample import Sphere
from afm_core.sim.tip import paraboloid_cone_tip


def brute_force_image(surface, tip):
    """i(x) = max_u s(x+u) + t(u), edges clamped, straight from the definition."""
    h = tip.shape[0] // 2
    padded = np.pad(surface, h, mode="edge")
    out = np.full(surface.shape, -np.inf)
    for du in range(-h, h + 1):
        for dv in range(-h, h + 1):
            shifted = padded[h + du: h + du + surface.shape[0], h + dv: h + dv + surface.shape[1]]
            out = np.maximum(out, shifted + tip[h + du, h + dv])
    return out


def test_dilation_matches_definition_for_an_asymmetric_tip():
    rng = np.random.default_rng(1)
    surface = rng.normal(size=(40, 50))
    tip = -rng.uniform(0, 3, size=(7, 7))
    tip[3, 3] = 0.0
    np.testing.assert_allclose(dilate(surface, tip), brute_force_image(surface, tip))


def test_tip_is_a_paraboloid_at_the_apex_and_a_cone_further_out():
    radius, angle, pixel = 20e-9, 20.0, 0.5e-9
    tip = paraboloid_cone_tip(radius, angle, pixel, depth=600e-9)
    c = tip.shape[0] // 2
    assert tip[c, c] == 0.0 and tip.max() == 0.0
    r = 3 * pixel
    assert tip[c, c + 3] == pytest.approx(-r**2 / (2 * radius))
    # cone wall: slope 1/tan(angle) between two points outside the tangent radius R/tan(angle) = 55 nm
    z1, z2 = tip[c, c + 200], tip[c, c + 300]
    assert (z1 - z2) / (100 * pixel) == pytest.approx(1 / np.tan(np.radians(angle)), rel=1e-9)


@pytest.mark.parametrize("bad, complaint", [
    (dict(size_x=-1e-6), "size_x"), (dict(pixels_x=1), "pixels_x"), (dict(scan_angle_deg=45.0), "scan_angle_deg"),
    (dict(origin_x=109.5e-6), "scanner range"), (dict(line_rate=float("nan")), "line_rate"),
    (dict(mode="nc"), "mode"),
])
def test_scan_request_errors_name_the_field(bad, complaint):
    fields = dict(origin_x=1e-6, origin_y=1e-6, size_x=1e-6, size_y=1e-6, pixels_x=64, pixels_y=64)
    fields.update(bad)
    with pytest.raises(ValueError, match=complaint):
        ScanRequest(**fields).validate()


def test_sphere_image_is_at_or_above_the_surface_and_broadened_by_the_tip():
    config = SimConfig(noise_sigma=0.0, spheres=[(2e-6, 2e-6, 100e-9)], tip_apex_radius=20e-9)
    afm = SimulatedAfm(config)
    scan = afm.raster_scan(ScanRequest(1.5e-6, 1.5e-6, 1e-6, 1e-6, 200, 200))
    xs = 1.5e-6 + (np.arange(200) + 0.5) * 5e-9
    surface = afm.sample.height(*np.meshgrid(xs, xs))
    assert np.all(scan.height >= surface.astype(np.float32) - 1e-12)
    assert scan.height.max() == pytest.approx(200e-9, abs=0.5e-9)
    # apparent width at half height exceeds the true chord (tip broadening) but not by more than 2 tip radii
    row = scan.height[100]
    apparent = np.count_nonzero(row > 100e-9) * 5e-9
    true_chord = 2 * np.sqrt(100e-9**2 - 0.0)   # the half-height plane crosses the sphere at its equator
    assert true_chord < apparent < true_chord + 4 * 20e-9


def test_line_times_follow_the_slow_scan_direction():
    afm = SimulatedAfm(SimConfig(noise_sigma=0.0))
    up = afm.raster_scan(ScanRequest(1e-6, 1e-6, 1e-6, 1e-6, 32, 16, line_rate=2.0))
    down = afm.raster_scan(ScanRequest(1e-6, 1e-6, 1e-6, 1e-6, 32, 16, line_rate=2.0, slow_scan_up=False))
    turned = afm.raster_scan(ScanRequest(1e-6, 1e-6, 1e-6, 1e-6, 32, 16, line_rate=2.0, scan_angle_deg=90.0))
    np.testing.assert_allclose(up.line_start_times, np.arange(16) * 0.5)
    np.testing.assert_allclose(down.line_start_times, np.arange(16)[::-1] * 0.5)
    assert len(turned.line_start_times) == 32            # a 90 deg line is a column
    assert down.start_time == pytest.approx(up.start_time + 16 * 0.5)


def test_same_seed_same_noise():
    request = ScanRequest(1e-6, 1e-6, 1e-6, 1e-6, 32, 32)
    a = SimulatedAfm(SimConfig(seed=4)).raster_scan(request).height
    b = SimulatedAfm(SimConfig(seed=4)).raster_scan(request).height
    c = SimulatedAfm(SimConfig(seed=5)).raster_scan(request).height
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
