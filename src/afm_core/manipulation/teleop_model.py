"""What a teleoperated contact move is believed to do: where the tip is in the task frame and
which objects the push model says it pushes, segment by segment (the live view, issue 33).

Task frame (`BelievedTip`): the localizer's believed tip pose (/afm/tip_pose) is the tip's
task-frame position at the end of one commanded move; a commanded scanner point c maps to
pose + M (c - c_pose), M the calibration's scanner matrix and c_pose the commanded position
when the pose was made (push_steps.task_to_command, inverted). Before any pose the task frame
is taken to be the scanner frame (the localizer's own starting assumption).

Objects (`PushPredictor`): the newest landmark map as a Sample of spheres and rods/tubes, moved
in place by the project's pushing model (afm_core.physics.pushing.push_along_path, the one the
planners predict with) along each contact segment's task-frame path. The uncertainty of a
pushed object is its map sigma; the model's own error is not added (no measurement since, and
the operator sees the object's next image).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from afm_core.physics.contact import ContactParams
from afm_core.physics.pushing import push_along_path
from afm_core.physics.sample import Rod, Sample, Sphere

# a segment's path is integrated in time steps of this (push_along_path re-samples it in space
# anyway: its step is a fraction of the smallest radius, so nothing tunnels)
MODEL_DT = 1e-3  # s
# m: smaller objects are left out of the prediction. The model's mechanics step is a fraction
# of the smallest radius near the path, so a 1 fm sphere in a map (nothing checks a radius but
# > 0) made one 50 nm segment 10^8 steps and the teleop node ran out of memory; 0.1 nm is an
# atom's size, below any particle a tip pushes (at it a segment takes about 10 ms)
MIN_RADIUS = 1e-10


class BelievedTip:
    """Commanded scanner points -> believed task-frame points (module docstring)."""

    def __init__(self, scanner_matrix=None):
        self.matrix = np.eye(2) if scanner_matrix is None else np.asarray(scanner_matrix, float)
        self.pose: np.ndarray | None = None
        self.commanded_at_pose: np.ndarray | None = None

    def observe(self, pose_xy, commanded_xy) -> None:
        """A believed tip position and the commanded position it belongs to."""
        self.pose = np.asarray(pose_xy, float)
        self.commanded_at_pose = np.asarray(commanded_xy, float)

    def to_task(self, commanded_xy) -> np.ndarray:
        c = np.asarray(commanded_xy, float)
        if self.pose is None:
            return c.copy()
        return self.pose + self.matrix @ (c - self.commanded_at_pose)


@dataclass(frozen=True)
class PredictedObject:
    id: int
    kind: str  # "sphere", "rod" or "tube"
    x: float  # m, task frame
    y: float
    orientation: float  # rad (rods, tubes)
    radius: float  # m
    length: float  # m (rods, tubes; 0 for spheres)
    sigma: float  # m, 1-sigma radius of the position


class PushPredictor:
    """The push model run on the landmarks along the teleoperated contact segments."""

    def __init__(self, contact: ContactParams | None = None):
        self.contact = contact if contact is not None else ContactParams()
        self.sample = Sample()
        self.sigma: dict[int, float] = {}
        self.pushed: set[int] = set()

    def load(self, landmarks) -> None:
        """Start over from a landmark map (afm_core.imaging.landmarks.Landmark objects, task
        frame); pits and unknown kinds do not move and are left out, and so are objects whose
        shape is not finite or smaller than MIN_RADIUS."""
        spheres, rods, sigma = [], [], {}
        for mark in landmarks:
            shape = (mark.x, mark.y, mark.radius, mark.length, mark.orientation)
            if not (np.all(np.isfinite(shape)) and mark.radius >= MIN_RADIUS):
                continue
            if mark.kind == "sphere":
                spheres.append(Sphere(int(mark.id), float(mark.x), float(mark.y), mark.radius))
            elif mark.kind in ("rod", "tube") and mark.length > 0:
                rods.append(
                    Rod(
                        int(mark.id),
                        float(mark.x),
                        float(mark.y),
                        float(mark.orientation),
                        float(mark.length),
                        float(mark.radius),
                        mark.kind,
                    )
                )
            else:
                continue
            cov = np.asarray(mark.covariance, float).reshape(2, 2)
            if np.all(np.isfinite(cov)):
                sigma[int(mark.id)] = math.sqrt(max(float(np.max(np.linalg.eigvalsh(cov))), 0.0))
            # else none: objects() says nan (unknown), where eigvalsh of a NaN gave -0.0 (known
            # exactly)
        self.sample = Sample(spheres=spheres, rods=rods)
        self.sigma = sigma
        self.pushed = set()

    def push(self, start, end, duration: float) -> list[int]:
        """Move the objects the tip meets going from `start` to `end` (task frame, m) in
        contact in `duration` s; the ids of those that moved in this segment."""
        if not self.sample.movable:
            return []
        steps = max(2, int(math.ceil(duration / MODEL_DT)) + 1)
        xs = np.linspace(float(start[0]), float(end[0]), steps)
        ys = np.linspace(float(start[1]), float(end[1]), steps)
        result = push_along_path(self.sample, xs, ys, duration / (steps - 1), self.contact)
        self.pushed.update(int(i) for i in result.moved_ids)
        return [int(i) for i in result.moved_ids]

    def objects(self, only_pushed: bool = True) -> list[PredictedObject]:
        """The objects as believed now: those pushed since `load` (or all)."""
        out = []
        for obj in self.sample.movable:
            if only_pushed and obj.id not in self.pushed:
                continue
            rod = isinstance(obj, Rod)
            out.append(
                PredictedObject(
                    int(obj.id),
                    obj.kind,
                    float(obj.x),
                    float(obj.y),
                    float(obj.angle) if rod else 0.0,
                    float(obj.radius),
                    float(obj.length) if rod else 0.0,
                    self.sigma.get(int(obj.id), math.nan),
                )
            )
        return out
