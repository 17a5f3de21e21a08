"""The simulator's optional physics (issue 8: each effect a lab recording may show) against
closed forms: ramped drift, scanner bow, z-sensor gain and latency, spatially varying
friction, stick-slip, tip wear, 1/f noise; and every new key at its default changes nothing.

Expected values come from the formulas in default_config.yaml, never from the code under test.
"""

import math

import numpy as np
import pytest
from scipy import signal

from afm_core.instrument import LineRequest, ScanRequest
from afm_core.physics.contact import ContactParams
from afm_core.physics.pushing import push_along_path
from afm_core.physics.sample import Rod, Sample
from afm_core.sim.config import SimConfig, config_from_dict, dump_config, load_config, merge
from afm_core.sim.instrument import SimulatedAfm

QUIET = {
    "noise": {"height_white_sigma": 0.0, "height_flicker_sigma": 0.0, "deflection_sigma": 0.0},
    "sample": {"roughness_sigma": 0.0},
}
NO_SPHERES = {"sample": {"spheres": []}}
ONE_SPHERE = {"sample": {"spheres": [{"x": 5e-6, "y": 5e-6, "radius": 80e-9}]}}
STILL = {
    "enabled": True,
    "mean_velocity_x": 0.0,
    "mean_velocity_y": 0.0,
    "sigma_velocity_x": 0.0,
    "sigma_velocity_y": 0.0,
}


def ideal(*overrides: dict) -> SimConfig:
    """Every imperfection off (exact scanner, no drift, no noise, smooth substrate), then the
    overrides in order: true scanner position = command, sample frame = scanner frame."""
    config = merge(load_config(), QUIET)
    flags = {
        f: False
        for f, v in vars(config.scanner).items()
        if isinstance(v, bool) and f.endswith("enabled")
    }
    config = merge(config, {"drift": {"enabled": False}, "scanner": flags})
    for override in overrides:
        config = merge(config, override)
    return config


def weighted_centre(height: np.ndarray, level: float) -> tuple[float, float]:
    """(row, column) centroid of the height above `level`, weighted by the excess (sub-pixel)."""
    w = np.clip(height.astype(float) - level, 0.0, None)
    rows, cols = np.indices(w.shape)
    return float((w * rows).sum() / w.sum()), float((w * cols).sum() / w.sum())


def crossing_centre(line, level: float) -> float:
    """Mid-point (commanded x) of where a line's height is above `level`, interpolated."""
    above = np.flatnonzero(line.height > level)
    i0, i1 = above[0], above[-1]
    x_up = np.interp(level, line.height[i0 - 1 : i0 + 1], line.x[i0 - 1 : i0 + 1])
    x_down = np.interp(level, line.height[i1 : i1 + 2][::-1], line.x[i1 : i1 + 2][::-1])
    return 0.5 * (x_up + x_down)


def lateral_force(trace, config: SimConfig) -> np.ndarray:
    """N, from the torsion: F = torsion x torsional stiffness / tip height."""
    return (
        trace.lateral_torsion * config.contact.lateral_spring_constant / config.contact.tip_height
    )


# ---------------------------------------------------------------------------- 1. ramped drift


def test_ramped_drift_truth_is_the_closed_form():
    v, a = np.array([1e-10, -0.5e-10]), np.array([3e-12, -2e-12])
    sim = SimulatedAfm(
        ideal(
            {
                "drift": {
                    **STILL,
                    "mean_velocity_x": v[0],
                    "mean_velocity_y": v[1],
                    "acceleration_x": a[0],
                    "acceleration_y": a[1],
                }
            }
        )
    )
    sim.hold(123.4)
    t = sim.time
    truth = sim.truth()
    np.testing.assert_allclose(truth["drift_offset"], v * t + 0.5 * a * t**2, rtol=1e-9)
    np.testing.assert_allclose(truth["drift_velocity"], v + a * t, rtol=1e-9)
    # the tip (held at the centre of the range) sits on the sample where the drift has put it
    np.testing.assert_allclose(
        truth["tip_position"],
        np.array(sim.commanded_position()) - truth["drift_offset"],
        rtol=0,
        atol=1e-15,
    )


def test_ramped_drift_moves_a_particle_by_half_a_t_squared_between_images():
    """A sphere imaged at times t1 and t2 (when the scan passes its centre) appears at
    X + 0.5 a t^2 each time: the centroids differ by 0.5 a (t2^2 - t1^2)."""
    a = np.array([4e-11, -3e-11])  # m/s^2, a strong ramp for a clear effect
    sim = SimulatedAfm(
        ideal(ONE_SPHERE, {"drift": {**STILL, "acceleration_x": a[0], "acceleration_y": a[1]}})
    )
    n, size, origin = 64, 1e-6, 4.5e-6
    request = ScanRequest(origin, origin, size, size, n, n, line_rate=8.0)

    def centre_and_time(scan):
        row, col = weighted_centre(scan.height, 40e-9)
        dt = 0.5 * scan.line_period / n  # pixel k of a line is taken (k + 1) dt after its start
        t = scan.start_time + np.interp(row, np.arange(n), scan.line_start_times) + (col + 1) * dt
        return np.array([origin + (col + 0.5) * size / n, origin + (row + 0.5) * size / n]), t

    c1, t1 = centre_and_time(sim.raster_scan(request))
    sim.hold(70.0)
    c2, t2 = centre_and_time(sim.raster_scan(request))
    expected = 0.5 * a * (t2**2 - t1**2)
    assert np.all(np.abs(expected) > 100e-9)  # many pixels (15.6 nm)
    np.testing.assert_allclose(c2 - c1, expected, rtol=0, atol=1e-9)
    np.testing.assert_allclose(c1, 5e-6 + 0.5 * a * t1**2, rtol=0, atol=1e-9)


# ---------------------------------------------------------------------------- 2. scanner bow


def test_scanner_bow_is_the_configured_paraboloid_about_the_range_centre():
    """A flat substrate, imaged off-centre, is the paraboloid 0.5 c r^2 about the scanner's
    range centre; it stays put in scanner coordinates while the sample drifts (it is the
    scanner's, not the sample's), and a scan line measures the same bow."""
    c = 20.0  # 1/m (a ~5 cm tube)
    config = ideal(
        NO_SPHERES,
        {
            "scanner": {"bow_curvature": c},
            "drift": {**STILL, "mean_velocity_x": 2e-9, "mean_velocity_y": -1e-9},
        },
    )
    sim = SimulatedAfm(config)
    xc, yc = config.scanner.range_x / 2, config.scanner.range_y / 2
    n, size, x0, y0 = 64, 4e-6, 20e-6, 70e-6
    scan = sim.raster_scan(ScanRequest(x0, y0, size, size, n, n, line_rate=4.0))
    centres = (np.arange(n) + 0.5) * size / n
    X, Y = np.meshgrid(x0 + centres, y0 + centres)
    expected = 0.5 * c * ((X - xc) ** 2 + (Y - yc) ** 2)
    np.testing.assert_allclose(scan.height, expected, rtol=1e-6, atol=1e-15)
    # the background fit: a full quadratic recovers the curvature, centre and no cross term
    u, v = (X - X.mean()).ravel(), (Y - Y.mean()).ravel()
    design = np.column_stack([np.ones_like(u), u, v, u * u, v * v, u * v])
    k = np.linalg.lstsq(design, scan.height.astype(float).ravel(), rcond=None)[0]
    assert 2 * k[3] == pytest.approx(c, rel=1e-4) and 2 * k[4] == pytest.approx(c, rel=1e-4)
    assert abs(k[5]) < 1e-4 * c
    assert X.mean() - k[1] / (2 * k[3]) == pytest.approx(xc, rel=1e-4)
    line = sim.local_scan(LineRequest(30e-6, 40e-6, 34e-6, 42e-6, samples=201, speed=10e-6))
    np.testing.assert_allclose(
        line.height, 0.5 * c * ((line.x - xc) ** 2 + (line.y - yc) ** 2), rtol=1e-9
    )
    assert sim.truth()["objects"] == []  # the sample itself is untouched


# -------------------------------------------------------------------- 3. sensor gain and latency


def test_height_gain_scales_every_measured_height_about_the_substrate_plane():
    """A miscalibrated z sensor scales objects, the rough substrate and the bow alike;
    the feedback itself (the deflection) is unchanged."""
    gain = 1.25
    base = ideal(
        ONE_SPHERE, {"sample": {"roughness_sigma": 0.4e-9}, "scanner": {"bow_curvature": 5.0}}
    )
    scaled = merge(base, {"noise": {"height_gain": gain}})
    request = ScanRequest(4.7e-6, 4.7e-6, 0.6e-6, 0.6e-6, 96, 96, line_rate=2.0)
    line = LineRequest(4.7e-6, 5e-6, 5.3e-6, 5e-6, samples=301, speed=1e-6)
    a, b = SimulatedAfm(base), SimulatedAfm(scaled)
    np.testing.assert_allclose(
        b.raster_scan(request).height, gain * a.raster_scan(request).height, rtol=1e-6
    )
    la, lb = a.local_scan(line), b.local_scan(line)
    np.testing.assert_allclose(lb.height, gain * la.height, rtol=1e-12)
    np.testing.assert_array_equal(lb.deflection, la.deflection)
    assert lb.height.max() - np.median(lb.height) == pytest.approx(
        gain * 160e-9, rel=0.01
    )  # the step


@pytest.mark.parametrize("direction", [+1, -1])
def test_latency_moves_a_line_crossing_by_speed_times_latency_along_the_scan(direction):
    speed, latency = 2e-6, 4.3e-3  # -> 8.6 nm: a fractional number of 2 nm samples
    start, end = (4.7e-6, 5.3e-6)[::direction]
    request = LineRequest(start, 5e-6, end, 5e-6, samples=301, speed=speed)
    crossings = []
    for lag in (0.0, latency):
        sim = SimulatedAfm(ideal(ONE_SPHERE, {"noise": {"sensor_latency": lag}}))
        crossings.append(crossing_centre(sim.local_scan(request), 80e-9))
    assert crossings[0] == pytest.approx(5e-6, abs=0.3e-9)
    assert crossings[1] - crossings[0] == pytest.approx(direction * speed * latency, abs=0.3e-9)


def test_latency_shifts_image_features_along_the_fast_axis_by_trace_speed_times_latency():
    n, size, line_rate, latency = 128, 1e-6, 2.0, 2e-3
    trace_speed = size / (0.5 / line_rate)  # the trace takes half the line period
    request = ScanRequest(4.5e-6, 4.5e-6, size, size, n, n, line_rate=line_rate)
    centres = []
    for lag in (0.0, latency):
        sim = SimulatedAfm(ideal(ONE_SPHERE, {"noise": {"sensor_latency": lag}}))
        centres.append(
            np.array(weighted_centre(sim.raster_scan(request).height, 40e-9)) * size / n
        )
    shift_y, shift_x = centres[1] - centres[0]
    assert shift_x == pytest.approx(trace_speed * latency, abs=0.3e-9)  # 8 nm
    assert shift_y == pytest.approx(0.0, abs=0.3e-9)  # the slow axis moves 0.03 nm in 2 ms


def test_latency_delays_force_trace_and_indentation_signals():
    sphere = {"sample": {"spheres": [{"x": 5e-6, "y": 5e-6, "radius": 100e-9}]}}
    traces, latency = [], 0.0
    for _lag in ("none", "three samples"):
        sim = SimulatedAfm(ideal(sphere, {"noise": {"sensor_latency": latency}}))
        sim.move_tip(4.7e-6, 5e-6, 10e-6)
        traces.append(
            (
                sim.move_tip(5.2e-6, 5e-6, 1e-6, contact=True).trace,
                sim.sample.spheres[0].x,
                sim.indent(3e-6, 3e-6, force=1e-7, dwell=0.2).trace,
            )
        )
        latency = (
            3.0 / traces[0][0].sample_rate
        )  # ~6 ms: the trace's samples are ~2 nm, 2 ms apart
    (push0, x0, indent0), (push1, x1, indent1) = traces
    np.testing.assert_allclose(push1.lateral_torsion[3:], push0.lateral_torsion[:-3], rtol=1e-9)
    np.testing.assert_allclose(push1.lateral_torsion[:3], push0.lateral_torsion[0], rtol=1e-9)
    assert np.ptp(push0.lateral_torsion) > 0  # there is something to delay
    np.testing.assert_array_equal(push1.commanded_x, push0.commanded_x)  # commands are not delayed
    assert x1 == x0  # nor is the physics
    k_n = sim.config.contact.normal_spring_constant
    t = indent1.times - latency
    expected = 1e-7 / k_n * np.clip(np.minimum(t / 0.05, (0.3 - t) / 0.05), 0, 1)
    np.testing.assert_allclose(indent1.vertical_deflection, expected, rtol=1e-12, atol=1e-20)
    np.testing.assert_array_equal(indent1.commanded_z, indent0.commanded_z)


# ---------------------------------------------------------------------------- 4. friction regions


def test_pushing_in_a_friction_region_takes_the_scaled_force():
    """A central push at v past a region boundary: the trace's lateral force is mu N before
    contact, mu N + F_c + c v while pushing, F_c scaled once the sphere's centre is inside,
    mu N scaled once the tip is inside. Where the sphere goes does not change."""
    s_f, s_t, boundary = 3.0, 2.0, 5.05e-6
    sphere = {"sample": {"spheres": [{"x": 5e-6, "y": 5e-6, "radius": 100e-9}]}}
    region = {
        "x0": boundary,
        "y0": 4e-6,
        "x1": 7e-6,
        "y1": 6e-6,
        "substrate_friction_scale": s_f,
        "mu_tip_substrate_scale": s_t,
    }
    results = {}
    for name, regions in (("plain", []), ("region", [region])):
        config = ideal(sphere, {"contact": {"friction_regions": regions}})
        sim = SimulatedAfm(config)
        sim.move_tip(4.6e-6, 5e-6, 10e-6)
        trace = sim.move_tip(5.3e-6, 5e-6, 1e-6, contact=True).trace
        results[name] = (trace.commanded_x, lateral_force(trace, config), sim.sample.spheres[0].x)
    p = config.contact
    speed = 1e-6
    sliding, pushing = (
        p.mu_tip_substrate * p.normal_force,
        p.substrate_friction_force + p.viscous_coefficient * speed,
    )
    contact_at = 5e-6 - (p.tip_radius + 100e-9)  # tip x where the push starts (sphere at 5 um)
    sphere_in_at = boundary - (p.tip_radius + 100e-9)  # tip x when the sphere's centre enters
    x, plain, end_plain = results["plain"]
    _, scaled, end_scaled = results["region"]
    margin = 6e-9
    stretches = [
        (x < contact_at - margin, sliding, sliding),
        (
            (x > contact_at + margin) & (x < sphere_in_at - margin),
            sliding + pushing,
            sliding + pushing,
        ),
        (
            (x > sphere_in_at + margin) & (x < boundary - margin),
            sliding + pushing,
            sliding + p.substrate_friction_force * s_f + p.viscous_coefficient * speed,
        ),
        (
            x > boundary + margin,
            sliding + pushing,
            s_t * sliding + p.substrate_friction_force * s_f + p.viscous_coefficient * speed,
        ),
    ]
    for where, outside, inside in stretches:
        assert where.sum() >= 10
        np.testing.assert_allclose(plain[where], outside, rtol=1e-6)
        np.testing.assert_allclose(scaled[where], inside, rtol=1e-6)
    assert end_scaled == end_plain  # quasi-static: forces change, not the motion


def test_a_rod_in_a_friction_region_takes_its_scaled_length_friction():
    L, r, s_f, s_t = 800e-9, 20e-9, 0.5, 0.0
    px = np.zeros(6001)
    py = np.linspace(-400e-9, 200e-9, 6001)
    dt = 1e-3
    speed = (py[1] - py[0]) / dt
    params = ContactParams(
        friction_regions=[
            {
                "x0": -1e-6,
                "y0": -1e-6,
                "x1": 1e-6,
                "y1": 1e-6,
                "substrate_friction_scale": s_f,
                "mu_tip_substrate_scale": s_t,
            }
        ]
    )
    result = push_along_path(Sample(rods=[Rod(0, 0.0, 0.0, 0.0, L, r)]), px, py, dt, params)
    expected = (
        s_t * params.mu_tip_substrate * params.normal_force
        + (s_f * params.rod_friction_per_length + params.rod_viscous_per_length * speed) * L
    )
    np.testing.assert_allclose(
        result.lateral_force[py > -(params.tip_radius + r) + 10e-9], expected, rtol=1e-6
    )
    np.testing.assert_array_equal(result.lateral_force[py < -(params.tip_radius + r) - 10e-9], 0.0)


# ---------------------------------------------------------------------------- 5. stick-slip


def test_stick_slip_shows_a_saw_tooth_of_the_closed_form_period_and_amplitude():
    """Sliding the tip at v on the bare substrate: the spring loads by k per unit travel from
    landing (force 0), slips at the static friction F_s = ratio F_k back to F_k: the force at
    travel s is k s before the first slip, then F_k + ((k s - F_s) mod (F_s - F_k))."""
    ratio, k, speed, distance = 2.0, 0.0213, 1e-6, 1e-6
    config = ideal(
        NO_SPHERES,
        {
            "contact": {
                "stick_slip_enabled": True,
                "static_friction_ratio": ratio,
                "stick_slip_stiffness": k,
            }
        },
    )
    sim = SimulatedAfm(config)
    sim.move_tip(3e-6, 3e-6, 10e-6)
    trace = sim.move_tip(3e-6 + distance, 3e-6, speed, contact=True).trace
    force = lateral_force(trace, config)
    kinetic = config.contact.mu_tip_substrate * config.contact.normal_force
    static, drop = ratio * kinetic, (ratio - 1) * kinetic
    travel = trace.commanded_x - 3e-6  # exact scanner: travel since landing
    closed_form = np.where(
        k * travel <= static, k * travel, kinetic + np.mod(k * travel - static, drop)
    )
    np.testing.assert_allclose(force, closed_form, rtol=0, atol=1e-6 * kinetic)
    # the saw-tooth as a recording shows it: slips, their period and the amplitude
    slips = np.flatnonzero(np.diff(force) < 0) + 1
    slip_times = trace.times[slips]
    period = np.polyfit(np.arange(slips.size), slip_times, 1)[0]
    assert slips.size == math.floor((k * distance - static) / drop) + 1
    assert period == pytest.approx(drop / (k * speed), rel=2e-3)  # 47 ms
    assert slip_times[0] == pytest.approx(static / (k * speed), abs=1.0 / trace.sample_rate)
    steady = force[slips[0] :]
    step = k * distance / len(force)  # the spring's load per sample
    assert steady.max() == pytest.approx(static, abs=step) and steady.max() <= static
    assert steady.min() == pytest.approx(kinetic, abs=step) and steady.min() >= kinetic
    assert steady.max() - steady.min() == pytest.approx(drop, abs=2 * step)
    # ratio 1 (static = kinetic, the bound an identification may reach): the spring loads to
    # the kinetic level and the tip slides steadily, no saw-tooth
    steady_config = merge(config, {"contact": {"static_friction_ratio": 1.0}})
    sim = SimulatedAfm(steady_config)
    sim.move_tip(3e-6, 3e-6, 10e-6)
    trace = sim.move_tip(3e-6 + distance, 3e-6, speed, contact=True).trace
    np.testing.assert_allclose(
        lateral_force(trace, steady_config),
        np.minimum(k * (trace.commanded_x - 3e-6), kinetic),
        rtol=0,
        atol=1e-6 * kinetic,
    )


def test_stick_slip_rides_on_the_pushing_force_and_off_it_is_exactly_absent():
    sphere = {"sample": {"spheres": [{"x": 5e-6, "y": 5e-6, "radius": 100e-9}]}}
    forces = {}
    for enabled in (False, True):
        config = ideal(
            sphere,
            {
                "contact": {
                    "stick_slip_enabled": enabled,
                    "static_friction_ratio": 3.0,
                    "stick_slip_stiffness": 0.1,
                }
            },
        )
        sim = SimulatedAfm(config)
        sim.move_tip(4.7e-6, 5e-6, 10e-6)
        forces[enabled] = lateral_force(
            sim.move_tip(5.3e-6, 5e-6, 1e-6, contact=True).trace, config
        )
    p = config.contact
    kinetic = p.mu_tip_substrate * p.normal_force
    tip_part = forces[True] - (forces[False] - kinetic)  # the objects' part is the same in both
    late = slice(len(tip_part) // 2, None)
    assert tip_part[late].min() == pytest.approx(kinetic, rel=0.05)
    assert tip_part[late].max() == pytest.approx(3.0 * kinetic, rel=0.05)


# ---------------------------------------------------------------------------- 6. tip wear


def test_worn_tip_radius_follows_the_slid_distance_and_later_images_use_it():
    R0, rate = 20e-9, 0.02  # m, m of radius per m slid
    wear = {
        "tip": {
            "apex_radius": R0,
            "half_angle_deg": 10.0,
            "wear_enabled": True,
            "wear_rate": rate,
            "max_apex_radius": 200e-9,
        }
    }
    sim = SimulatedAfm(ideal(ONE_SPHERE, wear))
    sim.move_tip(3e-6, 3e-6, 10e-6)
    sim.move_tip(4e-6, 3e-6, 1e-6, contact=True)  # 1 um slid
    sim.move_tip(4e-6, 3.5e-6, 1e-6, contact=True)  # + 0.5 um
    sim.move_tip(3e-6, 3e-6, 10e-6)  # lifted: no wear
    worn = R0 + rate * 1.5e-6  # 50 nm
    assert sim.truth()["tip_apex_radius"] == pytest.approx(worn, rel=1e-9)
    request = ScanRequest(4.7e-6, 4.7e-6, 0.6e-6, 0.6e-6, 120, 120, line_rate=2.0)
    line = LineRequest(4.7e-6, 5e-6, 5.3e-6, 5e-6, samples=301, speed=1e-6)
    after = sim.raster_scan(request).height, sim.local_scan(line).height
    fresh_worn = SimulatedAfm(
        ideal(ONE_SPHERE, {"tip": {"apex_radius": worn, "half_angle_deg": 10.0}})
    )
    fresh_new = SimulatedAfm(
        ideal(ONE_SPHERE, {"tip": {"apex_radius": R0, "half_angle_deg": 10.0}})
    )
    worn_images = fresh_worn.raster_scan(request).height, fresh_worn.local_scan(line).height
    new_image = fresh_new.raster_scan(request).height
    np.testing.assert_allclose(after[0], worn_images[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(after[1], worn_images[1], rtol=0, atol=1e-12)
    assert np.count_nonzero(after[0] > 80e-9) > 1.2 * np.count_nonzero(
        new_image > 80e-9
    )  # broader
    sim.move_tip(3e-6, 3e-6 + 20e-6, 1e-4, contact=True)  # 20 um more: capped at max_apex_radius
    assert sim.truth()["tip_apex_radius"] == 200e-9


# ---------------------------------------------------------------------------- 7. 1/f noise


def spectral_slope(sequence: np.ndarray) -> float:
    f, power = signal.welch(np.asarray(sequence, dtype=float), nperseg=4096)
    band = (f > 2e-3) & (f < 0.2)  # cycles per sample, away from DC and Nyquist
    return float(np.polyfit(np.log(f[band]), np.log(power[band]), 1)[0])


def test_flicker_noise_is_one_over_f_along_the_acquisition_sequence():
    sigma = 1e-9
    sim = SimulatedAfm(ideal(NO_SPHERES, {"noise": {"height_flicker_sigma": sigma}}))
    scan = sim.raster_scan(ScanRequest(3e-6, 3e-6, 2e-6, 2e-6, 256, 256, line_rate=4.0))
    sequence = scan.height.ravel()  # 0 deg, frame up: rows in time order, pixels along x
    assert spectral_slope(sequence) == pytest.approx(-1.0, abs=0.1)
    assert sequence.std() == pytest.approx(sigma, rel=1e-3)
    line = sim.local_scan(LineRequest(3e-6, 3e-6, 4e-6, 3e-6, samples=40000, speed=1e-6))
    assert spectral_slope(line.height) == pytest.approx(-1.0, abs=0.1)
    white = SimulatedAfm(ideal(NO_SPHERES, {"noise": {"height_white_sigma": sigma}}))
    assert spectral_slope(
        white.raster_scan(ScanRequest(3e-6, 3e-6, 2e-6, 2e-6, 256, 256)).height.ravel()
    ) == pytest.approx(0.0, abs=0.1)  # the fit tells white from pink


# --------------------------------------------------------------------- defaults: nothing changes

NEW_KEYS_AT_DEFAULT = {
    "drift": {"acceleration_x": 0.0, "acceleration_y": 0.0},
    "scanner": {"bow_curvature": 0.0},
    "noise": {"height_gain": 1.0, "sensor_latency": 0.0},
    "contact": {
        "friction_regions": [],
        "stick_slip_enabled": False,
        "static_friction_ratio": 1.5,
        "stick_slip_stiffness": 0.05,
    },
}


def session(config: SimConfig) -> dict:
    """A small session on the default sample: 0 and 90 deg scans, a line, a push, an indent."""
    sim = SimulatedAfm(config)
    out = {
        "scan": sim.raster_scan(
            ScanRequest(54.6e-6, 54.6e-6, 1.4e-6, 1.4e-6, 64, 64, line_rate=2.0)
        ).height,
        "scan90": sim.raster_scan(
            ScanRequest(
                54.6e-6,
                54.6e-6,
                1.4e-6,
                1.4e-6,
                48,
                48,
                scan_angle_deg=90.0,
                slow_scan_up=False,
                line_rate=2.0,
            )
        ).height,
    }
    line = sim.local_scan(LineRequest(54.7e-6, 55e-6, 55.3e-6, 55e-6, samples=301, speed=1e-6))
    out["line_height"], out["line_deflection"] = line.height, line.deflection
    sim.move_tip(54.7e-6, 55.0e-6, 10e-6)
    push = sim.move_tip(55.25e-6, 55.0e-6, 1e-6, contact=True).trace
    out["torsion"], out["push_deflection"] = push.lateral_torsion, push.vertical_deflection
    out["spheres"] = np.array([[s.x, s.y] for s in sim.sample.spheres])
    truth = sim.truth()
    out["truth"] = np.array(
        [
            truth["time"],
            *truth["tip_position"],
            *truth["drift_offset"],
            *truth["drift_velocity"],
            truth["tip_apex_radius"],
        ]
    )
    out["indent"] = sim.indent(55.5e-6, 54.5e-6, 1e-7, 0.1).trace.vertical_deflection
    return out


# The same session computed by the code before these effects existed (commit 4fe485b).
BEFORE = {
    "scan_sum": 4.827247187243704e-05,
    "scan_0_0": 6.331760671329789e-10,
    "scan90_sum": 2.63979335240996e-05,
    "line_height_sum": 2.3258696152656574e-05,
    "line_deflection_sum": -6.06051949253514e-10,
    "torsion_sum": 0.013106271254600874,
    "sphere0_x": 5.532159246647913e-05,
    "truth_time": 57.50087928468682,
}


def test_new_keys_at_their_defaults_change_nothing():
    absent = load_config()
    present = merge(load_config(), NEW_KEYS_AT_DEFAULT)
    # switched off, an effect's parameters do nothing either
    off_but_set = merge(
        present, {"contact": {"static_friction_ratio": 3.0, "stick_slip_stiffness": 1.0}}
    )
    reference = session(absent)
    for config in (present, off_but_set):
        for key, value in session(config).items():
            np.testing.assert_array_equal(value, reference[key], err_msg=key)
    # and against numbers taken from the code before the effects existed (a relative 1e-12
    # rather than bits: a numpy FFT or summation change must not fail this test)
    now = {
        "scan_sum": float(np.sum(reference["scan"], dtype=np.float64)),
        "scan_0_0": float(reference["scan"][0, 0]),
        "scan90_sum": float(np.sum(reference["scan90"], dtype=np.float64)),
        "line_height_sum": float(reference["line_height"].sum()),
        "line_deflection_sum": float(reference["line_deflection"].sum()),
        "torsion_sum": float(reference["torsion"].sum()),
        "sphere0_x": float(reference["spheres"][0, 0]),
        "truth_time": float(reference["truth"][0]),
    }
    for key, value in BEFORE.items():
        assert now[key] == pytest.approx(value, rel=1e-12, abs=1e-24), key


# ---------------------------------------------------------------------------- validation


@pytest.mark.parametrize(
    "override, key",
    [
        ({"drift": {"acceleration_x": "fast"}}, "drift.acceleration_x"),
        ({"drift": {"acceleration_y": float("nan")}}, "drift.acceleration_y"),
        ({"drift": {"acceleration_x": float("inf")}}, "drift.acceleration_x"),
        ({"scanner": {"bow_curvature": float("nan")}}, "scanner.bow_curvature"),
        ({"scanner": {"bow_curvature": 1e4}}, "scanner.bow_curvature"),
        ({"scanner": {"bow_curvature": "flat"}}, "scanner.bow_curvature"),
        ({"noise": {"height_gain": 0.0}}, "noise.height_gain"),
        ({"noise": {"height_gain": -1.0}}, "noise.height_gain"),
        ({"noise": {"height_gain": float("nan")}}, "noise.height_gain"),
        ({"noise": {"height_gain": True}}, "noise.height_gain"),
        ({"noise": {"sensor_latency": -1e-3}}, "noise.sensor_latency"),
        ({"noise": {"sensor_latency": float("nan")}}, "noise.sensor_latency"),
        ({"noise": {"sensor_latency": 5.0}}, "noise.sensor_latency"),
        ({"contact": {"stick_slip_enabled": "yes"}}, "contact.stick_slip_enabled"),
        ({"contact": {"static_friction_ratio": 0.99}}, "contact.static_friction_ratio"),
        ({"contact": {"static_friction_ratio": float("nan")}}, "contact.static_friction_ratio"),
        ({"contact": {"stick_slip_stiffness": 0.0}}, "contact.stick_slip_stiffness"),
        ({"contact": {"stick_slip_stiffness": float("inf")}}, "contact.stick_slip_stiffness"),
        ({"contact": {"friction_regions": "everywhere"}}, "contact.friction_regions"),
        ({"contact": {"friction_regions": [5]}}, r"contact.friction_regions\[0\]"),
        (
            {"contact": {"friction_regions": [{"x0": 0, "y0": 0, "x1": 1e-6}]}},
            r"contact.friction_regions\[0\].*y1",
        ),
        (
            {
                "contact": {
                    "friction_regions": [{"x0": 0, "y0": 0, "x1": 1e-6, "y1": 1e-6, "mu": 2}]
                }
            },
            r"contact.friction_regions\[0\].*'mu'",
        ),
        (
            {
                "contact": {
                    "friction_regions": [
                        {"x0": 0, "y0": 0, "x1": 1e-6, "y1": 1e-6},
                        {"x0": 0, "y0": 0, "x1": -1e-6, "y1": 1e-6},
                    ]
                }
            },
            r"contact.friction_regions\[1\].*x1 > x0",
        ),
        (
            {
                "contact": {
                    "friction_regions": [{"x0": float("nan"), "y0": 0, "x1": 1e-6, "y1": 1e-6}]
                }
            },
            r"contact.friction_regions\[0\].x0",
        ),
        (
            {
                "contact": {
                    "friction_regions": [
                        {
                            "x0": 0,
                            "y0": 0,
                            "x1": 1e-6,
                            "y1": 1e-6,
                            "substrate_friction_scale": -2.0,
                        }
                    ]
                }
            },
            r"contact.friction_regions\[0\].substrate_friction_scale",
        ),
    ],
)
def test_bad_values_of_the_new_keys_are_errors_naming_the_key(override, key):
    with pytest.raises(ValueError, match=key):
        merge(load_config(), override)


def test_friction_regions_round_trip_with_default_scales():
    config = merge(
        load_config(),
        {
            "contact": {
                "friction_regions": [
                    {"x0": 1e-6, "y0": 2e-6, "x1": 3e-6, "y1": 4e-6, "mu_tip_substrate_scale": 2}
                ]
            }
        },
    )
    assert config.contact.friction_regions == [
        {
            "x0": 1e-6,
            "y0": 2e-6,
            "x1": 3e-6,
            "y1": 4e-6,
            "substrate_friction_scale": 1.0,
            "mu_tip_substrate_scale": 2.0,
        }
    ]
    assert config_from_dict(__import__("yaml").safe_load(dump_config(config))) == config
