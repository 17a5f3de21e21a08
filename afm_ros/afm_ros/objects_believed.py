"""Objects as a model believes them (afm_msgs/ObjectArray on /afm/objects/believed): the push
model's prediction after a stroke, or where local lines or a rescan observed the object; what
a live view draws while a push runs (no rescan needed to see the particle move)."""

from __future__ import annotations

import math

import numpy as np
from std_msgs.msg import Header

from afm_core.manipulation.execute import OBSERVED, PREDICTED
from afm_ros.conversions import FRAME_TASK, OBJECT_KINDS, seconds_to_time

SOURCES = {PREDICTED: 0, OBSERVED: 1}  # afm_msgs/ObjectArray.PREDICTED / OBSERVED


def position_sigma(covariance) -> float:
    """1-sigma radius of a 2x2 position covariance (m^2): its major semi-axis, so the circle
    of that radius holds the ellipse; nan when unknown."""
    if covariance is None:
        return math.nan
    values = np.linalg.eigvalsh(np.asarray(covariance, float).reshape(2, 2))
    return float(math.sqrt(max(values.max(), 0.0)))


def believed_objects(landmark, position, covariance, belief: str, origin: str, time: float):
    """One object (a core Landmark: its kind and size) at `position` (task frame, m) as an
    ObjectArray stamped at instrument time `time` (s). belief: PREDICTED or OBSERVED."""
    from afm_msgs.msg import ObjectArray, ObjectState

    if belief not in SOURCES:
        raise ValueError(f"belief={belief!r}: expected one of {sorted(SOURCES)}")
    state = ObjectState(id=int(landmark.id), kind=OBJECT_KINDS.get(landmark.kind, 0))
    state.position.x, state.position.y = (float(v) for v in np.asarray(position, float)[:2])
    state.position.z = float(landmark.radius)
    state.radius = float(landmark.radius)
    state.length = float(landmark.length)
    state.orientation = float(landmark.orientation)
    return ObjectArray(
        header=Header(stamp=seconds_to_time(time), frame_id=FRAME_TASK),
        source=SOURCES[belief],
        origin=origin,
        objects=[state],
        position_sigma=[position_sigma(covariance)],
    )
