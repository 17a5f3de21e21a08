"""An rclpy ActionClient without the race of ros2/rclpy#1123.

In rclpy 7.1 (Jazzy, the version our wheels carry) a goal sent from one thread can be
answered before the client has recorded the request's sequence number, when another thread
of a MultiThreadedExecutor takes the response in between: the client logs "Ignoring
unexpected goal response" and the goal's future never completes. Upstream fixed it
(rclpy#1308, backported in #1519) by holding one lock while a request is sent and recorded
and while responses are taken; this subclass does the same until the wheels carry the fix.
"""
from __future__ import annotations

import threading

from rclpy.action import ActionClient


class SafeActionClient(ActionClient):
    def __init__(self, *args, **kwargs):
        self._request_lock = threading.RLock()
        super().__init__(*args, **kwargs)

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
