"""Collision geometry of the pushing model: closest points of the objects' axes (a sphere's
is its centre, a rod's a segment), their overlaps, and the way out of an electrode.

Objects are separated along the line of their closest points (sphere-sphere along the centre
line); electrodes are fixed walls an object leaves by the shortest translation. Pure Python
floats: these run once per mechanics step and object pair.
"""

from __future__ import annotations

import math

from afm_core.physics.sample import Rod

OVERLAP_TOLERANCE = 1e-13  # m, overlaps below this are contact


def closest_on_segment(px, py, ax, ay, bx, by):
    """The point of segment ab closest to p, and its parameter t in [0, 1] along ab."""
    abx, aby = bx - ax, by - ay
    ab2 = abx * abx + aby * aby
    t = ((px - ax) * abx + (py - ay) * aby) / ab2 if ab2 > 0 else 0.0
    t = 0.0 if t < 0.0 else (1.0 if t > 1.0 else t)
    return ax + t * abx, ay + t * aby, t


def closest_segments(p1x, p1y, q1x, q1y, p2x, p2y, q2x, q2y):
    """Closest points of segments p1q1 and p2q2 (Ericson, Real-Time Collision Detection 5.1.9)."""
    d1x, d1y, d2x, d2y = q1x - p1x, q1y - p1y, q2x - p2x, q2y - p2y
    rx, ry = p1x - p2x, p1y - p2y
    a, e, f = d1x * d1x + d1y * d1y, d2x * d2x + d2y * d2y, d2x * rx + d2y * ry
    if a <= 1e-300 and e <= 1e-300:
        s = t = 0.0
    elif a <= 1e-300:
        s, t = 0.0, min(max(f / e, 0.0), 1.0)
    else:
        c = d1x * rx + d1y * ry
        if e <= 1e-300:
            t, s = 0.0, min(max(-c / a, 0.0), 1.0)
        else:
            b = d1x * d2x + d1y * d2y
            denom = a * e - b * b
            s = min(max((b * f - c * e) / denom, 0.0), 1.0) if denom > 1e-30 * a * e else 0.0
            t = (b * s + f) / e
            if t < 0.0:
                t, s = 0.0, min(max(-c / a, 0.0), 1.0)
            elif t > 1.0:
                t, s = 1.0, min(max((b - c) / a, 0.0), 1.0)
    return p1x + d1x * s, p1y + d1y * s, s, p2x + d2x * t, p2y + d2y * t, t


def rod_ends(rod: Rod):
    """The two ends (ax, ay, bx, by) of a rod's axis segment."""
    hx, hy = 0.5 * rod.length * math.cos(rod.angle), 0.5 * rod.length * math.sin(rod.angle)
    return rod.x - hx, rod.y - hy, rod.x + hx, rod.y + hy


def capsule_out_of_box(ax, ay, bx, by, r, x0, x1, y0, y1):
    """Shortest translation (separating-axis test over the box normals, the segment normal and
    the corner-to-segment directions) that takes a capsule out of a box, or None."""
    axes = [(1.0, 0.0), (0.0, 1.0)]
    sx, sy = bx - ax, by - ay
    sl = math.hypot(sx, sy)
    if sl > 0:
        axes.append((-sy / sl, sx / sl))
    corners = ((x0, y0), (x1, y0), (x0, y1), (x1, y1))
    for cx, cy in corners:
        qx, qy, _ = closest_on_segment(cx, cy, ax, ay, bx, by)
        dl = math.hypot(qx - cx, qy - cy)
        if dl > 0:
            axes.append(((qx - cx) / dl, (qy - cy) / dl))
    best = None
    for kx, ky in axes:
        pa, pb = ax * kx + ay * ky, bx * kx + by * ky
        smin, smax = min(pa, pb) - r, max(pa, pb) + r
        proj = [cx * kx + cy * ky for cx, cy in corners]
        rmin, rmax = min(proj), max(proj)
        forward, backward = rmax - smin, smax - rmin  # move +k by forward, or -k by backward
        if forward <= 0 or backward <= 0:
            return None
        if best is None or min(forward, backward) < best[0]:
            best = (forward, kx, ky) if forward < backward else (backward, -kx, -ky)
    return best[0] * best[1], best[0] * best[2]


def object_overlap(a, a_is_rod: bool, b, b_is_rod: bool):
    """How far objects a and b overlap, with the unit normal from a to b and the axis
    parameters t of both contact points: (overlap, nx, ny, ta, tb), or None when they do not
    overlap by more than OVERLAP_TOLERANCE."""
    if not a_is_rod and not b_is_rod:
        qax, qay, ta, qbx, qby, tb = a.x, a.y, 0.5, b.x, b.y, 0.5
    elif not a_is_rod:
        qax, qay, ta = a.x, a.y, 0.5
        qbx, qby, tb = closest_on_segment(a.x, a.y, *rod_ends(b))
    elif not b_is_rod:
        qbx, qby, tb = b.x, b.y, 0.5
        qax, qay, ta = closest_on_segment(b.x, b.y, *rod_ends(a))
    else:
        qax, qay, ta, qbx, qby, tb = closest_segments(*rod_ends(a), *rod_ends(b))
    dx, dy = qbx - qax, qby - qay
    d = math.hypot(dx, dy)
    overlap = a.radius + b.radius - d
    if overlap <= OVERLAP_TOLERANCE:
        return None
    if d > 1e-30:
        nx, ny = dx / d, dy / d
    elif a_is_rod:  # axes cross: push b off a's axis sideways
        ex, ey = math.cos(a.angle), math.sin(a.angle)
        nx, ny = -ey, ex
        if (b.x - a.x) * nx + (b.y - a.y) * ny < 0:
            nx, ny = -nx, -ny
    else:
        nx, ny = 1.0, 0.0
    return overlap, nx, ny, ta, tb
