"""The node graph `afm launch` starts, for a full ROS 2 install (`ros2 launch afm_bringup
afm.launch.py [record:=session.mcap] [nodes:=driver,imaging]`).

The node list and each node's parameter file come from afm_bringup.launcher (NODES, GRAPH),
the table `afm launch` uses, so the two cannot drift apart. Each node runs its package's
console script with the package's installed config/<node>.yaml. `record:=FILE` also starts
the MCAP recorder (first, so it hears the others start) and tells the sim-to-real node where
the live recording is, as `afm launch --record FILE` does; on the simulator the driver,
localizer, planner and nano-hand get its calibration, as `afm launch` gives it.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from afm_bringup.launcher import (
    GRAPH,
    NODES,
    default_params_file,
    sim_calibration_file,
    with_sim_calibration,
)


def _node(name: str, overrides: dict) -> Node:
    spec = NODES[name]
    params_file = default_params_file(name)
    parameters = ([str(params_file)] if params_file else []) + ([overrides] if overrides else [])
    # executable = the console script, which setup.py names after the node (NODES' key)
    return Node(package=spec.package, executable=name, parameters=parameters, output="screen")


def _graph(context, *args, **kwargs):
    record = LaunchConfiguration("record").perform(context)
    chosen = LaunchConfiguration("nodes").perform(context)
    nodes = [n.strip() for n in chosen.split(",") if n.strip()] if chosen else list(GRAPH)
    unknown = [n for n in nodes if n not in NODES]
    if unknown:
        raise ValueError(
            f"nodes:={chosen}: {unknown} unknown; expected names from {sorted(NODES)}"
        )
    actions = [_node("recorder", {"output": record})] if record else []
    overrides: dict[str, dict] = {"sim2real": {"live_recording": record}} if record else {}
    # on the simulator, its calibration for the calibrated nodes, as `afm launch` gives it
    with_sim_calibration(nodes, overrides, sim_calibration_file())
    for name in nodes:
        actions.append(_node(name, overrides.get(name, {})))
    return actions


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "record", default_value="", description="MCAP file to record to ('' = none)"
            ),
            DeclareLaunchArgument(
                "nodes",
                default_value="",
                description=f"comma-separated nodes ('' = {','.join(GRAPH)})",
            ),
            OpaqueFunction(function=_graph),
        ]
    )
