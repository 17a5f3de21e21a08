"""Input checks shared by every interface of the core, the nodes and the CLI.

Each takes the field's name first and the value second, returns the value converted, and
raises ValueError with a message that names the field, the value, its unit and the limit it
broke, so a user knows what to change. A node's parameters, an action goal's fields and a
core function's arguments are checked by the same words.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np


def _unit(unit: str) -> str:
    return f" {unit}" if unit else ""


def finite(name: str, value, unit: str = "") -> float:
    """A finite number (not a string that reads as one: every interface takes numbers in SI
    units, and '5e-6' would be compared with numbers further on)."""
    if isinstance(value, (str, bytes)):
        raise ValueError(
            f"{name}={value!r}: must be a number, not text" + (f" ({unit})" if unit else "")
        )
    try:
        number = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}={value!r}: must be a number{_unit(unit)}") from exc
    if not math.isfinite(number):
        raise ValueError(f"{name}={value}: must be finite{_unit(unit)}")
    return number


def positive(name: str, value, unit: str = "", *, upper: float | None = None) -> float:
    """A finite number > 0, at most `upper` when given."""
    number = finite(name, value, unit)
    if not number > 0:
        raise ValueError(f"{name}={number}: must be finite and > 0{_unit(unit)}")
    if upper is not None and number > upper:
        raise ValueError(
            f"{name}={number:.4g}{_unit(unit)}: above the limit {upper:.4g}{_unit(unit)}"
        )
    return number


def non_negative(name: str, value, unit: str = "", *, upper: float | None = None) -> float:
    """A finite number >= 0, at most `upper` when given."""
    number = finite(name, value, unit)
    if not number >= 0:
        raise ValueError(f"{name}={number}: must be finite and >= 0{_unit(unit)}")
    if upper is not None and number > upper:
        raise ValueError(
            f"{name}={number:.4g}{_unit(unit)}: above the limit {upper:.4g}{_unit(unit)}"
        )
    return number


def count(name: str, value, minimum: int = 0, maximum: int | None = None) -> int:
    """A whole number in [minimum, maximum] (no maximum when None)."""
    if isinstance(value, (str, bytes)):
        raise ValueError(f"{name}={value!r}: must be a whole number, not text")
    try:
        whole = int(value)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ValueError(f"{name}={value!r}: must be a whole number") from exc
    if whole != value or whole < minimum or (maximum is not None and whole > maximum):
        limit = f"[{minimum}, {maximum}]" if maximum is not None else f">= {minimum}"
        raise ValueError(f"{name}={value}: need a whole number {limit}")
    return whole


def point(name: str, value, unit: str = "m") -> np.ndarray:
    """A finite point (x, y)."""
    try:
        xy = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}={value!r}: must be a point (x, y){_unit(unit)}") from exc
    if xy.size != 2:
        raise ValueError(f"{name}={value!r}: must be a point (x, y){_unit(unit)}")
    if not np.all(np.isfinite(xy)):
        raise ValueError(f"{name}={tuple(xy)}: must be finite{_unit(unit)}")
    return xy


def one_of(name: str, value, choices) -> object:
    """One of a fixed set of choices."""
    if value not in choices:
        raise ValueError(f"{name}={value!r}: must be one of {list(choices)}")
    return value


def few(items, shown: int = 10) -> str:
    """The first `shown` of `items` for a message, and how many more: a map of 20000
    landmarks made a 120 KB error message when every id was listed."""
    items = [str(item) for item in items]
    more = f" and {len(items) - shown} more" if len(items) > shown else ""
    return ", ".join(items[:shown]) + more


def new_file(
    name: str, path, suffixes: tuple[str, ...] = (), *, overwrite: bool = False, option: str = ""
) -> Path:
    """A file about to be written, checked before the work (which may take hours): not a
    folder, in a folder that exists, ending in one of `suffixes` (any if empty), and new unless
    `overwrite` (`option` is the flag that allows it, named in the refusal); else ValueError
    naming the field."""
    target = Path(path)
    if target.is_dir():
        raise ValueError(f"{name} {path}: a folder; name a file")
    if target.exists() and not overwrite:
        fix = f"use {option} to replace it" if option else "not overwriting it"
        raise ValueError(f"{name} {path}: already exists; {fix} (or choose another name)")
    if not target.parent.is_dir():
        raise ValueError(f"{name} {path}: the folder {str(target.parent)!r} does not exist")
    if suffixes and target.suffix.lower() not in suffixes:
        raise ValueError(f"{name} {path}: must end in {' or '.join(suffixes)}")
    return target


def inside(name: str, path, roots, hint: str = "") -> Path:
    """`path` resolved (symlinks followed, so a link cannot lead out), when it lies in one of
    the folders `roots` (resolved the same way; empty entries ignored); else ValueError naming
    the field, the path and the folders."""
    resolved = Path(path).expanduser().resolve()
    folders = [Path(root).expanduser().resolve() for root in roots if str(root)]
    if any(resolved == folder or folder in resolved.parents for folder in folders):
        return resolved
    allowed = ", ".join(repr(str(folder)) for folder in folders) or "none"
    raise ValueError(f"{name}={str(path)!r}: outside the allowed folders ({allowed}){_hint(hint)}")


def _hint(hint: str) -> str:
    return f"; {hint}" if hint else ""
