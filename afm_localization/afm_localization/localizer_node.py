"""Localizer node: the calibrated motion model and the landmark Kalman filter.

Scaffold: the node runs in the graph with its name and lifecycle; its topics and actions
arrive with issue 5, which builds the algorithms in afm_core.
"""
import sys

from rclpy.node import Node

from afm_bringup.node_main import run


class LocalizerNode(Node):
    def __init__(self):
        super().__init__("afm_localizer")
        self.get_logger().info("running; the calibrated motion model and the landmark Kalman filter arrive with issue 5")


def main(args=None):
    return run(LocalizerNode, "afm_localizer", args)


if __name__ == "__main__":
    sys.exit(main())
