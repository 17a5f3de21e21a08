"""The localizer's calibration: what the experiments of book 7.2.2 measured on this
instrument, in one YAML file (SI units). `afm_core.localization.calibration.procedure` runs
the experiments and writes it; the motion model, the observation model and the planner read
it.

Defaults are the book's figures, for an instrument nobody has calibrated yet.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from afm_core.instrument import ScannerLimits
from afm_core.localization.motion_noise import MotionNoise
from afm_core.sim.config import dataclass_from_dict
from afm_core.yaml_files import load_yaml

_LONGEST = ScannerLimits().range_x  # m


@dataclass
class HysteresisFit:
    """Prandtl-Ishlinskii model of one axis driven open loop (no feed-forward), about the
    range centre: y - centre = H[x - centre] (afm_core.pzt.PrandtlIshlinskii arguments)."""

    thresholds: list[float] = field(default_factory=list)  # m
    weights: list[float] = field(default_factory=list)  # 1
    polynomial: list[float] = field(default_factory=lambda: [1.0, 0.0, 0.0])
    loop_fraction: float = 0.0  # loop width / range on a full-range cycle, from the fit
    asymmetry: float = 0.0  # ascending/descending branch asymmetry, from the fit


@dataclass
class Calibration:
    source: str = "book defaults"  # what produced it, and when
    # true displacement per commanded displacement in normal (compensated) operation:
    # gain, x/y coupling and scan-line rotation together; rows: true x, true y.
    scanner_matrix: list[list[float]] = field(default_factory=lambda: [[1.0, 0.0], [0.0, 1.0]])
    # m: the longest commanded move the scanner matrix was measured over (its experiment's pit
    # grid). Its departure from the identity is the feed-forward's residual hysteresis of
    # short moves, which is bounded (a hysteresis offset saturates); the motion model lets it
    # grow over at most this much of a move instead of extrapolating it to long moves.
    scanner_matrix_span: float = 4.0e-6
    # true displacement per commanded displacement between positions on the images' own
    # hysteresis branch (a place reached through reversals, as the raster and the closed
    # loop's chains of scan lines reach it), in this calibration's frame: the identity for a
    # calibration measured in the images (the frame the maps live in); a metric one's is the
    # images' scale. The scanner matrix is what a short move after a reversal adds to that.
    image_matrix: list[list[float]] = field(default_factory=lambda: [[1.0, 0.0], [0.0, 1.0]])
    # m per unit of this calibration's lateral frame: the images' scale against the sample,
    # which the calibration's own experiments cannot see (it is common to every image) and a
    # grating measures; 1: the commanded frame taken as metres. A length measured in metres
    # (a particle's radius from its height, the tip's radius) is 1/lateral_scale of it in the
    # maps' frame: the push planners' contact distance
    lateral_scale: float = 1.0
    hysteresis_x: HysteresisFit = field(default_factory=HysteresisFit)
    hysteresis_y: HysteresisFit = field(default_factory=HysteresisFit)
    creep_time_constants: list[float] = field(default_factory=list)  # s
    creep_fractions_x: list[float] = field(
        default_factory=list
    )  # of a commanded step, per time constant
    creep_fractions_y: list[float] = field(default_factory=list)
    motion_noise_slope_x: float = (
        0.0701e-9  # m^2 per m moved along x (Fig. 7.20b a = 0.0701 nm^2/nm)
    )
    motion_noise_slope_y: float = 0.0701e-9  # m^2 per m moved along y
    motion_noise_cross_slope: float = 0.00701e-9  # m^2 per m moved along the other axis
    motion_noise_offset: float = 0.4345e-18  # m^2 per move (b = 0.4345 nm^2)
    drift_mean_velocity: list[float] = field(
        default_factory=lambda: [-4.0e-12, 9.9e-11]
    )  # m/s (Fig. 7.9)
    drift_sigma_velocity: list[float] = field(default_factory=lambda: [2.7e-11, 2.09e-10])  # m/s
    map_sigma: list[float] = field(
        default_factory=lambda: [5.0e-9, 4.5e-9]
    )  # m, x / y (Fig. 7.10)
    scan_region_sigma: float = 4.7e-9  # m (Fig. 7.11)
    line_deflection_mean_deg: float = 0.746  # deg (Fig. 7.12)
    line_deflection_sigma_deg: float = 0.393  # deg
    # the fields above that hold the book's defaults, not a measurement (an experiment that
    # could not measure leaves its fields at the defaults; run_calibration lists them here)
    defaults: list[str] = field(default_factory=list)
    # the fields above that were measured: {field: "experiment, UTC time"} (run_calibration;
    # a merge keeps each field's own entry, so a file says which run measured what)
    measured: dict[str, str] = field(default_factory=dict)

    def __post_init__(self):
        self.validate()

    def validate(self) -> None:
        for name in ("scanner_matrix", "image_matrix"):
            matrix = getattr(self, name)
            if (
                len(matrix) != 2
                or any(len(row) != 2 for row in matrix)
                or not all(math.isfinite(v) for row in matrix for v in row)
                or abs(np.linalg.det(np.asarray(matrix, float))) < 1e-6
            ):
                raise ValueError(
                    f"calibration {name}={matrix}: need a finite, invertible 2x2 matrix"
                )
        if not (math.isfinite(self.lateral_scale) and 0.5 <= self.lateral_scale <= 2.0):
            raise ValueError(
                f"calibration lateral_scale={self.lateral_scale}: need a value in [0.5, 2] "
                "(m per unit of the maps' frame)"
            )
        if not (math.isfinite(self.scanner_matrix_span) and self.scanner_matrix_span > 0):
            raise ValueError(
                f"calibration scanner_matrix_span={self.scanner_matrix_span}: need a value > 0 (m)"
            )
        if len(self.creep_fractions_x) != len(self.creep_time_constants) or len(
            self.creep_fractions_y
        ) != len(self.creep_time_constants):
            raise ValueError(
                "calibration creep_fractions_x/_y: need one value per creep_time_constants entry"
            )
        if not all(math.isfinite(t) and t > 0 for t in self.creep_time_constants):
            raise ValueError(
                f"calibration creep_time_constants={self.creep_time_constants}: "
                "need values > 0 (s)"
            )
        for name in ("creep_fractions_x", "creep_fractions_y"):
            fractions = getattr(self, name)
            # fractions of a commanded step that arrive late: the step's own direction, and
            # together less than the step (the fit bounds each to [0, 0.5])
            if not all(math.isfinite(f) and 0 <= f < 1 for f in fractions) or sum(fractions) >= 1:
                raise ValueError(
                    f"calibration {name}={fractions}: need values in [0, 1) with a sum < 1 "
                    "(fractions of a commanded step)"
                )
        for name in ("drift_mean_velocity", "drift_sigma_velocity", "map_sigma"):
            value = getattr(self, name)
            if len(value) != 2 or not all(math.isfinite(v) for v in value):
                raise ValueError(f"calibration {name}={value}: need two finite values (x, y)")
        if min(self.drift_sigma_velocity) < 0:
            raise ValueError(
                f"calibration drift_sigma_velocity={self.drift_sigma_velocity}: "
                "need values >= 0 (m/s)"
            )
        # standard deviations: >= 0, and a length no scanner spans is a unit slip (4.7 for
        # 4.7 nm), not a measurement
        for name, values, unit, top in (
            ("map_sigma", self.map_sigma, "m", _LONGEST),
            ("scan_region_sigma", [self.scan_region_sigma], "m", _LONGEST),
            ("line_deflection_sigma_deg", [self.line_deflection_sigma_deg], "deg", 90.0),
        ):
            if not all(math.isfinite(v) and 0 <= v <= top for v in values):
                raise ValueError(
                    f"calibration {name}={getattr(self, name)}: need values in [0, {top:g}] "
                    f"({unit})"
                )
        if not (
            math.isfinite(self.line_deflection_mean_deg)
            and abs(self.line_deflection_mean_deg) < 90
        ):
            raise ValueError(
                f"calibration line_deflection_mean_deg={self.line_deflection_mean_deg}: need a "
                "finite angle within (-90, 90) deg"
            )
        for name in ("hysteresis_x", "hysteresis_y"):
            fit = getattr(self, name)
            if len(fit.thresholds) != len(fit.weights) or len(fit.polynomial) != 3:
                raise ValueError(
                    f"calibration {name}: need one weight per threshold ({len(fit.thresholds)} "
                    f"thresholds, {len(fit.weights)} weights) and 3 polynomial coefficients "
                    f"({len(fit.polynomial)})"
                )
        self.motion_noise()  # checks the noise fields
        names = {f.name for f in dataclasses.fields(self)} - {"source", "defaults", "measured"}
        for label, listed in (("defaults", self.defaults), ("measured", self.measured)):
            unknown = sorted(set(listed) - names)
            if unknown:
                raise ValueError(
                    f"calibration {label}: unknown field(s) {unknown}; known: {sorted(names)}"
                )
        both = sorted(set(self.defaults) & set(self.measured))
        if both:
            raise ValueError(f"calibration: {both} listed both under defaults and measured")

    def motion_noise(self) -> MotionNoise:
        """The noise a free move adds."""
        return MotionNoise(
            k_h1=self.motion_noise_slope_x,
            k_h2=self.motion_noise_cross_slope,
            k_v1=self.motion_noise_slope_y,
            k_v2=self.motion_noise_cross_slope,
            offset_x=self.motion_noise_offset,
            offset_y=self.motion_noise_offset,
        )


def calibration_from_dict(data: dict) -> Calibration:
    return dataclass_from_dict(Calibration, data or {}, "calibration")


def load_calibration(path: str | Path) -> Calibration:
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"calibration file {str(path)!r} does not exist")
    try:
        data = load_yaml(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise ValueError(f"calibration file {str(path)!r} is not valid YAML: {exc}") from exc
    except OSError as exc:
        raise ValueError(f"calibration file {str(path)!r}: cannot be read ({exc})") from exc
    try:
        return calibration_from_dict(data)
    except (ValueError, TypeError, KeyError, AttributeError) as exc:
        raise ValueError(f"calibration file {str(path)!r}: {exc}") from exc


def save_calibration(calibration: Calibration, path: str | Path) -> None:
    """Written whole or not at all (temporary file, then rename)."""
    calibration.validate()
    path = Path(path)
    temporary = path.with_name(path.name + ".part")
    temporary.write_text(
        "# afm localization calibration (SI units: m, s, m^2); "
        "see afm_core.localization.calibration\n"
        + yaml.safe_dump(dataclasses.asdict(calibration), sort_keys=False)
    )
    temporary.replace(path)
