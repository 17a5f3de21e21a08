"""A node's parameters, each defined once: default, unit, limits, meaning, and whether a
running node can take a new value.

The node declares its ROS parameters from its table (afm_ros.params), its commented YAML file
is checked against the same table by the tests, and every value, at start or set later with
`ros2 param set`, goes through `Parameter.validate`. A value a running node cannot apply is
refused (the parameter is read-only), never accepted and ignored.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from afm_core import checks

Value = bool | int | float | str | list


@dataclass(frozen=True)
class Parameter:
    """One parameter. `minimum`/`maximum` bound numbers (and each number of a list);
    `above_minimum` / `below_maximum` make a bound strict (> rather than >=); `choices` lists the
    allowed values of a string; `check` is a further rule (value -> value, ValueError with
    the reason). `runtime`: a running node applies a new value (else it is read-only)."""

    name: str
    default: Value
    description: str
    unit: str = ""
    minimum: float | None = None
    maximum: float | None = None
    above_minimum: bool = False
    below_maximum: bool = False
    choices: tuple = ()
    check: Callable[[Value], Value] | None = None
    runtime: bool = False

    def __post_init__(self):
        self.validate(self.default)

    @property
    def label(self) -> str:
        return f"parameter {self.name}"

    def constraints(self) -> str:
        """The limits in words, for `ros2 param describe` and the documentation."""
        unit = f" {self.unit}" if self.unit else ""
        parts = []
        if self.minimum is not None:
            parts.append(f"{'>' if self.above_minimum else '>='} {self.minimum:g}{unit}")
        if self.maximum is not None:
            parts.append(f"{'<' if self.below_maximum else '<='} {self.maximum:g}{unit}")
        if self.choices:
            parts.append("one of " + ", ".join(repr(c) for c in self.choices))
        if not parts and self.unit:
            parts.append(f"in {self.unit}")
        text = "; ".join(parts)
        if not self.runtime:
            text = f"{text}; read-only while the node runs" if text else "read-only while running"
        return text

    def validate(self, value: Value) -> Value:
        """The value if it is allowed, else ValueError naming the parameter and the limit."""
        value = self._typed(value)
        numbers = value if isinstance(value, list) else [value]
        if isinstance(self.default, int | float) and not isinstance(self.default, bool):
            for number in numbers:
                self._bounded(number)
        elif isinstance(self.default, list):
            for number in numbers:
                if isinstance(number, int | float) and not isinstance(number, bool):
                    self._bounded(number)
        if self.choices:
            checks.one_of(self.label, value, self.choices)
        if self.check is not None:
            try:
                value = self.check(value)
            except ValueError as exc:
                raise ValueError(f"{self.label}={value!r}: {exc}") from exc
        return value

    def _typed(self, value: Value) -> Value:
        expected = type(self.default)
        if expected is bool:
            if not isinstance(value, bool):
                raise ValueError(f"{self.label}={value!r}: must be true or false")
        elif expected is int:
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                raise ValueError(f"{self.label}={value!r}: must be a whole number")
            value = int(value)
        elif expected is float:
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise ValueError(f"{self.label}={value!r}: must be a number{self._unit()}")
            value = float(value)
        elif expected is str:
            if not isinstance(value, str):
                raise ValueError(f"{self.label}={value!r}: must be a string")
        elif expected is list:
            if not isinstance(value, list | tuple):
                raise ValueError(f"{self.label}={value!r}: must be a list")
            value = list(value)
        return value

    def _bounded(self, number) -> None:
        if isinstance(number, float) and not math.isfinite(number):
            raise ValueError(f"{self.label}={number}: must be finite{self._unit()}")
        low, high = self.minimum, self.maximum
        if low is not None and (number <= low if self.above_minimum else number < low):
            sign = ">" if self.above_minimum else ">="
            raise ValueError(f"{self.label}={number}: must be {sign} {low:g}{self._unit()}")
        if high is not None and (number >= high if self.below_maximum else number > high):
            sign = "<" if self.below_maximum else "<="
            raise ValueError(f"{self.label}={number}: must be {sign} {high:g}{self._unit()}")

    def _unit(self) -> str:
        return f" {self.unit}" if self.unit else ""


class ParameterTable:
    """A node's parameters in declaration order."""

    def __init__(self, *parameters: Parameter):
        self._by_name = {p.name: p for p in parameters}
        if len(self._by_name) != len(parameters):
            raise ValueError("parameter names must be unique")

    def __iter__(self) -> Iterator[Parameter]:
        return iter(self._by_name.values())

    def __getitem__(self, name: str) -> Parameter:
        return self._by_name[name]

    def __contains__(self, name: str) -> bool:
        return name in self._by_name

    def names(self) -> list[str]:
        return list(self._by_name)

    def defaults(self) -> dict[str, Value]:
        return {p.name: p.default for p in self}

    def validate(self, values: dict[str, Value]) -> dict[str, Value]:
        """Every known value validated (unknown names are an error naming them)."""
        unknown = sorted(set(values) - set(self._by_name))
        if unknown:
            raise ValueError(f"unknown parameter(s) {unknown}; known: {self.names()}")
        return {name: self._by_name[name].validate(value) for name, value in values.items()}
