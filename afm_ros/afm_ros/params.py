"""Declare a node's parameters from one table of (name, default, meaning)."""

from rcl_interfaces.msg import ParameterDescriptor


def declare(node, table):
    """Declare every (name, default, description) and return {name: value}."""
    values = {}
    for name, default, description in table:
        node.declare_parameter(name, default, ParameterDescriptor(description=description))
        values[name] = node.get_parameter(name).value
    return values
