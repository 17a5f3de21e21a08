"""Sphere pushing: how a sphere moves when the tip presses on it (book ch. 2.3.3, 6.4.2,
eq. 6.16-6.17; SPEC section 5), the IRC model of eq. 6.16-6.17.

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
for small alpha: the particle moves practically along the contact normal. A push through
the centre (alpha = 0) moves it straight along u; any offset grows while it is pushed, so it
slides off to the side it was hit on (the instability of SPEC 5); a path whose lateral offset
exceeds R_T + R_P touches nothing. With mu_tp = 0 or a = 0 the particle moves exactly along
n. The spin about the IRC is the sphere's own rotation;
it is not stored (a sphere's pose and height do not change with it), and rolling is not
modelled (the particle slides, as in the book's model).
"""

from __future__ import annotations

import math

import numpy as np

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


def sticking_angle(alpha: float, eps: float) -> float:
    """beta(alpha) of a sticking contact for a / R_P = eps, interpolated in the table."""
    table = _beta_table(eps)
    x = min(alpha, _ALPHA_MAX) / _D_ALPHA
    k = min(int(x), _N_ALPHA - 2)
    return table[k] + (table[k + 1] - table[k]) * (x - k)


def _trapezoidal_normal(nx, ny, ox, oy, sx, sy, reach):
    """The mean of the contact normal now (nx, ny) and where the contact began in this step:
    the centre is (ox, oy) from the step's start point, which is (sx, sy) from its end (second
    order accurate in the step length)."""
    od = math.hypot(ox, oy)
    if od > reach:
        back = ox * sx + oy * sy
        lam = (
            -back
            - math.sqrt(max(back * back - (sx * sx + sy * sy) * (od * od - reach * reach), 0.0))
        ) / max(sx * sx + sy * sy, 1e-300)
        ox, oy = ox + lam * sx, oy + lam * sy
        od = math.hypot(ox, oy)
    if od > 0:
        mx, my = nx + ox / od, ny + oy / od
        ml = math.hypot(mx, my)
        if ml > 1e-12:
            nx, ny = mx / ml, my / ml
    return nx, ny


def sphere_push(
    to_centre: tuple[float, float, float],
    reach: float,
    push: tuple[float, float],
    mu_angle: float,
    patch_radius: float,
    radius: float,
    step_start: tuple[float, float, float, float] | None = None,
) -> tuple[float, float]:
    """The translation of a sphere the tip overlaps that restores contact, along the contact
    normal turned by beta towards the push direction (see the module docstring).

    to_centre: (dx, dy, d), from the tip to the sphere's centre and its length (< reach =
    R_T + R_P); push: the unit direction of the tip's step ((0, 0) at rest); mu_angle:
    atan(mu_tp); patch_radius: a; radius: R_P; step_start: when the contact began within this
    step, (ox, oy, sx, sy): the centre from the step's start point and that point from the tip."""
    dx, dy, d = to_centre
    nx, ny = dx / d, dy / d
    ux, uy = push
    if step_start is not None and (ux or uy):
        nx, ny = _trapezoidal_normal(nx, ny, *step_start, reach)
    beta = 0.0
    if (ux or uy) and mu_angle > 0 and patch_radius > 0:
        alpha = math.acos(max(-1.0, min(1.0, ux * nx + uy * ny)))
        beta = min(sticking_angle(alpha, min(patch_radius / radius, 1.0)), mu_angle)
    if beta > 0:
        sgn = 1.0 if nx * uy - ny * ux >= 0 else -1.0
        c, s = math.cos(beta), sgn * math.sin(beta)
        wx, wy = c * nx - s * ny, s * nx + c * ny
    else:
        wx, wy = nx, ny
    rw = dx * wx + dy * wy
    step = -rw + math.sqrt(max(rw * rw + reach * reach - d * d, 0.0))
    return step * wx, step * wy
