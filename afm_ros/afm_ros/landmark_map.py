"""The newest landmark map a node has heard on /afm/landmarks.

Several nodes publish landmark maps, latched (imaging after a scan, the nano-hand after moving a
particle): a node joining late may get them in any order, so the newest map by its header stamp
wins, and a node that moves a landmark publishes the map again stamped after the newest.
"""

from __future__ import annotations

import threading

from std_msgs.msg import Header

from afm_ros.conversions import (
    FRAME_TASK,
    landmarks_to_msg,
    msg_to_landmarks,
    newer_landmarks,
    seconds_to_time,
    stamp_of,
    wait_for_landmarks,
)


class NewestLandmarkMap:
    def __init__(self, logger):
        self._logger = logger
        self._lock = threading.Lock()
        self._marks: dict[int, object] = {}
        self._stamp: float | None = None

    def take(self, msg) -> None:
        """Subscription callback: keep `msg` if it is at least as new as what is held."""
        with self._lock:
            if not newer_landmarks(msg, self._stamp):
                return
        try:
            marks = {mark.id: mark for mark in msg_to_landmarks(msg)}
        except ValueError as exc:
            self._logger.error(f"landmarks ignored: {exc}")
            return
        with self._lock:
            self._marks, self._stamp = marks, stamp_of(msg.header)

    @property
    def stamp(self) -> float | None:
        """The held map's stamp (s), None before the first."""
        with self._lock:
            return self._stamp

    def current(self) -> dict:
        """The landmarks by id, as held now (empty before the first map)."""
        with self._lock:
            return dict(self._marks)

    def wait(self, timeout: float = 5.0) -> dict:
        """The landmarks by id; when none are held yet, those that arrive within `timeout` s (a
        latched map reaches a node a moment after it is published, later under load)."""
        return wait_for_landmarks(self.current, timeout)

    def dropped(self, landmark_id: int, time: float):
        """Hold no landmark with `landmark_id` (it is no longer where the map had it); the whole
        map as a LandmarkArray stamped at `time`, or just after the newest map held."""
        return self._update(lambda held: {k: v for k, v in held.items() if k != landmark_id}, time)

    def moved(self, landmark, time: float):
        """Hold `landmark` in place of the one with its id; the whole map as a LandmarkArray
        stamped at `time`, or just after the newest map held, to publish."""
        return self._update(lambda marks: {**marks, landmark.id: landmark}, time)

    def _update(self, change, time: float):
        with self._lock:  # one step, so a map taken meanwhile is not overwritten
            self._marks = marks = change(self._marks)
            stamp = max(time, (self._stamp or 0.0) + 1e-6)
            header = Header(stamp=seconds_to_time(stamp), frame_id=FRAME_TASK)
            self._stamp = stamp_of(header)
        return landmarks_to_msg(list(marks.values()), header)
