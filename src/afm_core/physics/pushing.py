"""Contact-mode pushing: the tip moves along a path and pushes spheres and rods on the
substrate.

Book ch. 2.3.3, 6.4.2 (eq. 6.16-6.17) and SPEC section 5. Everything is quasi-static (inertia
is negligible at nanometre scale and micrometre-per-second speeds) and planar: the tip is a
disc of effective contact radius R_T with its apex at substrate level, an object is hit when
the tip's footprint overlaps the object's footprint (a disc of radius R_P for a sphere, a
capsule of radius r around its axis segment for a rod). Whatever the tip overlaps after a
step is moved until the tip just touches it again; *how* it moves is the pushing law.

The model's parts: afm_core.physics.sphere_pushing (the IRC law of a sphere),
afm_core.physics.rod_pushing (the minimum-work law of a rod or tube),
afm_core.physics.push_world (the objects, their collisions, electrodes, riding over a jam),
afm_core.physics.contact (the parameters, friction, forces and stick-slip) and
afm_core.physics.collisions (the geometry of the contacts). This module walks the tip along
its path.

Paths are re-sampled for the mechanics at steps of at most ``substep_fraction`` of the
smallest of R_T and the radii of the objects near the path (dense samples are merged, sparse
ones subdivided), so nothing tunnels; a sample's force is that of the step it falls in.
Stretches where the tip touches nothing are found with vectorised distance tests, so only
steps in contact cost Python time. The friction tables (disc patch, beta, rod end caps) are
computed on first use, ~0.15 s in all.
"""

from __future__ import annotations

import math

import numpy as np

from afm_core.physics.collisions import OVERLAP_TOLERANCE
from afm_core.physics.contact import (
    ContactParams,
    FrictionMap,
    PushStepResult,
    StickSlipState,
    stick_slip_force,
)
from afm_core.physics.push_world import PushWorld
from afm_core.physics.sample import Sample

_DETAILED_STEPS_AFTER_CONTACT = 16


def _mechanics_vertices(x, y, h):
    """Vertices of the mechanics path: the samples where the arc length passes a multiple of h
    (plus the first and last), each chord between them cut into pieces no longer than h.
    Returns vertex x, y, time in sample units, and for every sample the step it falls in."""
    n = x.size
    seg = np.hypot(np.diff(x), np.diff(y))
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    cell = np.floor(cum / h).astype(np.int64)
    keep = np.zeros(n, dtype=bool)
    keep[0] = keep[-1] = True
    keep[1:] |= cell[1:] != cell[:-1]
    idx = np.nonzero(keep)[0]
    chord = np.hypot(np.diff(x[idx]), np.diff(y[idx]))
    pieces = np.maximum(np.ceil(chord / h).astype(np.int64), 1)
    first_step = np.concatenate(
        [[1], 1 + np.cumsum(pieces)[:-1]]
    )  # vertex index of each chord's first step
    which = np.repeat(np.arange(idx.size - 1), pieces)
    frac = (np.arange(which.size) - (first_step[which] - 1) + 1) / pieces[which]
    i0, i1 = idx[which], idx[which + 1]
    vx = np.concatenate([[x[0]], x[i0] + frac * (x[i1] - x[i0])])
    vy = np.concatenate([[y[0]], y[i0] + frac * (y[i1] - y[i0])])
    vt = np.concatenate([[0.0], i0 + frac * (i1 - i0)])
    # step of each sample: by its arc position within its chord
    samples = np.arange(1, n)
    chord_of = np.searchsorted(idx, samples, side="left") - 1
    span = cum[idx[chord_of + 1]] - cum[idx[chord_of]]
    pos = np.where(
        span > 0, (cum[samples] - cum[idx[chord_of]]) / np.where(span > 0, span, 1.0), 1.0
    )
    piece = np.clip(np.ceil(pos * pieces[chord_of]).astype(np.int64) - 1, 0, pieces[chord_of] - 1)
    sample_step = np.concatenate([[1], first_step[chord_of] + piece])
    return vx, vy, vt, sample_step


def _tip_substrate_scales(
    friction: FrictionMap,
    x: np.ndarray,
    y: np.ndarray,
    x_before: float | None,
    y_before: float | None,
) -> np.ndarray:
    """The tip friction scale for each sample, at the middle of the step into it (the first
    sample's step starts at (x_before, y_before), or at the sample itself)."""
    px = np.concatenate([[x[0] if x_before is None else x_before], x[:-1]])
    py = np.concatenate([[y[0] if y_before is None else y_before], y[:-1]])
    return friction.scales(0.5 * (px + x), 0.5 * (py + y), 1)


def _stick_slip_per_sample(x, y, p: ContactParams, friction, state: StickSlipState, before):
    """The stick-slip saw-tooth of the tip-substrate force per sample (stick-slip on); before:
    the tip's position ahead of the first sample, (None, None) when it has just landed."""
    kinetic = np.full(x.size, p.mu_tip_substrate * p.normal_force)
    if friction is not None:
        kinetic = kinetic * _tip_substrate_scales(friction, x, y, *before)
    return stick_slip_force(x, y, kinetic, p.static_friction_ratio, p.stick_slip_stiffness, state)


def _mechanics_step(world: PushWorld, x, y, p: ContactParams) -> float:
    """The longest mechanics step: substep_fraction of the smallest of R_T and the radii of
    the objects within reach of the path."""
    reach = (
        p.tip_radius + 2 * max((hb[1] - hb[0]) + (hb[3] - hb[2]) for hb in world.bl)
        if world.bl
        else 0.0
    )
    near = world.query_all(x.min() - reach, x.max() + reach, y.min() - reach, y.max() + reach)
    return p.substep_fraction * min(
        [p.tip_radius, *(world.objs[i].radius for i in near if world.objs[i].radius > 0)]
    )


def _settle_start(world: PushWorld, x, y, p: ContactParams) -> None:
    """Objects the tip overlaps at the first sample: a shallow overlap is a contact carried
    over from a previous call (a path fed in pieces), pushed out now; a deep one means the tip
    starts on top of the object and rides over it."""
    seeds = []
    for i in range(len(world.objs)):
        gap = world.tip_gap(i, x[0], y[0])[0]
        if gap < -OVERLAP_TOLERANCE:
            if -gap <= 0.25 * min(p.tip_radius, world.objs[i].radius):
                seeds.append(i)
            else:
                world.riding.add(i)
    if not seeds:
        return
    steps = np.flatnonzero(np.hypot(np.diff(x), np.diff(y)) > 0)
    if steps.size:
        k = int(steps[0])
        dx, dy = float(x[k + 1] - x[k]), float(y[k + 1] - y[k])
        world.ux, world.uy = dx / math.hypot(dx, dy), dy / math.hypot(dx, dy)
    x0, y0 = float(x[0]), float(y[0])
    world.localize(x0, y0)
    pushed = [i for i in seeds if world.push_from_tip(i, x0, y0)]
    world.riding.update(set(seeds) - set(pushed))
    if pushed:
        world.resolve(pushed, x0, y0)


def _sliding_only_forces(x, y, p: ContactParams, friction) -> np.ndarray:
    """Lateral force per sample when nothing can be pushed: mu_ts N while the tip moves (its
    first sample takes the second's), 0 at rest (stick-slip off)."""
    n = x.size
    forces = np.zeros(n)
    if n > 1:
        moving = np.concatenate([[False], np.hypot(np.diff(x), np.diff(y)) > 0])
        moving[0] = moving[1]
        sliding = p.mu_tip_substrate * p.normal_force
        if friction is None:
            forces[moving] = sliding
        else:
            scales = _tip_substrate_scales(friction, x, y, None, None)
            scales[0] = scales[1]
            forces[moving] = sliding * scales[moving]
    return forces


def _walk(world: PushWorld, X, Y, T, lengths, dt) -> np.ndarray:
    """Move the tip through the mechanics vertices; returns the objects' dissipation per unit
    tip travel (N) of each step. Stretches out of contact are skipped in growing windows found
    by the vectorised contact search; after a contact the steps are taken one by one."""
    m = X.size
    object_force = np.zeros(m)
    Xl, Yl, Tl, Ll = X.tolist(), Y.tolist(), T.tolist(), lengths.tolist()
    j = 1
    detailed_until = 0
    window = 64
    while j < m:
        if world.riding or j < detailed_until:
            k = j
        else:
            k = world.first_contact(X, Y, j, min(j + window, m))
            if k >= min(j + window, m):
                j = k
                window = min(window * 2, 1 << 16)
                continue
            window = 64
        j = k
        length = Ll[j]
        if length > 0:
            world.ux, world.uy = (Xl[j] - Xl[j - 1]) / length, (Yl[j] - Yl[j - 1]) / length
        world.prev_x, world.prev_y = Xl[j - 1], Yl[j - 1]
        energy, contact = world.step(Xl[j], Yl[j], length, (Tl[j] - Tl[j - 1]) * dt)
        if length > 0:
            object_force[j] = energy / length
        if contact or world.snap:
            detailed_until = j + _DETAILED_STEPS_AFTER_CONTACT
        j += 1
    return object_force


def push_along_path(
    sample: Sample,
    path_x: np.ndarray,
    path_y: np.ndarray,
    dt: float,
    params: ContactParams,
    stick_slip: StickSlipState | None = None,
) -> PushStepResult:
    """Move the tip through the true positions (path_x[k], path_y[k]) (sample frame, m), one
    every dt seconds, in contact with the substrate; push the sample's movable objects in
    place. Returns the ids of the objects that moved and the force trace per sample.
    stick_slip: the tip-substrate spring to continue from when params.stick_slip_enabled
    (updated in place; default: a relaxed spring, the tip just landed)."""
    x = np.asarray(path_x, dtype=float).ravel()
    y = np.asarray(path_y, dtype=float).ravel()
    if x.shape != y.shape:
        raise ValueError(f"path_x and path_y differ in length: {x.size} vs {y.size}")
    if not dt > 0:
        raise ValueError(f"dt = {dt} must be > 0")
    n = x.size
    p = params
    deflection = np.full(n, p.normal_force / p.normal_spring_constant)
    if n == 0:
        empty = np.zeros(0)
        return PushStepResult([], empty, deflection, empty.copy())
    friction = FrictionMap(p.friction_regions) if p.friction_regions else None
    if p.stick_slip_enabled and stick_slip is None:
        stick_slip = StickSlipState()
    before = (stick_slip.x, stick_slip.y) if stick_slip is not None else (None, None)
    world = PushWorld(sample, p, friction)
    h = _mechanics_step(world, x, y, p)
    _settle_start(world, x, y, p)
    if n == 1 or not world.objs:
        if p.stick_slip_enabled:
            forces = _stick_slip_per_sample(x, y, p, friction, stick_slip, before)
        else:
            forces = _sliding_only_forces(x, y, p, friction)
        return PushStepResult(
            [], forces, deflection, forces * p.tip_height / p.lateral_spring_constant
        )

    X, Y, T, sample_step = _mechanics_vertices(x, y, h)
    lengths = np.concatenate([[0.0], np.hypot(np.diff(X), np.diff(Y))])
    object_force = _walk(world, X, Y, T, lengths, dt)
    if p.stick_slip_enabled:
        forces = object_force[sample_step]
        forces[0] = forces[1]
        forces = forces + _stick_slip_per_sample(x, y, p, friction, stick_slip, before)
    else:
        sliding = p.mu_tip_substrate * p.normal_force
        if friction is None:
            tip_force = np.where(lengths > 0, sliding, 0.0)
        else:  # scaled at the middle of each step
            mid_scale = friction.scales(0.5 * (X[:-1] + X[1:]), 0.5 * (Y[:-1] + Y[1:]), 1)
            tip_force = np.where(lengths > 0, sliding * np.concatenate([[1.0], mid_scale]), 0.0)
        # (tip + objects, summed per step in this order: the same arithmetic as ever)
        forces = (tip_force + object_force)[sample_step]
        forces[0] = forces[1]
    moved = [world.objs[i].id for i in world.touched_order if world.pose(i) != world.initial[i]]
    return PushStepResult(
        moved, forces, deflection, forces * p.tip_height / p.lateral_spring_constant
    )
