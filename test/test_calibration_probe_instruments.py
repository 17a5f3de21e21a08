"""Hysteresis and rescans on simulated instruments the repository's tests did not have (an
outside checker's probes), against the simulator's configuration:

- 512 pixels per line (a common controller): every rescan-based experiment refused its
  rescan ("would need 665 pixels"), and the hysteresis experiment cycled for half an hour,
  found 2 of 66 pits in lines 194 nm apart and advised a finer pixel, which cannot fit. Now
  the rescans take the finest pixel the instrument has (creep within 10 % of the truth), and
  the hysteresis experiment refuses before its cycle with what it needs (GeometryError).
- a cycle set small (--set hysteresis.cycle_fraction): the loop fraction extrapolated from
  it read 0.038 against 0.12 with its precision check "ok"; now a warning.
- a loop the model cannot follow (0.30 of the range on a cycle of 0.7): residual 498 nm,
  reported "ok"; now the fit's residual is checked against the motion noise of a move
  across the cycle, which a right fit stays below (the default instrument: ok).
"""

import pytest

from afm_core.localization.calibration.creep import creep_step_response, measure_creep
from afm_core.localization.calibration.experiment import GeometryError
from afm_core.localization.calibration.fit_checks import calibration_checks
from afm_core.localization.calibration.hysteresis import measure_hysteresis
from afm_core.sim.config import load_config, merge
from afm_core.sim.instrument import SimulatedAfm


def _config(seed, **sections):
    return merge(load_config(), {"seed": seed, **sections})


def _hysteresis(config, axis=0, **options):
    s = config.scanner
    creep = (list(s.creep_time_constants), list(s.creep_fractions))
    return measure_hysteresis(SimulatedAfm(config), axis, creep=creep, **options)


def _checks(config, experiment, axis="x"):
    """The checks of a run of this hysteresis fit, with the simulator's motion noise standing
    in for the motion-noise experiment's (it comes within 10 % of it)."""
    s = config.scanner
    noise = {
        "pooled_slope": s.positioning_noise_slope,
        "pooled_offset": s.positioning_noise_offset,
    }
    return calibration_checks(
        {
            f"hysteresis_{axis}": {"parameters": experiment.parameters, "data": experiment.data},
            "motion_noise": {"parameters": noise},
        }
    )


def _level(checks, parameter):
    return [c["level"] for c in checks if c["parameter"] == parameter]


def test_an_instrument_of_512_pixels_measures_what_its_lines_allow():
    config = _config(5, limits={"max_pixels": 512})
    p = measure_creep(SimulatedAfm(config)).parameters
    s = config.scanner
    truth = creep_step_response(s.creep_time_constants, s.creep_fractions, [25.0])[0]
    assert p["step_response_25s"] == pytest.approx([truth, truth], rel=0.10)
    afm = SimulatedAfm(config)
    with pytest.raises(GeometryError, match="max_pixels 512") as refused:
        measure_hysteresis(afm, 0)
    assert "pixels per line" in str(refused.value)
    # refused before the cycle: only the probe pit was punched (seconds, not half an hour)
    assert afm.time < 60.0


def test_a_cycle_smaller_than_checked_flags_the_extrapolated_loop():
    config = _config(5)
    experiment = _hysteresis(config, cycle_fraction=0.33)
    truth = config.scanner.hysteresis_fraction
    # the case still tests the flag: the extrapolated loop is far from the simulator's
    assert abs(experiment.parameters["loop_fraction"] / truth - 1) > 0.10
    flagged = [
        c
        for c in _checks(config, experiment)
        if c["parameter"] == "loop_fraction" and c["level"] == "warning"
    ]
    assert flagged and "extrapolated from a cycle of 0.33" in flagged[0]["message"]


def test_a_loop_the_model_cannot_follow_is_said_not_to_hold():
    wide = _config(3, scanner={"hysteresis_fraction": 0.30}, controller={"model_error": 0.05})
    experiment = _hysteresis(wide, cycle_fraction=0.7)
    assert _level(_checks(wide, experiment), "rms_residual") == ["warning"]
    # the same check on the default instrument, whose loop the fit recovers, holds
    default = _config(3)
    experiment = _hysteresis(default)
    truth = default.scanner.hysteresis_fraction
    assert experiment.parameters["loop_fraction"] == pytest.approx(truth, rel=0.03)
    assert _level(_checks(default, experiment), "rms_residual") == ["ok"]
