"""Centre pushing, the baseline (book 6.4.3, Fig. 6.18a-e; SPEC section 5).

Straight pushes along the line through the *estimated* centre: with the true centre off that
line by e, the contact normal is tilted by asin(e / D), the particle slides off to the side it
was hit on, and the tilt grows while it is pushed (SPEC 5). Repeated short pushes (the same
push/back lengths as the hand) turn a Gaussian uncertainty into two lobes on arcs of radius
D around the tip's end points; one long push loses the particle altogether for e of a few nm.
The frame of a push (u, along, D) is defined in afm_core.manipulation.plans.
"""

from __future__ import annotations

import math

from afm_core.checks import count, point, positive
from afm_core.instrument import ScannerLimits
from afm_core.manipulation.plans import (
    DEFAULT_MAX_DISTANCE,
    DEFAULT_TIP_RADIUS,
    NM,
    PushPlan,
    Stroke,
    check_plan_limits,
    particle_estimate,
    push_axis,
)


def centre_push_plan(
    particle,
    goal,
    *,
    tip_radius: float = DEFAULT_TIP_RADIUS,
    particle_radius: float | None = None,
    push: float = 156 * NM,
    back: float = 120 * NM,
    approach: float = 78 * NM,
    steps: int | None = None,
    single: bool = False,
    limits: ScannerLimits | None = None,
    max_distance: float = DEFAULT_MAX_DISTANCE,
) -> PushPlan:
    """Straight pushes through the estimated centre towards the goal.

    single=True: one stroke from `approach` before contact to where the tip touches a particle
    sitting on the goal (along = distance - D). Otherwise repeated strokes of `push` with
    `back` retraction (the same rhythm as the nano-hand, Fig. 6.18a-c), `steps` of them
    (default: as many as needed), the last one ending at along = distance - D; for an exactly
    known centre the particle ends on the goal.
    """
    est = particle_estimate(particle, particle_radius)
    c0, g = est.xy, point("goal", goal)
    u, dist = push_axis(c0, g, positive("max_distance", max_distance, "m"))
    positive("tip_radius", tip_radius, "m")
    for name, value in (("push", push), ("back", back), ("approach", approach)):
        positive(name, value, "m")
    if back >= push:
        raise ValueError(
            f"back={back:.4e} m: must be < push={push:.4e} m (each step must advance)"
        )
    D = est.radius + tip_radius
    s0 = -(D + approach)
    final = dist - D
    if single:
        ends = [(s0, final)]
    else:
        ends = _repeated_pushes(s0, final, push, back, steps, dist)
    strokes = [Stroke(c0 + a * u, c0 + b * u, True, "centre") for a, b in ends]
    plan = PushPlan(
        "centre",
        strokes,
        c0,
        g,
        u,
        est.radius,
        tip_radius,
        path_offsets=(0.0, 0.0),
        predicted=g.copy(),
        params={"push": push, "back": back, "approach": approach, "single": single},
    )
    if limits is not None:
        check_plan_limits(plan, limits)
    return plan


def _repeated_pushes(
    s0: float, final: float, push: float, back: float, steps: int | None, dist: float
) -> list[tuple[float, float]]:
    """(start, end) along u of each push: `push` long, `back` apart, from s0; the last one ends
    at `final`."""
    adv = push - back
    if steps is None:
        steps = max(1, int(math.ceil((final - (s0 + push)) / adv - 1e-9)) + 1)
    steps = count("steps", steps, 1)
    ends = []
    for k in range(steps):
        start = s0 + k * adv
        ends.append((start, start + push))
    start_last = ends[-1][0]
    if final <= start_last + 1e-12:
        raise ValueError(
            f"steps={steps}: too many for a {dist:.4e} m push (the last stroke would start "
            f"beyond where it has to end)"
        )
    ends[-1] = (start_last, final)
    return ends
