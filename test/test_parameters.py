"""Parameters defined once: the rule of each, and every node's commented YAML file against
its node's table (same names, same defaults)."""

import importlib
import math
from pathlib import Path

import pytest
import yaml

from afm_core.parameters import Parameter, ParameterTable

ROOT = Path(__file__).resolve().parents[1]
# every node the launcher knows: its module and its commented YAML file
NODES = [
    (spec.module, f"{spec.package}/config/{spec.params_file}")
    for _, spec in sorted(importlib.import_module("afm_bringup.launcher").NODES.items())
]


def speed(**kw):
    return Parameter("speed", 1e-6, "Tip speed.", unit="m/s", minimum=0.0, **kw)


def test_a_number_is_checked_against_its_limits_with_its_name_and_unit():
    strict = speed(above_minimum=True, maximum=1e-4)
    assert strict.validate(2e-6) == 2e-6
    assert speed().validate(1) == 1.0 and isinstance(speed().validate(1), float)
    with pytest.raises(ValueError, match=r"parameter speed=0.0: must be > 0 m/s"):
        strict.validate(0.0)
    with pytest.raises(ValueError, match=r"parameter speed=0.001: must be <= 0.0001 m/s"):
        strict.validate(1e-3)
    with pytest.raises(ValueError, match="must be finite"):
        strict.validate(math.nan)
    with pytest.raises(ValueError, match="must be a number"):
        strict.validate("fast")
    assert speed().validate(0.0) == 0.0  # a lower bound is inclusive unless made strict
    half_open = Parameter("f", 0.5, "", minimum=0.0, maximum=1.0, below_maximum=True)
    with pytest.raises(ValueError, match="must be < 1"):
        half_open.validate(1.0)


def test_types_choices_and_a_further_rule():
    with pytest.raises(ValueError, match="must be a whole number"):
        Parameter("n", 3, "").validate(2.5)
    with pytest.raises(ValueError, match="must be true or false"):
        Parameter("flag", False, "").validate(1)
    mode = Parameter("mode", "a", "", choices=("a", "b"))
    with pytest.raises(ValueError, match=r"must be one of \['a', 'b'\]"):
        mode.validate("c")

    def odd(n):
        if n % 2 == 0:
            raise ValueError("must be odd")
        return n

    with pytest.raises(ValueError, match=r"parameter size=4: must be odd"):
        Parameter("size", 3, "", check=odd).validate(4)
    with pytest.raises(ValueError):  # a default that breaks its own rule is a programming error
        Parameter("size", 4, "", check=odd)


def test_constraints_say_the_limits_and_whether_a_running_node_takes_a_change():
    assert speed(above_minimum=True).constraints() == "> 0 m/s; read-only while the node runs"
    assert speed(runtime=True, maximum=2.0).constraints() == ">= 0 m/s; <= 2 m/s"


def test_a_table_refuses_unknown_and_duplicate_names():
    table = ParameterTable(speed(), Parameter("mode", "a", "", choices=("a", "b")))
    assert table.defaults() == {"speed": 1e-6, "mode": "a"}
    assert table.validate({"mode": "b"}) == {"mode": "b"}
    with pytest.raises(ValueError, match=r"unknown parameter\(s\) \['sped'\]"):
        table.validate({"sped": 1.0})
    with pytest.raises(ValueError, match="unique"):
        ParameterTable(speed(), speed())


@pytest.mark.parametrize("module, yaml_file", NODES, ids=[m for m, _ in NODES])
def test_each_node_yaml_lists_every_parameter_with_its_default(module, yaml_file):
    table = importlib.import_module(module).PARAMETERS
    (node,) = yaml.safe_load((ROOT / yaml_file).read_text()).values()
    values = node["ros__parameters"]
    assert list(values) == table.names(), f"{yaml_file}: names or order differ from {module}"
    for name, value in values.items():
        default = table[name].default
        if isinstance(default, float):
            assert value == pytest.approx(default, rel=1e-12), f"{yaml_file}: {name}"
        else:
            assert value == default, f"{yaml_file}: {name}"
        table[name].validate(value)


@pytest.mark.parametrize("module, yaml_file", NODES, ids=[m for m, _ in NODES])
def test_each_node_yaml_says_which_parameters_a_running_node_takes(module, yaml_file):
    table = importlib.import_module(module).PARAMETERS
    header = []
    for line in (ROOT / yaml_file).read_text().splitlines():
        if not line.startswith("#"):
            break
        header.append(line.lstrip("# "))
    text = " ".join(header)
    runtime = [p.name for p in table if p.runtime]
    if runtime:
        said = text.split("(ros2 param set): ", 1)[1].split(". The others", 1)[0]
        assert said.split(", ") == runtime, yaml_file
    else:
        assert "Every parameter is read-only once the node runs" in text, yaml_file


def test_a_path_must_lie_in_an_allowed_folder_after_links_and_dots(tmp_path):
    from afm_core.checks import inside

    root = tmp_path / "data"
    (root / "sub").mkdir(parents=True)
    (root / "escape").symlink_to(tmp_path)
    assert inside("recording", root / "sub" / "a.mcap", [str(root)]) == root / "sub" / "a.mcap"
    assert inside("report_dir", root, ["", str(root)]) == root
    for path in (tmp_path / "a.mcap", root / ".." / "a.mcap", root / "escape" / "a.mcap"):
        with pytest.raises(ValueError, match=r"recording='.*': outside the allowed folders"):
            inside("recording", path, [str(root)], "see read_roots")
    with pytest.raises(ValueError, match=r"allowed folders \(none\)"):
        inside("recording", root / "a.mcap", [""])


def test_push_settings_refuse_a_unit_slip_and_agree_with_the_rod_goal_rule():
    """50 for 50 nm was taken as a 50 m tip; pi/2 passed the table and every rod push using the
    default then failed on the rod goal's open interval."""
    from afm_core.manipulation.push_parameters import PUSH_PARAMETERS
    from afm_core.manipulation.rod_loop import rod_goal_for

    for name in ("tip_radius", "default_tolerance", "rescan_margin", "rescan_pixel"):
        with pytest.raises(ValueError, match=rf"{name}=50.*<= 0.00011 m"):
            PUSH_PARAMETERS.validate({name: 50.0})
    with pytest.raises(ValueError, match=r"default_angle_tolerance=1.5707.*< 1.5708"):
        PUSH_PARAMETERS.validate({"default_angle_tolerance": math.pi / 2})
    accepted = PUSH_PARAMETERS.validate({"default_angle_tolerance": math.pi / 2 - 1e-9})
    rod = type("Rod", (), {"id": "r", "kind": "tube", "orientation": 0.3})()
    assert rod_goal_for(rod, None, accepted["default_angle_tolerance"]) is not None
