"""Lengths typed by people: '500nm', '1.5um', '2e-6' (metres) -> metres; angles: '15deg',
'0.26rad', '0.26' (radians) -> radians."""

import argparse
import math
import re

UNITS = {"m": 1.0, "mm": 1e-3, "um": 1e-6, "µm": 1e-6, "nm": 1e-9, "pm": 1e-12}
_NUMBER = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([a-zµ]*)\s*$")


def _parse(text: str, name: str, units: dict, default: str, expected: str) -> float:
    """A number with an optional unit from `units` (`default` when none) -> SI; the error
    names the field and what was expected."""
    match = _NUMBER.match(str(text))
    if not match or match.group(2) not in ("",) + tuple(units):
        raise ValueError(f"{name}={text!r}: expected a number with an optional unit {expected}")
    value = float(match.group(1)) * units[match.group(2) or default]
    if not math.isfinite(value):
        raise ValueError(f"{name}={text!r}: must be finite")
    return value


# A number typed without a unit is metres; beyond this it was meant in another unit (no
# length an AFM works with comes near a millimetre: the widest scanners reach ~100 um).
BARE_METRES_MAX = 1e-3


def parse_length(text: str, name: str = "length") -> float:
    value = _parse(text, name, UNITS, "m", f"({', '.join(UNITS)}), e.g. 500nm or 2e-6 (metres)")
    if abs(value) > BARE_METRES_MAX and _NUMBER.match(str(text)).group(2) == "":
        raise ValueError(
            f"{name}={text!r}: a number without a unit is metres, and {value:g} m is beyond "
            f"any AFM length (at most {BARE_METRES_MAX:g} m without a unit): give the unit, "
            f"e.g. {text.strip()}nm"
        )
    return value


ANGLE_UNITS = {"rad": 1.0, "deg": math.pi / 180}


def parse_angle(text: str, name: str = "angle") -> float:
    return _parse(text, name, ANGLE_UNITS, "rad", "(rad, deg), e.g. 15deg or 0.26 (radians)")


def _argparse_type(parse, name: str):
    """An argparse `type` that parses with `parse` and reports its error as argparse's."""

    def convert(text):
        try:
            return parse(text, name)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from exc

    convert.parse = parse  # what it reads, for those that list the options by kind (--help)
    return convert


def angle_type(name: str):
    """An argparse `type` for an angle option: radians, or a number with a unit."""
    return _argparse_type(parse_angle, name)


def nm(metres: float) -> str:
    return f"{metres * 1e9:.1f} nm"


def length_type(name: str, positive: bool = False):
    """An argparse `type` for a length option: metres, or a number with a unit; `positive`:
    refused unless above 0 (a size, a tolerance)."""
    return _argparse_type(_above_zero(parse_length) if positive else parse_length, name)


def positive_type(name: str, kind=float):
    """An argparse `type` for a count or rate that must be above 0: refused by argparse, before
    anything is sent, with the field's name."""

    def parse(text, name):
        try:
            return kind(text)
        except ValueError:
            raise ValueError(f"{name}={text!r}: expected {kind.__name__}") from None

    return _argparse_type(_above_zero(parse), name)


def count_type(name: str, minimum: int, maximum: int):
    """An argparse `type` for a whole number in [minimum, maximum] (an id, an index)."""

    def parse(text, name):
        try:
            value = int(text)
        except ValueError:
            raise ValueError(f"{name}={text!r}: expected a whole number") from None
        if not minimum <= value <= maximum:
            raise ValueError(f"{name}={text!r}: must be within [{minimum}, {maximum}]")
        return value

    return _argparse_type(parse, name)


def _above_zero(parse):
    def checked(text, name):
        value = parse(text, name)
        if not value > 0:
            raise ValueError(f"{name}={text!r}: must be above 0")
        if not math.isfinite(value):  # a timeout of inf waited for ever, a rate of inf failed late
            raise ValueError(f"{name}={text!r}: must be finite")
        return value

    return checked


# argparse takes only bare negative numbers (-2, -0.5) for values; '-15deg' or '-2nm' it reads
# as an unknown option, and `--goal-angle -15deg` failed with "expected one argument"; so did
# '-inf' and '-1GiB', whose own checks say what is wrong with them
NEGATIVE_QUANTITY = re.compile(
    r"^-(?:(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?\s*[a-zA-Zµ]*|inf|nan|infinity)$", re.IGNORECASE
)


def _shown(value) -> str:
    """A parsed value as a message shows it: 6e-9, not 6.000000000000001e-09."""
    if isinstance(value, (list, tuple)):
        return " ".join(_shown(v) for v in value)
    return f"{value:.6g}" if isinstance(value, float) else repr(value)


class _StoreOnce(argparse._StoreAction):
    """An option's value, refused when the option comes again with another value: argparse
    keeps the last, so `-o a.npz -o b.npz` wrote b.npz without a word about a.npz."""

    def __call__(self, parser, namespace, values, option_string=None):
        given = getattr(parser, "_given_options", None)
        if option_string is not None and given is not None:
            if self.dest in given and given[self.dest] != values:
                first, then = _shown(given[self.dest]), _shown(values)
                raise argparse.ArgumentError(
                    self, f"given twice ({first}, then {then}); give it once"
                )
            given[self.dest] = values
        super().__call__(parser, namespace, values, option_string)


class QuantityArgumentParser(argparse.ArgumentParser):
    """An ArgumentParser that reads a negative number with a unit as a value, and refuses an
    option given twice with different values. Its subcommands' parsers are of its class
    (argparse's add_subparsers default), so one at the top is enough. None of our options
    looks like a negative number, so none is shadowed."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = NEGATIVE_QUANTITY
        self.register("action", None, _StoreOnce)
        self.register("action", "store", _StoreOnce)

    def parse_known_args(self, args=None, namespace=None):
        self._given_options = {}  # one parse's options (a parser may parse twice)
        return super().parse_known_args(args, namespace)
