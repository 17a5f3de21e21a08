"""DAQ backend: the scanner driven through a DAQ card (AO to the x/y piezo inputs, AI from the
z-piezo monitor and the deflection), as on the book's Dimension 3100 platform.

`DaqInstrument` is the Instrument; `DaqBoundary` is the one hardware seam, implemented by
`NidaqmxBoundary` (NI-DAQmx, imported lazily) and by `FakeDaq` for tests without hardware.
"""

from afm_core.daq.boundary import DaqBoundary, DaqUnavailable, FakeDaq
from afm_core.daq.instrument import (
    DaqCalibration,
    DaqInstrument,
    FeedForward,
    IdentityFeedForward,
    as_feed_forward,
)
from afm_core.daq.nidaqmx_boundary import NidaqmxBoundary

__all__ = [
    "DaqBoundary",
    "DaqCalibration",
    "DaqInstrument",
    "DaqUnavailable",
    "FakeDaq",
    "FeedForward",
    "load_calibration",
    "open_daq_instrument",
    "IdentityFeedForward",
    "NidaqmxBoundary",
    "as_feed_forward",
]


def load_calibration(path=None) -> DaqCalibration:
    """DaqCalibration from a YAML file (any subset of its fields; tuples as 2-lists).
    `x_hysteresis` / `y_hysteresis` ({thresholds, weights, polynomial}: a fitted PI model in
    metres) install that model's inverse as the axis' feed-forward."""
    from pathlib import Path

    import yaml

    from afm_core.yaml_files import load_yaml

    if path is None:
        return DaqCalibration()
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"parameter daq_calibration: {str(path)!r} does not exist")
    try:
        data = load_yaml(path.read_text()) or {}
        return _daq_calibration(data, path)
    except (yaml.YAMLError, OSError, TypeError, KeyError, AttributeError, ValueError) as exc:
        if str(path) in str(exc):
            raise
        raise ValueError(f"daq calibration {str(path)!r}: malformed ({exc})") from exc


def _daq_calibration(data, path) -> DaqCalibration:
    import dataclasses

    if not isinstance(data, dict):
        raise ValueError(f"daq calibration {str(path)!r}: expected a mapping of fields")
    fields = {f.name for f in dataclasses.fields(DaqCalibration)}
    values = {}
    for key, value in data.items():
        if key in ("x_hysteresis", "y_hysteresis"):
            from afm_core.pzt import PrandtlIshlinskii

            model = PrandtlIshlinskii(
                value["thresholds"],
                value["weights"],
                tuple(value.get("polynomial", (1.0, 0.0, 0.0))),
            )
            values[key[0] + "_feed_forward"] = model.inverse()
        elif key in fields:
            values[key] = tuple(value) if isinstance(value, list) else value
        else:
            raise ValueError(
                f"daq calibration {str(path)!r}: unknown key {key!r}; known: {sorted(fields)}"
            )
    calibration = DaqCalibration(**values)
    try:
        calibration.validate()
    except ValueError as exc:  # a value the lab measured or typed, not a malformed file
        raise ValueError(f"daq calibration {str(path)!r}: {exc}") from exc
    return calibration


def open_daq_instrument(device: str = "Dev1", calibration_path=None) -> DaqInstrument:
    """The instrument on a real card; DaqUnavailable (with what is missing) without one."""
    calibration = load_calibration(calibration_path)
    return DaqInstrument(NidaqmxBoundary(device), calibration)
