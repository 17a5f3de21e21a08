"""NanoHand node: virtual nano-hand push and assemble actions.

Scaffold: the node runs in the graph with its name and lifecycle; its topics and actions
arrive with issue 7, which builds the algorithms in afm_core.
"""
import sys

from rclpy.node import Node

from afm_bringup.node_main import run


class NanoHandNode(Node):
    def __init__(self):
        super().__init__("afm_nano_hand")
        self.get_logger().info("running; virtual nano-hand push and assemble actions arrive with issue 7")


def main(args=None):
    return run(NanoHandNode, "afm_nano_hand", args)


if __name__ == "__main__":
    sys.exit(main())
