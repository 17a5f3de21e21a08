"""Calibration experiments on simulated instruments away from the default (issue 37), each a
single experiment on a fresh simulator (the full run on several instruments is
bench/bench_calibration_instruments.py), against the simulator's configuration:

- hysteresis on loops of 0.05-0.25 of the range with asymmetry up to 0.1: the loop fraction
  within 10 %; the asymmetry within 10 % or the run says it was fitted without all four tip
  pits (fit_checks' tip check); issue 37's y-after-x case on its narrow asymmetric loop.
- the rows' matching on synthetic rows (closed form: the punched positions are known).
- motion noise at 0.25 um after a full-range excursion (issue 37: "only 0 trials measured").
- the fit checks flag a fit matched one pit off.
- rerunning one experiment and merging it into an earlier calibration.
"""

import copy

import numpy as np
import pytest

from afm_core.localization.calibration import hysteresis as hysteresis_module
from afm_core.localization.calibration import hysteresis_rows
from afm_core.localization.calibration.experiment import Experiment
from afm_core.localization.calibration.fit_checks import calibration_checks
from afm_core.localization.calibration.hysteresis import measure_hysteresis, refit_hysteresis
from afm_core.localization.calibration.matching import _smooth_step_counts, monotone_placements
from afm_core.localization.calibration.model import Calibration
from afm_core.localization.calibration.motion_error import measure_motion_noise
from afm_core.localization.calibration.procedure import (
    checked_experiments,
    merge_calibration,
    run_calibration,
)
from afm_core.sim.config import load_config, merge
from afm_core.sim.instrument import SimulatedAfm

QUICK_HYSTERESIS = {"steps_per_sweep": 96, "pixel": 35e-9}


def _instrument(seed, loop, asymmetry, creep=1.0, coupling=0.01, noise=1.0):
    base = load_config().scanner
    return merge(
        load_config(),
        {
            "seed": seed,
            "scanner": {
                "hysteresis_fraction": loop,
                "hysteresis_asymmetry": asymmetry,
                "creep_time_constants": [creep * t for t in base.creep_time_constants],
                "creep_fractions": [creep * f for f in base.creep_fractions],
                "coupling_x_to_y": coupling,
                "coupling_y_to_x": coupling,
                "positioning_noise_slope": noise * base.positioning_noise_slope,
                "positioning_noise_offset": noise * base.positioning_noise_offset,
            },
        },
    )


def _true_creep(config):
    s = config.scanner
    return (list(s.creep_time_constants), list(s.creep_fractions))


def _hysteresis_summary(experiment: Experiment, axis: str) -> dict:
    return {f"hysteresis_{axis}": {"parameters": experiment.parameters, "data": experiment.data}}


@pytest.mark.parametrize(
    "seed, loop, asymmetry, creep, coupling, noise, axis",
    [
        (5, 0.05, 0.10, 3.0, 0.01, 0.5, 0),
        (6, 0.18, 0.08, 0.6, 0.02, 2.0, 1),
    ],
)
def test_hysteresis_recovered_or_flagged_across_instruments(
    seed, loop, asymmetry, creep, coupling, noise, axis
):
    config = _instrument(seed, loop, asymmetry, creep, coupling, noise)
    experiment = measure_hysteresis(
        SimulatedAfm(config), axis, creep=_true_creep(config), **QUICK_HYSTERESIS
    )
    p = experiment.parameters
    assert p["loop_fraction"] == pytest.approx(loop, rel=0.10)
    checks = calibration_checks(_hysteresis_summary(experiment, "xy"[axis]))
    asymmetry_flagged = any(
        c["parameter"] == "asymmetry" and c["level"] == "warning" for c in checks
    )
    assert asymmetry_flagged or p["asymmetry"] == pytest.approx(asymmetry, rel=0.10)
    # the fit's own precision check passes on a right match
    precision = [c for c in checks if c["parameter"] == "loop_fraction"]
    assert precision and precision[0]["level"] == "ok", precision


@pytest.mark.parametrize(
    "seed, loop, asymmetry, axis, options",
    [(2, 0.18, 0.08, 0, QUICK_HYSTERESIS), (4, 0.25, 0.10, 1, {})],
)
def test_wide_asymmetric_loops_recover_the_asymmetry_unflagged(
    seed, loop, asymmetry, axis, options
):
    """Issue 37: on wide loops the asymmetry read 5-13 % low with every tip pit found, and
    nothing warned. The cause was the rescans: an up pass first (a full-range move down and a
    reversal after the cycle) placed the pits up to 1.3 um low over its first ~40 um, even
    with a perfect feed-forward and no creep, and a box fixed at 0.95 of the half range
    started a pass beyond what the compensated scanner can reach. Down first, in a box that
    follows the loop's tips: the loop and the asymmetry within 10 %, and no warning unless a
    tip pit is missing (coupling 0.02, creep 0.6x, noise 2x). The widest loop on the default
    cycle (128 steps): on the tests' coarse one (96 steps, 35 nm pixels) its rows are not
    always matched (then the run says so, see the repeat test below)."""
    config = _instrument(seed, loop, asymmetry, 0.6, 0.02, 2.0)
    experiment = measure_hysteresis(
        SimulatedAfm(config), axis, creep=_true_creep(config), **options
    )
    p = experiment.parameters
    assert "retried" not in experiment.data
    assert p["loop_fraction"] == pytest.approx(loop, rel=0.10)
    assert p["asymmetry"] == pytest.approx(asymmetry, rel=0.10)
    checks = calibration_checks(_hysteresis_summary(experiment, "xy"[axis]))
    # a tip pit lost where the rows converge (the widest loop's top) is still said
    expected = ["ok", "ok" if experiment.data["tip_pits_found"] == 4 else "warning"]
    assert [c["level"] for c in checks] == expected, checks


def test_the_widest_loop_with_strong_negative_asymmetry_is_recovered():
    """Loop 0.25, asymmetry -0.1, coupling 0.05, noise 4x: at a cycle of 0.9 of the half
    range the bottom tip lands 4.4 um past the cycle, outside the rescan box; the rows (0.15-
    0.7 um apart, not parallel) are split by a line each and matched, or where they cannot be
    the experiment repeats itself at 0.8 (RETRY_CYCLE_FRACTION) on a fresh lane: the loop
    within 10 %, the asymmetry within 10 % or flagged (missing tips or a repeat flag it).
    Before: 'the rows of pits do not close at the loop's tips', nothing measured."""
    config = _instrument(7, 0.25, -0.10, 0.3, 0.05, 4.0)
    experiment = measure_hysteresis(
        SimulatedAfm(config), 0, creep=_true_creep(config), **QUICK_HYSTERESIS
    )
    p = experiment.parameters
    assert p["loop_fraction"] == pytest.approx(0.25, rel=0.10)
    if "retried" in experiment.data:
        assert experiment.data["cycle_fraction"] == 0.8
    checks = calibration_checks(_hysteresis_summary(experiment, "x"))
    flagged = any(c["parameter"] == "asymmetry" and c["level"] == "warning" for c in checks)
    assert flagged or p["asymmetry"] == pytest.approx(-0.10, rel=0.10)


def test_rows_not_matched_are_measured_again_on_a_smaller_cycle():
    """Loop 0.25, asymmetry +0.1, y axis (seed 4): at 0.9 the rows do not close at the top
    tip (outside the rescan); the experiment repeats at 0.8 on a fresh lane, ignoring the
    first attempt's pits: the loop within 10 % of the simulator's, and the asymmetry flagged
    (not all four tip pits found on the smaller cycle)."""
    config = _instrument(4, 0.25, 0.10, 0.3, 0.05, 4.0)
    experiment = measure_hysteresis(
        SimulatedAfm(config), 1, creep=_true_creep(config), **QUICK_HYSTERESIS
    )
    assert "do not close" in experiment.data["retried"]
    assert experiment.data["cycle_fraction"] == hysteresis_module.RETRY_CYCLE_FRACTION
    assert experiment.parameters["loop_fraction"] == pytest.approx(0.25, rel=0.10)
    warnings = [
        c
        for c in calibration_checks(_hysteresis_summary(experiment, "y"))
        if c["parameter"] == "asymmetry" and c["level"] == "warning"
    ]
    assert warnings and "--only hysteresis_y" in warnings[0]["message"]


@pytest.fixture(scope="module")
def narrow_loop_y_after_x():
    """Issue 37's instrument: loop 0.07, asymmetry 0.05, creep 1.5x, coupling 0.02, noise 2x;
    the y cycle run after the x cycle (whose rows cross its lane)."""
    config = _instrument(1, 0.07, 0.05, 1.5, 0.02, 2.0)
    afm = SimulatedAfm(config)
    creep = _true_creep(config)
    first = measure_hysteresis(afm, 0, creep=creep, **QUICK_HYSTERESIS)
    second = measure_hysteresis(
        afm, 1, creep=creep, ignore=first.data["all_detected"], **QUICK_HYSTERESIS
    )
    return config, creep, first, second


def test_y_hysteresis_after_x_on_a_narrow_asymmetric_loop(narrow_loop_y_after_x):
    """Issue 37: y came out 70 % off (0.119 for 0.07) after x, silently."""
    config, _, first, second = narrow_loop_y_after_x
    for experiment in (first, second):
        assert experiment.parameters["loop_fraction"] == pytest.approx(0.07, rel=0.10)
        assert experiment.parameters["asymmetry"] == pytest.approx(0.05, rel=0.10)


def test_the_checks_flag_a_fit_matched_one_pit_off(narrow_loop_y_after_x):
    """A branch matched one pit off (what issue 37's y fit was) must not pass silently: the
    residual grows, so does the fit's standard error, and the check warns naming the
    experiment to repeat."""
    _, creep, _, experiment = narrow_loop_y_after_x
    assert calibration_checks(_hysteresis_summary(experiment, "y"))[0]["level"] == "ok"
    slipped = copy.deepcopy(experiment)
    branch = np.array(slipped.data["branch"])
    position = np.array(slipped.data["position"])
    ascending = np.flatnonzero(branch == "ascending")
    # each ascending pit takes its neighbour's position: the placement one pit off
    position[ascending[:-1]] = position[ascending[1:]]
    keep = np.ones(len(branch), dtype=bool)
    keep[ascending[-1]] = False
    for key in ("branch", "drive", "time"):
        slipped.data[key] = list(np.asarray(slipped.data[key], dtype=object)[keep])
    slipped.data["position"] = list(position[keep])
    slipped.parameters = {
        key: value
        for key, value in refit_hysteresis(slipped, creep=creep).items()
        if key in hysteresis_module.FIT_PARAMETERS
    }
    checks = calibration_checks(_hysteresis_summary(slipped, "y"))
    warning = [c for c in checks if c["parameter"] == "loop_fraction"][0]
    assert warning["level"] == "warning", warning
    assert "--only hysteresis_y" in warning["message"]


def test_rows_are_placed_by_their_shared_tips_not_by_the_drive():
    """Synthetic rows of an asymmetric loop whose ends land 3.5 um from their drive (more than
    a pit spacing near the tip) with the end pit of the ascending row missing: the placement
    must put every detection on its own punch (the end tolerance against the drive slipped
    it by one)."""
    drives = np.linspace(5.5e-6, 104.5e-6, 25)
    u = (drives - 55e-6) / 55e-6
    # two branches meeting at the tips, 3.5 um above the drive at the top, 3.6 um at the bottom
    descending = drives + 3.5e-6 * (1 + u) / 2 + 3.6e-6 * (1 - u) / 2 + 4e-6 * (1 - u**2)
    ascending = drives + 3.5e-6 * (1 + u) / 2 + 3.6e-6 * (1 - u) / 2 - 4e-6 * (1 - u**2)
    branches = np.array(["descending"] * 25 + ["ascending"] * 25)
    all_drives = np.concatenate([drives, drives])
    rows = {
        "descending": (np.arange(25), descending),
        "ascending": (np.arange(25, 50), ascending[:-1]),  # the top pit not found
    }
    placed = hysteresis_rows.placed_rows(rows, all_drives, 0, "up")
    np.testing.assert_allclose(placed["descending"][1], descending)
    np.testing.assert_allclose(placed["ascending"][1][:-1], ascending[:-1])
    assert np.isnan(placed["ascending"][1][-1])
    assert branches.size == all_drives.size


def test_gap_counts_follow_a_fast_changing_spacing():
    """A spacing that triples along the row with one pit missing where the spacing is small:
    its double gap is 1.5 times the local median, which the median rule counted as one."""
    spacing = np.linspace(1.7, 5.5, 24)
    positions = np.concatenate([[0.0], np.cumsum(spacing)])
    detected = np.delete(positions, 2)
    steps = _smooth_step_counts(np.diff(detected), 24)
    np.testing.assert_array_equal(steps, [1, 2] + [1] * 21)
    placements = monotone_placements(np.arange(25.0), detected, smooth_spacing=True)
    assert len(placements) == 1
    assert list(placements[0][1]) == [0, 1, -1] + list(range(2, 24))


def test_motion_noise_at_a_quarter_micron_after_a_full_range_excursion():
    """Issue 37: motion noise at d=0.25 um measured 0 trials once the scanner's compensation
    residual plus the drift offset passed the imaged field's margin (the simulator's field
    left the pits out of a thin rescan box)."""
    config = merge(load_config(), {"seed": 23, "drift": {"mean_velocity_y": 1e-9}})
    afm = SimulatedAfm(config)
    afm.move_tip(105e-6, 105e-6, 50e-6)
    afm.move_tip(5e-6, 5e-6, 50e-6)
    afm.hold(1500.0)
    experiment = measure_motion_noise(afm, distances=(0.25e-6, 0.5e-6), trials=8, precision=None)
    for axis in "xy":
        assert [row["trials"] for row in experiment.data[axis]] == [7, 7]


def test_only_one_experiment_and_merge():
    """Rerun one experiment and merge it into an earlier calibration: its fields replaced and
    marked measured by this run, every other field and mark kept."""
    with pytest.raises(ValueError, match="hysteresis_y"):
        checked_experiments(["hysteresis_z"])
    with pytest.raises(ValueError, match="add drift"):
        checked_experiments(["map_errors"])
    previous = Calibration(
        source="earlier",
        line_deflection_mean_deg=9.0,
        motion_noise_slope_x=1e-10,
        measured={"motion_noise_slope_x": "motion_noise, earlier"},
        defaults=["line_deflection_mean_deg", "line_deflection_sigma_deg"],
    )
    config = load_config()
    calibration, report = run_calibration(
        SimulatedAfm(config), only=["line_deflection"], previous=previous
    )
    assert set(report) >= {"line_deflection", "checks"}
    assert "hysteresis_x" not in report
    merged = merge_calibration(previous, calibration, ["line_deflection"])
    assert merged.line_deflection_mean_deg == calibration.line_deflection_mean_deg != 9.0
    assert merged.motion_noise_slope_x == 1e-10
    assert merged.measured["motion_noise_slope_x"] == "motion_noise, earlier"
    assert merged.measured["line_deflection_mean_deg"].startswith("line_deflection, ")
    assert "line_deflection_mean_deg" not in merged.defaults


def test_progress_within_an_experiment():
    """Issue 37: minutes with no progress. Each lane of the motion-noise experiment is
    reported with how many are left and an estimate of the time left."""
    lines = []
    run_calibration(
        SimulatedAfm(load_config()),
        only=["motion_noise"],
        motion_noise={"distances": (0.5e-6, 1e-6), "trials": 8},
        progress=lines.append,
    )
    assert lines[0] == "experiment 1 of 1: motion_noise ..."
    within = [line for line in lines if line.startswith("motion_noise: lane of 8 trials")]
    assert within[-1].startswith("motion_noise: lane of 8 trials 4 of 4, about 0 s left")
    assert lines[-1].startswith("experiment 1 of 1: motion_noise done in ")


def test_cli_reruns_one_experiment_into_an_existing_file(tmp_path):
    """`afm calibrate --only line_deflection --merge earlier.yaml`: the file written keeps the
    earlier fields and marks, replaces the rerun's, and the report holds its fit and the
    checks; a bad experiment name is refused naming the choices."""
    import json
    import subprocess
    import sys

    from afm_core.localization.calibration.model import load_calibration, save_calibration

    earlier = tmp_path / "earlier.yaml"
    save_calibration(
        Calibration(
            source="earlier",
            motion_noise_slope_x=1e-10,
            measured={"motion_noise_slope_x": "motion_noise, earlier"},
            defaults=["line_deflection_mean_deg", "line_deflection_sigma_deg"],
        ),
        earlier,
    )
    afm = [sys.executable, "-m", "afm_bringup.cli", "calibrate"]
    out, report = tmp_path / "out.yaml", tmp_path / "report.json"
    done = subprocess.run(
        afm
        + ["--only", "line_deflection", "--merge", str(earlier), "-o", str(out)]
        + ["--report", str(report)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert "line_deflection: " in done.stdout or "experiment 1 of 1" in done.stdout
    merged = load_calibration(out)
    assert merged.motion_noise_slope_x == 1e-10
    assert merged.measured["motion_noise_slope_x"] == "motion_noise, earlier"
    assert merged.measured["line_deflection_mean_deg"].startswith("line_deflection, ")
    assert merged.defaults == []
    written = json.loads(report.read_text())
    assert "parameters" in written["line_deflection"] and "checks" in written
    readable = report.with_suffix(".md").read_text()
    assert "| line_deflection | measured | mean_deg " in readable
    # the figure of its raw data beside the report, linked from the readable one
    figure = tmp_path / "report_figures" / "line_deflection.png"
    assert figure.read_bytes()[:4] == b"\x89PNG"
    assert "(report_figures/line_deflection.png)" in readable
    refused = subprocess.run(
        afm + ["--only", "hysteresis_z", "-o", str(tmp_path / "x.yaml")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert refused.returncode != 0
    assert "hysteresis_z" in refused.stderr and "hysteresis_y" in refused.stderr
    assert not (tmp_path / "x.yaml").exists()


def test_the_readable_report_lists_failures_and_warnings_first():
    """report_markdown: a failed experiment with its reason, a measured one with its headline
    numbers, and the checks with errors and warnings before the ok ones."""
    from afm_core.localization.calibration.procedure import report_markdown

    summary = {
        "motion_noise": {"failed": "RuntimeError: only 0 trials measured"},
        "creep": {
            "parameters": {
                "time_constants": [0.5, 5.0, 50.0],
                "step_response_25s": [0.016, 0.0165],
                "step_response_25s_sigma": [0.01, 0.0002],
            },
            "data": {},
        },
    }
    summary["checks"] = calibration_checks(summary)
    text = report_markdown(summary)
    assert "| motion_noise | failed | RuntimeError: only 0 trials measured |" in text
    assert "| creep | measured | time_constants [0.5, 5, 50]" in text
    levels = [line.split("**")[1] for line in text.splitlines() if line.startswith("- **")]
    assert levels[0] == "error" and levels[1] == "warning" and levels[-1] == "ok"
    assert "--only creep" in text and "--only motion_noise" in text
