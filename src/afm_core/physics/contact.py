"""Contact forces and friction of the pushing model: the parameters, friction regions,
stick-slip of the tip on the substrate, and the energy the pushed objects dissipate.

Forces
------
Power balance: the tip does the work the pushed objects dissipate, so the lateral force
opposing the tip's motion is mu_ts N (the apex keeps sliding on the substrate while it
pushes, so this term stays) plus the dissipated energy per unit tip travel ((F_c + c v) |dx|
per sphere, the length integrals for rods; the spin dissipation, of relative order a/R_P, is
left out). When only sliding it is mu_ts N; with the tip at rest it is 0. Torsion (rad) =
F_lat * tip_height / lateral_spring_constant, positive when resisting the motion (the
instrument knows how the cantilever is oriented and may flip the sign with the scan
direction). The vertical deflection is the contact-mode setpoint N / k_n.

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
the tip slides steadily). A contact move starts relaxed (force 0) and carries the spring over
between the pieces it is fed in (``StickSlipState``); at rest the spring holds its force.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from afm_core import checks
from afm_core.physics.sample import Rod, Sphere


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
        # validated only, not converted: the values stay exactly as given
        checks.positive("contact.tip_radius", self.tip_radius, "m")
        checks.positive("contact.normal_spring_constant", self.normal_spring_constant, "N/m")
        checks.positive("contact.lateral_spring_constant", self.lateral_spring_constant, "N m/rad")
        checks.positive("contact.tip_height", self.tip_height, "m")
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
            checks.non_negative(f"contact.{name}", getattr(self, name))
        if not 0 < self.substep_fraction <= 0.5:
            raise ValueError(
                f"contact.substep_fraction={self.substep_fraction}: must be in (0, 0.5]"
            )
        if not (math.isfinite(self.static_friction_ratio) and self.static_friction_ratio >= 1):
            raise ValueError(
                f"contact.static_friction_ratio={self.static_friction_ratio}: must be finite and "
                ">= 1 (static over kinetic friction)"
            )
        checks.positive("contact.stick_slip_stiffness", self.stick_slip_stiffness, "N/m")
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


def sphere_dissipation(
    sphere: Sphere,
    x: float,
    y: float,
    dt: float,
    params: ContactParams,
    friction: FrictionMap | None,
) -> float:
    """Energy (J) a sphere dissipated sliding from (x, y) to where it is now in dt: Coulomb
    friction (taken at the middle of the step) plus viscous friction, times the distance."""
    dist = math.hypot(sphere.x - x, sphere.y - y)
    coulomb = params.substrate_friction_force
    if friction is not None:
        coulomb *= friction.scale(0.5 * (sphere.x + x), 0.5 * (sphere.y + y), 0)
    return (coulomb + params.viscous_coefficient * dist / dt) * dist


def rod_dissipation(
    rod: Rod,
    x: float,
    y: float,
    angle: float,
    dt: float,
    params: ContactParams,
    friction: FrictionMap | None,
) -> float:
    """Energy (J) a rod dissipated moving from the pose (x, y, angle) to where it is now in
    dt: the line integrals of Coulomb and viscous friction per unit length over its axis
    (trapezoidal rule on 8 intervals; each point's friction scale midway along its step)."""
    c0, s0, c1, s1 = math.cos(angle), math.sin(angle), math.cos(rod.angle), math.sin(rod.angle)
    k = 8
    coulomb = viscous = 0.0
    for j in range(k + 1):
        s = (j / k - 0.5) * rod.length
        w = 0.5 if j in (0, k) else 1.0
        dd = math.hypot(rod.x - x + s * (c1 - c0), rod.y - y + s * (s1 - s0))
        # x 1.0 without regions: exactly the value before friction regions existed
        scale = (
            1.0
            if friction is None
            else friction.scale(
                0.5 * (rod.x + x + s * (c0 + c1)), 0.5 * (rod.y + y + s * (s0 + s1)), 0
            )
        )
        coulomb += w * scale * dd
        viscous += w * dd * dd
    ds = rod.length / k if rod.length > 0 else 1.0
    return (
        params.rod_friction_per_length * coulomb + params.rod_viscous_per_length * viscous / dt
    ) * ds
