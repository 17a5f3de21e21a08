"""The arc-shaped virtual nano-hand: gathering particles onto a ring (book 7.3: Fig. 7.26).

Gathering particles onto a ring (the hexagon of Fig. 7.26f with six particles): slots equally
spaced on the ring, particles assigned to slots by minimum total distance (Hungarian
assignment), then each particle is carried to its slot by a nano-hand zigzag
(afm_core.manipulation.nano_hand) aimed radially; the hands' last strokes lie on an arc around
the ring's centre, together they form the arc-shaped hand. Particles are pushed nearest-first
and the whole plan is checked in the model with all particles present.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from afm_core.checks import count, finite, point, positive
from afm_core.instrument import ScannerLimits
from afm_core.manipulation.nano_hand import NanoHandParams, nano_hand_plan
from afm_core.manipulation.plans import (
    DEFAULT_MAX_DISTANCE,
    DEFAULT_TIP_RADIUS,
    NM,
    ParticleEstimate,
    PushPlan,
    Stroke,
    check_plan_limits,
    model_contact_params,
    particle_estimate,
    simulate_strokes,
)


def arc_hand_plan(
    particles: Sequence,
    centre,
    radius: float,
    *,
    slots: int | None = None,
    phase: float = 0.0,
    params: NanoHandParams | None = None,
    tip_radius: float = DEFAULT_TIP_RADIUS,
    tolerance: float = 2 * NM,
    contact_params=None,
    limits: ScannerLimits | None = None,
    max_distance: float = DEFAULT_MAX_DISTANCE,
) -> PushPlan:
    """Gather particles onto a ring of `radius` about `centre`: `slots` equally spaced places
    (default: one per particle, so six particles make the hexagon of Fig. 7.26f) starting at
    angle `phase`; each particle is assigned a slot (minimum total distance) and carried there
    by a nano-hand zigzag aimed at it (particles already within `tolerance` of their slot are
    left alone). The plan's predicted_track holds the predicted centres of all particles after
    the last stroke (model run with all particles present); extra["assignment"] maps particle
    index -> slot (x, y)."""
    from afm_core.physics.sample import Sample, Sphere

    ests = [particle_estimate(p, None) for p in particles]
    if not ests:
        raise ValueError("particles: empty; nothing to gather")
    c = point("centre", centre)
    slot_xy = _ring_slots(ests, c, radius, slots, phase)
    assignment, order = _assign(ests, slot_xy)
    strokes: list[Stroke] = []
    sub_plans = {}
    for i in order:
        e = ests[i]
        if np.hypot(*(e.xy - assignment[i])) <= tolerance:
            continue
        sub = nano_hand_plan(
            e,
            assignment[i],
            params,
            tip_radius=tip_radius,
            contact_params=contact_params,
            max_distance=max_distance,
        )
        sub_plans[i] = sub
        strokes.extend(sub.strokes)
    if not strokes:
        raise ValueError(
            "particles: all already on their slots (within tolerance); nothing to push"
        )
    sample = Sample(spheres=[Sphere(i, e.x, e.y, e.radius) for i, e in enumerate(ests)])
    simulate_strokes(sample, strokes, model_contact_params(contact_params, tip_radius))
    finals = np.array([[s.x, s.y] for s in sample.spheres])
    plan = PushPlan(
        "arc",
        strokes,
        c.copy(),
        c.copy(),
        np.array([1.0, 0.0]),
        max(e.radius for e in ests),
        tip_radius,
        predicted=finals.mean(axis=0),
        predicted_track=[finals],
        params=params if params is not None else NanoHandParams.book(),
        extra={
            "assignment": assignment,
            "radius": radius,
            "slots": slot_xy,
            "order": order,
            "sub_plans": sub_plans,
        },
    )
    if limits is not None:
        check_plan_limits(plan, limits)
    return plan


def _ring_slots(
    ests: list[ParticleEstimate], c: np.ndarray, radius: float, slots: int | None, phase: float
) -> np.ndarray:
    """(slots, 2) places equally spaced on the ring from angle `phase`, refused when closer
    than a particle's diameter."""
    positive("radius", radius, "m")
    n_slots = count("slots", len(ests) if slots is None else slots, len(ests))
    finite("phase", phase)
    chord = 2 * radius * math.sin(math.pi / n_slots) if n_slots > 1 else math.inf
    widest = 2 * max(e.radius for e in ests)
    if chord < widest:
        raise ValueError(
            f"radius={radius:.4e} m: {n_slots} slots are {chord:.4e} m apart, closer than a "
            f"particle's diameter {widest:.4e} m"
        )
    angles = phase + 2 * math.pi * np.arange(n_slots) / n_slots
    return c + radius * np.stack([np.cos(angles), np.sin(angles)], axis=1)


def _assign(ests: list[ParticleEstimate], slot_xy: np.ndarray) -> tuple[dict, list[int]]:
    """Particle index -> slot (x, y) by minimum total distance (Hungarian assignment), and the
    order to push them in: nearest to its slot first."""
    from scipy.optimize import linear_sum_assignment

    cost = np.array([[np.hypot(*(e.xy - s)) for s in slot_xy] for e in ests])
    rows, cols = linear_sum_assignment(cost)
    assignment = {int(r): slot_xy[cc] for r, cc in zip(rows, cols)}
    order = sorted(assignment, key=lambda i: cost[i, cols[list(rows).index(i)]])
    return assignment, order
