"""Destroying a node so that the ROS graph forgets it at once, in a process that goes on."""

from rclpy.action import ActionClient, ActionServer


def destroy_node_fully(node, context=None) -> None:
    """Destroy `node` with its action clients and servers, then `context` if given.

    rclpy's destroy_node leaves action clients and servers alone (they are waitables), and each
    holds the node's handle, so the node itself was never destroyed: in a process that goes on
    (pytest, a lab's notebook) every other process listed it, its action endpoints and a
    context's participant for as long as that process lived. A graph test then found a second,
    dead nano-hand server beside the live one, and its client never counted the server as
    available (2026-11-29)."""
    for waitable in list(node.waitables):
        if isinstance(waitable, (ActionClient, ActionServer)):
            waitable.destroy()
    node.destroy_node()
    if context is not None:
        context.try_shutdown()
        context.destroy()
