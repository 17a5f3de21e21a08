"""`DaqCalibration`: how metres and newtons map to a DAQ card's volts, and its channels.

`validate` refuses a calibration a lab could plausibly get wrong without noticing: a value in
the wrong unit (um/V where m/V is asked: a factor 1e6 that would otherwise scale every image
silently), a channel missing, named twice or of the wrong kind (an input where an output is
asked), or text where a number is asked.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

# Plausible magnitudes, (lowest, highest), wide enough for any scanner from a 100 nm tube to
# an 800 um flexure stage behind a +-1..10 V card; a value outside is a unit mistake (um/V or
# nm/V for m/V, m/V for V/m), not an instrument. Negative values (an inverted axis or monitor)
# are fine: the magnitude is what is checked.
_PLAUSIBLE = {
    "x_volts_per_metre": (1e3, 1e10, "V/m"),
    "y_volts_per_metre": (1e3, 1e10, "V/m"),
    "z_volts_per_metre": (1e3, 1e10, "V/m"),
    "z_monitor_metres_per_volt": (1e-10, 1e-3, "m/V"),
    "deflection_metres_per_volt": (1e-11, 1e-4, "m/V"),
    "lateral_radians_per_volt": (1e-9, 1.0, "rad/V"),
}
_POSITIVE = {
    "normal_spring_constant": (1e-5, 1e4, "N/m"),
    "lateral_spring_constant": (1e-16, 1e-3, "N*m/rad"),
    # NI cards clock AO at up to a few MS/s; below 1 Hz a 2-sample chunk already takes 2 s
    "sample_rate": (1.0, 1e7, "Hz"),
}
_UNIT_HINT = {
    "V/m": "volts per metre (0.18 V/um is 0.18e6)",
    "m/V": "metres per volt (0.35 um/V is 0.35e-6, 50 nm/V is 50e-9)",
}
_REQUIRED_CHANNELS = {"ao_x": "ao", "ao_y": "ao", "ai_z": "ai", "ai_deflection": "ai"}
_OPTIONAL_CHANNELS = {"ao_z": "ao", "ai_lateral": "ai"}


def _number(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"calibration.{name}={value!r}: must be a number")
    return float(value)


def _channel_key(name: str) -> str:
    """Channels compare by terminal: "ai0" and "Dev1/ai0" are the same input."""
    return name.strip().lower().rsplit("/", 1)[-1]


@dataclass
class DaqCalibration:
    """How metres and newtons map to the card's volts, and which channels carry what (SI units).

    Defaults are plausible for a Dimension 3100 scanner behind a +-10 V card; every value must
    be measured on the real set-up (scanner sensitivity on a calibration grating, deflection
    sensitivity on a force curve on a hard sample, spring constants by thermal tune).
    """

    # Lateral outputs: volts = offset + volts_per_metre * command position; 0.18 V/um over
    # 110 um spans -9.9 V .. +9.9 V.
    x_volts_per_metre: float = 0.18e6
    y_volts_per_metre: float = 0.18e6
    x_offset_volts: float = -9.9
    y_offset_volts: float = -9.9
    # Clamps: no sample is ever written outside them, and requests that would need it are refused.
    x_volts_limits: tuple[float, float] = (-10.0, 10.0)
    y_volts_limits: tuple[float, float] = (-10.0, 10.0)
    # Optional z output added to the controller's z (indentation): volts = offset + V/m * z.
    z_volts_per_metre: float = 2.5e6
    z_offset_volts: float = 0.0
    z_volts_limits: tuple[float, float] = (-10.0, 10.0)
    # Inputs: metres = metres_per_volt * (volts - offset).
    z_monitor_metres_per_volt: float = 0.35e-6  # topography from the z-piezo monitor
    z_monitor_offset_volts: float = 0.0
    deflection_metres_per_volt: float = 50e-9  # inverse optical-lever sensitivity
    deflection_offset_volts: float = 0.0
    lateral_radians_per_volt: float = 1e-3  # torsion
    lateral_offset_volts: float = 0.0
    normal_spring_constant: float = 0.2  # N/m
    lateral_spring_constant: float = 1e-9  # N*m/rad
    sample_rate: float = 100e3  # Hz, one clock for AO and AI
    # Channels (device-relative names).
    ao_x: str = "ao0"
    ao_y: str = "ao1"
    ao_z: str | None = None
    ai_z: str = "ai0"
    ai_deflection: str = "ai1"
    ai_lateral: str | None = None
    ai_range: tuple[float, float] = (-10.0, 10.0)
    # Most samples one synchronised ramp (a raster line: trace + retrace; a local scan line)
    # may take: it is held in memory whole, about 100 bytes a sample with the readings.
    max_ramp_samples: int = 4_000_000
    # Most samples a force trace (push, indentation) keeps: a longer one is averaged in blocks
    # as it is recorded (its sample_rate says by how much), so a long dwell cannot fill memory.
    max_trace_samples: int = 1_000_000
    # Inverse hysteresis per axis (FeedForward, plain callable, or None for identity).
    x_feed_forward: Any = None
    y_feed_forward: Any = None

    def validate(self) -> None:
        for name, (low, high, unit) in _PLAUSIBLE.items():
            value = _number(name, getattr(self, name))
            if not (math.isfinite(value) and value != 0.0):
                raise ValueError(f"calibration.{name}={value}: must be finite and non-zero")
            if not low <= abs(value) <= high:
                raise ValueError(
                    f"calibration.{name}={value:g} {unit}: magnitude outside the plausible "
                    f"[{low:g}, {high:g}] {unit}; the unit is {_UNIT_HINT.get(unit, unit)}"
                )
        for name, (low, high, unit) in _POSITIVE.items():
            value = _number(name, getattr(self, name))
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"calibration.{name}={value}: must be finite and > 0")
            if not low <= value <= high:
                raise ValueError(
                    f"calibration.{name}={value:g} {unit}: outside the plausible "
                    f"[{low:g}, {high:g}] {unit}"
                )
        for name in ("x_offset_volts", "y_offset_volts", "z_offset_volts") + tuple(
            f"{s}_offset_volts" for s in ("z_monitor", "deflection", "lateral")
        ):
            if not math.isfinite(_number(name, getattr(self, name))):
                raise ValueError(f"calibration.{name}={getattr(self, name)}: must be finite")
        for name in ("x_volts_limits", "y_volts_limits", "z_volts_limits", "ai_range"):
            pair = getattr(self, name)
            if not (isinstance(pair, (tuple, list)) and len(pair) == 2):
                raise ValueError(f"calibration.{name}={pair!r}: must be a pair [min, max] in V")
            lo, hi = (_number(name, v) for v in pair)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ValueError(f"calibration.{name}={(lo, hi)}: must be finite with min < max")
        for name in ("max_ramp_samples", "max_trace_samples"):
            most = _number(name, getattr(self, name))
            if not (math.isfinite(most) and most.is_integer() and most >= 4):
                raise ValueError(f"calibration.{name}={most!r}: must be a whole number >= 4")
        self._validate_channels()

    def _validate_channels(self) -> None:
        seen: dict[str, str] = {}
        for name, kind in {**_REQUIRED_CHANNELS, **_OPTIONAL_CHANNELS}.items():
            channel = getattr(self, name)
            if name in _OPTIONAL_CHANNELS and channel in (None, ""):
                continue
            if not (isinstance(channel, str) and channel.strip()):
                raise ValueError(
                    f"calibration.{name}={channel!r}: needs a channel name (e.g. {kind}0)"
                )
            key = _channel_key(channel)
            if not key.startswith(kind):
                raise ValueError(
                    f"calibration.{name}={channel!r}: must be an analog "
                    f"{'output' if kind == 'ao' else 'input'} ({kind}0, {kind}1, ...)"
                )
            if key in seen:
                raise ValueError(
                    f"calibration.{name}={channel!r}: the same channel as "
                    f"calibration.{seen[key]}; every signal needs its own channel"
                )
            seen[key] = name
