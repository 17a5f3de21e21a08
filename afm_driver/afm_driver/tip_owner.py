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

A teleop node that dies while holding the tip would block the instrument: when no client of
the teleop endpoint has been in the graph for OWNER_GONE_S, the driver takes the tip back.
"""

from __future__ import annotations

import json
import time

from std_srvs.srv import SetBool

from afm_ros import topics

OWNER_GONE_S = 2.0  # s without any teleop client before the driver takes the tip back
# (a live node's client never leaves the graph; DDS discovery under load takes well below 1 s)


class TipOwner:
    def __init__(self, node, gate, commanded_position):
        self.node = node
        self.gate = gate
        self.commanded_position = commanded_position
        self.teleop = False
        self.client_seen = 0.0
        node.create_service(SetBool, topics.SERVICE_DRIVER_TELEOP, self.on_request)
        node.create_timer(0.5, self.check_owner_alive)

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
                return self.answer(response, True, "teleop already holds the tip")
            if self.gate.admitted > 0:
                return self.answer(
                    response,
                    False,
                    f"{self.gate.admitted} driver goal(s) running or waiting: an automatic "
                    "action holds the tip",
                )
            self.teleop = True
            self.client_seen = time.monotonic()
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

    def check_owner_alive(self) -> None:
        if not self.teleop:
            return
        send_goal = f"{topics.ACTION_TELEOP_MOVE_TIP}/_action/send_goal"
        if self.node.count_clients(send_goal) > 0:
            self.client_seen = time.monotonic()
        elif time.monotonic() - self.client_seen > OWNER_GONE_S:
            with self.gate.condition:
                self.teleop = False
            self.node.get_logger().warning(
                f"teleop held the tip but no teleop client has been seen for {OWNER_GONE_S} s: "
                "the tip is back with the automatic clients"
            )
