"""Push plans: what every planner makes, the inputs they share, and the model they predict with.

Book ch. 2.3.3, 6.4.2-6.4.3 (Fig. 6.18) and 7.3 (Fig. 7.24-7.26, Table 7.6); SPEC section 5.
A plan is a list of tip strokes in the afm_task frame (SI units): each stroke is a straight
tip motion from `start` to `end`, in contact (pushing) or lifted. The executor
(afm_core.manipulation.execute) lifts the tip between strokes, so the order of the strokes is
the whole motion; nothing here moves anything. The planners: centre pushing
(afm_core.manipulation.centre_push), the virtual nano-hand zigzag (.nano_hand), the rod-like
hand (.rod_hand) and the arc-shaped hand (.arc_hand).

Frame of a push
---------------
u is the push axis (unit vector from the estimated particle centre c0 to the goal); "left" is
u turned by +90 deg (n = (-u_y, u_x)), as seen looking along the push. `along` and `lateral`
coordinates of a point p are (p - c0) . u and (p - c0) . n. D = R_P + R_T is the centre
distance of tip and particle at contact (the planar contact model of
afm_core.physics.pushing). lead(e) = sqrt(D^2 - e^2) is how far the particle's centre is
ahead of the tip along u when a path with lateral offset e touches it.

The model as the planner's predictor
------------------------------------
The planners predict with the project's pushing physics, afm_core.physics.pushing
.push_along_path, on an afm_core.physics.sample.Sample moved in place (simulate_strokes,
predict_particle), with an afm_core.physics.contact.ContactParams (default: its defaults with
the plan's tip radius); nothing here writes another model.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np

from afm_core.checks import non_negative, point, positive
from afm_core.instrument import ScannerLimits
from afm_core.physics.sample import distance_to_segment

NM = 1e-9
DEFAULT_TIP_RADIUS = 50e-9  # m, effective contact radius R_T (book 7.3: 50 nm)
DEFAULT_PARTICLE_RADIUS = 100e-9  # m, polystyrene spheres (book: ~100 nm)
DEFAULT_SIGMA = 10e-9  # m, centre uncertainty (book 6.4.3: 10 nm)
DEFAULT_MAX_DISTANCE = 20e-6  # m, longest push a plan accepts


# --------------------------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Stroke:
    """One straight tip motion (afm_task frame, m). contact=True pushes; False moves lifted."""

    start: np.ndarray
    end: np.ndarray
    contact: bool = True
    label: str = ""  # "left", "right", "centre", "rod", "axial", ...

    @property
    def length(self) -> float:
        return float(np.hypot(*(np.asarray(self.end) - np.asarray(self.start))))


@dataclass
class ParticleEstimate:
    """Where the particle is believed to be (afm_task frame) and how sure we are."""

    x: float
    y: float
    radius: float = DEFAULT_PARTICLE_RADIUS
    sigma: float = DEFAULT_SIGMA  # m, 1-sigma of the centre per axis (relative to the tip)

    @property
    def xy(self) -> np.ndarray:
        return np.array([self.x, self.y], dtype=float)


@dataclass
class PushPlan:
    """A list of strokes plus what the planner assumed and predicted."""

    kind: str  # "centre", "nano_hand", "rod", "arc"
    strokes: list[Stroke]
    particle: np.ndarray  # (2,) estimated start centre (rod: centre)
    goal: np.ndarray  # (2,) goal centre
    axis: np.ndarray  # (2,) unit push axis u (rod/arc: centre -> goal)
    particle_radius: float
    tip_radius: float
    # lateral coordinates of the (left, right) paths at the end
    path_offsets: tuple[float, float] | None = None
    predicted: np.ndarray | None = None  # (2,) predicted final centre (model, nominal start)
    # predicted centre (or pose) after each stroke
    predicted_track: list = field(default_factory=list)
    params: object = None
    goal_angle: float | None = None  # rod plans: goal axis angle (rad)
    predicted_angle: float | None = None
    extra: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.strokes)

    def __iter__(self) -> Iterator[Stroke]:
        return iter(self.strokes)

    def __getitem__(self, index):
        return self.strokes[index]

    @property
    def normal(self) -> np.ndarray:
        """Left of the push axis: u turned by +90 deg."""
        return np.array([-self.axis[1], self.axis[0]])

    def along(self, points) -> np.ndarray:
        return (np.asarray(points, float) - self.particle) @ self.axis

    def lateral(self, points) -> np.ndarray:
        return (np.asarray(points, float) - self.particle) @ self.normal


# --------------------------------------------------------------------------------------------
# Inputs every planner shares
# --------------------------------------------------------------------------------------------


def particle_estimate(obj, radius: float | None, sigma: float | None = None) -> ParticleEstimate:
    """Accept a ParticleEstimate, a Sphere / Landmark (x, y, radius) or a point (x, y)."""
    if isinstance(obj, ParticleEstimate):
        est = ParticleEstimate(
            obj.x,
            obj.y,
            obj.radius if radius is None else radius,
            obj.sigma if sigma is None else sigma,
        )
    elif hasattr(obj, "x") and hasattr(obj, "y"):
        r = radius if radius is not None else getattr(obj, "radius", DEFAULT_PARTICLE_RADIUS)
        est = ParticleEstimate(
            float(obj.x), float(obj.y), float(r), DEFAULT_SIGMA if sigma is None else sigma
        )
    else:
        p = point("particle", obj)
        est = ParticleEstimate(
            p[0],
            p[1],
            DEFAULT_PARTICLE_RADIUS if radius is None else radius,
            DEFAULT_SIGMA if sigma is None else sigma,
        )
    point("particle", (est.x, est.y))
    positive("particle.radius", est.radius, "m")
    non_negative("particle.sigma", est.sigma, "m")
    return est


def push_axis(
    start: np.ndarray, goal: np.ndarray, max_distance: float
) -> tuple[np.ndarray, float]:
    """The unit push axis from start to goal and the distance, refused beyond max_distance."""
    d = goal - start
    dist = float(np.hypot(*d))
    if dist == 0.0:
        raise ValueError("goal: the same point as the particle (distance 0 m): nothing to push")
    if dist > max_distance:
        raise ValueError(
            f"goal: {dist:.4e} m from the particle, beyond max_distance={max_distance:.4e} m"
        )
    return d / dist, dist


def check_plan_limits(plan: PushPlan, limits: ScannerLimits, margin: float = 0.0) -> None:
    """Raise ValueError naming the stroke and the limit if any stroke point leaves
    [margin, range - margin] of the scanner (or the goal does)."""
    for name, p in [
        ("goal", plan.goal),
        *[
            (f"strokes[{i}].{end}", getattr(s, end))
            for i, s in enumerate(plan.strokes)
            for end in ("start", "end")
        ],
    ]:
        x, y = float(p[0]), float(p[1])
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ValueError(f"{name}=({x}, {y}): must be finite")
        if not margin <= x <= limits.range_x - margin:
            raise ValueError(
                f"{name}.x={x:.4e} m: outside the scanner range [{margin:.4e}, "
                f"{limits.range_x - margin:.4e}] m"
            )
        if not margin <= y <= limits.range_y - margin:
            raise ValueError(
                f"{name}.y={y:.4e} m: outside the scanner range [{margin:.4e}, "
                f"{limits.range_y - margin:.4e}] m"
            )


# --------------------------------------------------------------------------------------------
# The pushing model as the planner's predictor
# --------------------------------------------------------------------------------------------


def model_contact_params(contact_params, tip_radius: float):
    """The model's ContactParams: the given ones, or the defaults with this tip radius."""
    from afm_core.physics.contact import ContactParams

    if contact_params is None:
        return ContactParams(tip_radius=tip_radius)
    return contact_params


def simulate_strokes(
    sample, strokes: Iterable[Stroke], contact_params, track_id: int | None = None
) -> list:
    """Apply the contact strokes to a Sample (afm_core.physics.sample) in place with
    afm_core.physics.pushing.push_along_path (lifted strokes move nothing). Returns the
    tracked object's (x, y[, angle]) after each stroke."""
    from afm_core.physics.pushing import push_along_path

    track = []
    objs = {o.id: o for o in sample.movable}
    for stroke in strokes:
        if stroke.contact:
            push_along_path(
                sample,
                np.array([stroke.start[0], stroke.end[0]]),
                np.array([stroke.start[1], stroke.end[1]]),
                1e-3,
                contact_params,
            )
        if track_id is not None:
            o = objs[track_id]
            track.append((o.x, o.y, o.angle) if hasattr(o, "angle") else (o.x, o.y))
    return track


def predict_particle(plan: PushPlan, contact_params=None, start=None) -> list[np.ndarray]:
    """The particle's centre after each stroke of `plan` in the pushing model, starting at
    `start` (default: the plan's estimate)."""
    from afm_core.physics.sample import Sample, Sphere

    c0 = plan.particle if start is None else point("start", start)
    sample = Sample(spheres=[Sphere(0, float(c0[0]), float(c0[1]), plan.particle_radius)])
    track = simulate_strokes(
        sample, plan.strokes, model_contact_params(contact_params, plan.tip_radius), 0
    )
    return [np.array(p) for p in track]


def path_blocker(start, goal, radius: float, tip_radius: float, others, tip_reach: float = 0.0):
    """The first of `others` (objects with x, y, radius: landmarks; a tube's or rod's also with
    length and orientation) a particle of `radius` would run into on its way from `start` to
    `goal` ((2,) m): the corridor it sweeps (its radius plus the other's), the tip's approach
    behind it and, for a zigzag, the tip running `tip_reach` (its centre's farthest offset)
    beside the push line. A goal at the start (a rod turned in place) sweeps the disc of
    `radius` about it. A tube or rod is in the way when any point of its axis is. None when
    the way is clear."""
    start, goal = np.asarray(start, float), np.asarray(goal, float)
    axis = goal - start
    length = float(np.hypot(*axis))
    if length == 0:
        near = [o for o in others if _axis_distance(o, start) < radius + o.radius]
        return min(near, key=lambda o: _axis_distance(o, start)) if near else None
    u = axis / length
    half_width = max(radius, tip_reach + tip_radius)
    hits = []
    for other in others:
        # the box of the sphere's test for each point of the other's axis, so a long tube whose
        # centre lies beside the corridor but whose body crosses it is found
        along = _first_in_box(
            other,
            start,
            u,
            (-(radius + 2 * tip_radius), length + radius + other.radius),
            half_width + other.radius,
        )
        if along is not None:
            hits.append((along, other))
    return min(hits, key=lambda h: h[0])[1] if hits else None


def _axis(other) -> tuple[np.ndarray, np.ndarray]:
    """The ends of the other's axis (both its centre for a sphere)."""
    half = 0.5 * float(getattr(other, "length", 0.0) or 0.0)
    angle = float(getattr(other, "orientation", 0.0) or 0.0)
    t = half * np.array([math.cos(angle), math.sin(angle)])
    centre = np.array([other.x, other.y], float)
    return centre - t, centre + t


def _axis_distance(other, point) -> float:
    """The distance from `point` to the other's axis."""
    return float(distance_to_segment(*_axis(other), point[0], point[1]))


def _first_in_box(other, start, u, along_range, half_width) -> float | None:
    """How far along `u` from `start` the other's axis (a point for a sphere) first enters the
    open box along_range x (-half_width, half_width); None when it stays out (the segment
    clipped to the box, Liang-Barsky)."""
    ends = [p - start for p in _axis(other)]
    (a0, c0), (a1, c1) = ((float(p @ u), float(p[0] * u[1] - p[1] * u[0])) for p in ends)
    lo, hi = 0.0, 1.0
    for p, q in (
        (-(a1 - a0), a0 - along_range[0]),
        (a1 - a0, along_range[1] - a0),
        (-(c1 - c0), c0 + half_width),
        (c1 - c0, half_width - c0),
    ):
        if p == 0.0:
            if q <= 0.0:
                return None
        elif p < 0.0:
            lo = max(lo, q / p)
        else:
            hi = min(hi, q / p)
    if lo > hi or (lo == hi and a0 != a1):
        return None
    return min(a0 + lo * (a1 - a0), a0 + hi * (a1 - a0))
