"""Imaging node: drift compensation, blind tip estimation, reconstruction and landmark extraction.

Scaffold: the node runs in the graph with its name and lifecycle; its topics and actions
arrive with issue 4, which builds the algorithms in afm_core.
"""
import sys

from rclpy.node import Node

from afm_bringup.node_main import run


class ImagingNode(Node):
    def __init__(self):
        super().__init__("afm_imaging")
        self.get_logger().info("running; drift compensation, blind tip estimation, reconstruction and landmark extraction arrive with issue 4")


def main(args=None):
    return run(ImagingNode, "afm_imaging", args)


if __name__ == "__main__":
    sys.exit(main())
