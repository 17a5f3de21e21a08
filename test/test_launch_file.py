"""afm_bringup/launch/afm.launch.py, checked without `ros2 launch` (the pip workspace has no
launch packages): the file is run against stand-ins for launch and launch_ros that record what
it asks for, and the nodes it starts must be `afm launch`'s graph, each with its config file."""

import importlib.util
import sys
import types
from pathlib import Path

import pytest

from afm_bringup.launcher import CALIBRATED_NODES, GRAPH, NODES, sim_calibration_file

LAUNCH_FILE = Path(__file__).resolve().parents[1] / "afm_bringup" / "launch" / "afm.launch.py"


class _Recorded:
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


class _Config:
    values: dict = {}

    def __init__(self, name):
        self.name = name

    def perform(self, context):
        return self.values.get(self.name, "")


def _stand_ins(monkeypatch):
    modules = {
        "launch": {"LaunchDescription": _Recorded},
        "launch.actions": {"DeclareLaunchArgument": _Recorded, "OpaqueFunction": _Recorded},
        "launch.substitutions": {"LaunchConfiguration": _Config},
        "launch_ros": {},
        "launch_ros.actions": {"Node": _Recorded},
    }
    for name, attributes in modules.items():
        module = types.ModuleType(name)
        for key, value in attributes.items():
            setattr(module, key, value)
        monkeypatch.setitem(sys.modules, name, module)


def _nodes(monkeypatch, **arguments):
    _stand_ins(monkeypatch)
    spec = importlib.util.spec_from_file_location("afm_launch_file", LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    description = module.generate_launch_description()
    declared = [a.args[0] for a in description.args[0] if a.args]
    assert declared == ["record", "nodes"]
    (opaque,) = [a for a in description.args[0] if "function" in a.kwargs]
    monkeypatch.setattr(_Config, "values", arguments)
    return [node.kwargs for node in opaque.kwargs["function"](context=None)]


def test_launch_file_starts_the_graph_with_config_files(monkeypatch):
    nodes = _nodes(monkeypatch)
    assert [n["executable"] for n in nodes] == GRAPH
    for node in nodes:
        spec = NODES[node["executable"]]
        assert node["package"] == spec.package
        # the installed config file, as `afm launch` passes it
        assert node["parameters"] and Path(node["parameters"][0]).name == spec.params_file
        # on the simulator, its calibration for the nodes that load one, as `afm launch` does
        given = [p.get("calibration_file") for p in node["parameters"][1:] if isinstance(p, dict)]
        wanted = [sim_calibration_file()] if node["executable"] in CALIBRATED_NODES else []
        assert given == wanted, node


def test_launch_file_record_starts_the_recorder_first(monkeypatch):
    nodes = _nodes(monkeypatch, record="s.mcap", nodes="driver,sim2real")
    assert [n["executable"] for n in nodes] == ["recorder", "driver", "sim2real"]
    assert {"output": "s.mcap"} in nodes[0]["parameters"]
    assert {"live_recording": "s.mcap"} in nodes[2]["parameters"]


def test_launch_file_refuses_unknown_nodes(monkeypatch):
    with pytest.raises(ValueError, match="nosuch"):
        _nodes(monkeypatch, nodes="driver,nosuch")
