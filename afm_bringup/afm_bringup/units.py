"""Lengths typed by people: '500nm', '1.5um', '2e-6' (metres) -> metres; angles: '15deg',
'0.26rad', '0.26' (radians) -> radians."""

import argparse
import math
import re

UNITS = {"m": 1.0, "mm": 1e-3, "um": 1e-6, "µm": 1e-6, "nm": 1e-9, "pm": 1e-12}
_LENGTH = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([a-zµ]*)\s*$")


def parse_length(text: str, name: str = "length") -> float:
    match = _LENGTH.match(str(text))
    if not match or match.group(2) not in ("",) + tuple(UNITS):
        raise ValueError(
            f"{name}={text!r}: expected a number with an optional unit "
            f"({', '.join(UNITS)}), e.g. 500nm or 2e-6 (metres)"
        )
    value = float(match.group(1)) * UNITS.get(match.group(2) or "m")
    if not math.isfinite(value):
        raise ValueError(f"{name}={text!r}: must be finite")
    return value


ANGLE_UNITS = {"rad": 1.0, "deg": math.pi / 180}


def parse_angle(text: str, name: str = "angle") -> float:
    match = _LENGTH.match(str(text))
    if not match or match.group(2) not in ("",) + tuple(ANGLE_UNITS):
        raise ValueError(
            f"{name}={text!r}: expected a number with an optional unit (rad, deg), e.g. 15deg "
            "or 0.26 (radians)"
        )
    value = float(match.group(1)) * ANGLE_UNITS[match.group(2) or "rad"]
    if not math.isfinite(value):
        raise ValueError(f"{name}={text!r}: must be finite")
    return value


def angle_type(name: str):
    """An argparse `type` for an angle option: radians, or a number with a unit."""

    def convert(text):
        try:
            return parse_angle(text, name)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from exc

    return convert


def nm(metres: float) -> str:
    return f"{metres * 1e9:.1f} nm"


def length_type(name: str):
    """An argparse `type` for a length option: metres, or a number with a unit."""

    def convert(text):
        try:
            return parse_length(text, name)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from exc

    return convert
