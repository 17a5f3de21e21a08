"""YAML files people write (simulator configurations, calibrations): PyYAML's safe loader with
YAML 1.2's numbers.

PyYAML follows YAML 1.1, where a float needs a dot and an exponent needs a sign: `3e-10`, `1E5`
and `1.5e9` are read as strings, and a configuration in SI units written that way was refused as
"expected a number". YAML 1.2's core
schema (and every other YAML library in use) reads them as numbers, so this loader does too.
Everything else is PyYAML's safe loader.
"""

from __future__ import annotations

import re

import yaml


class _SafeLoader(yaml.SafeLoader):
    pass


# a copy: adding to SafeLoader's own table would change every yaml.safe_load in the process
_SafeLoader.yaml_implicit_resolvers = {
    first: list(resolvers) for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_SafeLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)


def load_yaml(text: str):
    """The document in `text`, as yaml.safe_load reads it, but with every number in exponent form
    (`3e-10`, `1.5e9`, `.5E3`) read as a float. Raises yaml.YAMLError as safe_load does."""
    return yaml.load(text, Loader=_SafeLoader)  # noqa: S506 - a SafeLoader subclass
