"""Piezo scanner model against textbook definitions, closed forms and naive per-sample loops."""

import dataclasses
import math
import time

import numpy as np
import pytest

from afm_core.pzt import (
    Creep,
    LateralScanner,
    PlayOperatorBank,
    PrandtlIshlinskii,
    ScannerParams,
    limit_slew,
)

# -- references written from the definitions ------------------------------------------------


def naive_play(x, thresholds, state):
    """y(k) = max(x(k) - r, min(x(k) + r, y(k-1))), one sample at a time."""
    y = np.empty((len(x), len(thresholds)))
    z = np.array(state, dtype=float)
    for k, xk in enumerate(x):
        for i, r in enumerate(thresholds):
            z[i] = max(xk - r, min(xk + r, z[i]))
        y[k] = z
    return y


def naive_pi(x, thresholds, weights, poly, state):
    a1, a2, a3 = poly
    v = [a1 * xk + a2 * xk**2 + a3 * xk**3 for xk in x]
    plays = naive_play(v, thresholds, state)
    return np.array([sum(w * p for w, p in zip(weights, row)) for row in plays])


def naive_creep(u, dt, lam, c, a, x0, u_prev):
    x, out = list(x0), []
    for uk in u:
        x = [
            math.exp(-rate * dt) * xi + (1 - math.exp(-rate * dt)) * u_prev
            for rate, xi in zip(lam, x)
        ]
        out.append(sum(ci * xi for ci, xi in zip(c, x)) + a * uk)
        u_prev = uk
    return np.array(out)


def naive_slew(x, d, start):
    y, prev = [], start
    for xk in x:
        prev = min(prev + d, max(prev - d, xk))
        y.append(prev)
    return np.array(y)


def piecewise_linear(rng, n_knots, scale=1.0):
    """Reversals of every size, from tiny minor loops to the full range, with plateaus."""
    steps = rng.choice([-1, 1], n_knots) * scale * 10 ** rng.uniform(-4, 0, n_knots)
    steps[rng.uniform(size=n_knots) < 0.1] = 0.0
    knots = np.cumsum(steps)
    lengths = rng.integers(1, 30, n_knots)
    t_knots = np.concatenate(([0], np.cumsum(lengths)))
    values = np.concatenate(([0.0], knots))
    return np.interp(np.arange(t_knots[-1] + 1), t_knots, values)


def triangle(low, high, points_per_ramp, cycles, start_mid=True):
    """Starts at the middle going up (or at `low`), reverses exactly at low and high."""
    up = np.linspace(low, high, points_per_ramp + 1)
    cycle = np.concatenate((up[1:], up[::-1][1:]))
    x = np.tile(cycle, cycles)
    if start_mid:
        mid = points_per_ramp // 2
        x = np.concatenate((up[mid:], up[::-1][1:], x))
    return x


def branches(x, y, low, high):
    """Ascending and descending outputs of the last cycle, both sorted by increasing input."""
    last_high = len(x) - 1 - np.argmax(x[::-1] == high)
    last_low = last_high - 1 - np.argmax(x[:last_high][::-1] == low)
    asc = slice(last_low, last_high + 1)
    desc_x, desc_y = x[last_high:][::-1], y[last_high:][::-1]
    assert desc_x[0] == low and np.array_equal(desc_x, x[asc])
    return x[asc], y[asc], desc_y


# -- play operators ----------------------------------------------------------------------------


def test_single_play_operator_on_a_triangle_is_textbook_backlash():
    x = [0, 1, 2, 3, 3, 2, 1, 0, -1, -2, -1, 0, 1, 2]
    # r = 1 from rest at 0: the output lags 1 behind a rising input, 1 ahead of a falling one,
    # and holds for 2 units of travel after each reversal.
    expected_r1 = [0, 0, 1, 2, 2, 2, 2, 1, 0, -1, -1, -1, 0, 1]
    bank = PlayOperatorBank([0.0, 1.0, 5.0])
    y = bank.apply(x)
    np.testing.assert_array_equal(y[:, 0], x)  # r = 0 is the identity
    np.testing.assert_array_equal(y[:, 1], expected_r1)
    np.testing.assert_array_equal(y[:, 2], np.zeros(len(x)))  # never pushed out of its band
    np.testing.assert_array_equal(bank.state, [2, 1, 0])
    bank.reset(0.0)
    np.testing.assert_array_equal(
        np.vstack([bank.apply(x[:5]), bank.apply(x[5:6]), bank.apply(x[6:])]), y
    )


@pytest.mark.parametrize("seed", range(6))
def test_vectorised_play_equals_the_per_sample_loop_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    x = (
        piecewise_linear(rng, 200) if seed % 2 else rng.normal(size=2000)
    )  # noise: every sample turns
    thresholds = np.sort(rng.uniform(0, 0.5, 6))
    state = rng.normal(0, 2, 6)  # even outside the band
    bank = PlayOperatorBank(thresholds)
    bank.state = state
    np.testing.assert_array_equal(bank.apply(x), naive_play(x, thresholds, state))
    bank.state = state
    cuts = np.sort(rng.choice(np.arange(1, len(x)), 7, replace=False))
    chunks = [bank.apply(part) for part in np.split(x, cuts)]
    np.testing.assert_array_equal(np.vstack(chunks), naive_play(x, thresholds, state))


def test_vectorised_pi_equals_the_per_sample_loop():
    rng = np.random.default_rng(7)
    x = piecewise_linear(rng, 150)
    model = PrandtlIshlinskii([0.0, 0.05, 0.2, 0.4], [1.0, 0.3, -0.2, 0.4], (0.9, 0.05, 0.02))
    model.state = rng.normal(0, 0.1, 4)
    expected = naive_pi(x, model.thresholds, model.weights, model.polynomial, model.state)
    np.testing.assert_allclose(
        model.apply(x), expected, rtol=1e-13, atol=1e-13 * np.abs(expected).max()
    )


# -- Prandtl-Ishlinskii loops ------------------------------------------------------------------


def test_symmetric_pi_closes_its_loop_with_the_closed_form_width():
    centre, amplitude = 0.3, 1.0
    r = np.array([0.0, 0.1, 0.3, 0.6, 0.9, 1.4])  # below, above A/2 and beyond A
    w = np.array([0.7, 0.2, 0.15, 0.1, 0.05, 0.3])
    model = PrandtlIshlinskii(r, w)
    model.reset(centre)
    low, high = centre - amplitude, centre + amplitude
    x = triangle(low, high, 400, 3)
    y = model.apply(x)
    period = 800
    # closed loop after the first cycle: the last two cycles are identical
    np.testing.assert_allclose(y[-period:], y[-2 * period : -period], rtol=0, atol=1e-15)
    xs, asc, desc = branches(x, y, low, high)
    # the branches meet at the turning points ...
    assert asc[0] == pytest.approx(desc[0], abs=1e-15) and asc[-1] == pytest.approx(
        desc[-1], abs=1e-15
    )
    # ... and the output reverses exactly where the input does, leaving with slope w_0
    reversals = np.flatnonzero(np.diff(np.sign(np.diff(x)))) + 1
    np.testing.assert_array_equal(np.flatnonzero(np.diff(np.sign(np.diff(y)))) + 1, reversals)
    dx = x[reversals + 1] - x[reversals]
    np.testing.assert_allclose(y[reversals + 1] - y[reversals], w[0] * dx, rtol=1e-9)
    # Loop width: operator i contributes min(2 r_i, 2 (A - r_i), A - |x - centre|) (>= 0), each
    # largest at the centre, so the width is sum_i w_i max(0, min(2 r_i, 2 (A - r_i))).
    width = np.sum(w * np.maximum(0.0, np.minimum(2 * r, 2 * (amplitude - r))))
    assert np.max(desc - asc) == pytest.approx(width, rel=1e-12)
    # a symmetric loop is point-symmetric about its centre
    np.testing.assert_allclose(asc + desc[::-1], asc[200] + desc[200], atol=1e-12)


@pytest.mark.parametrize("asymmetry", [0.0, 0.03, -0.2])
def test_from_fraction_loop_has_the_requested_width_and_gain(asymmetry):
    span, fraction = 100e-6, 0.12
    model = PrandtlIshlinskii.from_fraction(span, fraction, n=8, asymmetry=asymmetry)
    model.reset(0.0)
    x = triangle(-span / 2, span / 2, 800, 3)
    xs, asc, desc = branches(x, model.apply(x), -span / 2, span / 2)
    assert np.max(desc - asc) == pytest.approx(fraction * span, rel=1e-9)
    assert asc[-1] - asc[0] == pytest.approx(span, rel=1e-12)  # tip to tip: output spans the input
    assert np.all(np.diff(asc) > 0) and np.all(np.diff(desc) > 0)
    symmetry_defect = np.max(np.abs(asc + desc[::-1] - asc[400] - desc[400]))
    if asymmetry == 0.0:
        assert symmetry_defect < 1e-12 * span
    else:
        assert symmetry_defect > 0.1 * abs(asymmetry) * span


def test_from_fraction_refuses_what_it_cannot_build():
    with pytest.raises(ValueError, match="hysteresis_fraction"):
        PrandtlIshlinskii.from_fraction(1e-6, 0.4)
    with pytest.raises(ValueError, match="asymmetry"):
        PrandtlIshlinskii.from_fraction(1e-6, 0.1, asymmetry=0.9)
    with pytest.raises(ValueError, match="span"):
        PrandtlIshlinskii.from_fraction(0.0, 0.1)


def test_model_checks_monotonicity_at_construction():
    with pytest.raises(ValueError, match=r"polynomial.*p'\(x\)"):
        PrandtlIshlinskii([0.0, 1.0], [1.0, 0.1], (1.0, 0.1, 0.0))  # a parabola turns back
    with pytest.raises(ValueError, match="polynomial"):
        PrandtlIshlinskii([0.0, 1.0], [1.0, 0.1], (1.0, 1.0, 0.3))  # a2^2 > 3 a1 a3
    with pytest.raises(ValueError, match=r"weights.*w_0 \+ \.\.\. \+ w_1"):
        PrandtlIshlinskii([0.0, 1.0], [1.0, -1.0])
    with pytest.raises(ValueError, match="weights"):
        PrandtlIshlinskii([0.0, 1.0], [0.0, 1.0])
    with pytest.raises(ValueError, match="thresholds"):
        PrandtlIshlinskii([0.1, 1.0], [1.0, 1.0])
    with pytest.raises(ValueError, match="thresholds"):
        PrandtlIshlinskii([0.0, 1.0, 1.0], [1.0, 1.0, 1.0])


# -- the inverse --------------------------------------------------------------------------------


def test_inverse_parameters_for_two_operators():
    # y = v + F_1[v]: slope 1 within 2 of a reversal, 2 beyond, reached at output distance 1
    inverse = PrandtlIshlinskii([0.0, 1.0], [1.0, 1.0]).inverse()
    np.testing.assert_allclose(inverse.thresholds, [0.0, 1.0])
    np.testing.assert_allclose(inverse.weights, [1.0, -0.5])


MODELS = [
    lambda: PrandtlIshlinskii([0.0, 0.05, 0.2, 0.4], [1.0, 0.3, -0.2, 0.4]),
    lambda: PrandtlIshlinskii([0.0, 0.05, 0.2, 0.4], [0.5, 0.3, 0.2, 0.4], (0.9, 0.3, 0.2)),
    lambda: PrandtlIshlinskii.from_fraction(2.0, 0.15, n=8, asymmetry=0.3),
]


@pytest.mark.parametrize("make", MODELS)
@pytest.mark.parametrize("seed", range(3))
def test_inverse_composes_to_the_identity_in_both_orders(make, seed):
    rng = np.random.default_rng(seed)
    forward = make()
    forward.reset(0.1)
    past = 0.1 + piecewise_linear(rng, 50, 0.5)
    forward.apply(past)  # start from a state with a history ...
    history = forward.state

    x = past[-1] + piecewise_linear(rng, 300, 0.1)  # ... that small reversals do not wipe out
    inverse = forward.inverse()
    y = forward.apply(x)
    np.testing.assert_allclose(inverse.apply(y), x, rtol=0, atol=1e-9 * np.abs(x).max())

    forward.state = history
    inverse = forward.inverse()
    target = y[0] + piecewise_linear(rng, 300, 0.1)
    command = inverse.apply(target)
    np.testing.assert_allclose(
        forward.apply(command), target, rtol=0, atol=1e-9 * np.abs(target).max()
    )
    # fed in chunks, the pair stays matched
    chunks = [forward.apply(inverse.apply(part)) for part in np.split(target, [7, 8, 300])]
    np.testing.assert_allclose(
        np.concatenate(chunks), target, rtol=0, atol=1e-9 * np.abs(target).max()
    )


@pytest.mark.parametrize("asymmetry", [1e-12, 1e-8, 1e-4, 0.03, -0.5])
def test_inverse_is_exact_in_metres_for_any_asymmetry(asymmetry):
    # tiny asymmetries make the cubic's closed-form root cancel badly: the Newton polish must
    # fix it
    forward = PrandtlIshlinskii.from_fraction(110e-6, 0.12, asymmetry=asymmetry)
    inverse = forward.inverse()
    target = piecewise_linear(np.random.default_rng(2), 200, 40e-6)
    np.testing.assert_allclose(
        forward.apply(inverse.apply(target)), target, rtol=0, atol=1e-12 * 40e-6
    )


def test_inverse_reset_matches_forward_reset():
    forward = PrandtlIshlinskii.from_fraction(2.0, 0.12, asymmetry=0.1)
    inverse = forward.inverse()
    x0 = 0.37
    forward.reset(x0)
    a1, a2, a3 = forward.polynomial
    inverse.reset(forward.weights.sum() * (a1 * x0 + a2 * x0**2 + a3 * x0**3))
    target = x0 + piecewise_linear(np.random.default_rng(3), 200, 0.5)
    np.testing.assert_allclose(forward.apply(inverse.apply(target)), target, rtol=0, atol=1e-12)


# -- creep ----------------------------------------------------------------------------------------


def test_creep_step_response_is_the_first_order_closed_form():
    lam, c, a = np.array([2.0, 0.2, 0.02]), np.array([0.01, 0.006, 0.004]), 0.98
    creep = Creep(lam, c, a)
    creep.reset(0.0)
    dt = 0.01
    y = creep.apply(np.ones(5000), dt)
    # sample 0: the operators have not seen the step yet, only the direct path has
    assert y[0] == pytest.approx(a, rel=1e-15)
    assert y[1] == pytest.approx(a + np.sum(c * (1 - np.exp(-lam * dt))), rel=1e-14)
    for k in (1, 10, 50, 137, 1000, 4999):
        t = k * dt
        closed = a + sum(ci * (1 - math.exp(-li * t)) for li, ci in zip(lam, c))
        assert y[k] == pytest.approx(closed, rel=1e-12)
    np.testing.assert_allclose(creep.step_response(dt * np.arange(5000)), y, rtol=1e-12)
    # a different sample period later still lands on the continuous response (zero-order hold)
    y2 = creep.apply(np.ones(100), 0.5)
    np.testing.assert_allclose(
        y2, creep.step_response(4999 * dt + 0.5 * np.arange(1, 101)), rtol=1e-12
    )


def test_creep_equals_the_per_sample_loop_and_resumes_across_calls():
    rng = np.random.default_rng(4)
    lam, c, a = [3.0, 0.3], [0.02, -0.01], 0.99
    u = np.cumsum(rng.normal(size=700))
    creep = Creep(lam, c, a)
    creep.state = [0.5, -0.2, 1.5]
    expected = naive_creep(u, 0.003, lam, c, a, [0.5, -0.2], 1.5)
    np.testing.assert_allclose(creep.apply(u, 0.003), expected, rtol=1e-12, atol=1e-12)
    creep.state = [0.5, -0.2, 1.5]
    parts = [creep.apply(part, 0.003) for part in np.split(u, [1, 250, 251])]
    np.testing.assert_allclose(np.concatenate(parts), expected, rtol=1e-12, atol=1e-12)


def test_creep_reset_is_a_settled_rest():
    creep = Creep([1.0, 0.1], [0.02, 0.01], 0.97)
    creep.reset(2.5)
    np.testing.assert_allclose(creep.apply(np.full(50, 2.5), 0.1), 2.5, rtol=1e-15)


# -- slew-rate limit ------------------------------------------------------------------------------


def test_slew_limit_never_exceeds_max_speed_and_reaches_the_target():
    dt, max_speed = 1e-4, 50e-6
    d = max_speed * dt
    target = 3.2e-6
    x = np.concatenate((np.zeros(10), np.full(1000, target)))
    y = limit_slew(x, dt, max_speed)
    assert np.all(np.abs(np.diff(y)) <= d * (1 + 1e-9))
    ramp_samples = math.ceil(target / d)
    assert np.all(y[10 + ramp_samples :] == target)
    assert y[10 + ramp_samples - 2] < target
    # starting elsewhere: the first sample is limited too
    y = limit_slew(np.full(300, 1e-6), dt, max_speed, start=0.0)  # 200 steps of d
    assert y[0] == pytest.approx(d) and y[-1] == 1e-6


@pytest.mark.parametrize("seed", range(4))
def test_slew_limit_equals_the_per_sample_loop(seed):
    rng = np.random.default_rng(seed)
    x = piecewise_linear(rng, 300, 1e-6)
    d = 1e-8
    y = limit_slew(x, 1e-3, d / 1e-3, start=5e-7)
    np.testing.assert_allclose(y, naive_slew(x, d, 5e-7), rtol=0, atol=1e-18)
    assert np.all(np.abs(np.diff(np.concatenate(([5e-7], y)))) <= d * (1 + 1e-9))


def test_slow_paths_pass_the_slew_limit_untouched():
    x = np.linspace(0, 1e-6, 1000)
    np.testing.assert_array_equal(limit_slew(x, 1e-3, 1e-6 / 999 / 1e-3 * 1.01), x)


# -- the scanner ----------------------------------------------------------------------------------


def switched(**changes) -> ScannerParams:
    """Defaults with every *_enabled flag off, then `changes`."""
    flags = {
        f.name: False for f in dataclasses.fields(ScannerParams) if f.name.endswith("_enabled")
    }
    return ScannerParams(**{**flags, **changes})


def random_commands(rng, n, span):
    return np.clip(span / 2 + piecewise_linear(rng, n // 10, span / 4)[:n], 0, span)


def test_scanner_with_every_effect_off_is_exact():
    rng = np.random.default_rng(0)
    cmd_x, cmd_y = random_commands(rng, 3000, 110e-6), random_commands(rng, 3000, 110e-6)
    zero = ScannerParams(
        hysteresis_fraction=0.0,
        hysteresis_asymmetry=0.0,
        creep_fractions=[0.0, 0.0, 0.0],
        coupling_x_to_y=0.0,
        coupling_y_to_x=0.0,
        deflection_deg=0.0,
    )
    for params in (switched(), zero):
        scanner = LateralScanner(params)
        scanner.reset(cmd_x[0], cmd_y[0])
        true_x, true_y = scanner.apply(cmd_x, cmd_y, 1e-3)
        np.testing.assert_array_equal(true_x, cmd_x)
        np.testing.assert_array_equal(true_y, cmd_y)


def test_scanner_clamps_commands_to_its_range():
    scanner = LateralScanner(switched(range_x=10e-6, range_y=20e-6))
    true_x, true_y = scanner.apply([-1e-6, 5e-6, 12e-6], [25e-6, -3e-6, 7e-6], 1e-3)
    np.testing.assert_array_equal(true_x, [0.0, 5e-6, 10e-6])
    np.testing.assert_array_equal(true_y, [20e-6, 0.0, 7e-6])


def test_coupling_and_deflection_are_matrices_about_the_range_centre():
    kxy, kyx, angle = 0.02, -0.01, 0.746
    params = switched(
        coupling_enabled=True,
        deflection_enabled=True,
        clamp_to_range=False,
        coupling_x_to_y=kxy,
        coupling_y_to_x=kyx,
        deflection_deg=angle,
    )
    scanner = LateralScanner(params)
    centre = np.array([params.range_x, params.range_y]) / 2
    theta = math.radians(angle)
    rotation = np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])
    matrix = rotation @ np.array([[1.0, kyx], [kxy, 1.0]])
    rng = np.random.default_rng(1)
    cmd = centre[:, None] + rng.uniform(-50e-6, 50e-6, (2, 500))
    out = np.array(scanner.apply(cmd[0], cmd[1], 1e-3))
    np.testing.assert_allclose(
        out - centre[:, None], matrix @ (cmd - centre[:, None]), rtol=0, atol=1e-18
    )
    # a pure x scan line comes out tilted by the deflection plus the coupling's own angle
    line = np.linspace(10e-6, 100e-6, 50)
    lx, ly = scanner.apply(line, np.full(50, centre[1]), 1e-3)
    assert math.degrees(math.atan2(ly[-1] - ly[0], lx[-1] - lx[0])) == pytest.approx(
        angle + math.degrees(math.atan(kxy)), rel=1e-12
    )
    # the deflection alone is a rotation: lengths kept
    rotate = LateralScanner(
        switched(deflection_enabled=True, clamp_to_range=False, deflection_deg=angle)
    )
    rx, ry = rotate.apply(cmd[0], cmd[1], 1e-3)
    np.testing.assert_allclose(
        np.hypot(rx - centre[0], ry - centre[1]), np.hypot(*(cmd - centre[:, None])), rtol=1e-14
    )


def test_scanner_hysteresis_is_the_pi_model_on_the_deviation_from_mid_range():
    params = switched(hysteresis_enabled=True)
    scanner = LateralScanner(params)
    scanner.reset()
    span = params.range_x
    x = span / 2 + triangle(-span / 2, span / 2, 500, 2)
    true_x, true_y = scanner.apply(x, np.full(x.size, span / 2), 1e-3)
    model = PrandtlIshlinskii.from_fraction(
        span, params.hysteresis_fraction, params.hysteresis_operators, params.hysteresis_asymmetry
    )
    np.testing.assert_allclose(true_x, span / 2 + model.apply(x - span / 2), rtol=1e-15)
    np.testing.assert_array_equal(true_y, span / 2)
    _, asc, desc = branches(x, true_x, 0.0, span)
    assert np.max(desc - asc) == pytest.approx(params.hysteresis_fraction * span, rel=1e-9)


def test_scanner_creep_follows_the_closed_form_after_a_move():
    params = switched(creep_enabled=True)
    scanner = LateralScanner(params)
    centre = params.range_x / 2
    scanner.reset(centre, centre)
    step = 20e-6
    dt = 0.05
    true_x, _ = scanner.apply(np.full(2000, centre + step), np.full(2000, centre), dt)
    t = dt * np.arange(2000)
    fractions, taus = np.array(params.creep_fractions), np.array(params.creep_time_constants)
    expected = centre + step * (
        1 - fractions.sum() + (fractions * (1 - np.exp(-t[:, None] / taus))).sum(axis=1)
    )
    np.testing.assert_allclose(true_x, expected, rtol=1e-12)
    creep_25s = true_x[500] - true_x[0]  # the book's 25 s after a move: a few % of the step
    assert 0.01 * step < creep_25s < 0.03 * step


def test_scanner_snapshots_and_chunks():
    rng = np.random.default_rng(5)
    scanner = LateralScanner()
    scanner.reset(30e-6, 70e-6)
    warm = random_commands(rng, 500, 110e-6), random_commands(rng, 500, 110e-6)
    scanner.apply(*warm, 1e-3)
    snapshot = scanner.state()
    cmd = random_commands(rng, 2000, 110e-6), random_commands(rng, 2000, 110e-6)
    whole = scanner.apply(*cmd, 1e-3)
    scanner.set_state(snapshot)
    again = scanner.apply(*cmd, 1e-3)
    np.testing.assert_array_equal(whole, again)
    scanner.set_state(snapshot)
    parts = [
        scanner.apply(cmd[0][s], cmd[1][s], 1e-3)
        for s in (slice(0, 1), slice(1, 900), slice(900, None))
    ]
    np.testing.assert_allclose(np.concatenate([p[0] for p in parts]), whole[0], rtol=1e-13)
    np.testing.assert_allclose(np.concatenate([p[1] for p in parts]), whole[1], rtol=1e-13)


def test_scanner_at_rest_in_the_centre_stays_there():
    scanner = LateralScanner()
    scanner.reset()
    centre = scanner.params.range_x / 2
    true_x, true_y = scanner.apply(np.full(100, centre), np.full(100, centre), 0.1)
    np.testing.assert_allclose(true_x, centre, rtol=1e-14)
    np.testing.assert_allclose(true_y, centre, rtol=1e-14)


@pytest.mark.parametrize(
    "field, value",
    [
        ("hysteresis_fraction", 0.5),
        ("creep_fractions", [0.5, 0.6, 0.0]),
        ("creep_time_constants", [1.0, -1.0, 5.0]),
        ("range_x", 0.0),
        ("coupling_x_to_y", 1.5),
        ("hysteresis_asymmetry", 1.0),
    ],
)
def test_scanner_params_name_the_bad_field(field, value):
    with pytest.raises(ValueError, match=f"scanner.{field}"):
        ScannerParams(**{field: value})


# -- speed ----------------------------------------------------------------------------------------


def test_half_a_million_samples_through_an_8_operator_pi_is_fast():
    model = PrandtlIshlinskii.from_fraction(100e-6, 0.12, n=8, asymmetry=0.03)
    rng = np.random.default_rng(0)
    raster = triangle(-50e-6, 50e-6, 1000, 250)[:500_000]
    noisy = raster + rng.normal(0, 1e-7, raster.size)  # turning points at most samples
    for name, x in (("raster", raster), ("noisy raster", noisy)):
        model.reset(0.0)
        start = time.perf_counter()
        y = model.apply(x)
        elapsed = time.perf_counter() - start
        print(f"PI, 8 operators, {x.size} samples ({name}): {elapsed * 1e3:.0f} ms")
        assert y.shape == x.shape
        assert elapsed < 2.0
