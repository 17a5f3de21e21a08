"""The rod-like virtual nano-hand: translate and rotate a rod or tube (book Fig. 2.11, 7.26).

Two pushing points at +-grip * L/2 along a rod or tube, pushed alternately across the axis
(and, for an axial error, at an end cap along the axis), each push at most `step` deep, chosen
greedily by the model (the rod law of the pushing model, afm_core.physics.rod_pushing: a push
off the centre turns the rod about a point towards the far end) until the predicted pose is
within tolerance: translate and rotate a rod, e.g. to bridge two electrodes (pass them as
`electrodes`, the model treats them as walls).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from afm_core.checks import finite, point, positive
from afm_core.instrument import ScannerLimits
from afm_core.manipulation.plans import (
    DEFAULT_MAX_DISTANCE,
    DEFAULT_TIP_RADIUS,
    NM,
    PushPlan,
    Stroke,
    check_plan_limits,
    model_contact_params,
    simulate_strokes,
)


def rod_hand_plan(
    rod,
    goal_pose,
    *,
    tip_radius: float = DEFAULT_TIP_RADIUS,
    step: float = 40 * NM,
    grip: float = 0.8,
    clearance: float = 60 * NM,
    tolerance: float = 5 * NM,
    max_strokes: int = 200,
    axial: bool = False,
    electrodes: Sequence = (),
    contact_params=None,
    limits: ScannerLimits | None = None,
    max_distance: float = DEFAULT_MAX_DISTANCE,
) -> PushPlan:
    """A rod-like virtual nano-hand: translate and rotate a rod/tube to goal_pose (x, y, angle).

    rod: anything with x, y, angle, length, radius (an afm_core.physics.sample.Rod or a tube
    Landmark converted). Two pushing points at +-grip * length/2 are pushed alternately across
    the axis (at most `step` deep per stroke, from `clearance` outside the rod); the greedy
    choice runs on the pushing model until the predicted axis points are within `tolerance` of
    the goal's lines (or max_strokes). Motion along the rod's own axis is not controlled unless
    axial=True, which also pushes an end cap along the axis when that error is the largest: on
    a thin tube that push is as unstable as centre pushing a sphere (a tip a few nm off the axis
    slides off the cap and turns the tube), so it is off by default; plan goals across the axis
    plus a rotation."""
    from afm_core.physics.sample import Electrode, Rod, Sample

    rx, ry, ang, length, radius = _rod_pose(rod)
    gx, gy, ga = _goal_pose(
        goal_pose, (rx, ry, ang), length, tip_radius, step, tolerance, grip, max_distance
    )
    walls = [
        Electrode(1000 + i, e.x0, e.y0, e.x1, e.y1, e.thickness) for i, e in enumerate(electrodes)
    ]
    model_rod = Rod(0, rx, ry, ang, length, radius, getattr(rod, "kind", "rod"))
    sample = Sample(rods=[model_rod], electrodes=walls)
    hand = _RodHand(
        (gx, gy, ga),
        grip * 0.5 * length,
        length,
        tip_radius + radius,
        clearance,
        step,
        tolerance,
        axial,
    )
    cp = model_contact_params(contact_params, tip_radius)
    strokes, track = hand.pushes(sample, model_rod, cp, max_strokes)
    if not strokes:
        raise ValueError("goal_pose: nothing to push within tolerance")
    c0 = np.array([rx, ry])
    g = np.array([gx, gy])
    axis = (
        (g - c0) / np.hypot(*(g - c0))
        if np.hypot(*(g - c0)) > 0
        else np.array([math.cos(ang), math.sin(ang)])
    )
    plan = PushPlan(
        "rod",
        strokes,
        c0,
        g,
        axis,
        radius,
        tip_radius,
        predicted=np.array(track[-1][:2]),
        predicted_track=track,
        params={"step": step, "grip": grip, "clearance": clearance, "tolerance": tolerance},
        goal_angle=ga,
        predicted_angle=track[-1][2],
        extra={"start_angle": ang, "length": length, "converged": len(strokes) < max_strokes},
    )
    if limits is not None:
        check_plan_limits(plan, limits)
    return plan


def _wrap_half_turn(angle: float) -> float:
    """Angle difference folded into (-pi/2, pi/2] (a rod's axis has no head)."""
    return (angle + 0.5 * math.pi) % math.pi - 0.5 * math.pi


def _rod_pose(rod) -> tuple[float, float, float, float, float]:
    """(x, y, angle, length, radius) of anything with those attributes, checked."""
    for name in ("x", "y", "angle", "length", "radius"):
        if not hasattr(rod, name):
            raise ValueError(f"rod: needs x, y, angle, length, radius (missing {name})")
    rx, ry = point("rod", (rod.x, rod.y))
    ang = finite("rod.angle", rod.angle)
    length = positive("rod.length", rod.length, "m")
    radius = positive("rod.radius", rod.radius, "m")
    return rx, ry, ang, length, radius


def _goal_pose(
    goal_pose, start, length, tip_radius, step, tolerance, grip, max_distance
) -> tuple[float, float, float]:
    """The goal (x, y, angle), its angle taken within a half turn of the rod's (the material
    orientation is kept); refused when too far or already reached, or the hand's sizes are
    not positive."""
    rx, ry, ang = start
    try:
        gx, gy, ga = (float(v) for v in goal_pose)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"goal_pose={goal_pose!r}: must be (x, y, angle)") from exc
    if not all(math.isfinite(v) for v in (gx, gy, ga)):
        raise ValueError(f"goal_pose={goal_pose!r}: must be finite")
    positive("tip_radius", tip_radius, "m")
    positive("step", step, "m")
    positive("tolerance", tolerance, "m")
    positive("grip", grip, upper=1.0)
    dist = math.hypot(gx - rx, gy - ry)
    dang = _wrap_half_turn(ga - ang)
    if dist > max_distance:
        raise ValueError(
            f"goal_pose: {dist:.4e} m from the rod, beyond max_distance={max_distance:.4e} m"
        )
    if dist < tolerance and abs(dang) * 0.5 * length * grip < tolerance:
        raise ValueError("goal_pose: the rod is already there (within tolerance): nothing to push")
    return gx, gy, ang + dang


class _RodHand:
    """The greedy choice of the next push on the rod as the model has it now."""

    def __init__(self, goal, half_grip, length, reach, clearance, step, tolerance, axial):
        self.gx, self.gy, ga = goal
        self.goal_axis = np.array([math.cos(ga), math.sin(ga)])
        self.half_grip, self.length, self.reach = half_grip, length, reach
        self.clearance, self.step, self.tolerance, self.axial = clearance, step, tolerance, axial

    def pushes(self, sample, model_rod, contact_params, max_strokes: int) -> tuple[list, list]:
        """Push greedily in the model (`sample`, with `model_rod` in it, moved in place) until
        within tolerance or max_strokes: the strokes and the rod's (x, y, angle) after each."""
        strokes: list[Stroke] = []
        track = []
        last_point = None
        for _ in range(max_strokes):
            stroke = self.next_push(model_rod, last_point)
            if stroke is None:
                break
            simulate_strokes(sample, [stroke], contact_params)
            strokes.append(stroke)
            track.append((model_rod.x, model_rod.y, model_rod.angle))
            last_point = stroke.label
        return strokes, track

    def point_errors(self, c: np.ndarray, t: np.ndarray, n: np.ndarray) -> list:
        """(|error|, label, position along the rod, signed error) of each pushing point (across
        the axis) and, with axial, of the centre along the axis."""
        # goal angle relative to the current one (keep the material orientation)
        g_dir = self.goal_axis if self.goal_axis @ t >= 0 else -self.goal_axis
        options = []
        for label, sp in (("rod+", self.half_grip), ("rod-", -self.half_grip)):
            here = c + sp * t
            there = np.array([self.gx, self.gy]) + sp * g_dir
            r = float((there - here) @ n)
            options.append((abs(r), label, sp, r))
        if self.axial:
            along = float((np.array([self.gx, self.gy]) - c) @ t)
            options.append((abs(along), "axial", 0.0, along))
        return options

    def next_push(self, model_rod, last_point: str | None) -> Stroke | None:
        """The push on the worst point, at most `step` deep; None when all are within
        tolerance."""
        c = np.array([model_rod.x, model_rod.y])
        t = np.array([math.cos(model_rod.angle), math.sin(model_rod.angle)])
        n = np.array([-t[1], t[0]])
        options = self.point_errors(c, t, n)
        worst = max(options, key=lambda o: o[0])
        if worst[0] < self.tolerance:
            return None
        # alternate the two points when both are off (the rod-like hand), never the same twice
        # in a row unless it is the only one left
        normal_opts = sorted(
            [o for o in options if o[1] != "axial" and o[0] >= self.tolerance],
            key=lambda o: -o[0],
        )
        if worst[1] != "axial" and len(normal_opts) == 2 and normal_opts[0][1] == last_point:
            worst = normal_opts[1]
        _, label, sp, r = worst
        depth = min(abs(r), self.step)
        sign = 1.0 if r > 0 else -1.0
        if label == "axial":
            # push the rear end cap along the axis
            where = c - sign * (0.5 * self.length) * t
            d = sign * t
        else:
            where = c + sp * t
            d = sign * n
        start = where - (self.reach + self.clearance) * d
        end = where - self.reach * d + depth * d
        return Stroke(start, end, True, label)
