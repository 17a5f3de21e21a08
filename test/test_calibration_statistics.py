"""The calibration's stated uncertainties against the simulator (issue 37): the drift mean's
95 % interval covers the configured mean at about its nominal rate (the pairs are correlated);
motion noise adds the trials its precision needs; the scanner matrix's gains are checked
against the image frame."""

import numpy as np
import pytest

from afm_core.localization.calibration.drift_statistics import mean_error
from afm_core.localization.calibration.fit_checks import ACCURACY_TARGET, Z_95, calibration_checks
from afm_core.localization.calibration.motion_error import (
    ROW_SIGMAS,
    _fitted_slopes,
    calibrated_slopes,
    measure_motion_noise,
)
from afm_core.localization.calibration.simulator_comparison import (
    lane_image_scales,
    lane_pits,
    matched_rows,
)
from afm_core.sim.config import load_config, merge
from afm_core.sim.drift import DriftParams, ThermalDrift
from afm_core.sim.instrument import SimulatedAfm

PAIR_HALF = 280.0  # s, half the stretch a frame pair averages the velocity over (measure_drift)


def _pair_velocities(seed: int, pairs: int, interval: float, params: DriftParams) -> np.ndarray:
    """What measure_drift's pairs see of the simulator's drift: the mean velocity over each
    pair's stretch, a pair every `interval` s."""
    drift = ThermalDrift(params, seed)
    t = 900.0 + interval * np.arange(pairs)
    return (drift.offset(t + PAIR_HALF) - drift.offset(t - PAIR_HALF)) / (2 * PAIR_HALF)


def _coverage(pairs: int, interval: float, params: DriftParams, seeds: int = 300):
    mean = np.array([params.mean_velocity_x, params.mean_velocity_y])
    stated, naive = [], []
    for seed in range(seeds):
        v = _pair_velocities(seed, pairs, interval, params)
        for axis in range(2):
            error = mean_error(v[:, axis])
            miss = abs(v[:, axis].mean() - mean[axis])
            stated.append(miss <= error["interval95"])
            naive.append(miss <= 1.96 * v[:, axis].std(ddof=1) / np.sqrt(pairs))
    return float(np.mean(stated)), float(np.mean(naive))


@pytest.mark.parametrize(
    "pairs, interval, correlation_time",
    [(6, 1800.0, 1800.0), (6, 3600.0, 1800.0), (20, 1800.0, 1800.0)],
)
def test_the_drift_mean_interval_covers_the_configured_mean(pairs, interval, correlation_time):
    """Issue 37: 'ok' for a mean 3.9 sampling errors off the configured one (6 pairs,
    sigma / sqrt(n)). Pairs closer than the drift's correlation time are correlated: the
    stated 95 % interval covers the configured mean in 84-99 % of seeds (the pairs' own
    correlation estimate is noisy with 6), where sigma / sqrt(n) covered 73-90 %."""
    params = DriftParams(correlation_time=correlation_time)
    stated, naive = _coverage(pairs, interval, params)
    assert 0.84 <= stated <= 0.99, (stated, naive)
    assert stated > naive + 0.03, (stated, naive)


@pytest.mark.parametrize("pairs, interval", [(6, 1800.0), (20, 1800.0)])
def test_the_drift_spread_is_corrected_for_correlated_pairs(pairs, interval):
    """The velocity's spread (drift_sigma_velocity, the filter's drift state) was the sample
    spread of correlated pairs, low by their correlation (median 0.79 of the configured with
    6 pairs a correlation time apart, 0.90 with 20) and with no interval. Corrected alike
    (mean_error's shrink) its median is nearer the configured one (measured 0.88 / 0.94; the
    pairs' 560 s average itself spreads 0.95-0.96 of it), and its chi-square interval on the
    effective degrees of freedom covers the configured spread in 85-99 % of seeds (measured
    0.91 / 0.965)."""
    params = DriftParams(correlation_time=1800.0)
    sigma = np.array([params.sigma_velocity_x, params.sigma_velocity_y])
    covered, corrected, sampled = [], [], []
    for seed in range(300):
        v = _pair_velocities(seed, pairs, interval, params)
        for axis in range(2):
            error = mean_error(v[:, axis])
            low, high = error["sigma_interval95"]
            covered.append(low <= sigma[axis] <= high)
            corrected.append(error["sigma"] / sigma[axis])
            sampled.append(v[:, axis].std(ddof=1) / sigma[axis])
    assert 0.85 <= np.mean(covered) <= 0.99, np.mean(covered)
    assert abs(np.median(corrected) - 1) < abs(np.median(sampled) - 1), (
        np.median(corrected),
        np.median(sampled),
    )


def test_the_drift_mean_interval_of_independent_pairs_is_the_students_t_one():
    """Independent pairs (spacing 10x the correlation time): no inflation beyond what the
    small-sample correlation estimate adds, coverage near 95 %."""
    params = DriftParams(correlation_time=180.0)
    stated, _ = _coverage(8, 1800.0, params)
    assert 0.90 <= stated <= 0.995, stated


def test_pairs_closer_than_half_the_correlation_time_are_under_covered_but_far_less():
    """The limit of estimating the pairs' correlation from 6 of them: a pair every half
    correlation time, the interval covers 82-85 % (measured, 300-1500 seeds), against 55 %
    for sigma / sqrt(n); measure_drift's default interval (3600 s) keeps pairs a correlation
    time of the book's drift apart or more."""
    stated, naive = _coverage(6, 1800.0, DriftParams(correlation_time=3600.0))
    assert stated > naive + 0.2, (stated, naive)


def test_motion_noise_adds_the_trials_its_precision_needs_on_a_noisy_instrument():
    """Issue 37: the slope was flagged on every instrument (95 % interval 15 % wide) and read
    14-21 % low at noise 4x (trials whose cross error passed a third of the row spacing were
    dropped: the largest errors). A first round too imprecise for the 10 % target plans a
    second from its own standard error, with rows spaced from the cross error it measured;
    the pooled slope then lies within its (narrower) 95 % interval of the configured one."""
    base = load_config().scanner
    config = merge(
        load_config(),
        {
            "seed": 4,
            "scanner": {
                "positioning_noise_slope": 4.0 * base.positioning_noise_slope,
                "positioning_noise_offset": 4.0 * base.positioning_noise_offset,
            },
        },
    )
    experiment = measure_motion_noise(SimulatedAfm(config), distances=(1e-6, 4e-6), trials=20)
    p, rounds = experiment.parameters, experiment.data["rounds"]
    assert len(rounds) == 2 and rounds[1]["trials"] > rounds[0]["trials"], rounds
    first = experiment.data["x"][:2] + experiment.data["y"][:2]
    largest = max(np.sqrt(row["variance_across"]) for row in first)
    assert rounds[1]["row_spacing"] >= ROW_SIGMAS * largest * (1 - 1e-9)
    configured = config.scanner.positioning_noise_slope
    assert abs(p["pooled_slope"] - configured) <= Z_95 * p["pooled_slope_sigma"], (
        p["pooled_slope"] / configured
    )


def test_motion_noise_is_measured_in_the_images_frame_on_a_wide_loop():
    """Issue 37: the slope read -14.1 % on a wide loop (0.18, asymmetry 0.08) whose controller
    model is 10 % off. The feed-forward's error makes the short moves and the rescans' short
    strokes alike about 10 % longer than commanded, so the images see the true-metre noise
    times (image / true length)^2 = s^2: the frame the localizer works in. Against the same
    trials' true separations (the simulator's pits, fitted alike) the measured slope is the
    true one times s^2 to the calibration's accuracy target (measured: 0.90 for s^2 0.83;
    the scanner's gain also varies along a stroke), and below the true one."""
    config = merge(
        load_config(),
        {"seed": 2, "scanner": {"hysteresis_fraction": 0.18, "hysteresis_asymmetry": 0.08}},
    )
    afm = SimulatedAfm(config)
    experiment = measure_motion_noise(afm, distances=(1e-6, 4e-6), trials=40, precision=None)
    squared = float(
        np.mean([s**2 for *_, s in lane_image_scales(experiment.data, afm.sample.pits)])
    )
    samples = []
    for axis, lane, pits in lane_pits(experiment.data, afm.sample.pits):
        along = np.array([[p.x, p.y][axis] for p in pits])
        across = np.array([[p.y, p.x][axis] for p in pits])
        _, rows = matched_rows(axis, lane, pits)
        variances = []
        for position in (along, across):
            true = position[2 * rows + 1] - position[2 * rows]
            residual = true - np.polyval(np.polyfit(rows, true, 1), rows)
            variances.append(np.sum(residual**2) / (len(rows) - 2))
        samples.append((axis, lane["distance"], len(rows) - 1, *variances))
    ratio = experiment.parameters["pooled_slope"] / _fitted_slopes(samples)["pooled_slope"]
    assert squared < 1.0 - ACCURACY_TARGET, squared
    assert abs(ratio / squared - 1.0) < ACCURACY_TARGET, (ratio, squared)
    # the pits' position noise only adds to the images' variance: below 1 is the frame's scale
    assert ratio < 1.0, ratio


def test_the_calibration_keeps_the_pooled_slope_where_a_component_agrees():
    """Each component has a fraction of the pooled slope's samples (issue 37's narrowest
    instrument: cross slope -11 % on its own, unflagged): where it agrees with the pooled one
    (fit_checks' agreement: within Z_CONSISTENT of its standard error) the pooled slope is
    kept, where it does not (a warning there) its own."""
    parameters = {
        "pooled_slope": 7.0e-11,
        "pooled_slope_sigma": 0.2e-11,
        "slope_x": 6.2e-11,  # 2 standard errors low: agrees
        "slope_x_sigma": 0.4e-11,
        "slope_y": 7.3e-11,
        "slope_y_sigma": 0.4e-11,
        "cross_slope": 3.0e-11,  # 10 standard errors and 57 % low: its own
        "cross_slope_sigma": 0.4e-11,
    }
    kept = calibrated_slopes(parameters)
    assert kept == {"slope_x": 7.0e-11, "slope_y": 7.0e-11, "cross_slope": 3.0e-11}
    flagged = {
        c["parameter"]
        for c in calibration_checks({"motion_noise": {"parameters": parameters}})
        if c["level"] != "ok"
    }
    assert flagged == {"cross_slope"}


@pytest.mark.parametrize(
    "gain, error, level",
    [(1.08, 0.005, "warning"), (1.08, 0.05, "ok"), (1.03, 0.001, "ok"), (0.93, 0.005, "warning")],
)
def test_moves_that_disagree_with_the_images_flag_the_slope(gain, error, level):
    """Issue 37's widest loop (0.25, asymmetry 0.1): moves of 1-4 um appeared 6-9 % long in the
    images, the lanes' true separations 24-42 % long, and the slope measured through that
    frame was off against either truth, unflagged. A lane whose g^2 departs from 1 by more
    than the accuracy target and g from 1 by more than Z_CONSISTENT standard errors flags
    the pooled slope; a departure within its error or under the target does not."""
    parameters = {
        "pooled_slope": 7.0e-11,
        "pooled_slope_sigma": 0.2e-11,
        **{name: 7.0e-11 for name in ("slope_x", "slope_y", "cross_slope")},
        **{f"{name}_sigma": 0.4e-11 for name in ("slope_x", "slope_y", "cross_slope")},
        "move_gains": [[0, 0.25e-6, 1.0, 0.003], [0, 4e-6, gain, error]],
    }
    checks = calibration_checks({"motion_noise": {"parameters": parameters}})
    flagged = [c for c in checks if c["level"] != "ok"]
    assert [c["level"] for c in flagged] == ([level] if level != "ok" else []), flagged
    if flagged:
        assert flagged[0]["parameter"] == "pooled_slope"
        assert "afm calibrate --only motion_noise" in flagged[0]["message"]


def test_the_scanner_matrix_gain_is_checked_against_the_image_frame_not_the_open_loop_gain():
    """Issue 37 printed ok for an image-frame gain 0.9508 against an open-loop gain 1.0052
    and would have warned only past 10 % between two quantities that do not measure the
    same thing. Now each gain is checked against 1 with its standard error; the open-loop
    gain is shown, not compared."""
    hysteresis = {"gain": 1.0052}

    def checks(gain, sigma):
        matrix = {
            "scanner_matrix": [[1.0, 0.0], [0.0, gain]],
            "scanner_matrix_sigma": [[0.001, 0.001], [0.001, sigma]],
        }
        summary = {
            "scanner_matrix": {"parameters": matrix},
            "hysteresis_y": {"parameters": hysteresis},
        }
        found = [c for c in calibration_checks(summary) if c["parameter"] == "gain_y"]
        assert len(found) == 1
        return found[0]

    assert checks(0.9508, 0.002)["level"] == "ok"
    flagged = checks(0.85, 0.002)
    assert flagged["level"] == "warning" and "--only scanner_matrix" in flagged["message"]
    assert "not comparable" in flagged["message"]
    # as far off but not resolved by the grid (a standard error of 6 %): no warning
    assert checks(0.85, 0.06)["level"] == "ok"
