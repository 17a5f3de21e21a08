"""Contact-mode pushing: the tip moves along a path and pushes spheres and rods on the substrate.

Book ch. 2.3.3, 6.4.2 (eq. 6.16-6.17) and SPEC section 5. Everything is quasi-static (inertia
is negligible at nanometre scale and micrometre-per-second speeds) and planar: the tip is a
disc of effective contact radius R_T with its apex at substrate level, an object is hit when
the tip's footprint overlaps the object's footprint (a disc of radius R_P for a sphere, a
capsule of radius r around its axis segment for a rod). Whatever the tip overlaps after a
step is moved until the tip just touches it again; *how* it moves is the pushing law.

Spheres (the IRC model of eq. 6.16-6.17)
----------------------------------------
The particle slides on a circular contact patch of radius a (``substrate_contact_radius``,
uniform pressure: Coulomb force F_c = ``substrate_friction_force`` when translating, plus
viscous ``viscous_coefficient`` * v). The tip presses on it at a point a lever arm R_P from
its centre along the contact normal n (tip centre -> particle centre). The particle's motion
is a rotation about an instantaneous rotation centre (IRC) at a distance S from its centre:
a translation of speed V_O plus a spin V_O / S about the vertical axis. For a disc patch the
friction force points along the centre velocity, with magnitude F_c f(S/a), and the friction
torque is F_c a m(S/a) (f, m: integrals over the patch, f -> 1 and m -> a/(4S) far from the
IRC, f -> 0 and m -> 2/3 when spinning on the spot). The tip force, inclined by beta from n
towards the push direction u, balances both. With alpha = angle(u, n) and a contact that
sticks, the kinematics (contact point moves with the tip; normal velocity shared) give
S = R_P / (cos beta (tan alpha - tan beta)) and the torque balance
R_P sin(beta) f(S/a) = a m(S/a); so V_P / V_O = L_P / S with L_P the distance from the IRC to
the pushing point, which is eq. 6.17. beta is the unique root in [0, alpha]; if tan(beta)
exceeds the tip-particle friction coefficient mu_tp the contact slides and beta = atan(mu_tp).
The particle's centre therefore moves along n rotated by beta towards u, by exactly the
distance that restores tip-particle contact (the direction is the mean of the normals at the
start and end of each step, which makes the discrete path second-order accurate). Because
a << R_P the patch resists spin only weakly (at most 2/3 F_c a) and beta ~ alpha (a/R_P)^2 / 4
for small alpha: the particle moves practically along the contact normal. A push through the centre (alpha = 0) moves it straight along u; any
offset grows while it is pushed, so it slides off to the side it was hit on (the instability
of SPEC 5); a path whose lateral offset exceeds R_T + R_P touches nothing. With mu_tp = 0 or
a = 0 the particle moves exactly along n. The spin about the IRC is the sphere's own rotation;
it is not stored (a sphere's pose and height do not change with it), and rolling is not
modelled (the particle slides, as in the book's model).

Rods and tubes (capsules)
-------------------------
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

Forces
------
Power balance: the tip does the work the pushed objects dissipate, so the lateral force
opposing the tip's motion is mu_ts N (the apex keeps sliding on the substrate while it
pushes, so this term stays) plus the dissipated energy per unit tip travel ((F_c + c v) |dx| per sphere, the length integrals for
rods; the spin dissipation, of relative order a/R_P, is left out). When only sliding it is
mu_ts N; with the tip at rest it is 0. Torsion (rad) = F_lat * tip_height /
lateral_spring_constant, positive when resisting the motion (the instrument knows how the
cantilever is oriented and may flip the sign with the scan direction). The vertical
deflection is the contact-mode setpoint N / k_n.

Spatially varying friction (``friction_regions``): axis-aligned rectangles of the sample
(afm_task frame) inside which a sphere's Coulomb friction F_c (and a rod's per length) and
the tip-substrate friction mu_ts are scaled (a point inside several takes the product of
their scales). A sphere's friction is taken at its centre's mid-step position, a rod's at
each point of its length, the tip's at the middle of its step. In this quasi-static model
the motion law depends on friction ratios, not magnitudes, so a region changes the forces
(the force trace, the work done), not where the objects go.

Stick-slip (``stick_slip_enabled``): the tip-substrate term mu_ts N becomes a 1-D
spring-slider along the path. The contact sticks while the lateral spring (stiffness
``stick_slip_stiffness``) loads by k per unit of tip travel, slips when it reaches the
static friction (``static_friction_ratio`` x mu_ts N) and drops back to the kinetic level
mu_ts N, and sticks again: a saw-tooth of amplitude (ratio - 1) mu_ts N and period
(ratio - 1) mu_ts N / (k v) in time (ratio 1: no saw-tooth, the spring loads to mu_ts N and
the tip slides steadily). A contact move starts relaxed (force 0) and carries
the spring over between the pieces it is fed in (``StickSlipState``); at rest the spring
holds its force.

Paths are re-sampled for the mechanics at steps of at most ``substep_fraction`` of the
smallest of R_T and the radii of the objects near the path (dense samples are merged, sparse
ones subdivided), so nothing tunnels; a sample's force is that of the step it falls in.
Stretches where the tip touches nothing are found with vectorised distance tests, so only
steps in contact cost Python time. The friction tables (disc patch, beta, rod end caps) are
computed on first use, ~0.15 s in all.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from afm_core.sim.sample import Rod, Sample


@dataclass
class ContactParams:
    """Tip, contact and friction parameters (SI units)."""

    tip_radius: float = 50e-9  # m, effective contact radius R_T (book: 50 nm)
    mu_tip_particle: float = 0.3  # tip-object friction coefficient mu_tp
    substrate_friction_force: float = (
        5e-9  # N, Coulomb sliding friction F_c of a sphere (adhesion + weight load)
    )
    viscous_coefficient: float = 1e-3  # N s/m, sphere viscous friction c (c v = 1 nN at 1 um/s)
    substrate_contact_radius: float = (
        10e-9  # m, radius a of a sphere's contact patch (spin friction)
    )
    mu_tip_substrate: float = 0.1  # tip-substrate sliding friction coefficient mu_ts
    normal_force: float = 10e-9  # N, contact-mode setpoint N
    normal_spring_constant: float = 0.2  # N/m, cantilever k_n
    lateral_spring_constant: float = 1e-9  # N m/rad, torsional stiffness
    tip_height: float = 10e-6  # m, lever arm of the lateral force about the cantilever axis
    rod_friction_per_length: float = (
        0.05  # N/m, Coulomb friction of a rod per unit length (F_c per 100 nm)
    )
    rod_viscous_per_length: float = (
        1e4  # N s/m^2, viscous friction of a rod per unit length (c per 100 nm)
    )
    rod_contact_halfwidth: float = 5e-9  # m, half-length b of the tip's contact on a rod
    substep_fraction: float = 0.1  # mechanics step <= this x min(R_T, smallest object radius)
    # {x0, y0, x1, y1 (m, afm_task frame), substrate_friction_scale, mu_tip_substrate_scale}:
    # inside, F_c (spheres; rods per length) and mu_ts are scaled (see the module docstring)
    friction_regions: list = field(default_factory=list)
    stick_slip_enabled: bool = False  # tip-substrate friction as a stick-slip saw-tooth
    static_friction_ratio: float = (
        1.5  # static / kinetic tip-substrate friction (>= 1; 1: no saw-tooth)
    )
    stick_slip_stiffness: float = 0.05  # N/m, lateral contact stiffness of the spring-slider

    def __post_init__(self):
        positive = (
            "tip_radius",
            "normal_spring_constant",
            "lateral_spring_constant",
            "tip_height",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"ContactParams.{name} = {getattr(self, name)} must be > 0")
        for name in (
            "mu_tip_particle",
            "substrate_friction_force",
            "viscous_coefficient",
            "substrate_contact_radius",
            "mu_tip_substrate",
            "normal_force",
            "rod_friction_per_length",
            "rod_viscous_per_length",
            "rod_contact_halfwidth",
        ):
            if not getattr(self, name) >= 0:
                raise ValueError(f"ContactParams.{name} = {getattr(self, name)} must be >= 0")
        if not 0 < self.substep_fraction <= 0.5:
            raise ValueError(
                f"ContactParams.substep_fraction = {self.substep_fraction} must be in (0, 0.5]"
            )
        if not (math.isfinite(self.static_friction_ratio) and self.static_friction_ratio >= 1):
            raise ValueError(
                f"contact.static_friction_ratio={self.static_friction_ratio}: must be finite and >= 1 "
                "(static over kinetic friction)"
            )
        if not (math.isfinite(self.stick_slip_stiffness) and self.stick_slip_stiffness > 0):
            raise ValueError(
                f"contact.stick_slip_stiffness={self.stick_slip_stiffness}: must be finite and > 0 (N/m)"
            )
        self.friction_regions = [
            _checked_region(region, i) for i, region in enumerate(self.friction_regions)
        ]


_REGION_BOUNDS = ("x0", "y0", "x1", "y1")
_REGION_SCALES = ("substrate_friction_scale", "mu_tip_substrate_scale")


def _checked_region(region, index: int) -> dict:
    """A friction region as a dict of floats (scales default to 1); errors name the key."""
    where = f"contact.friction_regions[{index}]"
    if not isinstance(region, dict):
        raise ValueError(
            f"{where}={region!r}: expected a mapping {{x0, y0, x1, y1, substrate_friction_scale, "
            "mu_tip_substrate_scale}"
        )
    unknown = sorted(set(region) - set(_REGION_BOUNDS + _REGION_SCALES))
    if unknown:
        raise ValueError(
            f"{where}: unknown key(s) {unknown}; known: {list(_REGION_BOUNDS + _REGION_SCALES)}"
        )
    missing = [key for key in _REGION_BOUNDS if key not in region]
    if missing:
        raise ValueError(f"{where}: missing {missing} (m, afm_task frame)")
    out = {}
    for key in _REGION_BOUNDS + _REGION_SCALES:
        value = region.get(key, 1.0)
        if (
            isinstance(value, bool)
            or not isinstance(value, (int, float))
            or not math.isfinite(value)
        ):
            raise ValueError(f"{where}.{key}={value!r}: expected a finite number")
        if key in _REGION_SCALES and value < 0:
            raise ValueError(f"{where}.{key}={value!r}: must be >= 0")
        out[key] = float(value)
    if not (out["x1"] > out["x0"] and out["y1"] > out["y0"]):
        raise ValueError(
            f"{where}: need x1 > x0 and y1 > y0, got x {out['x0']}..{out['x1']}, "
            f"y {out['y0']}..{out['y1']}"
        )
    return out


class FrictionMap:
    """Friction scales of the substrate at points: the product of the scales of the regions
    containing each point (1 outside every region)."""

    def __init__(self, regions: list[dict]):
        self.regions = [
            (
                r["x0"],
                r["x1"],
                r["y0"],
                r["y1"],
                r["substrate_friction_scale"],
                r["mu_tip_substrate_scale"],
            )
            for r in regions
        ]

    def scales(self, x, y, which: int) -> np.ndarray:
        """Vectorised; which = 0: the objects' substrate friction, 1: the tip's."""
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        out = np.ones(np.broadcast(x, y).shape)
        for region in self.regions:
            x0, x1, y0, y1 = region[:4]
            out = np.where(
                (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1), out * region[4 + which], out
            )
        return out

    def scale(self, x: float, y: float, which: int) -> float:
        """One point in pure Python (the mechanics steps)."""
        out = 1.0
        for region in self.regions:
            if region[0] <= x <= region[1] and region[2] <= y <= region[3]:
                out *= region[4 + which]
        return out


@dataclass
class StickSlipState:
    """The tip-substrate contact's spring, carried between the pieces a contact move is fed in."""

    force: float = 0.0  # N, spring force (0: the tip has just landed)
    x: float | None = None  # m, last tip position (sample frame); None: no sample yet
    y: float | None = None


def stick_slip_force(
    x: np.ndarray,
    y: np.ndarray,
    kinetic: np.ndarray,
    ratio: float,
    stiffness: float,
    state: StickSlipState,
) -> np.ndarray:
    """Lateral force (N) of a 1-D spring-slider at the tip positions (x, y): the spring loads
    by stiffness x distance travelled; where it exceeds the static friction ratio x kinetic it
    slips back to the kinetic level and loads again over the rest of the step (so the
    saw-tooth's period is exact, not rounded to samples). kinetic: the kinetic friction (N) per
    sample. Updates `state`."""
    n = x.size
    if n == 0:
        return np.zeros(0)
    first = 0.0 if state.x is None else math.hypot(float(x[0]) - state.x, float(y[0]) - state.y)
    travel = np.concatenate([[first], np.hypot(np.diff(x), np.diff(y))]).tolist()
    force = state.force
    out = []
    for ds, level in zip(travel, kinetic.tolist()):
        force += stiffness * ds
        static = ratio * level
        if force > static:
            drop = static - level
            force = level + (math.fmod(force - static, drop) if drop > 0 else 0.0)
        out.append(force)
    state.force, state.x, state.y = force, float(x[-1]), float(y[-1])
    return np.array(out)


@dataclass
class PushStepResult:
    moved_ids: list[int]
    lateral_force: np.ndarray  # N, per path sample, positive = opposing the tip's motion
    vertical_deflection: np.ndarray  # m
    lateral_torsion: np.ndarray  # rad


# --------------------------------------------------------------------------------------------
# Sphere law: friction of a disc patch and the deflection angle beta(alpha)
# --------------------------------------------------------------------------------------------

_LOG_RHO = np.linspace(np.log(1e-3), np.log(1e3), 193)
_DISC: tuple[np.ndarray, np.ndarray] | None = None
_BETA_TABLES: dict[float, list[float]] = {}
_N_ALPHA = 361
_ALPHA_MAX = 0.5 * math.pi - 1e-6
_D_ALPHA = _ALPHA_MAX / (_N_ALPHA - 1)


def disc_friction(rho: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Friction of a uniformly pressed disc patch (radius a, total Coulomb force 1) rotating
    about a point at distance rho * a from its centre: (force f, torque m / a). Tabulated once
    by midpoint quadrature in polar coordinates; far field f = 1, m = 1/(4 rho)."""
    global _DISC
    if _DISC is None:
        nr, nt = 120, 120  # half disc x >= 0 (the integrands are even in x)
        r = (np.arange(nr) + 0.5) / nr
        th = (np.arange(nt) + 0.5) * (np.pi / nt) - 0.5 * np.pi
        rr, tt = np.meshgrid(r, th, indexing="ij")
        x, y = (rr * np.cos(tt)).ravel(), (rr * np.sin(tt)).ravel()
        w = rr.ravel() * (1.0 / nr) * (np.pi / nt) * 2.0 / np.pi
        f, m = [], []
        for chunk in np.array_split(
            np.exp(_LOG_RHO), 12
        ):  # IRC at (0, -rho): velocity (-(y + rho), x)
            yy = y[None, :] + chunk[:, None]
            d = np.hypot(x[None, :], yy)
            f.extend(np.sum(w * yy / d, axis=1))
            m.extend(np.sum(w * (x * x + y * yy) / d, axis=1))
        _DISC = (np.array(f), np.array(m))
    f_tab, m_tab = _DISC
    rho = np.asarray(rho, dtype=float)
    lr = np.log(np.clip(rho, 1e-300, None))
    f = np.interp(lr, _LOG_RHO, f_tab)
    m = np.interp(lr, _LOG_RHO, m_tab)
    far = rho > 1e3
    f = np.where(far, 1.0, np.where(rho < 1e-3, f_tab[0] * rho / 1e-3, f))
    m = np.where(far, 0.25 / np.where(far, rho, 1.0), m)
    return f, m


def sticking_deflection(alpha: np.ndarray, eps) -> np.ndarray:
    """beta(alpha) for a sticking tip contact: the root in [0, alpha] of
    sin(beta) f(rho) = eps m(rho), rho = 1 / (eps cos(beta) (tan(alpha) - tan(beta))),
    eps = a / R_P > 0 (vectorised bisection, broadcasting alpha against eps; the left side
    minus the right grows with beta, from -eps m < 0 at beta = 0 to sin(alpha) > 0)."""
    alpha, eps = np.broadcast_arrays(np.asarray(alpha, dtype=float), np.asarray(eps, dtype=float))
    lo, hi = np.zeros(alpha.shape), alpha.copy()
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for _ in range(56):
            mid = 0.5 * (lo + hi)
            gap = np.tan(alpha) - np.tan(mid)
            rho = np.where(
                gap > 0, 1.0 / (eps * np.cos(mid) * np.where(gap > 0, gap, 1.0)), np.inf
            )
            f, m = disc_friction(rho)
            positive = np.sin(mid) * f - eps * m > 0
            hi = np.where(positive, mid, hi)
            lo = np.where(positive, lo, mid)
    return 0.5 * (lo + hi)


_EPS_GRID = np.geomspace(1e-3, 1.0, 49)
_BETA_2D: np.ndarray | None = None


def _beta_table(eps: float) -> list[float]:
    """beta_s on the alpha grid for a / R_P = eps (interpolated in log eps between the rows
    of a table made once; ~eps^2 below the grid)."""
    global _BETA_2D
    key = round(eps, 9)
    table = _BETA_TABLES.get(key)
    if table is None:
        if _BETA_2D is None:
            _BETA_2D = sticking_deflection(
                np.linspace(0.0, _ALPHA_MAX, _N_ALPHA)[None, :], _EPS_GRID[:, None]
            )
        if key <= _EPS_GRID[0]:
            row = _BETA_2D[0] * (key / _EPS_GRID[0]) ** 2
        else:
            x = np.log(key / _EPS_GRID[0]) / np.log(_EPS_GRID[1] / _EPS_GRID[0])
            k = min(int(x), _EPS_GRID.size - 2)
            row = _BETA_2D[k] + (_BETA_2D[k + 1] - _BETA_2D[k]) * (x - k)
        table = row.tolist()
        _BETA_TABLES[key] = table
    return table


# --------------------------------------------------------------------------------------------
# Rod law: minimum-work twist for a push at a point of the axis
# --------------------------------------------------------------------------------------------

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


# --------------------------------------------------------------------------------------------
# Geometry helpers (pure Python floats: these run per step)
# --------------------------------------------------------------------------------------------


def _closest_on_segment(px, py, ax, ay, bx, by):
    abx, aby = bx - ax, by - ay
    ab2 = abx * abx + aby * aby
    t = ((px - ax) * abx + (py - ay) * aby) / ab2 if ab2 > 0 else 0.0
    t = 0.0 if t < 0.0 else (1.0 if t > 1.0 else t)
    return ax + t * abx, ay + t * aby, t


def _closest_segments(p1x, p1y, q1x, q1y, p2x, p2y, q2x, q2y):
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


def _rod_ends(rod: Rod):
    hx, hy = 0.5 * rod.length * math.cos(rod.angle), 0.5 * rod.length * math.sin(rod.angle)
    return rod.x - hx, rod.y - hy, rod.x + hx, rod.y + hy


def _capsule_out_of_box(ax, ay, bx, by, r, x0, x1, y0, y1):
    """Shortest translation (separating-axis test over the box normals, the segment normal and
    the corner-to-segment directions) that takes a capsule out of a box, or None."""
    axes = [(1.0, 0.0), (0.0, 1.0)]
    sx, sy = bx - ax, by - ay
    sl = math.hypot(sx, sy)
    if sl > 0:
        axes.append((-sy / sl, sx / sl))
    corners = ((x0, y0), (x1, y0), (x0, y1), (x1, y1))
    for cx, cy in corners:
        qx, qy, _ = _closest_on_segment(cx, cy, ax, ay, bx, by)
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


# --------------------------------------------------------------------------------------------
# The world the tip moves in
# --------------------------------------------------------------------------------------------

_TOL = 1e-13  # m, overlaps below this are contact
_MAX_PASSES = 8
_DETAILED_STEPS_AFTER_CONTACT = 16


class _World:
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
        self.initial = [self._pose(i) for i in range(len(self.objs))]
        self.touched_order: list[int] = []
        self.touched: set[int] = set()
        self.snap: dict[int, tuple[float, float, float]] = {}
        self.ux = self.uy = 0.0
        self.prev_x = self.prev_y = 0.0

    # ---- bookkeeping
    def _pose(self, i):
        o = self.objs[i]
        return (o.x, o.y, o.angle if self.is_rod[i] else 0.0)

    def _before_move(self, i):
        if i not in self.snap:
            self.snap[i] = self._pose(i)
            if i not in self.touched:
                self.touched.add(i)
                self.touched_order.append(i)

    def _bounds_of(self, i):
        o = self.objs[i]
        r = o.radius
        if self.is_rod[i]:
            ax, ay, bx, by = _rod_ends(o)
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
        rod = self.objs[i]
        L = rod.length
        if L <= 1e-15:
            self.translate(i, delta * nx, delta * ny)
            return
        ex, ey = math.cos(rod.angle), math.sin(rod.angle)
        nlx, nly = nx * ex + ny * ey, -nx * ey + ny * ex
        if (t <= 0.0 or t >= 1.0) and abs(nlx) > 1e-9:
            se = 1.0 if t >= 1.0 else -1.0
            sy = 1.0 if nly >= 0 else -1.0
            psi = math.atan2(sy * nly, max(-se * nlx, 0.0))
            table = _END_TABLE if _END_TABLE is not None else rod_end_twists().tolist()
            x = psi / _D_PSI
            k = min(int(x), len(table) - 2)
            fr = x - k
            vxc, vyc, wc = (a + (b - a) * fr for a, b in zip(table[k], table[k + 1]))
            vx, vy, w = se * vxc, sy * vyc, se * sy * wc / L
        else:
            s_c = (t - 0.5) * L
            b = self.p.rod_contact_halfwidth
            arm = math.copysign(max(abs(s_c) - b, 0.0), s_c)
            sy = 1.0 if nly >= 0 else -1.0
            if arm == 0.0:
                vx, vy, w = nlx, nly, 0.0
            else:
                x0 = arm - math.copysign(math.sqrt(arm * arm + 0.25 * L * L), arm)
                w = 1.0 / ((s_c - x0) * sy)
                vx, vy = 0.0, -w * x0
        self.rigid(i, delta * (vx * ex - vy * ey), delta * (vx * ey + vy * ex), delta * w)

    def push_object(self, i, qx, qy, t, nx, ny, delta):
        """Frictionless push of object i at its axis point (qx, qy) / parameter t along n."""
        if self.is_rod[i]:
            self.push_rod(i, t, nx, ny, delta)
        else:
            self.translate(i, delta * nx, delta * ny)

    # ---- the tip
    def tip_gap(self, i, px, py):
        """(distance from the tip to object i's axis minus contact distance, normal, t)."""
        o = self.objs[i]
        if self.is_rod[i]:
            ax, ay, bx, by = _rod_ends(o)
            qx, qy, t = _closest_on_segment(px, py, ax, ay, bx, by)
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
        first = moving
        for _ in range(4):
            gap, d, dx, dy, t = self.tip_gap(i, px, py)
            if gap >= -_TOL:
                return True
            if d < 1e-3 * o.radius:
                return False
            nx, ny = dx / d, dy / d
            if self.is_rod[i]:
                self.push_rod(i, t, nx, ny, -gap)
                continue
            D = self.rt + o.radius
            ux, uy = self.ux, self.uy
            if first and (ux or uy):
                # trapezoidal direction: mean of the normals where the contact began in this
                # step and where it is now (second-order accurate in the step length)
                ox, oy = o.x - self.prev_x, o.y - self.prev_y
                od = math.hypot(ox, oy)
                if od > D:
                    sx, sy = self.prev_x - px, self.prev_y - py
                    back = ox * sx + oy * sy
                    lam = (
                        -back
                        - math.sqrt(
                            max(back * back - (sx * sx + sy * sy) * (od * od - D * D), 0.0)
                        )
                    ) / max(sx * sx + sy * sy, 1e-300)
                    ox, oy = ox + lam * sx, oy + lam * sy
                    od = math.hypot(ox, oy)
                if od > 0:
                    mx, my = nx + ox / od, ny + oy / od
                    ml = math.hypot(mx, my)
                    if ml > 1e-12:
                        nx, ny = mx / ml, my / ml
            first = False
            beta = 0.0
            if (ux or uy) and self.mu_angle > 0 and self.p.substrate_contact_radius > 0:
                alpha = math.acos(max(-1.0, min(1.0, ux * nx + uy * ny)))
                table = _beta_table(min(self.p.substrate_contact_radius / o.radius, 1.0))
                x = min(alpha, _ALPHA_MAX) / _D_ALPHA
                k = min(int(x), _N_ALPHA - 2)
                beta = min(table[k] + (table[k + 1] - table[k]) * (x - k), self.mu_angle)
            if beta > 0:
                sgn = 1.0 if nx * uy - ny * ux >= 0 else -1.0
                c, s = math.cos(beta), sgn * math.sin(beta)
                wx, wy = c * nx - s * ny, s * nx + c * ny
            else:
                wx, wy = nx, ny
            rw = dx * wx + dy * wy
            step = -rw + math.sqrt(max(rw * rw + D * D - d * d, 0.0))
            self.translate(i, step * wx, step * wy)
            return True
        return True

    # ---- object-object contacts
    def overlap(self, a, b):
        """Overlap of a and b with the unit normal from a to b and both contact points."""
        oa, ob = self.objs[a], self.objs[b]
        ra, rb = self.is_rod[a], self.is_rod[b]
        if not ra and not rb:
            qax, qay, ta, qbx, qby, tb = oa.x, oa.y, 0.5, ob.x, ob.y, 0.5
        elif not ra:
            qax, qay, ta = oa.x, oa.y, 0.5
            qbx, qby, tb = _closest_on_segment(oa.x, oa.y, *_rod_ends(ob))
        elif not rb:
            qbx, qby, tb = ob.x, ob.y, 0.5
            qax, qay, ta = _closest_on_segment(ob.x, ob.y, *_rod_ends(oa))
        else:
            qax, qay, ta, qbx, qby, tb = _closest_segments(*_rod_ends(oa), *_rod_ends(ob))
        dx, dy = qbx - qax, qby - qay
        d = math.hypot(dx, dy)
        ov = oa.radius + ob.radius - d
        if ov <= _TOL:
            return None
        if d > 1e-30:
            nx, ny = dx / d, dy / d
        else:  # axes cross: push b off a's axis sideways
            if ra:
                ex, ey = math.cos(oa.angle), math.sin(oa.angle)
                nx, ny = -ey, ex
                if (ob.x - oa.x) * nx + (ob.y - oa.y) * ny < 0:
                    nx, ny = -nx, -ny
            else:
                nx, ny = 1.0, 0.0
        return ov, nx, ny, qax, qay, ta, qbx, qby, tb

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
                ax, ay, bx, by = _rod_ends(o)
            else:
                ax = bx = o.x
                ay = by = o.y
            mtv = _capsule_out_of_box(ax, ay, bx, by, o.radius, x0, x1, y0, y1)
            if mtv is not None and math.hypot(*mtv) > _TOL:
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
                ov, nx, ny, qax, qay, ta, qbx, qby, tb = hit
                if rank.get(b, math.inf) > rank[a]:
                    self.push_object(b, qbx, qby, tb, nx, ny, ov)
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
                if i not in self.riding and self.tip_gap(i, px, py)[0] < -_TOL:
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
                    ov, nx, ny, qax, qay, ta, qbx, qby, tb = hit
                    self.push_object(b, qbx, qby, tb, nx, ny, 0.5 * ov)
                    self.push_object(a, qax, qay, ta, -nx, -ny, 0.5 * ov)
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
            if self.tip_gap(i, px, py)[0] < -_TOL:
                contact = True
                if length > 0 and self.push_from_tip(i, px, py, moving=True):
                    seeds.append(i)
                else:
                    self.riding.add(i)
        if seeds:
            self.resolve(seeds, px, py)
        return self.dissipation(dt), contact

    def dissipation(self, dt) -> float:
        p = self.p
        energy = 0.0
        for i, (x, y, ang) in self.snap.items():
            o = self.objs[i]
            if not self.is_rod[i]:
                dist = math.hypot(o.x - x, o.y - y)
                coulomb = p.substrate_friction_force
                if self.friction is not None:
                    coulomb *= self.friction.scale(0.5 * (o.x + x), 0.5 * (o.y + y), 0)
                energy += (coulomb + p.viscous_coefficient * dist / dt) * dist
                continue
            c0, s0, c1, s1 = math.cos(ang), math.sin(ang), math.cos(o.angle), math.sin(o.angle)
            k = 8
            coulomb = viscous = 0.0
            for j in range(k + 1):
                s = (j / k - 0.5) * o.length
                w = 0.5 if j in (0, k) else 1.0
                dd = math.hypot(o.x - x + s * (c1 - c0), o.y - y + s * (s1 - s0))
                # this point's friction scale, midway along its step (x 1.0 is exact: no regions, no change)
                scale = (
                    1.0
                    if self.friction is None
                    else self.friction.scale(
                        0.5 * (o.x + x + s * (c0 + c1)), 0.5 * (o.y + y + s * (s0 + s1)), 0
                    )
                )
                coulomb += w * scale * dd
                viscous += w * dd * dd
            ds = o.length / k if o.length > 0 else 1.0
            energy += (
                p.rod_friction_per_length * coulomb + p.rod_viscous_per_length * viscous / dt
            ) * ds
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
            ends = np.array([_rod_ends(self.objs[i]) for i in rods])
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


# --------------------------------------------------------------------------------------------
# The path
# --------------------------------------------------------------------------------------------


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

    def sliding_per_sample() -> np.ndarray:
        """The stick-slip saw-tooth of the tip-substrate force per sample (stick-slip on)."""
        kinetic = np.full(n, p.mu_tip_substrate * p.normal_force)
        if friction is not None:
            kinetic = kinetic * _tip_substrate_scales(friction, x, y, *before)
        return stick_slip_force(
            x, y, kinetic, p.static_friction_ratio, p.stick_slip_stiffness, stick_slip
        )

    world = _World(sample, p, friction)
    reach = (
        p.tip_radius + 2 * max((hb[1] - hb[0]) + (hb[3] - hb[2]) for hb in world.bl)
        if world.bl
        else 0.0
    )
    near = world.query_all(x.min() - reach, x.max() + reach, y.min() - reach, y.max() + reach)
    h = p.substep_fraction * min(
        [p.tip_radius, *(world.objs[i].radius for i in near if world.objs[i].radius > 0)]
    )
    # Objects the tip overlaps at the first sample: a shallow overlap is a contact carried over
    # from a previous call (a path fed in pieces), pushed out now; a deep one means the tip
    # starts on top of the object and rides over it.
    seeds = []
    for i in range(len(world.objs)):
        gap = world.tip_gap(i, x[0], y[0])[0]
        if gap < -_TOL:
            if -gap <= 0.25 * min(p.tip_radius, world.objs[i].radius):
                seeds.append(i)
            else:
                world.riding.add(i)
    if seeds:
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
    sliding = p.mu_tip_substrate * p.normal_force
    if n == 1 or not world.objs:
        if p.stick_slip_enabled:
            forces = sliding_per_sample()
        else:
            forces = np.zeros(n)
            if n > 1:
                moving = np.concatenate([[False], np.hypot(np.diff(x), np.diff(y)) > 0])
                moving[0] = moving[1]
                if friction is None:
                    forces[moving] = sliding
                else:
                    scales = _tip_substrate_scales(friction, x, y, None, None)
                    scales[0] = scales[1]
                    forces[moving] = sliding * scales[moving]
        return PushStepResult(
            [], forces, deflection, forces * p.tip_height / p.lateral_spring_constant
        )

    X, Y, T, sample_step = _mechanics_vertices(x, y, h)
    m = X.size
    lengths = np.concatenate([[0.0], np.hypot(np.diff(X), np.diff(Y))])
    if friction is None:
        tip_force = np.where(lengths > 0, sliding, 0.0)
    else:  # scaled at the middle of each step
        mid_scale = friction.scales(0.5 * (X[:-1] + X[1:]), 0.5 * (Y[:-1] + Y[1:]), 1)
        tip_force = np.where(lengths > 0, sliding * np.concatenate([[1.0], mid_scale]), 0.0)
    object_force = np.zeros(m)  # N, the pushed objects' dissipation per unit tip travel
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

    if p.stick_slip_enabled:
        forces = object_force[sample_step]
        if n > 1:
            forces[0] = forces[1]
        forces = forces + sliding_per_sample()
    else:
        # (tip + objects, summed per step in this order: the same arithmetic as ever)
        forces = (tip_force + object_force)[sample_step]
        if n > 1:
            forces[0] = forces[1]
    moved = [world.objs[i].id for i in world.touched_order if world._pose(i) != world.initial[i]]
    return PushStepResult(
        moved, forces, deflection, forces * p.tip_height / p.lateral_spring_constant
    )
