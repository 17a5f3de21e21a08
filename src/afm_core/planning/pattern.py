"""Assembly patterns: the goals of a small pattern of particles, placed on a mapped sample and
assigned to particles so that every push can run in any order (book 6.3, 7.3: assembly as
the main job of a nano-manipulation system).

`pattern_offsets(shape, count, pitch)` gives the pattern about its centroid ("line", "L", or
"ring"). `plan_pattern(objects, offsets, area=..., limits=...)` places it on the sample: it
tries the pattern turned by each of `angles` (default: the four right angles) at centres on a
grid over the mapped area and, for each, assigns particles to goals by the least total push
distance (Hungarian method, scipy's `linear_sum_assignment`), then keeps the placement with the
least total distance that passes every check:

- every goal lies inside the mapped area (what lies outside it is not known to be clear) and
  inside the scanner's range;
- every goal is clear of every object other than the particle pushed there, by `clearance`
  between their edges (a rod or tube counts as its bounding circle), and no object is nearer
  a goal than the pattern's own neighbours are (so whatever keeps the pattern's neighbours
  out of the way, DEFAULT_PITCH, keeps the others out too);
- every particle's way from its start to its goal is clear of the other objects' starts and of
  the other goals (`afm_core.manipulation.path_blocker`, each radius grown by `clearance`):
  whatever order the planner gives (PlanSequence orders by observation distance only), every
  other particle is then either still at its start or already at its goal, and neither lies in
  the way;
- no push is longer than `max_push`.

Only spheres are pushed; rods, tubes and the spheres left out are obstacles. All SI (m), in
the map's frame (afm_task). Bad input raises ValueError naming the field and its limit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from afm_core import checks
from afm_core.instrument import ScannerLimits
from afm_core.manipulation.plans import path_blocker

SHAPES = ("line", "L", "ring")
MAX_COUNT = 20  # the Hungarian assignment and the grid search stay well under a second
# Free room between a pushed particle's edge and any other object's edge, on its way and at
# its goal: the nano-hand's zigzag runs the tip L_h/2 = 60 nm beside the particle's centre
# line, so with R_T = 50 nm it sweeps 10 nm beyond a 100 nm particle's edge; 3 sigma of a
# mapped centre (book Fig. 7.10: 5 nm) and of the tip after localizing (~15 nm) add 60 nm,
# rounded up to the tip's diameter (2 R_T) so the tip can pass between the two.
DEFAULT_CLEARANCE = 100e-9  # m
# Neighbours in a pattern: the closed loop's local lines across a particle reach
# R + R_T + 3 sigma + 50 nm (particle_observation.line_half_length: ~250 nm for a 100 nm
# sphere) from its centre, and a neighbour's tip-broadened edge starts R + R_T = 150 nm from
# its own: 400 nm keeps a placed neighbour out of the lines that place the next particle.
DEFAULT_PITCH = 400e-9  # m
DEFAULT_MAX_PUSH = 1.5e-6  # m: the nano-hand's before/after rescans stay small (7.3)
# the pattern as given and turned by each right angle: a letter that does not fit one way often
# fits another, and a right angle keeps it upright to a reader
DEFAULT_ANGLES = (0.0, math.pi / 2, math.pi, 3 * math.pi / 2)
GRID_STEP_FRACTION = 0.25  # the placement grid's step as a share of the pitch


@dataclass(frozen=True)
class PatternObject:
    """What the plan needs of a mapped object (an afm_core.imaging.Landmark has these)."""

    id: int
    kind: str  # "sphere" pushed; anything else an obstacle
    x: float
    y: float
    radius: float
    length: float = 0.0  # m, a rod's or tube's axis length


@dataclass(frozen=True)
class PatternPlan:
    """Particles and their goals, in the same order; `offsets` the pattern as asked."""

    particle_ids: tuple[int, ...]
    starts: np.ndarray  # (n, 2) m, where the map has them
    goals: np.ndarray  # (n, 2) m
    centre: np.ndarray  # (2,) m, the pattern's centroid
    total_distance: float  # m, the sum of the straight pushes
    placements_tried: int

    @property
    def distances(self) -> np.ndarray:
        return np.hypot(*(self.goals - self.starts).T)


def pattern_offsets(shape: str, count: int, pitch: float, angle: float = 0.0) -> np.ndarray:
    """(count, 2) m: the pattern's points about their centroid, neighbours `pitch` apart,
    turned by `angle` (rad). "line": along x; "L": a vertical bar of ceil(count / 2) + 1 and
    the rest along +x from its foot; "ring": a regular polygon with sides of `pitch`."""
    if shape not in SHAPES:
        raise ValueError(f"shape={shape!r}: must be one of {list(SHAPES)}")
    count = checks.count("count", count, 2 if shape != "ring" else 3, MAX_COUNT)
    pitch = checks.positive("pitch", pitch, "m", upper=10e-6)
    angle = checks.finite("angle", angle, "rad")
    if shape == "line":
        points = np.column_stack([np.arange(count) * pitch, np.zeros(count)])
    elif shape == "L":
        tall = min(count - 1, math.ceil(count / 2) + 1)
        bar = [(0.0, (tall - 1 - k) * pitch) for k in range(tall)]
        foot = [((k + 1) * pitch, 0.0) for k in range(count - tall)]
        points = np.array(bar + foot)
    else:
        circumradius = pitch / (2 * math.sin(math.pi / count))
        phi = 2 * math.pi * np.arange(count) / count + math.pi / 2
        points = circumradius * np.column_stack([np.cos(phi), np.sin(phi)])
    points = points - points.mean(axis=0)
    c, s = math.cos(angle), math.sin(angle)
    return points @ np.array([[c, s], [-s, c]])


def _objects(objects) -> list[PatternObject]:
    out = []
    for i, o in enumerate(objects):
        name = f"objects[{i}]"
        kind = str(getattr(o, "kind", "sphere"))
        out.append(
            PatternObject(
                int(o.id),
                kind,
                checks.finite(f"{name}.x", o.x, "m"),
                checks.finite(f"{name}.y", o.y, "m"),
                checks.positive(f"{name}.radius", o.radius, "m"),
                checks.non_negative(f"{name}.length", getattr(o, "length", 0.0) or 0.0, "m"),
            )
        )
    ids = [o.id for o in out]
    if len(set(ids)) != len(ids):
        raise ValueError("objects: each id once")
    return out


def _reach(o: PatternObject) -> float:
    """The radius of the circle that holds the object (a rod's bounding circle)."""
    return o.radius if o.kind == "sphere" else o.radius + 0.5 * o.length


def _area(area, limits: ScannerLimits) -> np.ndarray:
    try:
        a = np.array(area, dtype=float).reshape(4)
    except (TypeError, ValueError):
        raise ValueError(f"area: must be (x0, y0, x1, y1) in m, got {area!r}") from None
    if not np.isfinite(a).all() or not (a[0] < a[2] and a[1] < a[3]):
        raise ValueError(f"area={a.tolist()}: must be finite with x0 < x1 and y0 < y1 (m)")
    inside = np.array([0.0, 0.0, limits.range_x, limits.range_y])
    return np.array([max(a[0], 0.0), max(a[1], 0.0), min(a[2], inside[2]), min(a[3], inside[3])])


class _Disc:
    """An object as path_blocker sees it: centre and radius (grown by the clearance)."""

    def __init__(self, x: float, y: float, radius: float, ident: int):
        self.x, self.y, self.radius, self.id = x, y, radius, ident


def plan_pattern(
    objects,
    offsets,
    *,
    area,
    limits: ScannerLimits | None = None,
    clearance: float = DEFAULT_CLEARANCE,
    max_push: float = DEFAULT_MAX_PUSH,
    tip_radius: float = 50e-9,
    angles=DEFAULT_ANGLES,
) -> PatternPlan:
    """Place the pattern `offsets` ((n, 2) m about its centroid, e.g. `pattern_offsets`) on
    the mapped `objects` (landmarks: id, kind, x, y, radius, length) inside `area` (x0, y0, x1,
    y1) m, the region the map covers; the checks are the module docstring's. ValueError
    naming the field when the input is bad or no placement passes (saying what failed
    most)."""
    limits = limits or ScannerLimits()
    things = _objects(objects)
    try:
        pattern = np.array(offsets, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"offsets: must be an (n, 2) array in m, got {offsets!r}") from None
    if pattern.ndim != 2 or pattern.shape[1] != 2 or len(pattern) < 1:
        raise ValueError(f"offsets: must be an (n, 2) array in m, got shape {pattern.shape}")
    if not np.isfinite(pattern).all():
        raise ValueError("offsets: must be finite (m)")
    clearance = checks.non_negative("clearance", clearance, "m", upper=5e-6)
    max_push = checks.positive("max_push", max_push, "m")
    tip_radius = checks.positive("tip_radius", tip_radius, "m")
    box = _area(area, limits)
    spheres = [o for o in things if o.kind == "sphere"]
    if len(spheres) < len(pattern):
        raise ValueError(
            f"offsets: {len(pattern)} points but the map has {len(spheres)} spheres to push"
        )
    radius = max(o.radius for o in spheres)
    spacing = min(
        (np.hypot(*(a - b)) for i, a in enumerate(pattern) for b in pattern[i + 1 :]),
        default=2 * radius + clearance,  # one point: no neighbours
    )
    if spacing < 2 * radius + clearance:
        raise ValueError(
            f"offsets: points {spacing * 1e9:.0f} nm apart; particles of radius "
            f"{radius * 1e9:.0f} nm need at least {(2 * radius + clearance) * 1e9:.0f} nm "
            "(two radii and the clearance)"
        )
    try:
        turns = [checks.finite(f"angles[{k}]", a, "rad") for k, a in enumerate(angles)]
    except TypeError:
        raise ValueError(f"angles: must be a sequence of angles in rad, got {angles!r}") from None
    if not turns:
        raise ValueError("angles: must hold at least one angle (rad)")
    edge = radius + clearance  # a goal's particle stays this far inside the mapped area
    step = GRID_STEP_FRACTION * max(spacing, 2 * radius) if len(pattern) > 1 else radius
    starts = np.array([[o.x, o.y] for o in spheres])
    best, failures, tried, fitted = None, {}, 0, 0
    for angle in turns:
        c, s = math.cos(angle), math.sin(angle)
        turned = pattern @ np.array([[c, s], [-s, c]])
        low = box[:2] + edge - turned.min(axis=0)
        high = box[2:] - edge - turned.max(axis=0)
        if np.any(low > high):
            continue
        fitted += 1
        for cy in np.arange(low[1], high[1] + 0.5 * step, step):
            for cx in np.arange(low[0], high[0] + 0.5 * step, step):
                tried += 1
                goals = turned + (cx, cy)
                cost = np.hypot(
                    starts[:, None, 0] - goals[None, :, 0], starts[:, None, 1] - goals[None, :, 1]
                )
                rows, cols = linear_sum_assignment(cost)
                total = float(cost[rows, cols].sum())
                if best is not None and total >= best[0]:
                    continue
                chosen = [spheres[r] for r in rows]
                why = _placement_fault(
                    chosen, goals[cols], things, clearance, spacing, max_push, tip_radius
                )
                if why:
                    failures[why] = failures.get(why, 0) + 1
                    continue
                best = (total, chosen, goals[cols], np.array([cx, cy]))
    if not fitted:
        raise ValueError(
            f"offsets: the pattern ({np.ptp(pattern[:, 0]) * 1e9:.0f} x "
            f"{np.ptp(pattern[:, 1]) * 1e9:.0f} nm) does not fit in the area "
            f"{(box[2] - box[0]) * 1e9:.0f} x {(box[3] - box[1]) * 1e9:.0f} nm with "
            f"{edge * 1e9:.0f} nm to spare at its edges, at any of the angles"
        )
    if best is None:
        worst = max(failures, key=failures.get) if failures else "no placement"
        raise ValueError(
            f"offsets: no placement of the {len(pattern)}-point pattern in the area passes "
            f"({tried} tried; most often: {worst})"
        )
    total, chosen, goals, centre = best
    order = np.argsort([o.id for o in chosen])
    return PatternPlan(
        tuple(chosen[i].id for i in order),
        np.array([[chosen[i].x, chosen[i].y] for i in order]),
        goals[order],
        centre,
        total,
        tried,
    )


def _placement_fault(chosen, goals, things, clearance, spacing, max_push, tip_radius) -> str:
    """Why this assignment fails the module's checks ("" when it passes); `spacing`: the
    pattern's least distance between neighbours."""
    for o, goal in zip(chosen, goals):
        if math.hypot(goal[0] - o.x, goal[1] - o.y) > max_push:
            return f"a push longer than max_push={max_push:.3g} m"
        for other in things:
            reach = _reach(other)
            nearest = max(o.radius + reach + clearance, spacing + reach - other.radius)
            if other.id != o.id and math.hypot(goal[0] - other.x, goal[1] - other.y) < nearest:
                return "a goal too near another object"
    for k, (o, goal) in enumerate(zip(chosen, goals)):
        obstacles = [
            _Disc(p.x, p.y, _reach(p) + clearance, p.id) for p in things if p.id != o.id
        ] + [
            _Disc(g[0], g[1], q.radius + clearance, -1 - j)
            for j, (q, g) in enumerate(zip(chosen, goals))
            if j != k
        ]
        if path_blocker((o.x, o.y), goal, o.radius, tip_radius, obstacles) is not None:
            return "a way blocked by another object or goal"
    return ""
