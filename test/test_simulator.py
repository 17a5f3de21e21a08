"""The simulated instrument against closed forms (book ch. 2-5 physics)."""

import math

import numpy as np
import pytest
from scipy import ndimage, optimize

from afm_core.instrument import LineRequest, ScanRequest
from afm_core.sim.config import SimConfig, config_from_dict, dump_config, load_config, merge
from afm_core.sim.drift import DriftParams, ThermalDrift
from afm_core.sim.instrument import SimulatedAfm
from afm_core.sim.tip import Tip, TipParams, paraboloid_cone_tip

QUIET = {
    "noise": {"height_white_sigma": 0.0, "height_flicker_sigma": 0.0, "deflection_sigma": 0.0},
    "sample": {"roughness_sigma": 0.0},
}


def ideal(**overrides) -> SimConfig:
    """Every imperfection off: scanner exact, no drift, no noise, smooth substrate."""
    config = load_config()
    config = merge(config, QUIET)
    config = merge(config, {"drift": {"enabled": False}, "scanner": ideal_scanner(config)})
    return merge(config, overrides)


def ideal_scanner(config) -> dict:
    from dataclasses import asdict

    fields = asdict(config.scanner)
    return {k: False for k, v in fields.items() if isinstance(v, bool) and k.endswith("enabled")}


def test_config_rejects_unknown_keys_and_wrong_types_by_name():
    with pytest.raises(ValueError, match=r"drift: unknown key 'velocty'"):
        merge(load_config(), {"drift": {"velocty": 1}})
    with pytest.raises(ValueError, match=r"tip.apex_radius='big'"):
        merge(load_config(), {"tip": {"apex_radius": "big"}})
    round_trip = config_from_dict(__import__("yaml").safe_load(dump_config(load_config())))
    assert round_trip == load_config()


def test_a_config_file_may_write_numbers_without_a_dot(tmp_path):
    """3e-10 and 1.5e9 are strings to PyYAML (YAML 1.1) and numbers to YAML 1.2 and to people."""
    import yaml

    from afm_core.localization.calibration.model import load_calibration
    from afm_core.yaml_files import load_yaml

    path = tmp_path / "lab.yaml"
    path.write_text("noise: {height_white_sigma: 3e-10}\ntip: {apex_radius: 2E-8}\n")
    config = load_config(path)
    assert config.noise.height_white_sigma == 3e-10 and config.tip.apex_radius == 2e-8
    calibration = tmp_path / "calibration.yaml"
    calibration.write_text("map_sigma: [2e-9, 3e-9]\n")
    assert tuple(load_calibration(calibration).map_sigma) == (2e-9, 3e-9)
    assert yaml.safe_load("a: 3e-10") == {"a": "3e-10"}  # PyYAML's own loader left as it is
    for text, value in [("1.5e9", 1.5e9), ("-2.0e6", -2.0e6), (".5E3", 500.0), ("+1.e-3", 1e-3)]:
        assert load_yaml(f"a: {text}") == {"a": value}, text
    for text in ["1.5e", "e9", "1.5e9nm", "1_5e"]:
        assert load_yaml(f"a: {text}") == {"a": text}, text
    with pytest.raises(ValueError, match=r"noise.height_white_sigma='3nm'"):
        path.write_text("noise: {height_white_sigma: 3nm}\n")
        load_config(path)


def test_same_seed_same_session():
    request = ScanRequest(4.5e-6, 4.5e-6, 1e-6, 1e-6, 64, 64)
    a = SimulatedAfm(load_config()).raster_scan(request).height
    b = SimulatedAfm(load_config()).raster_scan(request).height
    c = SimulatedAfm(merge(load_config(), {"seed": 1})).raster_scan(request).height
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def exact_paraboloid_image(R, Rt, x):
    """Tip apex height over horizontal distance x from a sphere's centre, for a pure
    paraboloid tip z = -u^2 / (2 Rt): the 1-D maximisation i(x) = max_v s(v) - (v - x)^2 / (2 Rt)
    solved numerically on the exact sphere profile (independent of the 2-D grid code)."""

    def minus(v):
        return -(R + math.sqrt(max(R * R - v * v, 0.0)) - (v - x) ** 2 / (2 * Rt))

    best = optimize.minimize_scalar(
        minus, bounds=(-R, R), method="bounded", options={"xatol": 1e-14}
    )
    return max(-best.fun, 0.0)


def test_sphere_image_width_matches_the_paraboloid_tip_solution():
    R, Rt, pixel = 100e-9, 30e-9, 2.5e-9
    # a 10 deg cone meets the paraboloid 480 nm below the apex: within the sphere's 200 nm
    # the tip is the paraboloid alone
    config = ideal(
        sample={"spheres": [{"x": 5e-6, "y": 5e-6, "radius": R}]},
        tip={"apex_radius": Rt, "half_angle_deg": 10.0},
    )
    afm = SimulatedAfm(config)
    n = 200
    scan = afm.raster_scan(
        ScanRequest(5e-6 - n * pixel / 2, 5e-6 - n * pixel / 2, n * pixel, n * pixel, n, n)
    )
    profile = scan.height[n // 2]
    xs = (np.arange(n) + 0.5) * pixel - n * pixel / 2
    for level in (0.5 * R, 1.0 * R, 1.5 * R):
        measured = np.count_nonzero(profile > level) * pixel
        exact = 2 * optimize.brentq(lambda x: exact_paraboloid_image(R, Rt, x) - level, 0, 3 * R)
        assert measured == pytest.approx(exact, abs=2.5 * pixel), level
    expected = np.array([exact_paraboloid_image(R, Rt, abs(x)) for x in xs])
    # a grid samples the surface: allow the exact curve's change over one pixel, plus 0.5 nm
    allowed = 0.5e-9 + np.abs(np.gradient(expected, xs)) * pixel
    assert np.all(np.abs(profile - expected) <= allowed)


@pytest.mark.parametrize("frame_up", [True, False])
def test_constant_drift_stretches_frame_up_and_compresses_frame_down(frame_up):
    """Two spheres 1 um apart along y. With the sample drifting at v along +y and the slow
    scan advancing at V = pixel / line period, frame-up separations appear V/(V - v) times
    too long and frame-down ones V/(V + v) times."""
    v = 1.0e-9  # m/s, a fast drift for a clear effect
    pixels, size, line_rate = 200, 1.6e-6, 1.0
    V = size / pixels * line_rate
    config = ideal(
        sample={
            "spheres": [
                {"x": 5e-6, "y": 4.5e-6, "radius": 80e-9},
                {"x": 5e-6, "y": 5.5e-6, "radius": 80e-9},
            ]
        },
        drift={
            "enabled": True,
            "mean_velocity_x": 0.0,
            "mean_velocity_y": v,
            "sigma_velocity_x": 0.0,
            "sigma_velocity_y": 0.0,
        },
    )
    afm = SimulatedAfm(config)
    scan = afm.raster_scan(
        ScanRequest(
            4.2e-6, 4.2e-6, size, size, pixels, pixels, slow_scan_up=frame_up, line_rate=line_rate
        )
    )
    labels, count = ndimage.label(scan.height > 80e-9)
    assert count == 2
    rows = [c[0] for c in ndimage.center_of_mass(scan.height > 80e-9, labels, [1, 2])]
    apparent = abs(rows[1] - rows[0]) * size / pixels
    factor = V / (V - v) if frame_up else V / (V + v)
    assert apparent == pytest.approx(1e-6 * factor, abs=2 * size / pixels)
    assert abs(factor - 1) > 0.08  # the effect is far above the pixel size


def test_drift_statistics_and_exact_integral():
    params = DriftParams(
        mean_velocity_x=1e-9, mean_velocity_y=-2e-9, sigma_velocity_x=0.0, sigma_velocity_y=0.0
    )
    drift = ThermalDrift(params, seed=3)
    np.testing.assert_allclose(
        drift.offset([0.0, 10.0, 125.5]), [[0, 0], [1e-8, -2e-8], [125.5e-9, -251e-9]], atol=1e-18
    )
    wander = ThermalDrift(DriftParams(correlation_time=100.0), seed=4)
    t = np.arange(0, 200_000.0, 50.0)
    v = wander.velocity(t)
    assert np.mean(v[:, 1]) == pytest.approx(0.099e-9, abs=0.04e-9)
    assert np.std(v[:, 1]) == pytest.approx(0.209e-9, rel=0.15)
    # the offset is the integral of the velocity
    dense = np.arange(0, 1000.0, 0.25)
    numeric = np.cumsum(wander.velocity(dense)[:, 0]) * 0.25
    assert wander.offset(1000.0)[0] == pytest.approx(numeric[-1], rel=1e-3)
    # queried in any order, the same seed gives the same drift
    late_first = ThermalDrift(DriftParams(correlation_time=100.0), seed=4)
    late_first.offset(5000.0)
    assert late_first.offset(12.5)[1] == wander.offset(12.5)[1]


def test_tip_asymmetry_and_wear():
    symmetric = paraboloid_cone_tip(10e-9, 20.0, 2e-9, 200e-9)
    skewed = paraboloid_cone_tip(10e-9, 20.0, 2e-9, 200e-9, asymmetry=0.3)
    c = skewed.shape[0] // 2
    np.testing.assert_allclose(symmetric, symmetric[:, ::-1])
    assert (
        skewed[c, c + 30] > skewed[c, c - 30]
    )  # a > 0: the +x flank is blunter (falls off slower)
    tip = Tip(TipParams(apex_radius=10e-9, wear_enabled=True, wear_rate=1e-3))
    tip.slide(5e-6)
    assert tip.apex_radius == pytest.approx(10e-9 + 5e-9)
    unworn = Tip(TipParams(apex_radius=10e-9, wear_enabled=False, wear_rate=1e-3))
    unworn.slide(5e-6)
    assert unworn.apex_radius == 10e-9


def test_a_spherical_apex_is_a_sphere_blended_into_the_cone():
    """The cap is the sphere of the apex radius (closed form), it meets the cone where their
    slopes are equal (continuous and smooth), and below the apex it is sharper than the
    paraboloid of the same radius."""
    radius, angle, pixel = 20e-9, 20.0, 0.5e-9
    tip = paraboloid_cone_tip(radius, angle, pixel, 60e-9, apex_shape="sphere")
    parab = paraboloid_cone_tip(radius, angle, pixel, 60e-9)
    c = tip.shape[0] // 2
    r = np.arange(tip.shape[0] - c) * pixel
    profile = tip[c, c:]
    r_tangent = radius * np.cos(np.radians(angle))
    on_cap = r < r_tangent
    np.testing.assert_allclose(
        profile[on_cap], -(radius - np.sqrt(radius**2 - r[on_cap] ** 2)), atol=1e-15
    )
    z_tangent = -radius * (1 - np.sin(np.radians(angle)))
    cone = (r > r_tangent) & (profile > -60e-9)
    np.testing.assert_allclose(
        profile[cone], z_tangent - (r[cone] - r_tangent) / np.tan(np.radians(angle)), atol=1e-15
    )
    assert np.all(
        np.abs(np.diff(profile)) <= pixel / np.tan(np.radians(angle)) + 1e-15
    )  # no step at the seam
    cp = parab.shape[0] // 2
    parab = parab[cp - c : cp + c + 1, cp - c : cp + c + 1]  # the sphere's grid is smaller
    assert np.all(tip <= parab) and tip[c, c + 20] < parab[c, c + 20]
    with pytest.raises(ValueError, match="apex_shape"):
        TipParams(apex_shape="cone").validate()


def test_local_scan_line_finds_a_sphere_centre():
    config = ideal(sample={"spheres": [{"x": 5e-6, "y": 5e-6, "radius": 100e-9}]})
    afm = SimulatedAfm(config)
    line = afm.local_scan(LineRequest(4.6e-6, 5e-6, 5.4e-6, 5e-6, samples=801, speed=1e-6))
    above = line.x[line.height > 100e-9]
    assert 0.5 * (above[0] + above[-1]) == pytest.approx(5e-6, abs=1.5e-9)
    assert line.height.max() == pytest.approx(200e-9, abs=0.5e-9)
    assert np.all(np.diff(line.times) > 0) and line.times[-1] == pytest.approx(0.8, rel=1e-6)


def test_indentation_punches_a_pit_that_the_next_scan_shows():
    afm = SimulatedAfm(ideal(sample={"spheres": []}))
    result = afm.indent(3e-6, 3e-6, force=1e-6, dwell=0.5)
    depth = 1e-6 / afm.config.indentation.sample_stiffness
    assert result.completed and result.trace.task == "indent"
    assert result.trace.vertical_deflection.max() == pytest.approx(
        1e-6 / afm.config.contact.normal_spring_constant
    )
    scan = afm.raster_scan(ScanRequest(2.8e-6, 2.8e-6, 0.4e-6, 0.4e-6, 100, 100))
    assert scan.height.min() < -0.3 * depth
    row, col = np.unravel_index(np.argmin(scan.height), scan.height.shape)
    assert (2.8e-6 + (col + 0.5) * 4e-9) == pytest.approx(3e-6, abs=8e-9)


@pytest.mark.parametrize(
    "bad, field",
    [
        (dict(origin_x=float("nan")), "origin_x"),
        (dict(size_y=0.0), "size_y"),
        (dict(pixels_x=100_000), "pixels_x"),
        (dict(origin_x=109.9e-6), "scanner range"),
        (dict(line_rate=1e3), "line_rate"),
        (dict(pixels_x=64.5), "pixels_x=64.5: need a whole number"),
        # 1 nm at 64 px: a 13,000 px tip grid (the driver reached 23 GB and was killed)
        (dict(size_x=1e-9, size_y=1e-9), r"pixel size 0.0156 nm: finer than the simulator"),
    ],
)
def test_bad_scan_requests_name_the_field_and_move_nothing(bad, field):
    afm = SimulatedAfm(ideal())
    before = (afm.commanded_position(), afm.time)
    fields = dict(origin_x=1e-6, origin_y=1e-6, size_x=1e-6, size_y=1e-6, pixels_x=64, pixels_y=64)
    fields.update(bad)
    with pytest.raises(ValueError, match=field):
        afm.raster_scan(ScanRequest(**fields))
    assert (afm.commanded_position(), afm.time) == before


def test_moves_outside_the_range_or_too_fast_are_refused():
    afm = SimulatedAfm(ideal())
    with pytest.raises(ValueError, match=r"target.x=.*outside the scanner range"):
        afm.move_tip(111e-6, 5e-6, 1e-6)
    with pytest.raises(ValueError, match="slew limit"):
        afm.move_tip(5e-6, 5e-6, 1.0)
    with pytest.raises(ValueError, match="target.y=inf"):
        afm.move_tip(5e-6, float("inf"), 1e-6)


def test_cancel_stops_a_raster_between_lines():
    afm = SimulatedAfm(ideal())
    calls = []
    scan = afm.raster_scan(
        ScanRequest(4e-6, 4e-6, 1e-6, 1e-6, 64, 64),
        on_line=lambda done, total: calls.append(done),
        should_stop=lambda: len(calls) >= 20,
    )
    assert not scan.complete
    assert np.isnan(scan.height).any(axis=1).sum() == 64 - len(calls)
    assert calls == list(range(1, len(calls) + 1))


def test_pushing_moves_a_sphere_and_the_next_scan_shows_it():
    config = ideal(sample={"spheres": [{"x": 5e-6, "y": 5e-6, "radius": 100e-9}]})
    afm = SimulatedAfm(config)
    afm.move_tip(4.7e-6, 5e-6, 10e-6)
    move = afm.move_tip(5.2e-6, 5e-6, 1e-6, contact=True)
    sphere = afm.sample.spheres[0]
    assert sphere.x > 5.05e-6 and abs(sphere.y - 5e-6) < 5e-9
    assert move.trace is not None and move.trace.object_id == 0
    assert np.max(np.abs(move.trace.lateral_torsion)) > 0


def test_documented_default_file_matches_the_code_defaults():
    from afm_core.sim.config import DEFAULT_CONFIG_FILE

    assert (
        config_from_dict(__import__("yaml").safe_load(DEFAULT_CONFIG_FILE.read_text()))
        == SimConfig()
    )


def test_move_errors_accumulate_with_the_calibrated_variance_per_distance():
    """Each move adds an independent error of variance slope x distance + offset per axis
    (book Fig. 7.20b); the error persists, so it is the increments that are independent."""
    slope, offset = 0.5e-9, 4e-18
    sim = SimulatedAfm(
        ideal(
            scanner={
                "positioning_noise_enabled": True,
                "positioning_noise_slope": slope,
                "positioning_noise_offset": offset,
            }
        )
    )
    distance = 2e-6
    x0, y0 = sim.commanded_position()
    errors = []
    for k in range(400):
        sim.move_tip(x0 + (distance if k % 2 == 0 else 0.0), y0, 1e-4)
        truth = sim.truth()
        errors.append(np.subtract(truth["tip_position"], sim.commanded_position()))
    increments = np.diff(np.array(errors), axis=0)
    expected = slope * distance + offset
    measured = increments.var(axis=0)
    assert measured == pytest.approx([expected, expected], rel=0.2)
    assert abs(np.corrcoef(increments[:-1, 0], increments[1:, 0])[0, 1]) < 0.2


def test_a_fine_pixel_scan_dilates_in_bounded_memory_exactly_as_scipy():
    """A 100 nm image at 64 px needs a 135 px tip grid; scipy's grey filters precompute
    (tip pixels)^2 offsets for it (2.6 GB, the driver died). The shifted-slice path used for
    large tips gives the same numbers to the bit (compared here on a 61 px tip, where scipy
    still needs only ~110 MB)."""
    import resource

    from scipy import ndimage

    from afm_core.physics import tip_morphology
    from afm_core.sim.tip import paraboloid_cone_tip

    afm = SimulatedAfm(load_config())
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    scan = afm.raster_scan(ScanRequest(55e-6, 55e-6, 100e-9, 100e-9, 64, 64))
    grown = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024  # MiB
    assert np.isfinite(scan.height).all() and grown < 500, grown
    rng = np.random.default_rng(3)
    surface = rng.normal(0.0, 1e-9, (70, 90))
    surface[30:50, 40:70] += 60e-9  # as tall as the tip grid is deep: little is pruned
    tip = paraboloid_cone_tip(10e-9, 20.0, 1.0e-9, 60e-9, asymmetry=0.2, max_half_width=30)
    assert tip.shape == (61, 61) and tip_morphology._large(tip)
    for ours, theirs in (
        (tip_morphology.dilate, ndimage.grey_dilation),
        (tip_morphology.erode, ndimage.grey_erosion),
    ):
        expected = theirs(surface, structure=tip[::-1, ::-1], mode="nearest")
        np.testing.assert_array_equal(ours(surface, tip), expected)
