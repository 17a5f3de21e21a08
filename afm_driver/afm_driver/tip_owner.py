"""Who holds the tip: the automatic clients (the default) or teleoperation (issue 33).

The driver, not a convention between clients, enforces it. While teleop holds the tip every
goal on the ordinary actions (/afm/scan_image, /afm/local_scan, /afm/move_tip, /afm/indent) is
refused with a reason naming teleop, and only goals on the driver's own teleop endpoint
(/afm/teleop/move_tip, MoveTip) run; without teleop, that endpoint's goals are refused.

How the driver tells teleop's goals from others: by the action endpoint they arrive on. A ROS 2
action goal carries no caller identity (its id is random) and MoveTip has no owner field; a
token in the goal would change the interface every client builds and a client that left it
empty would look automatic. The endpoint is a fact the driver knows for every goal, old
clients are unchanged, and nothing automatic uses the teleop endpoint.

Taking (SERVICE_DRIVER_TELEOP, SetBool true) is refused while any goal runs or waits in the
driver's queue (checked and granted under the queue's lock, so no goal slips in between); the
teleop node also refuses while a higher action (a push, a localize) is between its goals.
Handing back (false) is the teleop node's after it has stopped the tip. The answer's message is
one JSON object: {"owner": "teleop" | "automatic", "commanded_position": [x, y] (m,
afm_scanner), "reason": text}.

A teleop node that dies while holding the tip would block the instrument, so the tip is held
on a lease: the teleop node renews it with a message on /afm/teleop/lease every RENEW_PERIOD_S,
and when none came for OWNER_LEASE_S the driver takes the tip back. A message only renews a
lease that is held (a renewal still on its way after the hand-back grants nothing). The graph
would tell too, but only once DDS drops a killed process's endpoints (~20 s, measured).
"""

from __future__ import annotations

import json
import time

from std_msgs.msg import Empty
from std_srvs.srv import SetBool

from afm_ros import topics

# The teleop node renews every RENEW_PERIOD_S; OWNER_LEASE_S without a renewal (6 missed in a
# row) means it is gone: the margin of afm_ros.action_client's SERVER_SILENCE_S, whose probes
# a live node answers within milliseconds even on a loaded machine.
RENEW_PERIOD_S = topics.TELEOP_LEASE_RENEW_S
OWNER_LEASE_S = 3.0


class TipOwner:
    def __init__(self, node, gate, commanded_position):
        self.node = node
        self.gate = gate
        self.commanded_position = commanded_position
        self.teleop = False
        self.renewed = 0.0
        node.create_service(SetBool, topics.SERVICE_DRIVER_TELEOP, self.on_request)
        node.create_subscription(Empty, topics.TELEOP_LEASE, self.on_renewal, 10)
        node.create_timer(RENEW_PERIOD_S, self.check_lease)

    def answer(self, response, success: bool, reason: str):
        x, y = self.commanded_position()
        response.success = success
        response.message = json.dumps(
            {
                "owner": "teleop" if self.teleop else "automatic",
                "commanded_position": [float(x), float(y)],
                "reason": reason,
            }
        )
        return response

    def on_request(self, request, response):
        with self.gate.condition:
            if not request.data:
                was = self.teleop
                self.teleop = False
                return self.answer(
                    response, True, "handed back" if was else "teleop did not hold the tip"
                )
            if self.teleop:
                self.renewed = time.monotonic()
                return self.answer(response, True, "teleop already holds the tip")
            if self.gate.admitted > 0:
                return self.answer(
                    response,
                    False,
                    f"{self.gate.admitted} driver goal(s) running or waiting: an automatic "
                    "action holds the tip",
                )
            self.teleop = True
            self.renewed = time.monotonic()
        self.node.get_logger().info("teleop holds the tip; automatic goals are refused")
        return self.answer(response, True, "teleop holds the tip")

    def refusal(self, teleop_goal: bool) -> str:
        """Why a goal may not run now ("" when it may)."""
        if teleop_goal and not self.teleop:
            return f"teleop does not hold the tip (take it with {topics.SERVICE_TELEOP_ENABLE})"
        if not teleop_goal and self.teleop:
            return (
                "teleop holds the tip (the operator hands it back with "
                f"{topics.SERVICE_TELEOP_ENABLE} false)"
            )
        return ""

    def on_renewal(self, _msg) -> None:
        with self.gate.condition:
            if self.teleop:
                self.renewed = time.monotonic()

    def check_lease(self) -> None:
        with self.gate.condition:
            if not self.teleop or time.monotonic() - self.renewed <= OWNER_LEASE_S:
                return
            self.teleop = False
        self.node.get_logger().warning(
            f"teleop held the tip but did not renew it for {OWNER_LEASE_S} s: the tip is back "
            "with the automatic clients"
        )
