"""Calibration experiments at the ends of issue 37's ranges, one experiment each on a fresh
simulator, against its configuration, and the report's figures:

- creep 3x in size and time: the early pits lag 3 um behind a 50 um step, past the first
  rescan box; the box grows with the lag measured and the runs move apart (creep.py).
- drift means of 1 nm/s: the particles travel half a frame over a pair; the frames follow
  the drift measured so far (drift_statistics.py).
- the report's figures (figures.py): a PNG per experiment from the report alone, linked from
  the readable report.
"""

import math

import numpy as np
import pytest

from afm_core.localization.calibration.creep import creep_step_response, measure_creep
from afm_core.localization.calibration.drift_statistics import measure_drift
from afm_core.localization.calibration.experiment import range_centre
from afm_core.localization.calibration.figures import calibration_figures
from afm_core.localization.calibration.fit_checks import Z_CONSISTENT, calibration_checks
from afm_core.localization.calibration.procedure import report_markdown
from afm_core.localization.calibration.scanner_matrix import measure_scanner_matrix
from afm_core.sim.config import load_config, merge
from afm_core.sim.instrument import SimulatedAfm


def creep_three_times():
    """The default instrument (seed 3) with creep 3x in size and time: time constants 1.5, 15,
    150 s and 6 % of the step."""
    base = load_config().scanner
    return merge(
        load_config(),
        {
            "seed": 3,
            "scanner": {
                "creep_time_constants": [3 * t for t in base.creep_time_constants],
                "creep_fractions": [3 * f for f in base.creep_fractions],
            },
        },
    )


def test_creep_three_times_the_default_is_recovered():
    """Creep 3x in size and time (time constants 1.5, 15, 150 s; 6 % of the step): the
    step response at 25 s within 10 % of the simulator's on both axes, and the early pits
    (the fast constant) found in the first run although they lag past the first box."""
    config = creep_three_times()
    result = measure_creep(SimulatedAfm(config), repeats=2)
    truth = creep_step_response(
        config.scanner.creep_time_constants, config.scanner.creep_fractions, [25.0]
    )[0]
    for axis, response in zip("xy", result.parameters["step_response_25s"]):
        assert abs(response / truth - 1) < 0.10, (axis, response, truth)
    first = result.data["x"][0]
    assert first["pits_found"] >= first["pits_punched"] - 2
    # the run lagged past the first box (5 % of the step + 0.5 um)
    assert first["lag"] > 0.05 * first["step"]


def test_a_small_fast_creep_is_recovered_or_its_terms_flagged():
    """Creep 0.3x in size and time under noise 4x (time constants 0.15, 1.5, 15 s, 0.6 % of
    the step; issue 37's widest instrument): the terms trade off against the pits' scatter
    (fitted 0.51 / 8.4 / 27 s in the bench, reported "ok"). Every time constant and fraction
    is within 10 % of the simulator's or its term is flagged, and a flagged term says why
    (its 95 % interval, or a 95 % upper bound where the term is not seen at this noise)."""
    base = load_config().scanner
    config = merge(
        load_config(),
        {
            "seed": 4,
            "scanner": {
                "hysteresis_fraction": 0.25,
                "hysteresis_asymmetry": 0.1,
                "creep_time_constants": [0.3 * t for t in base.creep_time_constants],
                "creep_fractions": [0.3 * f for f in base.creep_fractions],
                "positioning_noise_slope": 4.0 * base.positioning_noise_slope,
                "positioning_noise_offset": 4.0 * base.positioning_noise_offset,
            },
        },
    )
    p = measure_creep(SimulatedAfm(config)).parameters
    flagged = {
        c["parameter"]
        for c in calibration_checks({"creep": {"parameters": p}})
        if c["level"] != "ok"
    }
    order = np.argsort(config.scanner.creep_time_constants)
    taus = np.asarray(config.scanner.creep_time_constants)[order]
    fractions = np.asarray(config.scanner.creep_fractions)[order]
    wrong = []
    for i in range(3):
        fitted = [p["time_constants"][i], p["fractions_x"][i], p["fractions_y"][i]]
        true = [taus[i], fractions[i], fractions[i]]
        if any(abs(f / t - 1) > 0.10 for f, t in zip(fitted, true)):
            wrong.append(i)
            assert f"term_{i + 1}" in flagged, (i, fitted, true, flagged)
    assert wrong, "the case no longer tests the flag: every term within 10 %"


def test_the_scanner_matrix_does_not_depend_on_where_the_tip_came_from():
    """Issue 37: the scanner matrix's y gain read 0.92-0.95 in full runs. The creep of the
    moves before the grid ran on while its rows were punched one after another along y, so
    the gain followed the last long move: with creep 3x, 0.967 after a 45 um move from above
    and 1.026 from below. With a rest at the first pit the two agree within Z_CONSISTENT
    combined standard errors and lie nearer 1 than either did."""
    config = creep_three_times()
    axis, gains = 1, []
    for side in (1.0, -1.0):
        afm = SimulatedAfm(config)
        centre = range_centre(afm)
        afm.move_tip(centre[0] - 20e-6, centre[1] + side * 45e-6, 20e-6)
        p = measure_scanner_matrix(afm).parameters
        gains.append((p["scanner_matrix"][axis][axis], p["scanner_matrix_sigma"][axis][axis]))
    (above, s_above), (below, s_below) = gains
    assert abs(above - below) < Z_CONSISTENT * math.hypot(s_above, s_below), gains
    assert abs(above - 1) < 1 - 0.967 and abs(below - 1) < 0.026, gains


def test_drift_of_one_nanometre_per_second_is_measured():
    """Drift means of 1 nm/s (the particles move ~1.1 um over a pair, half the frame): every
    pair is measured and the mean is within its sampling error (3 sigma of the configured
    spread over the pairs) plus the pairs' own error (0.05 nm/s) of the configured mean."""
    config = merge(
        load_config(),
        {"seed": 3, "drift": {"mean_velocity_x": 1e-9, "mean_velocity_y": -1e-9}},
    )
    pairs = 3
    result = measure_drift(SimulatedAfm(config), pairs=pairs, interval=1800.0)
    sigma = np.array([config.drift.sigma_velocity_x, config.drift.sigma_velocity_y])
    tolerance = 3.0 * sigma / math.sqrt(pairs) + 0.05e-9
    mean = np.array(result.parameters["mean_velocity"])
    assert np.all(np.abs(mean - [1e-9, -1e-9]) < tolerance), (mean, tolerance)


def _summary() -> dict:
    """A report of run_calibration's shape with a few points per experiment (synthetic)."""
    drive = np.linspace(-40e-6, 40e-6, 12)
    branch = ["descending"] * 6 + ["ascending"] * 6
    return {
        "hysteresis_x": {
            "parameters": {"loop_fraction": 0.12, "loop_fraction_sigma": 0.001, "asymmetry": 0.03},
            "data": {
                "drive": (55e-6 + drive).tolist(),
                "centre": 55e-6,
                "position": (55e-6 + drive * 1.01).tolist(),
                "predicted": (55e-6 + drive).tolist(),
                "branch": branch,
                "time": list(range(12)),
                "pits_found": 12,
                "pits_punched": 12,
            },
        },
        "creep": {
            "parameters": {"time_constants": [0.5, 5.0, 50.0], "step_response_25s": [0.02, 0.02]},
            "data": {
                axis: [{"t": [1.0, 10.0, 100.0], "position": [1e-6, 1.1e-6, 1.2e-6]}]
                for axis in "xy"
            },
        },
        "motion_noise": {
            "parameters": {"pooled_slope": 7e-11, "pooled_slope_sigma": 5e-12},
            "data": {
                axis: [
                    {"distance": d, "variance_along": 7e-11 * d, "variance_across": 6e-11 * d}
                    for d in (0.5e-6, 1e-6, 2e-6)
                ]
                for axis in "xy"
            },
        },
        "drift": {
            "parameters": {
                "mean_velocity": [1e-10, 2e-10],
                "sigma_velocity": [3e-11, 2e-10],
                "pairs": 3,
            },
            "data": {"time": [0.0, 1800.0, 3600.0], "velocity": [[1e-10, 2e-10]] * 3},
        },
        "scanner_matrix": {"failed": "RuntimeError: only 3 pits found"},
    }


def test_the_report_has_a_figure_per_measured_experiment(tmp_path):
    """A PNG per experiment that measured (none for the failed one), each a real image, and
    the readable report links them."""
    summary = _summary()
    figures = calibration_figures(summary, tmp_path / "fits_figures")
    assert set(figures) == {"hysteresis_x", "creep", "motion_noise", "drift"}
    for path in figures.values():
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert path.stat().st_size > 5000  # axes, points and text, not an empty canvas
    relative = {name: path.relative_to(tmp_path) for name, path in figures.items()}
    text = report_markdown(summary, relative)
    assert "![creep](fits_figures/creep.png)" in text
    assert "scanner_matrix" in text and "failed" in text


@pytest.mark.parametrize("name", ["hysteresis_x", "creep"])
def test_a_figure_needs_only_the_report(tmp_path, name):
    """The figures come from the JSON-ready report alone (a report written earlier can be
    drawn again): an entry without its data has no figure rather than an error."""
    summary = {name: {"parameters": _summary()[name]["parameters"]}}
    assert calibration_figures(summary, tmp_path) == {}


def test_a_fit_the_calibration_refuses_keeps_the_others():
    """A creep fit with a time constant of 0 s (a free fast constant run to exp(-655)) made
    Calibration() raise after every experiment had run: the whole run was lost. Now that
    experiment's fields keep the defaults, it is marked failed with the reason, the rest
    stay."""
    from afm_core.localization.calibration.procedure import _accepted_fields

    fields = {
        "creep_time_constants": [0.0, 1.6, 20.0],
        "creep_fractions_x": [0.01, 0.01, 0.01],
        "creep_fractions_y": [0.01, 0.01, 0.01],
        "motion_noise_slope_x": 7e-11,
    }
    failed = {}
    accepted = _accepted_fields(fields, failed)
    assert accepted == {"motion_noise_slope_x": 7e-11}
    assert "creep_time_constants" in failed["creep"] and set(failed) == {"creep"}
