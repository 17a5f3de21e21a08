"""One configuration for the whole simulated instrument, loadable from one YAML file.

Every effect is switchable and parameterised here; defaults come from the book (see
default_config.yaml, which documents each value). Unknown keys and wrong types are errors
that name the key, so a typo never silently leaves an effect at its default.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from afm_core.instrument import ScannerLimits
from afm_core.physics.contact import ContactParams
from afm_core.pzt import ScannerParams
from afm_core.sim.drift import DriftParams
from afm_core.sim.generic_terms import parse_generic_terms
from afm_core.sim.tip import TipParams
from afm_core.yaml_files import load_yaml

DEFAULT_CONFIG_FILE = Path(__file__).with_name("default_config.yaml")


@dataclass
class NoiseParams:
    """The sensors: noise, the z feedback's lag, the z sensor's calibration and latency."""

    height_white_sigma: float = 0.3e-9  # m, white sensor noise per pixel
    height_flicker_sigma: float = 0.2e-9  # m, 1/f noise over the acquisition sequence
    deflection_sigma: float = 0.05e-9  # m, deflection signal noise
    feedback_time_constant: float = 2e-4  # s, z-feedback lag: deflection error ~ lag * dh/dt
    # A miscalibrated z sensor scales the z piezo signal it reports: every measured height
    # (objects, roughness, bow; about the mean substrate plane, height 0) is gain x the true one.
    height_gain: float = 1.0  # dimensionless, 1 = calibrated
    # Filters and the acquisition chain delay the measured signals (height, deflection,
    # force-trace deflection and torsion) against the commanded positions: the value reported
    # at time t is the one at t - latency, so an image shifts by scan speed x latency.
    sensor_latency: float = 0.0  # s

    def __post_init__(self):
        for name in (
            "height_white_sigma",
            "height_flicker_sigma",
            "deflection_sigma",
            "feedback_time_constant",
            "sensor_latency",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"noise.{name}={value}: must be finite and >= 0")
        if not (math.isfinite(self.height_gain) and 0 < self.height_gain <= 10):
            raise ValueError(f"noise.height_gain={self.height_gain}: must be within (0, 10]")
        if self.sensor_latency > 1.0:
            raise ValueError(f"noise.sensor_latency={self.sensor_latency}: must be <= 1 s")


@dataclass
class SampleParams:
    roughness_sigma: float = 0.3e-9  # m rms of the substrate
    roughness_correlation: float = 20e-9  # m
    # Near the scanner's centre (55 um, 55 um), where the tip rests at power-on.
    spheres: list = field(
        default_factory=lambda: [
            {"x": 55.0e-6, "y": 55.0e-6, "radius": 100e-9},
            {"x": 55.6e-6, "y": 55.3e-6, "radius": 100e-9},
            {"x": 54.6e-6, "y": 55.7e-6, "radius": 100e-9},
        ]
    )
    random_spheres: int = 0  # extra spheres scattered over random_area
    random_area: list = field(
        default_factory=lambda: [52e-6, 52e-6, 6e-6, 6e-6]
    )  # x0, y0, width, height (m)
    radius_mean: float = 100e-9  # m, polystyrene spheres (book: ~100 nm)
    radius_sigma: float = 5e-9  # m
    rods: list = field(default_factory=list)  # {x, y, angle (rad), length, radius, kind: rod|tube}
    electrodes: list = field(default_factory=list)  # {x0, y0, x1, y1, thickness}


@dataclass
class ControllerParams:
    """The AFM controller's own hysteresis feed-forward: it inverts a PI model of the
    scanner, as calibrated. The calibration is never exact, so a residual remains."""

    hysteresis_compensation: bool = True
    model_error: float = 0.1  # relative error of the calibrated loop width (0: perfect)
    asymmetry_error: float = 0.0  # its calibrated asymmetry is the scanner's minus this (0: exact)


@dataclass
class IndentParams:
    sample_stiffness: float = 50.0  # N/m, pit depth = force / stiffness
    approach_time: float = 0.05  # s
    retract_time: float = 0.05  # s


@dataclass
class SimConfig:
    seed: int = 0
    limits: ScannerLimits = field(default_factory=ScannerLimits)
    scanner: ScannerParams = field(default_factory=ScannerParams)
    controller: ControllerParams = field(default_factory=ControllerParams)
    drift: DriftParams = field(default_factory=DriftParams)
    tip: TipParams = field(default_factory=TipParams)
    contact: ContactParams = field(default_factory=ContactParams)
    noise: NoiseParams = field(default_factory=NoiseParams)
    sample: SampleParams = field(default_factory=SampleParams)
    indentation: IndentParams = field(default_factory=IndentParams)
    # generic offsets a sim-to-real diagnosis fitted where no library term explains
    # (sim/generic_terms.py)
    generic_terms: list = field(default_factory=list)

    def __post_init__(self):
        parse_generic_terms(self.generic_terms)  # a bad entry is an error naming its field
        check_ranges(self.limits, self.scanner)
        check_controller_model(self.scanner, self.controller)


RANGE_AXES = ("range_x", "range_y")


def check_ranges(limits: ScannerLimits, scanner: ScannerParams) -> None:
    """ValueError naming both keys when limits.range_* and scanner.range_* disagree.

    They are one travel: `limits` is what every request is checked against ([0, range]),
    `scanner` what the piezo model spans (centred at range/2, where the tip rests at power-on).
    A scanner shorter than the limits reports moves past its end as reached (its amplifier
    clamps them); limits shorter than the scanner put the power-on position outside them. A
    user file or `merge` that sets only one of the two sets the other to it (`_follow_ranges`).
    """
    for name in RANGE_AXES:
        limit, travel = getattr(limits, name), getattr(scanner, name)
        if not math.isclose(limit, travel, rel_tol=1e-9, abs_tol=0.0):
            raise ValueError(
                f"limits.{name}={limit:.4e} m and scanner.{name}={travel:.4e} m disagree: both "
                "are the scanner's travel (limits checks every request against [0, range], "
                "scanner models the piezo over it and rests at its centre at power-on); change "
                f"limits.{name} to {travel:.4e} m or scanner.{name} to {limit:.4e} m, whichever "
                "is not the scanner's real travel, or give only one of them: the other follows it"
            )


def check_controller_model(scanner: ScannerParams, controller: ControllerParams) -> None:
    """ValueError naming the keys when the controller's hysteresis model (the scanner's loop
    width x (1 + controller.model_error), its asymmetry minus controller.asymmetry_error) is not
    one the simulator can build (PrandtlIshlinskii.from_fraction): checked at load, so a
    config never fails later, when the instrument is built, on a value nobody wrote."""
    if not (
        controller.hysteresis_compensation
        and scanner.hysteresis_enabled
        and scanner.hysteresis_fraction > 0
    ):
        return  # no feed-forward: the controller has no model
    error = controller.model_error
    if not (math.isfinite(error) and error > -1.0):
        raise ValueError(
            f"controller.model_error={error}: must be finite and > -1 "
            "(relative error of the calibrated loop width)"
        )
    fraction = scanner.hysteresis_fraction * (1.0 + error)
    if not fraction < 1.0 / 3.0:
        raise ValueError(
            f"scanner.hysteresis_fraction={scanner.hysteresis_fraction} with "
            f"controller.model_error={error}: the controller's calibrated loop width, "
            f"hysteresis_fraction x (1 + model_error) = {fraction:.4g} of the range, must be "
            "below 1/3 (the widest loop the simulator's hysteresis model takes); lower "
            f"controller.model_error below {1.0 / (3.0 * scanner.hysteresis_fraction) - 1.0:.4g} "
            f"or scanner.hysteresis_fraction below {1.0 / (3.0 * (1.0 + error)):.4g}"
        )
    asymmetry = scanner.hysteresis_asymmetry - controller.asymmetry_error
    if not (math.isfinite(asymmetry) and asymmetry * asymmetry < 2.0 / 3.0):
        raise ValueError(
            f"controller.asymmetry_error={controller.asymmetry_error} with "
            f"scanner.hysteresis_asymmetry={scanner.hysteresis_asymmetry}: the controller's "
            f"asymmetry (scanner.hysteresis_asymmetry minus it) is {asymmetry}; need a finite "
            "value with square < 2/3"
        )


def _follow_ranges(data):
    """`data` (a user's nested mapping) with limits.range_x/y and scanner.range_x/y made to
    follow each other: where only one of a pair is given, the other is set to it (a copy; the
    caller's mapping is left alone). Both given and different stays an error (check_ranges)."""
    if not isinstance(data, dict):
        return data
    limits, scanner = data.get("limits", {}), data.get("scanner", {})
    if not (isinstance(limits, dict) and isinstance(scanner, dict)):
        return data  # the wrong type is reported, naming the key, by dataclass_from_dict
    limits, scanner = dict(limits), dict(scanner)
    for name in RANGE_AXES:
        # a value of the wrong type is not copied: its error names the key the user wrote
        if name in limits and name not in scanner and _is_number(limits[name]):
            scanner[name] = limits[name]
        elif name in scanner and name not in limits and _is_number(scanner[name]):
            limits[name] = scanner[name]
    out = dict(data)
    if limits:
        out["limits"] = limits
    if scanner:
        out["scanner"] = scanner
    return out


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def dataclass_from_dict(cls, data, path: str = ""):
    """An instance of dataclass `cls` from a nested mapping; unknown keys and wrong types are
    errors naming the key (path is the prefix used in those messages)."""
    if not isinstance(data, dict):
        raise ValueError(f"{path or 'config'}: expected a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"{path or 'config'}: unknown key(s) {unknown}; known: {sorted(names)}")
    values = {}
    for key, value in data.items():
        hint = hints[key]
        where = f"{path}.{key}" if path else key
        if dataclasses.is_dataclass(hint):
            values[key] = dataclass_from_dict(hint, value, where)
        else:
            values[key] = _coerce(hint, value, where)
    return cls(**values)


def _coerce(hint, value, where):
    origin = typing.get_origin(hint) or hint
    if origin is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{where}={value!r}: expected true or false")
        return value
    if origin is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{where}={value!r}: expected an integer")
        return value
    if origin is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{where}={value!r}: expected a number (SI units)")
        return float(value)
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"{where}={value!r}: expected a list")
        item_hints = typing.get_args(hint)
        if origin is list and len(item_hints) == 1:
            # a list's entries are checked as its own type is: '0.008' inside a list of numbers
            # is as wrong as on its own
            return [_coerce(item_hints[0], item, f"{where}[{i}]") for i, item in enumerate(value)]
        return origin(value)
    return value


def config_from_dict(data: dict) -> SimConfig:
    return dataclass_from_dict(SimConfig, _follow_ranges(data or {}), "")


def load_config(path: str | Path | None = None) -> SimConfig:
    """Defaults from default_config.yaml, overridden by the user's file (any subset of keys)."""
    config = config_from_dict(load_yaml(DEFAULT_CONFIG_FILE.read_text()) or {})
    if path is None:
        return config
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"simulator config {str(path)!r} does not exist")
    try:
        user = load_yaml(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise ValueError(f"simulator config {str(path)!r} is not valid YAML: {exc}") from exc
    except OSError as exc:
        raise ValueError(f"simulator config {str(path)!r}: cannot be read ({exc})") from exc
    # a file named on purpose that holds nothing is a mistake (a wrong or unsaved file), not
    # a wish for the defaults, which leaving the option out gives
    if user is None:
        raise ValueError(
            f"simulator config {str(path)!r} is empty: give the keys to change (a subset of "
            "default_config.yaml's), or no file for the defaults"
        )
    if not isinstance(user, dict):
        raise ValueError(
            f"simulator config {str(path)!r}: expected a mapping of keys, got a "
            f"{type(user).__name__}"
        )
    try:
        return merge(config, user)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"simulator config {str(path)!r}: {exc}") from exc


def check_config_file(path: str) -> str:
    """A parameter's rule for a simulator configuration file: "" (the defaults), or a file that
    loads (ValueError saying why not), so a node refuses a missing or broken model at start."""
    if path:
        load_config(path)
    return path


def merge(config: SimConfig, overrides: dict) -> SimConfig:
    """A new config with `overrides` (nested dict, any subset of keys) applied."""
    merged = _deep_update(dataclasses.asdict(config), _follow_ranges(overrides), "")
    return config_from_dict(merged)


def _deep_update(base: dict, overrides: dict, path: str) -> dict:
    if not isinstance(overrides, dict):
        raise ValueError(f"{path or 'config'}: expected a mapping")
    out = dict(base)
    for key, value in overrides.items():
        where = f"{path}.{key}" if path else key
        if key not in base:
            raise ValueError(f"{path or 'config'}: unknown key {key!r}; known: {sorted(base)}")
        out[key] = (
            _deep_update(base[key], value, where)
            if isinstance(base[key], dict) and isinstance(value, dict)
            else value
        )
    return out


def dump_config(config: SimConfig) -> str:
    return yaml.safe_dump(dataclasses.asdict(config), sort_keys=False)
