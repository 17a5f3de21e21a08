"""Creep on tubes the default simulator does not have (an outside checker's probes), against
the simulator's configuration:

- one creep time constant (10 s, 2 % of the step): the three-term fit put one term at the
  shortest bound with a fraction of 0 and two on 10 s, whose fractions' linearised errors are
  unbounded; the step response, right to 0.3 %, was stated +- 7 % of the step and flagged
  "cannot be trusted". fit_creep_terms drops the terms no axis tells from 0.
- two time constants (2 s and 20 s): the fit keeps two terms and each comes out as set.
- one run whose rescan loses its pits (a strong drift, here forced): the other runs are
  fitted, and a check says which run was left out; before, the whole experiment failed.
"""

import numpy as np
import pytest

from afm_core.localization.calibration import creep as creep_module
from afm_core.localization.calibration.creep import creep_step_response, measure_creep
from afm_core.localization.calibration.fit_checks import calibration_checks
from afm_core.sim.config import load_config, merge
from afm_core.sim.instrument import SimulatedAfm


def _tube(taus, fractions, seed=3):
    return merge(
        load_config(),
        {"seed": seed, "scanner": {"creep_time_constants": taus, "creep_fractions": fractions}},
    )


def _true_response(config) -> float:
    s = config.scanner
    return float(creep_step_response(s.creep_time_constants, s.creep_fractions, [25.0])[0])


def _checks(p):
    return calibration_checks({"creep": {"parameters": p}})


@pytest.mark.parametrize(
    "taus, fractions",
    [([10.0], [0.02]), ([2.0, 20.0], [0.012, 0.012])],
)
def test_creep_with_fewer_time_constants_is_fitted_and_trusted(taus, fractions):
    config = _tube(taus, fractions)
    p = measure_creep(SimulatedAfm(config)).parameters
    truth = _true_response(config)
    for axis, response in zip("xy", p["step_response_25s"]):
        assert response == pytest.approx(truth, rel=0.05), axis
    precision = {c["parameter"]: c["level"] for c in _checks(p)}
    assert precision["step_response_25s_x"] == "ok"
    assert precision["step_response_25s_y"] == "ok"
    # as many terms as the tube has, each near its time constant and fraction
    assert len(p["time_constants"]) == len(taus)
    assert p["time_constants"] == pytest.approx(taus, rel=0.10)
    for axis in "xy":
        assert p[f"fractions_{axis}"] == pytest.approx(fractions, rel=0.10)
    assert len(p["terms_dropped"]) == 3 - len(taus)


def test_a_run_that_loses_its_pits_leaves_the_others_fitted(monkeypatch):
    """The second x run's rescan is made to fail after it was punched (as a strong drift
    did: 2 nm/s carried a run's pits out of its rescan box); the other runs are fitted and
    the step response holds against the simulator's creep."""
    config = _tube([0.5, 5.0, 50.0], [0.008, 0.006, 0.006])
    real_run, calls = creep_module._creep_run, []

    def failing_second_run(*args, **kwargs):
        result = real_run(*args, **kwargs)
        calls.append(kwargs["label"])
        if len(calls) == 2:
            raise RuntimeError(f"{kwargs['label']}: only 3 of 40 pits found in the rescan")
        return result

    monkeypatch.setattr(creep_module, "_creep_run", failing_second_run)
    p = measure_creep(SimulatedAfm(config)).parameters
    assert p["runs_failed"] == ["creep (x, run 1): only 3 of 40 pits found in the rescan"]
    assert p["runs_fitted"] == len(calls) - 1
    truth = _true_response(config)
    assert np.allclose(p["step_response_25s"], truth, rtol=0.10)
    warned = [c for c in _checks(p) if c["parameter"] == "runs" and c["level"] == "warning"]
    assert warned and "creep (x, run 1)" in warned[0]["message"]


def test_no_run_of_an_axis_measured_is_a_clear_failure(monkeypatch):
    def lost(*args, **kwargs):
        raise RuntimeError(f"{kwargs['label']}: only 0 of 40 pits found in the rescan")

    monkeypatch.setattr(creep_module, "_creep_run", lost)
    with pytest.raises(RuntimeError, match="no run of axis x, y measured"):
        measure_creep(SimulatedAfm(load_config()), repeats=1)


def test_a_strong_drift_does_not_carry_the_pits_out_of_the_rescan():
    """At 2 nm/s (20x the book's y drift) a run's pits drift ~0.6 um past the step's end and
    across the lane while the run lasts: the first x run's rescan, 0.5 um past the end, found
    13 of its 40 pits. The box now grows on the side the found pits crowd."""
    config = merge(
        load_config(),
        {
            "seed": 3,
            "drift": {
                "mean_velocity_x": 2e-9,
                "mean_velocity_y": -2e-9,
                "sigma_velocity_x": 0.5e-9,
                "sigma_velocity_y": 0.5e-9,
            },
        },
    )
    data = measure_creep(SimulatedAfm(config), repeats=1).data
    for axis in "xy":
        (run,) = data[axis]
        assert run["pits_found"] >= 0.9 * run["pits_punched"], (axis, run["pits_found"])
