"""An rclpy ActionClient without the race of ros2/rclpy#1123.

In rclpy 7.1 (Jazzy, the version our wheels carry) a goal sent from one thread can be
answered before the client has recorded the request's sequence number, when another thread
of a MultiThreadedExecutor takes the response in between: the client logs "Ignoring
unexpected goal response" and the goal's future never completes. Upstream fixed it
(rclpy#1308, backported in #1519) by holding one lock while a request is sent and recorded
and while responses are taken; this subclass does the same until the wheels carry the fix.

It also knows when a server really answers (wait_until_answering): the ROS graph can list a
server whose process has just died, or one whose replies DDS has not matched to us yet, and a
goal sent to either is lost without a word.

And when a server stops answering while a goal runs (Heartbeat): a killed process's
goals never end and DDS forgets it only after its lease (tens of seconds), so whoever waits
for a result probes the server meanwhile, and gives up once it has been silent for
SERVER_SILENCE_S.
"""

from __future__ import annotations

import os
import threading
import time
import uuid

from rclpy.action import ActionClient
from rclpy.action.client import ClientGoalHandle
from unique_identifier_msgs.msg import UUID

# A live server answers a probe within milliseconds, even mid-goal and with its queue full
# (3 ms measured, test_faults_ros): its cancel service has executor threads of its own.
# SERVER_SILENCE_S without any answer, i.e. SERVER_SILENCE_S / HEARTBEAT_PERIOD_S = 6 probes
# in a row unanswered, is "gone": the "within a few seconds" the graph promises, with three
# orders of magnitude of margin over a live server's answer for a loaded machine.
HEARTBEAT_PERIOD_S = 0.5
SERVER_SILENCE_S = 3.0
# What rclpy's take_data returns for the server's replies to our requests (goal, cancel and
# result services); feedback and status are topics, which prove nothing about our requests.
ANSWERS = ("goal", "cancel", "result")
# A cancel request a live server has not even acknowledged in this long will not be honoured.
CANCEL_ACK_TIMEOUT_S = 3.0
# Set when this process is stopping (SIGINT/SIGTERM): every wait for a server gives up at once,
# so an action's execute callback ends and the node can exit (node_main sets it).
STOPPING = threading.Event()


def _nobodys_goal(client) -> ClientGoalHandle:
    return ClientGoalHandle(client, UUID(uuid=list(uuid.uuid4().bytes)), None)


class Heartbeat:
    """Probes a client's server every period_s while a caller waits; gone() once no probe
    has been answered for silence_s. The probe is a cancel for a goal nobody has (see
    wait_until_answering): it changes nothing on the server."""

    def __init__(self, client, period_s=HEARTBEAT_PERIOD_S, silence_s=SERVER_SILENCE_S):
        self.client = client
        self.period_s = period_s
        self.silence_s = silence_s
        self.last_answer = time.monotonic()
        self._next_probe = 0.0
        self._pending: list = []

    def beat(self) -> None:
        """Call often (every few tens of ms) from the waiting loop; sends a probe when due."""
        now = time.monotonic()
        if now < self._next_probe:
            return
        self._next_probe = now + self.period_s
        future = self.client._cancel_goal_async(_nobodys_goal(self.client))
        future.add_done_callback(self._answered)
        self._pending = [(f, t) for f, t in self._pending if not f.done()] + [(future, now)]

    def _answered(self, _future) -> None:
        self.last_answer = time.monotonic()
        self.client._answered_at = self.last_answer

    def silent_for(self) -> float:
        return time.monotonic() - self.last_answer

    def gone(self) -> bool:
        return self.silent_for() > self.silence_s

    def forget(self) -> None:
        """Drop the probes still waiting for an answer that will never come: those unanswered
        for silence_s. A live server answers the recent ones within milliseconds; dropping them
        too made rclpy warn "Ignoring unexpected cancel response" after every goal."""
        now = time.monotonic()
        overdue = [f for f, t in self._pending if not f.done() and now - t > self.silence_s]
        self.client._forget_requests(overdue)
        self._pending = []


class SafeActionClient(ActionClient):
    def __init__(self, *args, **kwargs):
        self._request_lock = threading.RLock()
        self._answered_at = -float("inf")  # when the server last answered us
        self.not_answering = ""  # why wait_until_answering last gave up
        super().__init__(*args, **kwargs)

    def wait_until_answering(self, timeout_sec: float, probe_interval: float = 1.0) -> bool:
        """True once a live server has answered this client; False after timeout_sec.

        The probe is a cancel request for a goal id nobody has (the server answers "unknown
        goal" and does nothing), repeated until one reply arrives: unlike resending a goal, a
        lost probe cannot start anything twice. Goals, cancels and results are services of the
        same server, created together, so an answered probe means its replies reach us."""
        if time.monotonic() - self._answered_at < SERVER_SILENCE_S:
            return True  # it answered just now; an older answer proves nothing (it may be dead)
        deadline = time.monotonic() + timeout_sec
        if not self.wait_for_server(timeout_sec=timeout_sec):
            # which nodes the graph knows tells a participant never discovered from one whose
            # action endpoints are not (yet) matched
            self.not_answering = (
                "the graph does not list its server: its status is published "
                f"{self.listed_servers()}; {self.known_nodes()}"
            )
            return False
        probes = 0
        # one event for all the probes: a late answer to an earlier probe is as good as the
        # newest one's (waiting for the newest only held a teleop segment for a whole probe
        # interval when the first answer came a moment after it)
        answered = threading.Event()
        while (remaining := deadline - time.monotonic()) > 0:
            self._cancel_goal_async(_nobodys_goal(self)).add_done_callback(
                lambda _f: answered.set()
            )
            probes += 1
            if answered.wait(min(probe_interval, remaining)):
                self._answered_at = time.monotonic()
                self.not_answering = ""
                return True
        self.not_answering = (
            f"its server is listed ({self.listed_servers()}) but answered none of {probes} probes"
        )
        return False

    def servers(self) -> list[str]:
        """Who the graph says serves this action (the publishers of its status topic, one per
        server): two where one was started means a dead one still listed, or another graph on
        the same domain, whose answers race the right server's."""
        listed = self._node.get_publishers_info_by_topic(f"{self._action_name}/_action/status")
        return sorted(f"{p.node_namespace.rstrip('/')}/{p.node_name}" for p in listed)

    def listed_servers(self) -> str:
        """servers() in words, with the domain, for an error message."""
        try:
            names = self.servers()
        except Exception as exc:  # noqa: BLE001 - a diagnosis must not hide the failure
            return f"by whom unknown: {exc}"
        domain = os.environ.get("ROS_DOMAIN_ID", "0")
        return f"by {len(names)} node(s) on domain {domain}: {', '.join(names) or 'none now'}"

    def known_nodes(self) -> str:
        """The nodes this client's graph lists, in words, for an error message."""
        try:
            names = self._node.get_node_names_and_namespaces()
        except Exception as exc:  # noqa: BLE001 - a diagnosis must not hide the failure
            return f"the nodes it lists are unknown: {exc}"
        listed = sorted(f"{ns.rstrip('/')}/{name}" for name, ns in names)
        return f"the graph lists {len(listed)} node(s): {', '.join(listed) or 'none'}"

    def _forget_requests(self, futures) -> None:
        """Remove cancel requests a dead server will never answer from the pending table."""
        with self._request_lock:
            for future in futures:
                self._remove_pending_cancel_request(future)

    def send_goal_async(self, *args, **kwargs):
        with self._request_lock:
            return super().send_goal_async(*args, **kwargs)

    def _cancel_goal_async(self, goal_handle):
        with self._request_lock:
            return super()._cancel_goal_async(goal_handle)

    def _get_result_async(self, goal_handle):
        with self._request_lock:
            return super()._get_result_async(goal_handle)

    def take_data(self):
        with self._request_lock:
            data = super().take_data()
        if any(key in data for key in ANSWERS):
            # a reply to one of our requests is as good an answer as a probe's: a client that
            # sends goal after goal (teleop, 20 a second) never stops to probe a server that
            # answers it all the time
            self._answered_at = time.monotonic()
        return data
