"""What reaches the viewer from outside, checked without ROS: a Twist a Foxglove client publishes
(the Teleop panel, a joystick panel), and the status and feedback of the graph's actions.

A client's message is refused, never forwarded, unless it is a JSON object of the
geometry_msgs/Twist shape whose numbers are all finite; the reason names the field.
"""

from __future__ import annotations

import json
import math
import numbers

TWIST_SCHEMAS = ("geometry_msgs/Twist", "geometry_msgs/msg/Twist", "")  # "" : the client gave none
CLIENT_ENCODING = "json"  # what the server advertises (supported_encodings) and accepts
AXES = ("x", "y", "z")
MAX_PAYLOAD = 4096  # bytes: a Twist in JSON is ~100; anything far larger is not one

# action_msgs/GoalStatus codes
STATUS_NAMES = {
    0: "unknown",
    1: "accepted",
    2: "executing",
    3: "canceling",
    4: "succeeded",
    5: "canceled",
    6: "aborted",
}
RUNNING = ("accepted", "executing", "canceling")


def parse_twist(payload: bytes) -> dict:
    """A client's JSON message -> {"linear": {x, y, z}, "angular": {x, y, z}} in floats (m/s,
    rad/s; a missing part or axis is 0). ValueError naming the field when it is not one."""
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"message of {len(payload)} bytes: a Twist is at most {MAX_PAYLOAD}")
    try:
        data = json.loads(payload)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"not JSON: {exc}") from exc
    except RecursionError as exc:  # 2000 nested brackets fit in MAX_PAYLOAD
        raise ValueError("not a Twist: the JSON nests too deep") from exc
    if not isinstance(data, dict):
        raise ValueError(
            f"expected a JSON object with linear and angular, got {type(data).__name__}"
        )
    unknown = sorted(set(data) - {"linear", "angular"})
    if unknown:
        raise ValueError(f"unknown field(s) {unknown}: a Twist has linear and angular")
    out = {}
    for part in ("linear", "angular"):
        vector = data.get(part, {})
        if not isinstance(vector, dict):
            raise ValueError(f"{part}: expected an object with x, y, z")
        extra = sorted(set(vector) - set(AXES))
        if extra:
            raise ValueError(f"{part}: unknown field(s) {extra}")
        out[part] = {}
        for axis in AXES:
            value = vector.get(axis, 0.0)
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise ValueError(f"{part}.{axis}={value!r}: must be a number")
            try:  # JSON's integers have no bound: 10**400 is no float
                number = float(value)
            except OverflowError:
                number = math.inf
            if not math.isfinite(number):
                shown = repr(value) if len(repr(value)) <= 24 else f"{repr(value)[:20]}..."
                raise ValueError(f"{part}.{axis}={shown}: must be finite")
            out[part][axis] = number
    return out


def goal_id(uuid) -> str:
    """A unique_identifier_msgs/UUID (16 bytes) as hex."""
    return bytes(int(b) for b in uuid.uuid).hex()


class ActionStates:
    """The latest status and feedback of each action's goals, as JSON for a Raw Messages panel:
    {"action", "goal_id", "status", "feedback"} of the newest goal, and every goal's status."""

    def __init__(self):
        self.states: dict[str, dict] = {}

    def status(self, action: str, status_array) -> dict:
        """An action_msgs/GoalStatusArray for `action`: the state to show."""
        state = self.states.setdefault(action, {"action": action, "goals": {}, "feedback": None})
        state["goals"] = {
            goal_id(s.goal_info.goal_id): STATUS_NAMES.get(int(s.status), str(int(s.status)))
            for s in status_array.status_list
        }
        return self.view(action)

    def feedback(self, action: str, goal: str, feedback: dict) -> dict:
        state = self.states.setdefault(action, {"action": action, "goals": {}, "feedback": None})
        state["feedback"], state["feedback_goal"] = feedback, goal
        return self.view(action)

    def view(self, action: str) -> dict:
        state = self.states[action]
        goals = state["goals"]
        running = [g for g, s in goals.items() if s in RUNNING]
        newest = (running or [state.get("feedback_goal") or next(reversed(goals), "")])[-1]
        return {
            "action": action,
            "goal_id": newest,
            "status": goals.get(newest, "unknown"),
            "feedback": state["feedback"] if state.get("feedback_goal") == newest else None,
            "goals": goals,
        }
