"""The world the tip moves in while pushing: the movable objects of a sample, their contacts
with the tip and with each other, and the electrodes.

Collisions, walls, the tip
--------------------------
After the tip moves objects, overlapping movable objects are separated along the line of
their closest points (sphere-sphere along the centre line): first along the chain outwards
from the tip (the pushed object moves by the whole overlap, a rod by the rod law), then, if
anything is still stuck, a few passes that split overlaps, push objects out of electrodes
(fixed walls: shortest translation out) and out of the tip. An object that is still pressed
into the tip after that is jammed (e.g. against an electrode): the contact-mode feedback
lifts the tip over it, the objects settle once more without the tip, and it stays where it
is until the tip has left its footprint; an object under the tip at the start of a path is
ridden over in the same way. In such jams residual overlaps between objects can remain at
the picometre level. For contacts the tip is always at substrate level (also over an
electrode).

A sphere moves by the law of afm_core.physics.sphere_pushing, a rod by that of
afm_core.physics.rod_pushing; the energy they dissipate is afm_core.physics.contact's.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from afm_core.physics.collisions import (
    OVERLAP_TOLERANCE,
    capsule_out_of_box,
    closest_on_segment,
    object_overlap,
    rod_ends,
)
from afm_core.physics.contact import (
    ContactParams,
    FrictionMap,
    rod_dissipation,
    sphere_dissipation,
)
from afm_core.physics.rod_pushing import rod_push_motion
from afm_core.physics.sample import Rod, Sample
from afm_core.physics.sphere_pushing import sphere_push

_MAX_PASSES = 8


class PushWorld:
    """The movable objects of a sample and the electrodes, as the tip meets them along a path:
    a box index for the neighbour queries, the elementary motions with the bookkeeping of what
    moved, the tip's contacts and the collisions between objects. Moves the sample's objects
    in place."""

    def __init__(self, sample: Sample, params: ContactParams, friction: FrictionMap | None = None):
        self.p = params
        self.friction = friction  # None: uniform friction (the default, exactly as before regions)
        self.objs = sample.movable
        self.is_rod = [isinstance(o, Rod) for o in self.objs]
        self.bl = [self._bounds_of(i) for i in range(len(self.objs))]  # (x0, x1, y0, y1)
        # for vectorised box queries: row (x0, -x1, y0, -y1) < (qx1, -qx0, qy1, -qy0)
        self.box = np.array([(b[0], -b[1], b[2], -b[3]) for b in self.bl], dtype=float).reshape(
            -1, 4
        )
        self.electrodes = [(e.x0, e.x1, e.y0, e.y1) for e in sample.electrodes]
        self.rt = params.tip_radius
        self.mu_angle = math.atan(params.mu_tip_particle)
        self.riding: set[int] = set()
        self.local_margin = max(
            8 * params.tip_radius,
            max((o.length for o in self.objs if isinstance(o, Rod)), default=0.0),
        )
        self.local_box = (0.0, 0.0, 0.0, 0.0)
        self.local: list[int] = []
        self.local_set: set[int] = set()
        self.initial = [self.pose(i) for i in range(len(self.objs))]
        self.touched_order: list[int] = []
        self.touched: set[int] = set()
        self.snap: dict[int, tuple[float, float, float]] = {}
        self.ux = self.uy = 0.0
        self.prev_x = self.prev_y = 0.0

    # ---- bookkeeping
    def pose(self, i):
        """(x, y, angle) of object i (angle 0 for a sphere)."""
        o = self.objs[i]
        return (o.x, o.y, o.angle if self.is_rod[i] else 0.0)

    def _before_move(self, i):
        if i not in self.snap:
            self.snap[i] = self.pose(i)
            if i not in self.touched:
                self.touched.add(i)
                self.touched_order.append(i)

    def _bounds_of(self, i):
        o = self.objs[i]
        r = o.radius
        if self.is_rod[i]:
            ax, ay, bx, by = rod_ends(o)
            return min(ax, bx) - r, max(ax, bx) + r, min(ay, by) - r, max(ay, by) + r
        return o.x - r, o.x + r, o.y - r, o.y + r

    def _update_bounds(self, i):
        b = self._bounds_of(i)
        self.bl[i] = b
        self.box[i] = (b[0], -b[1], b[2], -b[3])
        lx0, lx1, ly0, ly1 = self.local_box
        if b[0] < lx1 and b[1] > lx0 and b[2] < ly1 and b[3] > ly0 and i not in self.local_set:
            self.local_set.add(i)
            self.local.append(i)

    def localize(self, px, py):
        """Cache the objects near the tip: `local` holds every object whose bounds overlap
        local_box (kept true as objects move), so queries inside it need no array scan."""
        m = self.local_margin
        self.local_box = (px - m, px + m, py - m, py + m)
        self.local = self.query_all(*self.local_box)
        self.local_set = set(self.local)

    def query_all(self, x0, x1, y0, y1) -> list[int]:
        return np.flatnonzero((self.box < np.array((x1, -x0, y1, -y0))).all(axis=1)).tolist()

    def query(self, x0, x1, y0, y1) -> list[int]:
        """Objects whose bounding boxes overlap the box (x0, x1, y0, y1)."""
        lx0, lx1, ly0, ly1 = self.local_box
        if not (x0 >= lx0 and x1 <= lx1 and y0 >= ly0 and y1 <= ly1):
            return self.query_all(x0, x1, y0, y1)
        bl = self.bl
        return [
            i
            for i in self.local
            if bl[i][0] < x1 and bl[i][1] > x0 and bl[i][2] < y1 and bl[i][3] > y0
        ]

    # ---- elementary motions
    def translate(self, i, dx, dy):
        self._before_move(i)
        o = self.objs[i]
        o.x += dx
        o.y += dy
        self._update_bounds(i)

    def rigid(self, i, dx, dy, dth):
        """Move rod i by the rigid motion with this twist: a rotation by dth about the IRC
        c + z x (dx, dy) / dth (a translation if dth = 0); to first order the centre moves
        (dx, dy). Written with sin(dth)/dth and (cos(dth) - 1)/dth, exact and stable."""
        self._before_move(i)
        o = self.objs[i]
        if dth == 0.0:
            o.x += dx
            o.y += dy
        else:
            s1 = math.sin(dth) / dth
            c1 = -2.0 * math.sin(0.5 * dth) ** 2 / dth
            o.x += s1 * dx + c1 * dy
            o.y += s1 * dy - c1 * dx
            o.angle += dth
        self._update_bounds(i)

    def push_rod(self, i, t, nx, ny, delta):
        """Move rod i so that its axis point at parameter t moves `delta` along unit n."""
        self.rigid(
            i, *rod_push_motion(self.objs[i], t, nx, ny, delta, self.p.rod_contact_halfwidth)
        )

    def push_object(self, i, t, nx, ny, delta):
        """Frictionless push of object i at its axis point of parameter t along n."""
        if self.is_rod[i]:
            self.push_rod(i, t, nx, ny, delta)
        else:
            self.translate(i, delta * nx, delta * ny)

    # ---- the tip
    def tip_gap(self, i, px, py):
        """(distance from the tip to object i's axis minus contact distance, normal, t)."""
        o = self.objs[i]
        if self.is_rod[i]:
            ax, ay, bx, by = rod_ends(o)
            qx, qy, t = closest_on_segment(px, py, ax, ay, bx, by)
        else:
            qx, qy, t = o.x, o.y, 0.5
        dx, dy = qx - px, qy - py
        d = math.hypot(dx, dy)
        return d - (self.rt + o.radius), d, dx, dy, t

    def push_from_tip(self, i, px, py, moving: bool = False) -> bool:
        """Resolve the tip's penetration into object i by the pushing law (`moving`: the
        penetration comes from the tip's step prev -> p). False if the tip is (nearly) on
        its axis: then it is on top of it."""
        o = self.objs[i]
        for _ in range(4):  # a rod moves the contact point by the gap to first order only
            gap, d, dx, dy, t = self.tip_gap(i, px, py)
            if gap >= -OVERLAP_TOLERANCE:
                return True
            if d < 1e-3 * o.radius:
                return False
            if self.is_rod[i]:
                self.push_rod(i, t, dx / d, dy / d, -gap)
                continue
            # a contact that began within this step takes the mean normal over the step
            step_start = (
                (o.x - self.prev_x, o.y - self.prev_y, self.prev_x - px, self.prev_y - py)
                if moving
                else None
            )
            shift = sphere_push(
                (dx, dy, d),
                self.rt + o.radius,
                (self.ux, self.uy),
                self.mu_angle,
                self.p.substrate_contact_radius,
                o.radius,
                step_start,
            )
            self.translate(i, *shift)
            return True
        return True

    # ---- object-object contacts
    def overlap(self, a, b):
        """(overlap, normal from a to b, axis parameters of both contact points) or None."""
        return object_overlap(self.objs[a], self.is_rod[a], self.objs[b], self.is_rod[b])

    def neighbours(self, a):
        x0, x1, y0, y1 = self.bl[a]
        return [b for b in self.query(x0, x1, y0, y1) if b != a]

    def out_of_walls(self, i) -> bool:
        moved = False
        for x0, x1, y0, y1 in self.electrodes:
            bx0, bx1, by0, by1 = self.bl[i]
            if bx0 >= x1 or bx1 <= x0 or by0 >= y1 or by1 <= y0:
                continue
            o = self.objs[i]
            if self.is_rod[i]:
                ax, ay, bx, by = rod_ends(o)
            else:
                ax = bx = o.x
                ay = by = o.y
            mtv = capsule_out_of_box(ax, ay, bx, by, o.radius, x0, x1, y0, y1)
            if mtv is not None and math.hypot(*mtv) > OVERLAP_TOLERANCE:
                self.translate(i, mtv[0], mtv[1])
                moved = True
        return moved

    def resolve(self, seeds, px, py):
        """Separate everything the tip's pushes set in motion (see the module docstring)."""
        rank = {i: 0 for i in seeds}
        queue = deque(seeds)
        moved = set(seeds)
        stuck = False
        budget = 64 * (len(self.objs) + 1)
        while queue and budget > 0:
            a = queue.popleft()
            for b in self.neighbours(a):
                budget -= 1
                hit = self.overlap(a, b)
                if hit is None:
                    continue
                ov, nx, ny, ta, tb = hit
                if rank.get(b, math.inf) > rank[a]:
                    self.push_object(b, tb, nx, ny, ov)
                    rank[b] = rank[a] + 1
                    moved.add(b)
                    queue.append(b)
                else:
                    stuck = True
        if self.relax(moved, px, py, stuck):
            return
        jammed = [
            i
            for i in moved
            if i not in self.riding and self.tip_gap(i, px, py)[0] < -1e-3 * self.rt
        ]
        if jammed:
            self.riding.update(jammed)  # the feedback lifts the tip over them ...
            self.relax(moved, px, py, True)  # ... and the objects settle without it

    def relax(self, moved, px, py, overlapping) -> bool:
        """Passes of: out of the walls, out of the tip (unless ridden over), halve every
        overlap between objects. True when a pass found nothing left to do."""
        for _ in range(_MAX_PASSES):
            changed = False
            for i in list(moved):
                changed |= self.out_of_walls(i)
            for i in list(moved):
                if i not in self.riding and self.tip_gap(i, px, py)[0] < -OVERLAP_TOLERANCE:
                    self.push_from_tip(i, px, py)
                    changed = True
            if not (changed or overlapping):
                return True
            overlapping = False
            for a in list(moved):
                for b in self.neighbours(a):
                    hit = self.overlap(a, b)
                    if hit is None:
                        continue
                    ov, nx, ny, ta, tb = hit
                    self.push_object(b, tb, nx, ny, 0.5 * ov)
                    self.push_object(a, ta, -nx, -ny, 0.5 * ov)
                    moved.add(b)
                    overlapping = True
        for i in list(moved):
            self.out_of_walls(i)
        return False

    # ---- one mechanics step
    def step(self, px, py, length, dt) -> tuple[float, bool]:
        """Tip arrives at (px, py) after moving `length`; returns (dissipated energy, contact)."""
        self.snap = {}
        r = self.rt
        lx0, lx1, ly0, ly1 = self.local_box
        if not (px - r >= lx0 and px + r <= lx1 and py - r >= ly0 and py + r <= ly1):
            self.localize(px, py)
        seeds = []
        contact = bool(self.riding)
        for i in self.query(px - r, px + r, py - r, py + r):
            if i in self.riding:
                if self.tip_gap(i, px, py)[0] >= 0:
                    self.riding.discard(i)
                continue
            if self.tip_gap(i, px, py)[0] < -OVERLAP_TOLERANCE:
                contact = True
                if length > 0 and self.push_from_tip(i, px, py, moving=True):
                    seeds.append(i)
                else:
                    self.riding.add(i)
        if seeds:
            self.resolve(seeds, px, py)
        return self.dissipation(dt), contact

    def dissipation(self, dt) -> float:
        """Energy the objects moved in this step dissipated (J), summed in the order moved."""
        energy = 0.0
        for i, (x, y, ang) in self.snap.items():
            o = self.objs[i]
            if self.is_rod[i]:
                energy += rod_dissipation(o, x, y, ang, dt, self.p, self.friction)
            else:
                energy += sphere_dissipation(o, x, y, dt, self.p, self.friction)
        return energy

    # ---- vectorised search for the next contact while nothing moves
    def first_contact(self, X, Y, j0, j1) -> int:
        xs, ys = X[j0:j1], Y[j0:j1]
        r = self.rt
        cand = self.query_all(xs.min() - r, xs.max() + r, ys.min() - r, ys.max() + r)
        if not cand:
            return j1
        hit = np.zeros(xs.size, dtype=bool)
        spheres = [i for i in cand if not self.is_rod[i]]
        rods = [i for i in cand if self.is_rod[i]]
        if spheres:
            cx = np.array([self.objs[i].x for i in spheres])
            cy = np.array([self.objs[i].y for i in spheres])
            dd = np.array([self.objs[i].radius for i in spheres]) + r
            hit |= np.any((xs[:, None] - cx) ** 2 + (ys[:, None] - cy) ** 2 < dd * dd, axis=1)
        if rods:
            ends = np.array([rod_ends(self.objs[i]) for i in rods])
            ax, ay, bx, by = ends.T
            abx, aby = bx - ax, by - ay
            ab2 = np.maximum(abx * abx + aby * aby, 1e-300)
            t = np.clip(((xs[:, None] - ax) * abx + (ys[:, None] - ay) * aby) / ab2, 0.0, 1.0)
            dd = np.array([self.objs[i].radius for i in rods]) + r
            hit |= np.any(
                (xs[:, None] - ax - t * abx) ** 2 + (ys[:, None] - ay - t * aby) ** 2 < dd * dd,
                axis=1,
            )
        k = int(np.argmax(hit))
        return j0 + k if hit[k] else j1
