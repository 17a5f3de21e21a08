"""Declare a node's parameters from its table (afm_core.parameters) and keep them valid.

At start every value (default, YAML file or `-p` override) is validated; a bad one stops the
node with the parameter's name and limit (node_main exits 2). At run time `ros2 param set`
is validated by the same rule and refused with the reason; a parameter the node cannot
apply while running is declared read-only, so ROS refuses it with "read-only"; an accepted
value is written into the node's config dict and handed to `apply`, if given.
"""

from __future__ import annotations

from collections.abc import Callable

from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException

from afm_core.parameters import ParameterTable


def describe(parameter) -> ParameterDescriptor:
    unit = f"[{parameter.unit}] " if parameter.unit else ""
    return ParameterDescriptor(
        description=f"{unit}{parameter.description}",
        additional_constraints=parameter.constraints(),
        read_only=not parameter.runtime,
    )


KINDS = {
    bool: "true or false",
    int: "a whole number",
    float: "a number",
    str: "a string",
    list: "a list",
}


def _declare(node, parameter) -> None:
    """A float parameter is declared with dynamic typing, so a whole number reaches the
    table's rule (ROS reads `discovery_period:=-1` and `ros2 param set NODE gate 3` as
    integers, and refused them with "Wrong parameter type, expected 'Type.DOUBLE'"): a bad
    value, of any type, is refused with the parameter's limit, not with a type name."""
    descriptor = describe(parameter)
    descriptor.dynamic_typing = type(parameter.default) is float
    node.declare_parameter(parameter.name, parameter.default, descriptor)


def declare(node, table: ParameterTable, apply: Callable[[str, object], None] | None = None):
    """Declare every parameter of `table` on `node`; return {name: validated value}, a dict
    the node reads at use time and that accepted run-time changes update."""
    values = {}
    for parameter in table:
        try:
            _declare(node, parameter)
        except (InvalidParameterTypeException, InvalidParameterValueException) as exc:
            expected = KINDS.get(type(parameter.default), type(parameter.default).__name__)
            raise ValueError(
                f"{parameter.label}: the value given is not {expected} ({exc}); "
                f"default {parameter.default!r}"
            ) from exc
        values[parameter.name] = parameter.validate(node.get_parameter(parameter.name).value)

    def validate(changes) -> SetParametersResult:
        for change in changes:
            if change.name in table:
                try:
                    table[change.name].validate(change.value)
                except ValueError as exc:
                    return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def store(changes) -> None:
        for change in changes:
            if change.name in table:
                values[change.name] = table[change.name].validate(change.value)
                if apply is not None:
                    apply(change.name, values[change.name])

    node.add_on_set_parameters_callback(validate)
    node.add_post_set_parameters_callback(store)
    return values
