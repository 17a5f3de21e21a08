"""Calibration experiments (book 7.2.2) on the simulated AFM, against its configured values.

One calibration run (module fixture, smaller than the bench's) on the default simulator,
seeded; the drift statistics on an instrument of their own (see test_drift_statistics).
What is compared, and why:
- hysteresis: the loop fraction (loop width / span of the full-range major loop, as
  PrandtlIshlinskii.from_fraction defines it) within 10 %; and the branch curves: the fitted
  major loop's branches within 10 % of the loop width of the true ones (after the common
  shift the rescan leaves open). The branches are what the localizer uses the model for
  (where a drive puts the tip); the asymmetry alpha alone is a small second-order shape
  term (0.03) whose effect trades off against the weights, so it is checked loosely.
- creep: the creep step response over the book's 25 s within 10 % of the true creep
  (what the motion model predicts), and the time constants within 25 % (the slowest one
  trades off against the wandering drift over the finite window).
- motion noise: the slope of sigma^2 = a d + b within 20 % (pooled over both axes and both
  components: the simulator's noise is isotropic).
- drift: mean velocities within 10 %; sigma within 10 % of the spread of the true velocities
  at the same moments (see the test for why not of the configured sigma).
"""

import json
import math

import numpy as np
import pytest

from afm_core.instrument import ScanRequest
from afm_core.localization.calibration.creep import (
    WALK_MEASUREMENT_RATIO,
    creep_deficit,
    fit_creep,
    measure_creep,
    walk_whitener,
)
from afm_core.localization.calibration.drift_statistics import measure_drift
from afm_core.localization.calibration.experiment import Experiment
from afm_core.localization.calibration.hysteresis import measure_hysteresis, refit_hysteresis
from afm_core.localization.calibration.line_deflection import measure_line_deflection
from afm_core.localization.calibration.matching import match_monotone
from afm_core.localization.calibration.model import load_calibration, save_calibration
from afm_core.localization.calibration.motion_error import measure_motion_noise
from afm_core.localization.calibration.pits import find_pits
from afm_core.localization.calibration.procedure import report_json, run_calibration
from afm_core.localization.calibration.scanner_matrix import measure_scanner_matrix
from afm_core.localization.calibration.simulator_comparison import compare_with_simulator
from afm_core.sim.config import load_config, merge
from afm_core.sim.instrument import SimulatedAfm

# A smaller run than the bench's (bench/bench_calibration.py has the full one).
QUICK = dict(
    hysteresis={"steps_per_sweep": 96, "pixel": 35e-9},
    motion_noise={"distances": (0.5e-6, 1e-6, 2e-6, 4e-6), "precision": None},
    drift={"pairs": 3, "interval": 1800.0},
)


@pytest.fixture(scope="module")
def calibrated():
    config = load_config()
    afm = SimulatedAfm(config)
    calibration, report = run_calibration(afm, **QUICK)
    rows = {row["name"]: row for row in compare_with_simulator(calibration, report, config)}
    return calibration, report, rows, config


@pytest.mark.parametrize("axis", ["x", "y"])
def test_hysteresis_loop_fraction_and_branches(calibrated, axis):
    _, _, rows, config = calibrated
    assert abs(rows[f"hysteresis_{axis}.loop_fraction"]["relative_error"]) < 0.10
    assert rows[f"hysteresis_{axis}.branch_error"]["recovered"] < 0.10
    assert abs(rows[f"hysteresis_{axis}.asymmetry"]["relative_error"]) < 0.10


def test_the_report_file_holds_every_experiments_fit_and_data(calibrated):
    """`afm calibrate --report` wrote {} (issue 37): the report must carry each experiment's
    parameters and raw data, equal to what the run returned."""
    _, report, _, _ = calibrated
    written = json.loads(report_json(report))
    experiments = [name for name, value in report.items() if isinstance(value, dict)]
    assert {"creep", "hysteresis_x", "hysteresis_y", "motion_noise"} <= set(experiments)
    for name in experiments:
        assert set(written[name]["parameters"]) == set(report[name]["parameters"]) != set()
        assert set(written[name]["data"]) == set(report[name]["data"])
    assert written["hysteresis_y"]["parameters"]["loop_fraction"] == pytest.approx(
        report["hysteresis_y"]["parameters"]["loop_fraction"]
    )
    assert written["wall_seconds"] > 0


def test_ctrl_c_keeps_the_experiments_done_and_runs_no_more(monkeypatch):
    """Ctrl-C during an experiment lost every one done before it (hours on an instrument)."""
    from afm_core.localization.calibration import procedure

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(procedure, "measure_motion_noise", interrupted)
    heard = []
    only = ["scanner_matrix", "motion_noise", "line_deflection"]
    calibration, report = run_calibration(
        SimulatedAfm(load_config()), **QUICK, only=only, progress=heard.append
    )
    assert report["interrupted"] is True
    assert "scanner_matrix" in calibration.measured and "parameters" in report["scanner_matrix"]
    assert report["motion_noise"] == {"failed": "interrupted (Ctrl-C)"}
    assert report["line_deflection"] == {"failed": "not run (interrupted)"}
    assert "line_deflection_mean_deg" in calibration.defaults
    assert not any("line_deflection ..." in text for text in heard)


def test_a_failed_experiment_keeps_the_others_results(monkeypatch, tmp_path):
    """One experiment that cannot measure (issue 37: "motion noise: only 0 trials measured")
    must not lose the others: the file is written, the failed experiment's fields keep the
    defaults and are listed as such, the others are measured."""
    from afm_core.localization.calibration import procedure
    from afm_core.localization.calibration.model import (
        Calibration,
        load_calibration,
        save_calibration,
    )

    def cannot_measure(*args, **kwargs):
        raise ValueError("motion noise (y, d=2.5e-07 m): only 0 trials measured")

    monkeypatch.setattr(procedure, "measure_motion_noise", cannot_measure)
    config = load_config()
    heard = []
    calibration, report = run_calibration(SimulatedAfm(config), **QUICK, progress=heard.append)
    assert heard[0] == "experiment 1 of 8: drift ..."
    assert any(
        text.startswith("experiment 7 of 8: motion_noise failed (ValueError: motion noise")
        for text in heard
    )
    assert heard[-1].startswith("experiment 8 of 8: line_deflection done in ")
    assert report["motion_noise"] == {
        "failed": "ValueError: motion noise (y, d=2.5e-07 m): only 0 trials measured"
    }
    assert calibration.defaults == sorted(
        [
            "motion_noise_slope_x",
            "motion_noise_slope_y",
            "motion_noise_cross_slope",
            "motion_noise_offset",
        ]
    )
    assert calibration.motion_noise_slope_x == Calibration().motion_noise_slope_x
    path = tmp_path / "calibration.yaml"
    save_calibration(calibration, path)
    again = load_calibration(path)
    assert again.defaults == calibration.defaults
    assert again.hysteresis_y.loop_fraction == pytest.approx(
        config.scanner.hysteresis_fraction, rel=0.10
    )
    rows = {row["name"]: row for row in compare_with_simulator(calibration, report, config)}
    assert rows["motion_noise.slope_x"]["recovered"] is None
    assert "not measured" in rows["motion_noise.slope_x"]["note"]
    assert abs(rows["hysteresis_x.loop_fraction"]["relative_error"]) < 0.10


def test_hysteresis_asymmetry_exact_on_an_ideal_scanner():
    """With drift, noise, creep, coupling and the controller's model error off, the rescan
    shows the pits where they are, so the fit must return the configured asymmetry: a
    rescan that asks the compensated scanner for positions past its loop tips (clamped
    drive) misplaces the pits of the lower half and fails this (-4 %)."""
    config = merge(
        load_config(),
        {
            "drift": {"enabled": False},
            "controller": {"model_error": 0.0},
            "scanner": {
                "positioning_noise_enabled": False,
                "creep_enabled": False,
                "coupling_enabled": False,
                "deflection_enabled": False,
            },
            "noise": {"height_white_sigma": 0.0, "height_flicker_sigma": 0.0},
        },
    )
    experiment = measure_hysteresis(SimulatedAfm(config), 1)
    assert experiment.parameters["asymmetry"] == pytest.approx(
        config.scanner.hysteresis_asymmetry, rel=0.01
    )
    assert experiment.parameters["loop_fraction"] == pytest.approx(
        config.scanner.hysteresis_fraction, rel=0.01
    )


def test_hysteresis_fit_without_creep_model_is_biased(calibrated):
    """Creep during the cycle widens the measured loop: the same pits fitted without the
    creep term give a loop fraction biased upwards (the creep term matters, and the
    loop-fraction comparison can fail)."""
    _, report, _, config = calibrated
    experiment = Experiment(**report["hysteresis_x"])
    without = refit_hysteresis(experiment, creep=None)
    with_creep = report["hysteresis_x"]["parameters"]["loop_fraction"]
    truth = config.scanner.hysteresis_fraction
    # the bias is +1.9 to +2.6 % of the loop (by the pits' realization: a fresh simulator,
    # the full run); it must stand out of the fit's own standard error, 3 of them
    sigma = report["hysteresis_x"]["parameters"]["loop_fraction_sigma"]
    assert without["loop_fraction"] - truth > 3 * sigma
    assert abs(without["loop_fraction"] - truth) > abs(with_creep - truth)


def test_walk_whitener_whitens_the_random_walk_covariance():
    moves = np.array([1, 2, 3, 5, 6, 9])
    covariance = np.minimum.outer(moves, moves) + WALK_MEASUREMENT_RATIO * np.eye(moves.size)
    whitener = walk_whitener(moves)
    assert np.allclose(whitener @ covariance @ whitener.T, np.eye(moves.size))


def test_fit_creep_shares_fractions_per_group_through_a_random_walk():
    """Synthetic runs from known creep, each pit after one more move (a random walk of 3 nm
    steps), drift lines and 1 nm pit noise: the fit recovers the time constants and each
    group's fractions."""
    rng = np.random.default_rng(3)
    taus, truth = (
        np.array([0.5, 5.0, 50.0]),
        {"x": np.array([0.008, 0.006, 0.006]), "y": np.array([0.004, 0.009, 0.005])},
    )
    step, ramp = 50e-6, 0.5
    t = np.r_[np.linspace(0.55, 1.3, 8), np.geomspace(2.0, 300.0, 32)]
    runs = []
    for group in ("x", "x", "x", "y", "y", "y"):
        walk = np.cumsum(rng.normal(0.0, 3e-9, t.size))
        drift = rng.normal(0.0, 0.05e-9) * t
        x = (
            12e-6
            + drift
            + walk
            + rng.normal(0.0, 1e-9, t.size)
            - step * creep_deficit(t, taus, ramp) @ truth[group]
        )
        runs.append(
            {
                "t": t,
                "x": x,
                "step": step,
                "ramp_time": ramp,
                "group": group,
                "moves": np.arange(1, t.size + 1),
            }
        )
    fit = fit_creep(runs)
    assert np.allclose(fit["time_constants"], taus, rtol=0.1)
    for fitted, group in zip(fit["fractions"], ("x", "y")):
        assert np.allclose(fitted, truth[group], rtol=0.1)
    assert len(fit["settled"]) == len(runs)


def test_match_monotone_skips_a_stray_pit_past_the_row_end():
    expected = np.arange(40) * 150e-9
    detected = np.r_[
        expected * 1.03 + 2e-6, expected[-1] * 1.03 + 2e-6 + 190e-9
    ]  # one pit of the next row
    index = match_monotone(expected, detected)
    assert np.array_equal(index, np.arange(40))


@pytest.mark.parametrize("axis", ["x", "y"])
def test_creep_step_response(calibrated, axis):
    _, _, rows, _ = calibrated
    assert rows[f"creep.step_response_{axis}"]["recovered"] < 0.10
    # The time constants are less well determined than the curve they make: over a finite
    # window the slowest one trades off against the (wandering) drift; with five runs per axis
    # and the random-walk weighting, 10 seeds of the experiment gave at most 12 % (mean 3-6 %).
    for i in range(3):
        assert abs(rows[f"creep.time_constant[{i}]"]["relative_error"]) < 0.15


def test_motion_noise_slope(calibrated):
    _, report, rows, _ = calibrated
    assert abs(rows["motion_noise.pooled_slope"]["relative_error"]) < 0.20
    # per axis the sampling error is larger (fewer samples each); still the right size
    for name in ("slope_x", "slope_y", "cross_slope"):
        assert abs(rows[f"motion_noise.{name}"]["relative_error"]) < 0.35


def test_calibration_file_round_trip(calibrated, tmp_path):
    calibration, _, _, _ = calibrated
    path = tmp_path / "calibration.yaml"
    save_calibration(calibration, path)
    loaded = load_calibration(path)
    assert loaded == calibration
    assert len(loaded.hysteresis_x.weights) == len(loaded.hysteresis_x.thresholds) > 2
    assert loaded.motion_noise().k_h1 == calibration.motion_noise_slope_x


@pytest.mark.parametrize(
    "line, message",
    [
        ("creep_fractions_x: [-0.5, 0.006, 0.006]", r"creep_fractions_x=\[-0.5, .*\[0, 1\)"),
        ("creep_fractions_x: [0.6, 0.3, 0.2]", r"creep_fractions_x=.*a sum < 1"),
        ("creep_fractions_x: ['0.008', 0.006, 0.006]", r"creep_fractions_x\[0\]='0.008'"),
        ("creep_fractions_x: [.nan, 0.006, 0.006]", r"creep_fractions_x=\[nan"),
        ("scanner_matrix: [[1.0, '0'], [0.0, 1.0]]", r"scanner_matrix\[0\]\[1\]='0'"),
        ("map_sigma: [5.0e-9, 4nm]", r"map_sigma\[1\]='4nm': expected a number"),
        ("map_sigma: [-5.0e-9, 4.5e-9]", r"map_sigma=\[-5e-09, 4.5e-09\]: need values in \[0, "),
        ("scan_region_sigma: 4.7", r"scan_region_sigma=4.7: need values in \[0, 0.00011\]"),
        ("line_deflection_sigma_deg: -1", r"line_deflection_sigma_deg=-1.0: need values in"),
        ("hysteresis_x: {thresholds: [0.0, 1.0e-6]}", r"hysteresis_x: need one weight per thr"),
    ],
)
def test_a_calibration_file_with_a_bad_list_entry_is_refused_by_name(tmp_path, line, message):
    """A hand-edited list entry (a wrong sign, a quoted number) used to load and send the
    localizer hundreds of nm off while it reported a 33 nm sigma."""
    path = tmp_path / "calibration.yaml"
    path.write_text(
        "creep_time_constants: [1.0, 10.0, 100.0]\n"
        "creep_fractions_x: [0.008, 0.006, 0.006]\n"
        "creep_fractions_y: [0.008, 0.006, 0.006]\n"
    )
    assert load_calibration(path).creep_fractions_x == [0.008, 0.006, 0.006]
    field = line.split(":")[0]
    kept = [row for row in path.read_text().splitlines() if not row.startswith(field + ":")]
    path.write_text("\n".join(kept + [line]) + "\n")
    with pytest.raises(ValueError, match=message):
        load_calibration(path)


def test_observation_errors_are_measured(calibrated):
    """No configured value to compare with (see compare_with_simulator): sizes only."""
    calibration, _, _, _ = calibrated
    assert all(0 < s < 20e-9 for s in calibration.map_sigma)
    assert 0 < calibration.scan_region_sigma < 20e-9
    assert abs(calibration.line_deflection_mean_deg) < 1.0
    assert np.allclose(calibration.scanner_matrix, np.eye(2), atol=0.05)


def test_drift_statistics():
    """Frame-up / frame-down pairs. The instrument: the default one with a drift whose mean
    is large against its spread and a feed-forward without model error. Why: (1) the mean of
    n pairs has a sampling error sigma / sqrt(n), so 10 % of a mean needs sigma << mean
    unless n is in the hundreds; (2) with the default 10 % model error a small image's scale
    is off by the compensation residual of short moves (about 6 %), and velocities in image
    units with it (the bench shows it on the default instrument). The sigma is compared with
    the spread of the true pair-averaged velocities at the same moments: the configured
    sigma is a population value that 12 pairs estimate only to ~20 % (10 % needs ~200
    independent pairs, the bench's scale)."""
    config = merge(
        load_config(),
        {
            "controller": {"model_error": 0.0},
            "drift": {
                "mean_velocity_x": 0.5e-9,
                "mean_velocity_y": 0.8e-9,
                "sigma_velocity_x": 0.05e-9,
                "sigma_velocity_y": 0.08e-9,
                "correlation_time": 1800.0,
                "knot_interval": 5.0,
            },
        },
    )
    afm = SimulatedAfm(config)
    result = measure_drift(afm, pairs=12, interval=2000.0)
    mean = result.parameters["mean_velocity"]
    assert mean[0] == pytest.approx(0.5e-9, rel=0.10)
    assert mean[1] == pytest.approx(0.8e-9, rel=0.10)
    moments = np.asarray(result.data["time"])
    pair = 2 * 256.0 + 250.0
    truth = np.array(
        [(afm.drift.offset(t + pair / 2) - afm.drift.offset(t - pair / 2)) / pair for t in moments]
    )
    measured = np.asarray(result.data["velocity"])
    error = measured - truth
    assert np.sqrt(np.mean(error**2, axis=0)).max() < 0.03e-9  # per pair
    # The measured spread is that of the true velocities plus each pair's own error:
    # sigma^2 = var(truth) + var(error) + 2 cov. With errors up to 0.03 nm/s against a spread
    # of 0.04-0.08 nm/s the cross term of 12 pairs is not small: its sampling error is about
    # 2 std(truth) std(error) / sqrt(n - 1) (a pair moment 330 s later moved y's by 15 % with
    # the same per-pair errors, the correlation from -0.27 to +0.38). Within 3 of those. (The
    # pairs' sample spread: sigma_velocity is it corrected for their correlation.)
    n = len(measured)
    for axis in (0, 1):
        spread, noise = truth[:, axis].std(ddof=1), error[:, axis].std(ddof=1)
        excess = result.parameters["sample_sigma_velocity"][axis] ** 2 - spread**2 - noise**2
        assert abs(excess) < 3 * 2 * spread * noise / np.sqrt(n - 1), (axis, excess)


@pytest.mark.parametrize("asymmetry_error", [0.0, 0.05])
def test_feed_forward_inverts_the_controllers_calibrated_asymmetry(asymmetry_error):
    """The controller inverts its own model, whose asymmetry is the scanner's minus
    asymmetry_error: from rest at the centre a compensated move lands at
    H_scanner(H_controller^-1(command)) (exactly the command when the models agree)."""
    from afm_core.pzt import PrandtlIshlinskii

    config = merge(
        load_config(),
        {
            "drift": {"enabled": False},
            "controller": {"model_error": 0.0, "asymmetry_error": asymmetry_error},
            "scanner": {
                "positioning_noise_enabled": False,
                "creep_enabled": False,
                "coupling_enabled": False,
                "deflection_enabled": False,
            },
        },
    )
    afm = SimulatedAfm(config)
    scanner, centre = config.scanner, config.scanner.range_x / 2
    afm.move_tip(centre + 20e-6, centre, 1e-4)
    controller = PrandtlIshlinskii.from_fraction(
        scanner.range_x,
        scanner.hysteresis_fraction,
        scanner.hysteresis_operators,
        scanner.hysteresis_asymmetry - asymmetry_error,
    )
    controller.reset(0.0)
    drive = controller.inverse().apply([0.0, 20e-6])[-1]
    model = PrandtlIshlinskii.from_fraction(
        scanner.range_x,
        scanner.hysteresis_fraction,
        scanner.hysteresis_operators,
        scanner.hysteresis_asymmetry,
    )
    model.reset(0.0)
    expected = model.apply([0.0, drive])[-1]
    assert afm.truth()["tip_position"][0] - centre == pytest.approx(expected, abs=1e-12)
    assert (abs(expected - 20e-6) > 10e-9) == (asymmetry_error != 0.0)


@pytest.mark.parametrize(
    "controller",
    [{"asymmetry_error": float("nan")}, {"asymmetry_error": 2.0}, {"model_error": -1.5}],
)
def test_controller_model_errors_out_of_range_are_refused(controller):
    with pytest.raises(ValueError, match=f"controller.{next(iter(controller))}"):
        SimulatedAfm(merge(load_config(), {"controller": controller}))


def test_feed_forward_switch_does_not_move_the_tip():
    afm = SimulatedAfm(load_config())
    afm.move_tip(70e-6, 40e-6, 1e-4)
    before = afm.truth()["tip_position"]
    afm.feed_forward_enabled = False
    assert afm.truth()["tip_position"] == before
    drive = afm.commanded_position()
    assert drive != (70e-6, 40e-6)  # the raw drive the inverse model produced
    afm.move_tip(*drive, 1e-4)  # a move to where it is: nothing changes
    assert np.allclose(afm.truth()["tip_position"], before, atol=2e-9)
    afm.move_tip(90e-6, 20e-6, 1e-4)
    afm.move_tip(*drive, 1e-4)
    afm.feed_forward_enabled = True
    command = afm.commanded_position()
    afm.move_tip(*command, 1e-4)  # the model's idea of where it is: no jump
    assert np.allclose(afm.truth()["tip_position"], afm.truth()["tip_position"], atol=1e-12)
    # back on, the compensation works again: the tip goes (about) where commanded
    afm.move_tip(60e-6, 60e-6, 1e-4)
    position = np.asarray(afm.truth()["tip_position"]) + np.asarray(afm.truth()["drift_offset"])
    assert np.linalg.norm(position - [60e-6, 60e-6]) < 1.0e-6


def test_pits_found_to_a_nanometre_on_an_exact_instrument():
    import sys

    sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
    from test_simulator import ideal

    afm = SimulatedAfm(ideal())
    commanded = [(40e-6 + i * 0.31e-6, 40e-6 + j * 0.29e-6) for i in range(4) for j in range(4)]
    for x, y in commanded:
        afm.move_tip(x, y, 1e-5)
        afm.indent(x, y, 1e-6, 0.0)
    scan = afm.raster_scan(ScanRequest(39.7e-6, 39.7e-6, 1.6e-6, 1.6e-6, 160, 160, line_rate=10))
    pits = find_pits(scan)
    assert len(pits) == len(commanded)
    found = np.array([[p.x, p.y] for p in pits])
    for x, y in commanded:
        assert np.min(np.hypot(found[:, 0] - x, found[:, 1] - y)) < 1e-9


def test_bad_input_is_refused_before_anything_moves():
    afm = SimulatedAfm(load_config())
    start = (afm.time, afm.commanded_position(), len(afm.sample.pits))
    with pytest.raises(ValueError, match="step"):
        measure_creep(afm, step=float("nan"))
    with pytest.raises(ValueError, match="scanner range"):
        measure_creep(afm, step=50e-6, lane_offset=60e-6)
    with pytest.raises(ValueError, match="cycle_fraction"):
        measure_hysteresis(afm, 0, cycle_fraction=1.5)
    with pytest.raises(ValueError, match="axis"):
        measure_hysteresis(afm, 2)
    with pytest.raises(ValueError, match="distances"):
        measure_motion_noise(afm, distances=(1e-6, math.inf))
    with pytest.raises(ValueError, match="scanner range"):
        measure_scanner_matrix(afm, site=(60e-6, 0.0))
    with pytest.raises(ValueError, match="pairs"):
        measure_drift(afm, pairs=1)
    with pytest.raises(ValueError, match="force"):
        measure_line_deflection(afm, force=1.0)
    assert (afm.time, afm.commanded_position(), len(afm.sample.pits)) == start
