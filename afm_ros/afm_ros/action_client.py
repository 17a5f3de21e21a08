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
"""

from __future__ import annotations

import threading
import time
import uuid

from rclpy.action import ActionClient
from rclpy.action.client import ClientGoalHandle
from unique_identifier_msgs.msg import UUID


class SafeActionClient(ActionClient):
    def __init__(self, *args, **kwargs):
        self._request_lock = threading.RLock()
        self._answered = False
        super().__init__(*args, **kwargs)

    def wait_until_answering(self, timeout_sec: float, probe_interval: float = 1.0) -> bool:
        """True once a live server has answered this client; False after timeout_sec.

        The probe is a cancel request for a goal id nobody has (the server answers "unknown
        goal" and does nothing), repeated until one reply arrives: unlike resending a goal, a
        lost probe cannot start anything twice. Goals, cancels and results are services of the
        same server, created together, so an answered probe means its replies reach us."""
        if self._answered:
            return True
        deadline = time.monotonic() + timeout_sec
        if not self.wait_for_server(timeout_sec=timeout_sec):
            return False
        while (remaining := deadline - time.monotonic()) > 0:
            nobodys_goal = ClientGoalHandle(self, UUID(uuid=list(uuid.uuid4().bytes)), None)
            answered = threading.Event()
            self._cancel_goal_async(nobodys_goal).add_done_callback(lambda _f: answered.set())
            if answered.wait(min(probe_interval, remaining)):
                self._answered = True
                return True
        return False

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
            return super().take_data()
