"""A node destroyed in a process that goes on leaves every other process's graph at once, with
its action clients and servers (afm_ros.teardown): a dead one stayed listed for the life of
the process, and a later graph test found two nano-hand servers and counted neither."""

import time

import pytest
from conftest import wait_for
from rclpy.action import ActionClient, ActionServer

from afm_bringup.commander import AfmCommander
from afm_msgs.action import MoveTip
from afm_ros.teardown import destroy_node_fully

pytestmark = pytest.mark.ros


def listed(watcher, name: str) -> bool:
    return name in {n for n, _ in watcher.get_node_names_and_namespaces()}


def gone_within(watcher, name: str, seconds: float) -> float:
    start = time.monotonic()
    wait_for(lambda: not listed(watcher, name), seconds, what=f"{name} to leave the graph")
    return time.monotonic() - start


def test_a_node_with_action_endpoints_leaves_the_graph_when_destroyed(ros_node):
    import rclpy
    from rclpy.context import Context

    context = Context()
    rclpy.init(context=context)
    node = rclpy.create_node("afm_teardown_probe", context=context)
    ActionServer(node, MoveTip, "/afm_probe/move", lambda handle: MoveTip.Result())
    ActionClient(node, MoveTip, "/afm_probe/move")
    wait_for(lambda: listed(ros_node, "afm_teardown_probe"), 20, what="the probe to be listed")
    destroy_node_fully(node, context)
    assert gone_within(ros_node, "afm_teardown_probe", 5.0) < 5.0


def test_a_closed_commander_leaves_the_graph(ros_node):
    with AfmCommander(node_name="afm_commander_probe") as afm:
        wait_for(lambda: listed(ros_node, "afm_commander_probe"), 20, what="the commander")
    assert gone_within(ros_node, "afm_commander_probe", 5.0) < 5.0
    afm.close()  # a second close does nothing
