"""Planner node: observation planning, landmark paths and push sequencing.

Scaffold: the node runs in the graph with its name and lifecycle; its topics and actions
arrive with issue 6, which builds the algorithms in afm_core.
"""
import sys

from rclpy.node import Node

from afm_bringup.node_main import run


class PlannerNode(Node):
    def __init__(self):
        super().__init__("afm_planner")
        self.get_logger().info("running; observation planning, landmark paths and push sequencing arrive with issue 6")


def main(args=None):
    return run(PlannerNode, "afm_planner", args)


if __name__ == "__main__":
    sys.exit(main())
