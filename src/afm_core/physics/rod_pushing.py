"""Rod and tube pushing: how a rod (a capsule) moves when the tip or another object presses
on it at a point of its axis (SPEC section 5).

Uniform Coulomb friction per unit length along the axis. For a push at axis point s_c
(measured from the rod's centre) along the normal, the motion minimises the frictional work
integral |v(s)| ds subject to moving the contact point by the required normal displacement
(the principle of minimum work, equivalent to force/torque balance with Coulomb friction). For
a contact on the cylindrical part (normal perpendicular to the axis) the minimiser is a
rotation about an IRC on the axis at x0 = s_c - sign(s_c) sqrt(s_c^2 + L^2/4): at the end
(s_c = L/2) the rod pivots about the point L/sqrt(2) from the pushed end, i.e. towards the far
end; as s_c -> 0 the IRC runs to the far end, and a push at the centre translates the rod.
Uniform line friction makes translation and rotation about the far end equally costly at
s_c = 0 (the principle picks a family there); the tip's contact on the rod has a finite
half-length b (``rod_contact_halfwidth``), over which the contact can exert any moment, so a
push within b of the centre translates the rod and further out the effective arm is |s_c| - b.
A contact on a hemispherical end cap has a normal with an axial component; its minimiser (IRC
off the axis) is tabulated once by numerical minimisation over the twist for the angle of the
normal. The tip-rod contact is frictionless; electrodes push rods out by translation only.
"""

from __future__ import annotations

import math

import numpy as np

from afm_core.physics.sample import Rod

_END_PSI = np.linspace(0.0, 0.5 * math.pi, 46)
_D_PSI = float(_END_PSI[1] - _END_PSI[0])
_END_TABLE: list[tuple[float, float, float]] | None = None


def line_work(vx: float, vy: float, w: float) -> float:
    """Integral of |v(s)| over s in [-1/2, 1/2] for the twist v(s) = (vx, vy + w s) of a unit
    rod (closed form: with u = vy + w s, the integral of sqrt(vx^2 + u^2) du / |w|)."""
    if abs(w) < 1e-7:
        return math.hypot(vx, vy)
    a = abs(vx)

    def primitive(u):
        return 0.5 * (u * math.hypot(a, u) + (a * a * math.asinh(u / a) if a > 0 else 0.0))

    lo, hi = sorted((vy - 0.5 * w, vy + 0.5 * w))
    return (primitive(hi) - primitive(lo)) / abs(w)


def _nelder_mead_2d(f, x0, y0, step, tol=1e-11, max_iter=2000):
    """Minimise f(x, y) by the Nelder-Mead simplex method (standard coefficients)."""
    pts = [(x0, y0), (x0 + step, y0), (x0, y0 + step)]
    vals = [f(*q) for q in pts]
    for _ in range(max_iter):
        order = sorted(range(3), key=vals.__getitem__)
        pts, vals = [pts[k] for k in order], [vals[k] for k in order]
        if max(abs(pts[k][0] - pts[0][0]) + abs(pts[k][1] - pts[0][1]) for k in (1, 2)) < tol:
            break
        cx, cy = 0.5 * (pts[0][0] + pts[1][0]), 0.5 * (pts[0][1] + pts[1][1])
        wx, wy = pts[2]
        rx, ry = 2 * cx - wx, 2 * cy - wy
        fr = f(rx, ry)
        if fr < vals[0]:
            ex, ey = 3 * cx - 2 * wx, 3 * cy - 2 * wy
            fe = f(ex, ey)
            pts[2], vals[2] = ((ex, ey), fe) if fe < fr else ((rx, ry), fr)
        elif fr < vals[1]:
            pts[2], vals[2] = (rx, ry), fr
        else:
            kx, ky = (
                (0.5 * (cx + rx), 0.5 * (cy + ry))
                if fr < vals[2]
                else (0.5 * (cx + wx), 0.5 * (cy + wy))
            )
            fk = f(kx, ky)
            if fk < min(fr, vals[2]):
                pts[2], vals[2] = (kx, ky), fk
            else:  # shrink towards the best point
                bx, by = pts[0]
                pts = [pts[0]] + [(0.5 * (bx + qx), 0.5 * (by + qy)) for qx, qy in pts[1:]]
                vals = [vals[0]] + [f(*q) for q in pts[1:]]
    best = min(range(3), key=vals.__getitem__)
    return pts[best]


def rod_end_twists() -> np.ndarray:
    """Minimum-work twists (vx, vy, omega * L) per unit normal displacement for a push on the
    end cap at s = +L/2 with normal (-cos psi, sin psi) in the rod frame, psi on _END_PSI.
    Minimises line_work over the plane of twists meeting the constraint (Nelder-Mead on the
    two free coordinates, continued from the previous angle). Computed once, a few 10 ms."""
    global _END_TABLE
    if _END_TABLE is None:
        rows, previous = [], None
        for psi in _END_PSI:
            c = np.array([-math.cos(psi), math.sin(psi), 0.5 * math.sin(psi)])
            particular = c / (c @ c)
            null = np.linalg.svd(c[None, :])[2][1:].T
            z0 = np.zeros(2) if previous is None else null.T @ (previous - particular)
            (p0, p1, p2), (a0, a1, a2), (b0, b1, b2) = (
                particular.tolist(),
                null[:, 0].tolist(),
                null[:, 1].tolist(),
            )
            za, zb = _nelder_mead_2d(
                lambda u, v: line_work(
                    p0 + u * a0 + v * b0, p1 + u * a1 + v * b1, p2 + u * a2 + v * b2
                ),
                float(z0[0]),
                float(z0[1]),
                0.05 if previous is None else 0.01,
            )
            previous = particular + null @ np.array([za, zb])
            rows.append(tuple(float(v) for v in previous))
        _END_TABLE = rows
    return np.array(_END_TABLE)


def _end_cap_twist(t, nlx, nly, length):
    """Twist (vx, vy, omega) in the rod frame per unit normal displacement of a push on an end
    cap with normal (nlx, nly) in the rod frame (the tabulated minimiser, interpolated)."""
    se = 1.0 if t >= 1.0 else -1.0
    sy = 1.0 if nly >= 0 else -1.0
    psi = math.atan2(sy * nly, max(-se * nlx, 0.0))
    table = _END_TABLE if _END_TABLE is not None else rod_end_twists().tolist()
    x = psi / _D_PSI
    k = min(int(x), len(table) - 2)
    fr = x - k
    vxc, vyc, wc = (a + (b - a) * fr for a, b in zip(table[k], table[k + 1]))
    return se * vxc, sy * vyc, se * sy * wc / length


def _side_twist(t, nlx, nly, length, halfwidth):
    """Twist (vx, vy, omega) in the rod frame per unit normal displacement of a push on the
    cylindrical part at parameter t: a rotation about the minimum-work IRC on the axis, or a
    translation when the contact's half-length covers the centre."""
    s_c = (t - 0.5) * length
    arm = math.copysign(max(abs(s_c) - halfwidth, 0.0), s_c)
    sy = 1.0 if nly >= 0 else -1.0
    if arm == 0.0:
        return nlx, nly, 0.0
    x0 = arm - math.copysign(math.sqrt(arm * arm + 0.25 * length * length), arm)
    w = 1.0 / ((s_c - x0) * sy)
    return 0.0, -w * x0, w


def rod_push_motion(
    rod: Rod, t: float, nx: float, ny: float, delta: float, halfwidth: float
) -> tuple[float, float, float]:
    """The rigid motion (dx, dy, dtheta) of a rod pushed frictionlessly at its axis point of
    parameter t (0 and 1: the ends) so that this point moves `delta` along the unit normal n;
    (dx, dy) is the centre's first-order displacement, dtheta the rotation. halfwidth: the
    half-length b of the contact (``rod_contact_halfwidth``)."""
    length = rod.length
    if length <= 1e-15:
        return delta * nx, delta * ny, 0.0
    ex, ey = math.cos(rod.angle), math.sin(rod.angle)
    nlx, nly = nx * ex + ny * ey, -nx * ey + ny * ex
    if (t <= 0.0 or t >= 1.0) and abs(nlx) > 1e-9:
        vx, vy, w = _end_cap_twist(t, nlx, nly, length)
    else:
        vx, vy, w = _side_twist(t, nlx, nly, length, halfwidth)
    return delta * (vx * ex - vy * ey), delta * (vx * ey + vy * ex), delta * w
