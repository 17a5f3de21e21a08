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
    return dataclass_from_dict(SimConfig, data or {}, "")


def load_config(path: str | Path | None = None) -> SimConfig:
    """Defaults from default_config.yaml, overridden by the user's file (any subset of keys)."""
    config = config_from_dict(load_yaml(DEFAULT_CONFIG_FILE.read_text()) or {})
    if path is None:
        return config
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"simulator config {str(path)!r} does not exist")
    try:
        user = load_yaml(path.read_text()) or {}
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise ValueError(f"simulator config {str(path)!r} is not valid YAML: {exc}") from exc
    except OSError as exc:
        raise ValueError(f"simulator config {str(path)!r}: cannot be read ({exc})") from exc
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
    merged = _deep_update(dataclasses.asdict(config), overrides, "")
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
