"""Another lab's instrument configured: the simulator config's two ranges, the controller's
loop width checked at load, `afm calibrate`'s summary when experiments fail, and
image_frame_matrix on a scanner smaller than the default one."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from afm_core.evaluation import APPROACH_BEYOND, image_frame_matrix
from afm_core.sim.config import load_config, merge
from afm_core.sim.instrument import SimulatedAfm

SMALL = 10e-6  # m, a small-range scanner


# -- 1: limits.range_* and scanner.range_* are one travel -------------------------------------
@pytest.mark.parametrize("given", ["limits", "scanner"])
def test_setting_one_range_sets_the_other_and_the_instrument_stays_within_it(given):
    config = merge(load_config(), {given: {"range_x": SMALL, "range_y": 2 * SMALL}})
    for name in ("range_x", "range_y"):
        assert getattr(config.limits, name) == getattr(config.scanner, name)
    assert (config.limits.range_x, config.limits.range_y) == (SMALL, 2 * SMALL)
    sim = SimulatedAfm(config)
    x, y = sim.commanded_position()  # at power-on
    assert 0.0 <= x <= config.limits.range_x and 0.0 <= y <= config.limits.range_y
    assert np.allclose(sim.truth()["tip_position"], (x, y), atol=1e-12)
    # a target past the scanner's end is refused, not reported reached at the clamp
    with pytest.raises(ValueError, match="outside the scanner range"):
        sim.move_tip(3 * config.scanner.range_x, y, 50e-6)


def _values(limit, travel, name="range_x"):
    return (f"limits.{name}={limit:.4e} m", f"scanner.{name}={travel:.4e} m")


def test_ranges_that_disagree_are_refused_naming_both_keys(tmp_path):
    limit, travel = SMALL, 2 * SMALL
    with pytest.raises(ValueError) as refused:
        merge(load_config(), {"limits": {"range_x": limit}, "scanner": {"range_x": travel}})
    for text in _values(limit, travel):
        assert text in str(refused.value), refused.value
    assert "change limits.range_x" in str(refused.value)
    path = tmp_path / "mismatch.yaml"
    path.write_text(yaml.safe_dump({"limits": {"range_y": limit}, "scanner": {"range_y": travel}}))
    with pytest.raises(ValueError) as refused:
        load_config(path)
    for text in (str(path), *_values(limit, travel, "range_y")):
        assert text in str(refused.value), refused.value


def test_a_user_file_with_one_range_loads_with_both_and_leaves_the_mapping_alone(tmp_path):
    path = tmp_path / "small.yaml"
    path.write_text(yaml.safe_dump({"scanner": {"range_x": SMALL, "range_y": SMALL}}))
    config = load_config(path)
    assert (config.limits.range_x, config.limits.range_y) == (SMALL, SMALL)
    overrides = {"limits": {"range_x": SMALL}}
    merge(load_config(), overrides)
    assert overrides == {"limits": {"range_x": SMALL}}


# -- 3: the controller's loop width, checked at load ----------------------------------------
def test_a_controller_loop_too_wide_is_refused_at_load_naming_both_keys(tmp_path):
    fraction, error = 0.30, 0.3
    path = tmp_path / "misfit.yaml"
    path.write_text(
        yaml.safe_dump(
            {"scanner": {"hysteresis_fraction": fraction}, "controller": {"model_error": error}}
        )
    )
    with pytest.raises(ValueError) as refused:
        load_config(path)
    message = str(refused.value)
    for text in (
        f"scanner.hysteresis_fraction={fraction}",
        f"controller.model_error={error}",
        f"{fraction * (1 + error):.4g}",
        "1/3",
    ):
        assert text in message, message
    # just inside the limit: loads and the instrument builds
    inside = (1.0 / 3.0) / fraction - 1.0 - 1e-3
    SimulatedAfm(
        merge(
            load_config(),
            {"scanner": {"hysteresis_fraction": fraction}, "controller": {"model_error": inside}},
        )
    )


def test_without_compensation_the_controller_model_is_not_checked():
    config = merge(
        load_config(),
        {
            "scanner": {"hysteresis_fraction": 0.30},
            "controller": {"model_error": 0.3, "hysteresis_compensation": False},
        },
    )
    SimulatedAfm(config)


# -- 2: afm calibrate's summary ----------------------------------------------------------------
def test_calibrate_never_says_every_check_passed_when_experiments_failed(tmp_path, capsys):
    from afm_bringup.cli import main
    from afm_core.localization.calibration.procedure import checked_experiments

    # a 10 um scanner: the experiments' fixed geometry does not fit, every one fails
    config = tmp_path / "small.yaml"
    centre = SMALL / 2
    config.write_text(
        yaml.safe_dump(
            {
                "limits": {"range_x": SMALL, "range_y": SMALL},
                "sample": {"spheres": [{"x": centre, "y": centre, "radius": 1e-7}]},
            }
        )
    )
    report = tmp_path / "fits.json"
    status = main(
        [
            "calibrate",
            "-o",
            str(tmp_path / "cal.yaml"),
            "--sim-config",
            str(config),
            "--pairs",
            "3",
            "--report",
            str(report),
        ]
    )
    out = capsys.readouterr().out
    assert status == 1
    errors = [c for c in json.loads(report.read_text())["checks"] if c["level"] == "error"]
    assert errors
    assert "every fit check passed" not in out, out
    run = len(checked_experiments(None))
    assert f"{len({c['experiment'] for c in errors})} of {run} experiments failed" in out, out


# -- 4: image_frame_matrix within the config's own range -------------------------------------
def test_image_frame_matrix_near_the_corner_of_a_smaller_scanner():
    span = 100e-6
    config = merge(load_config(), {"limits": {"range_x": span, "range_y": span}})
    at = np.array([span, span]) - 1.2e-6  # closer to the corner than the approach overshoot
    assert (at + APPROACH_BEYOND > span).all()
    matrix = image_frame_matrix(config, at=tuple(at))
    # the truth: the same quiet instrument, approached from beyond within its own range
    quiet = merge(
        config,
        {
            "drift": {"enabled": False},
            "sample": {"spheres": [], "rods": [], "electrodes": [], "random_spheres": 0},
            "scanner": {"creep_enabled": False, "positioning_noise_enabled": False},
        },
    )
    step = 1e-6
    for axis in range(2):
        sim = SimulatedAfm(quiet)
        beyond = np.minimum(at + APPROACH_BEYOND, (config.limits.range_x, config.limits.range_y))
        sim.move_tip(*beyond, 1e-5)
        sim.move_tip(*at, 1e-5)
        before = np.array(sim.truth()["tip_position"])
        target = np.array(sim.commanded_position()) + step * np.eye(2)[axis]
        sim.move_tip(*target, 1e-5)
        moved = (np.array(sim.truth()["tip_position"]) - before) / step
        assert np.allclose(matrix[:, axis], moved, atol=1e-9), (matrix, moved)


def test_an_empty_or_non_mapping_config_file_is_refused_naming_the_file(tmp_path):
    """An empty file given on purpose is a wrong or unsaved file: it used to load silently as
    the defaults, so a lab's model was never the one it meant."""
    empty = tmp_path / "empty.yaml"
    empty.write_text("# nothing yet\n")
    with pytest.raises(ValueError, match="empty.yaml' is empty: give the keys to change"):
        load_config(empty)
    listed = tmp_path / "list.yaml"
    listed.write_text("- seed: 3\n")
    with pytest.raises(ValueError, match="list.yaml': expected a mapping of keys, got a list"):
        load_config(listed)
