"""Simulated imaging against closed forms and brute force."""

import numpy as np
import pytest

from afm_core.instrument import ScanRequest
from afm_core.physics.tip_morphology import dilate
from afm_core.sim.instrument import SimulatedAfm
from afm_core.sim.tip import paraboloid_cone_tip


def brute_force_image(surface, tip):
    """i(x) = max_u s(x+u) + t(u), edges clamped, straight from the definition."""
    h = tip.shape[0] // 2
    padded = np.pad(surface, h, mode="edge")
    out = np.full(surface.shape, -np.inf)
    for du in range(-h, h + 1):
        for dv in range(-h, h + 1):
            shifted = padded[
                h + du : h + du + surface.shape[0], h + dv : h + dv + surface.shape[1]
            ]
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
    assert tip[c, c + 3] == pytest.approx(-(r**2) / (2 * radius))
    # cone wall: slope 1/tan(angle) between two points outside the tangent radius
    # R/tan(angle) = 55 nm
    z1, z2 = tip[c, c + 200], tip[c, c + 300]
    assert (z1 - z2) / (100 * pixel) == pytest.approx(1 / np.tan(np.radians(angle)), rel=1e-9)


def test_line_times_follow_the_slow_scan_direction():
    from test_simulator import ideal

    afm = SimulatedAfm(ideal())
    up = afm.raster_scan(ScanRequest(1e-6, 1e-6, 1e-6, 1e-6, 32, 16, line_rate=2.0))
    down = afm.raster_scan(
        ScanRequest(1e-6, 1e-6, 1e-6, 1e-6, 32, 16, line_rate=2.0, slow_scan_up=False)
    )
    turned = afm.raster_scan(
        ScanRequest(1e-6, 1e-6, 1e-6, 1e-6, 32, 16, line_rate=2.0, scan_angle_deg=90.0)
    )
    np.testing.assert_allclose(up.line_start_times, np.arange(16) * 0.5, atol=1e-9)
    np.testing.assert_allclose(down.line_start_times, np.arange(16)[::-1] * 0.5, atol=1e-9)
    assert len(turned.line_start_times) == 32  # a 90 deg line is a column
    assert down.start_time > up.start_time + 16 * 0.5


def test_dilated_field_and_pointwise_dilation_agree():
    from afm_core.physics.sample import Pit, Roughness, Sample, Sphere
    from afm_core.sim.imaging import DilatedField, dilated_heights_at

    sample = Sample(
        spheres=[Sphere(0, 100e-9, 100e-9, 50e-9)],
        roughness=Roughness(1e-9, 10e-9, seed=1),
        pits=[Pit(1, 40e-9, 100e-9, 15e-9, 6e-9)],
    )
    tip = paraboloid_cone_tip(10e-9, 20.0, 2e-9, 120e-9)
    field = DilatedField(sample.height, tip, 0.0, 0.0, 100, 100, 2e-9)
    xs = np.linspace(20e-9, 180e-9, 41)
    ys = np.full_like(xs, 100e-9)
    np.testing.assert_allclose(
        field.at(xs, ys), dilated_heights_at(sample, tip, 2e-9, xs, ys), atol=1e-12
    )


def test_pointwise_dilation_tries_only_offsets_that_can_win_and_equals_the_definition():
    """Particles, a rod and an electrode on a rough, pitted substrate, seen along lines by a
    blunt asymmetric tip and a sharp one: the heights equal max over every tip offset of
    s(q+u) + t(u), though only the offsets that can win are tried."""
    from afm_core.physics.sample import Electrode, Pit, Rod, Roughness, Sample, Sphere
    from afm_core.sim.imaging import dilated_heights_at

    sample = Sample(
        spheres=[Sphere(0, 120e-9, 100e-9, 15e-9), Sphere(1, 160e-9, 110e-9, 5e-9)],
        rods=[Rod(2, 60e-9, 160e-9, 0.4, 120e-9, 8e-9)],
        electrodes=[Electrode(3, 150e-9, 150e-9, 260e-9, 220e-9, 25e-9)],
        pits=[Pit(4, 90e-9, 90e-9, 15e-9, 4e-9)],
        roughness=Roughness(1.5e-9, 10e-9, seed=3),
    )
    s = np.linspace(0.0, 1.0, 250)
    for radius, asymmetry, pixel in ((30e-9, 0.3, 2e-9), (4e-9, -0.2, 1e-9)):
        tip = paraboloid_cone_tip(radius, 20.0, pixel, 60e-9, asymmetry)
        half = tip.shape[0] // 2
        u = np.arange(-half, half + 1) * pixel
        ux, uy = (a.ravel() for a in np.meshgrid(u, u))
        for x0, y0, x1, y1 in ((20e-9, 100e-9, 280e-9, 110e-9), (60e-9, 20e-9, 220e-9, 240e-9)):
            xs, ys = x0 + s * (x1 - x0), y0 + s * (y1 - y0)
            definition = np.max(
                sample.height(xs[:, None] + ux, ys[:, None] + uy) + tip.ravel(), axis=1
            )
            np.testing.assert_array_equal(
                dilated_heights_at(sample, tip, pixel, xs, ys), definition
            )


def test_pointwise_dilation_of_a_large_particle_under_a_fine_tip_equals_the_definition():
    """The closed-loop sessions' local scans: 100 nm particles under a 20 nm tip gridded at
    1 nm (209 x 209 offsets, nearly all within a particle's reach), over a pit deeper than the
    roughness (the base tries per point only offsets that can beat the apex's own height, the
    particle only tiles of offsets whose bound can): every height equals the definition's,
    max over every offset, to the bit, on lines across the particle, its flank, the pit and a
    line clear of the particle."""
    from afm_core.physics.sample import Pit, Roughness, Sample, Sphere
    from afm_core.sim.imaging import dilated_heights_at

    sample = Sample(
        spheres=[Sphere(0, 300e-9, 300e-9, 100e-9), Sphere(1, 480e-9, 330e-9, 60e-9)],
        pits=[Pit(2, 150e-9, 300e-9, 25e-9, 10e-9), Pit(3, 160e-9, 305e-9, 25e-9, 6e-9)],
        roughness=Roughness(1.5e-9, 8e-9, seed=5),
    )
    pixel = 1e-9
    tip = paraboloid_cone_tip(20e-9, 20.0, pixel, 210e-9)
    half = tip.shape[0] // 2
    u = np.arange(-half, half + 1) * pixel
    ux, uy = (a.ravel() for a in np.meshgrid(u, u))
    s = np.linspace(0.0, 1.0, 160)
    lines = (
        (100e-9, 300e-9, 600e-9, 310e-9),  # the pit, across both particles
        (300e-9, 150e-9, 330e-9, 450e-9),  # across the large one
        (180e-9, 190e-9, 420e-9, 210e-9),  # along its flank
        (100e-9, 600e-9, 600e-9, 620e-9),  # clear of the particles
    )
    for x0, y0, x1, y1 in lines:
        xs, ys = x0 + s * (x1 - x0), y0 + s * (y1 - y0)
        definition = np.max(
            sample.height(xs[:, None] + ux, ys[:, None] + uy) + tip.ravel(), axis=1
        )
        np.testing.assert_array_equal(dilated_heights_at(sample, tip, pixel, xs, ys), definition)


@pytest.mark.parametrize("level_key", ["height_white_sigma", "height_flicker_sigma"])
def test_raster_sensor_noise_is_linear_in_its_level(level_key):
    """The sim2real noise curve re-simulates a noise term at two levels and takes every other
    level as their linear combination: the rasters' noise must be its level times draws that
    do not depend on it (the drift's wander, the positioning walk and the piezo unchanged)."""
    from afm_core.sim.config import load_config, merge

    def image(level):
        afm = SimulatedAfm(merge(load_config(), {"seed": 4, "noise": {level_key: level}}))
        return afm.raster_scan(
            ScanRequest(50e-6, 50e-6, 1e-6, 1e-6, 48, 24, line_rate=4.0)
        ).height.astype(float)

    zero, unit, far = image(0.0), image(0.3e-9), image(1.1e-9)
    assert np.std(far - zero) > 0.5e-9  # the level moves the image
    np.testing.assert_allclose(far, zero + 1.1 / 0.3 * (unit - zero), rtol=0, atol=2e-13)


def test_the_dilated_field_is_made_as_lines_need_it_and_equals_the_whole_fields_dilation():
    """A 4096-line scan's field is dilated in bands along the lines asked for, not whole
    before the first line (issue 30: a 2048 x 2048 scan could not be cancelled for minutes);
    every value equals the whole grid's dilation to the bit, in either scan direction."""
    from scipy import ndimage

    from afm_core.physics.sample import Roughness, Sample, Sphere
    from afm_core.physics.tip_morphology import dilate
    from afm_core.sim.imaging import BAND, DilatedField

    sample = Sample(
        spheres=[Sphere(0, 60e-9, 50e-9, 20e-9)], roughness=Roughness(1e-9, 10e-9, seed=2)
    )
    tip = paraboloid_cone_tip(10e-9, 20.0, 2e-9, 40e-9)
    big = DilatedField(sample.height, tip, 0.0, 0.0, 4400, 4400, 2e-9)
    xs = np.linspace(0.0, 4399 * 2e-9, 4400)
    big.at(xs, np.full_like(xs, 50e-9))
    assert list(big.bands) == [0] and big.bands[0].shape == (big.band, 4400)
    assert big.band <= BAND
    half = tip.shape[0] // 2
    grid = np.arange(-half, 300 + half) * 2e-9
    surface = sample.height(*np.meshgrid(grid, grid[: 290 + 2 * half]))
    whole = dilate(surface, tip)[half : half + 290, half : half + 300]
    rng = np.random.default_rng(0)
    qx, qy = rng.uniform(-10e-9, 610e-9, 500), rng.uniform(-10e-9, 590e-9, 500)
    reference = ndimage.map_coordinates(
        whole, np.stack([qy / 2e-9, qx / 2e-9]), order=1, mode="nearest"
    )
    for along_x in (True, False):
        small = DilatedField(sample.height, tip, 0.0, 0.0, 300, 290, 2e-9, along_x)
        small.band = 70  # several bands, the last one shorter
        assert np.array_equal(small.at(qx, qy), reference)
        assert np.array_equal(small.values, whole)
