"""Push plans: centre pushing, the virtual nano-hand zigzag, rod-like and arc-shaped hands.

Book ch. 2.3.3, 6.4.2-6.4.3 (Fig. 6.18) and 7.3 (Fig. 7.24-7.26, Table 7.6); SPEC section 5.
A plan is a list of tip strokes in the afm_task frame (SI units): each stroke is a straight
tip motion from `start` to `end`, in contact (pushing) or lifted. The executor
(afm_core.manipulation.execute) lifts the tip between strokes, so the order of the strokes is
the whole motion; nothing here moves anything.

Frame of a push
---------------
u is the push axis (unit vector from the estimated particle centre c0 to the goal); "left" is
u turned by +90 deg (n = (-u_y, u_x)), as seen looking along the push. `along` and `lateral`
coordinates of a point p are (p - c0) . u and (p - c0) . n. D = R_P + R_T is the centre
distance of tip and particle at contact (the planar contact model of afm_core.sim.pushing).
lead(e) = sqrt(D^2 - e^2) is how far the particle's centre is ahead of the tip along u when a
path with lateral offset e touches it.

Centre pushing (the baseline, Fig. 6.18a-e)
-------------------------------------------
Straight pushes along the line through the *estimated* centre: with the true centre off that
line by e, the contact normal is tilted by asin(e / D), the particle slides off to the side it
was hit on, and the tilt grows while it is pushed (SPEC 5). Repeated short pushes (the same
push/back lengths as the hand) turn a Gaussian uncertainty into two lobes on arcs of radius
D around the tip's end points; one long push loses the particle altogether for e of a few nm.

The virtual nano-hand zigzag (Fig. 6.18f-i, Fig. 7.24, Table 7.6): our reading
---------------------------------------------------------------------------
Two straight push paths parallel to u, at lateral offsets +L_h/2 (left) and -L_h/2 (right)
of the estimated centre line, i.e. along the edges of the centre's uncertainty region
(+-3 sigma = +-30 nm lies well inside +-60 nm) while still inside the contact reach D (60 nm
< 150 nm). Every push therefore hits the particle on a *known* side: the left path pushes it
to the right and the right path to the left, so the centre stays between the paths instead
of splitting (the book: "the possible position of the center is still between two parallel
manipulation paths after six push operations").

Step k (k = 0, 1, ...; k even on the left, odd on the right):

1. the tip starts at S_k, lifted, on its path;
2. it pushes forward by L_push (L_left_push / L_right_push, 156 nm) in contact;
3. it retracts by L_back (L_left_back / L_right_back, 120 nm) and moves L_h (120 nm) across
   to the other path: the start S_{k+1} of the next push is L_back behind the end of this one,
   so every step advances the pushing front by L_step = L_push - L_back = 36 nm (Table 7.6
   gives L_step = 36 = 156 - 120, which is what makes us read L_back as measured from the end
   of the push). The executor does step 3 as one lifted move.

S_0 is L_initial_h (78 nm) behind the first nominal contact on the left path: the tip runs
78 nm before it touches a particle that sits where it is estimated, i.e.
along(S_0) = -(lead(L_h/2) + L_initial_h). (Fig. 7.24c labels L_initial_h next to the first
left push; we read it as that push's approach distance. The other reading, a sideways move
of 78 nm from a start on the centre line, puts the paths at -78/+42 nm, asymmetric about the
centre; in the pushing model that lets a particle 2 sigma to the right escape past the right
path, and it does not give the book's simulated 507 nm. Our reading gives both.)

Prediction for n steps with the Table 7.6 values: the tip's front ends at
along = -lead(60) - 78 + 156 + (n - 1) 36, the particle's centre is lead(e_f) ahead of it
(e_f: offset at the last contact), so the particle moves
L_push - L_initial_h + (n - 1) L_step + lead(e_f) - lead(60) = 510 nm + (lead(e_f) - lead(60))
for n = 13. The last push slides the particle away from its path by
delta ~ D (sin t1 - sin t0), tan(t1/2) = tan(t0/2) exp(L_step / D), sin t0 = e / D (the
frictionless closed form; ~15 nm for e = 60 nm), so e_f ~ 74 nm and lead(e_f) - lead(60)
~ -7 nm: 503 nm along (the book's simulation: 507 nm, its experiment 530 nm) and ~13 nm
sideways, away from the side of the last push (13 is odd: the last push is on the left, so the
particle ends ~13 nm right of the axis; the experiment: 20 nm). The physics of
afm_core.sim.pushing (tip-particle friction bends the motion slightly towards u) gives
503.1 nm and 13.8 nm. On the SimulatedAfm the tip's own displacement errors add to that
(the controller's residual hysteresis ratchets the tip ~20 nm further along u over the 13
zigzag steps, and each move's random positioning error accumulates): 525 +- 12 nm along over
20 seeds, close to the book's measured 530 nm, whose gap to its 507 nm simulation the book
also puts down to the tip's displacement.

Aiming: with `aim=True` (default) the planner runs the plan through the pushing model
(afm_core.sim.pushing.push_along_path on one sphere at the estimated centre) and corrects it
until the predicted end is on the goal: the number of steps is the one whose nominal reach is
closest to the distance, the end of the last push is moved along u by the remaining along
error, and the whole corridor is shifted sideways by minus the predicted sideways offset (the
final slide of ~delta away from the last path is planned for, not suffered).

choose_nano_hand_params: the planner's choice from the uncertainties
--------------------------------------------------------------------
With sigma the 1-sigma uncertainty of the particle's centre relative to the tip (particle and
tip localisation combined), k = `confidence` (3) and m = `margin` (10 nm):

- half separation a = L_h / 2: the paths must straddle the uncertainty region, a >= k sigma + m,
  and still touch the particle when it is k sigma beyond a path's side, a + k sigma + m <= D.
  Inside that window we take a = 0.4 D (the book's 60 / 150), clipped into the window;
  an empty window (k sigma + m > D / 2) is an error: localise better first.
- L_step: the largest advance whose sideways slide at offset a (frictionless closed form above,
  an upper bound: friction only reduces it) is at most a / 4, so the particle stays well
  inside the corridor after each push; 37.5 nm for the book's case (Table 7.6: 36).
- L_initial_h = 2 k sigma + (lead(a - k sigma) - lead(a)) + m: the particle may be k sigma
  closer than estimated, the tip itself a further k sigma off, and a particle k sigma nearer
  the path is touched lead(a - k sigma) - lead(a) earlier; 79.5 nm for the book's case (Table 7.6: 78).
- L_back = L_initial_h + k sigma + (lead(a - delta) - lead(a + delta)): the next push, on the
  other path, starts at least L_initial_h + k sigma before its nominal contact (the particle
  is delta nearer that path than nominal, hence the lead difference); 122.7 nm (Table 7.6: 120).
- L_push = L_back + L_step (160.2 nm; Table 7.6: 156).

The margins are ours, chosen so that the rule gives Table 7.6 for the book's case (sigma 10 nm,
R_P 100 nm, R_T 50 nm); the structure (a window for a, a slide bound for L_step, run-ups for
the approach) is what makes it scale with the uncertainty.

Rod-like and arc-shaped hands (Fig. 2.11, 7.26)
-----------------------------------------------
rod_hand_plan: two pushing points at +-grip * L/2 along a rod or tube, pushed alternately
across the axis (and, for an axial error, at an end cap along the axis), each push at most
`step` deep, chosen greedily by the model (the rod law of afm_core.sim.pushing: a push off
the centre turns the rod about a point towards the far end) until the predicted pose is
within tolerance: translate and rotate a rod, e.g. to bridge two electrodes (pass them as
`electrodes`, the model treats them as walls).

arc_hand_plan: gathering particles onto a ring (the hexagon of Fig. 7.26f with six
particles): slots equally spaced on the ring, particles assigned to slots by minimum total
distance (Hungarian assignment), then each particle is carried to its slot by a nano-hand
zigzag aimed radially; the hands' last strokes lie on an arc around the ring's centre,
together they form the arc-shaped hand. Particles are pushed nearest-first and the whole plan
is checked in the model with all particles present.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from afm_core.instrument import ScannerLimits

NM = 1e-9
DEFAULT_TIP_RADIUS = 50e-9  # m, effective contact radius R_T (book 7.3: 50 nm)
DEFAULT_PARTICLE_RADIUS = 100e-9  # m, polystyrene spheres (book: ~100 nm)
DEFAULT_SIGMA = 10e-9  # m, centre uncertainty (book 6.4.3: 10 nm)
DEFAULT_MAX_DISTANCE = 20e-6  # m, longest push a plan accepts


# --------------------------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Stroke:
    """One straight tip motion (afm_task frame, m). contact=True pushes; False moves lifted."""

    start: np.ndarray
    end: np.ndarray
    contact: bool = True
    label: str = ""  # "left", "right", "centre", "rod", "axial", ...

    @property
    def length(self) -> float:
        return float(np.hypot(*(np.asarray(self.end) - np.asarray(self.start))))


@dataclass
class ParticleEstimate:
    """Where the particle is believed to be (afm_task frame) and how sure we are."""

    x: float
    y: float
    radius: float = DEFAULT_PARTICLE_RADIUS
    sigma: float = DEFAULT_SIGMA  # m, 1-sigma of the centre per axis (relative to the tip)

    @property
    def xy(self) -> np.ndarray:
        return np.array([self.x, self.y], dtype=float)


@dataclass
class PushPlan:
    """A list of strokes plus what the planner assumed and predicted."""

    kind: str  # "centre", "nano_hand", "rod", "arc"
    strokes: list[Stroke]
    particle: np.ndarray  # (2,) estimated start centre (rod: centre)
    goal: np.ndarray  # (2,) goal centre
    axis: np.ndarray  # (2,) unit push axis u (rod/arc: centre -> goal)
    particle_radius: float
    tip_radius: float
    path_offsets: tuple[float, float] | None = (
        None  # lateral coords of the (left, right) paths at the end
    )
    predicted: np.ndarray | None = None  # (2,) predicted final centre (model, nominal start)
    predicted_track: list = field(
        default_factory=list
    )  # predicted centre (or pose) after each stroke
    params: object = None
    goal_angle: float | None = None  # rod plans: goal axis angle (rad)
    predicted_angle: float | None = None
    extra: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.strokes)

    def __iter__(self) -> Iterator[Stroke]:
        return iter(self.strokes)

    def __getitem__(self, index):
        return self.strokes[index]

    @property
    def normal(self) -> np.ndarray:
        """Left of the push axis: u turned by +90 deg."""
        return np.array([-self.axis[1], self.axis[0]])

    def along(self, points) -> np.ndarray:
        return (np.asarray(points, float) - self.particle) @ self.axis

    def lateral(self, points) -> np.ndarray:
        return (np.asarray(points, float) - self.particle) @ self.normal

    def contact_strokes(self) -> list[Stroke]:
        return [s for s in self.strokes if s.contact]

    def first_steps(self, n: int) -> PushPlan:
        """The same plan cut after its first n contact strokes (and the lifted ones between)."""
        kept, count = [], 0
        for stroke in self.strokes:
            if stroke.contact:
                if count == n:
                    break
                count += 1
            kept.append(stroke)
        return replace(self, strokes=kept, predicted=None, predicted_track=[])


@dataclass(frozen=True)
class NanoHandParams:
    """The zigzag's geometry (Table 7.6 names, metres). step = push - back on each side."""

    left_push: float
    right_push: float
    left_back: float
    right_back: float
    initial_h: float  # approach of the first push before its nominal contact (L_initial_h)
    h: float  # separation of the two paths (L_h)
    step: float  # advance of the pushing front per step (L_step)

    @classmethod
    def book(cls) -> NanoHandParams:
        """Table 7.6 (book 7.3.1): 156, 156, 120, 120, 78, 120, 36 nm."""
        return cls(156 * NM, 156 * NM, 120 * NM, 120 * NM, 78 * NM, 120 * NM, 36 * NM)

    def validate(self) -> None:
        for name in (
            "left_push",
            "right_push",
            "left_back",
            "right_back",
            "initial_h",
            "h",
            "step",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"NanoHandParams.{name}={value}: must be finite and > 0 m")
        for side in ("left", "right"):
            push, back = getattr(self, f"{side}_push"), getattr(self, f"{side}_back")
            if abs(push - back - self.step) > 1e-12:
                raise ValueError(
                    f"NanoHandParams.{side}_push - {side}_back = {push - back:.4e} m: must equal "
                    f"step = {self.step:.4e} m (each step advances the front by L_step)"
                )
            if push <= self.initial_h:
                raise ValueError(
                    f"NanoHandParams.{side}_push={push:.4e} m: must exceed initial_h="
                    f"{self.initial_h:.4e} m, or the first push never touches the particle"
                )

    def push(self, k: int) -> float:
        return self.left_push if k % 2 == 0 else self.right_push

    def back(self, k: int) -> float:
        return self.left_back if k % 2 == 0 else self.right_back


# --------------------------------------------------------------------------------------------
# Validation helpers
# --------------------------------------------------------------------------------------------


def _point(name: str, value) -> np.ndarray:
    try:
        p = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}={value!r}: must be a point (x, y) in m") from exc
    if p.size != 2:
        raise ValueError(f"{name}={value!r}: must be a point (x, y) in m")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name}={tuple(p)}: must be finite")
    return p


def _positive(name: str, value: float, upper: float | None = None, unit: str = "m") -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name}={value}: must be finite and > 0 {unit}")
    if upper is not None and value > upper:
        raise ValueError(f"{name}={value:.4e} {unit}: above the limit {upper:.4e} {unit}")
    return value


def _particle(obj, radius: float | None, sigma: float | None = None) -> ParticleEstimate:
    """Accept a ParticleEstimate, a Sphere / Landmark (x, y, radius) or a point (x, y)."""
    if isinstance(obj, ParticleEstimate):
        est = ParticleEstimate(
            obj.x,
            obj.y,
            obj.radius if radius is None else radius,
            obj.sigma if sigma is None else sigma,
        )
    elif hasattr(obj, "x") and hasattr(obj, "y"):
        r = radius if radius is not None else getattr(obj, "radius", DEFAULT_PARTICLE_RADIUS)
        est = ParticleEstimate(
            float(obj.x), float(obj.y), float(r), DEFAULT_SIGMA if sigma is None else sigma
        )
    else:
        p = _point("particle", obj)
        est = ParticleEstimate(
            p[0],
            p[1],
            DEFAULT_PARTICLE_RADIUS if radius is None else radius,
            DEFAULT_SIGMA if sigma is None else sigma,
        )
    _point("particle", (est.x, est.y))
    _positive("particle.radius", est.radius)
    if not (math.isfinite(est.sigma) and est.sigma >= 0):
        raise ValueError(f"particle.sigma={est.sigma}: must be finite and >= 0 m")
    return est


def _axis(start: np.ndarray, goal: np.ndarray, max_distance: float) -> tuple[np.ndarray, float]:
    d = goal - start
    dist = float(np.hypot(*d))
    if dist == 0.0:
        raise ValueError("goal: the same point as the particle (distance 0 m): nothing to push")
    if dist > max_distance:
        raise ValueError(
            f"goal: {dist:.4e} m from the particle, beyond max_distance={max_distance:.4e} m"
        )
    return d / dist, dist


def check_plan_limits(plan: PushPlan, limits: ScannerLimits, margin: float = 0.0) -> None:
    """Raise ValueError naming the stroke and the limit if any stroke point leaves
    [margin, range - margin] of the scanner (or the goal does)."""
    for name, p in [
        ("goal", plan.goal),
        *[
            (f"strokes[{i}].{end}", getattr(s, end))
            for i, s in enumerate(plan.strokes)
            for end in ("start", "end")
        ],
    ]:
        x, y = float(p[0]), float(p[1])
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ValueError(f"{name}=({x}, {y}): must be finite")
        if not margin <= x <= limits.range_x - margin:
            raise ValueError(
                f"{name}.x={x:.4e} m: outside the scanner range [{margin:.4e}, "
                f"{limits.range_x - margin:.4e}] m"
            )
        if not margin <= y <= limits.range_y - margin:
            raise ValueError(
                f"{name}.y={y:.4e} m: outside the scanner range [{margin:.4e}, "
                f"{limits.range_y - margin:.4e}] m"
            )


# --------------------------------------------------------------------------------------------
# The pushing model as the planner's predictor
# --------------------------------------------------------------------------------------------


def _contact_params(contact_params, tip_radius: float):
    from afm_core.physics.contact import ContactParams

    if contact_params is None:
        return ContactParams(tip_radius=tip_radius)
    return contact_params


def simulate_strokes(
    sample, strokes: Iterable[Stroke], contact_params, track_id: int | None = None
) -> list:
    """Apply the contact strokes to a sim Sample in place with afm_core.sim.pushing (lifted
    strokes move nothing). Returns the tracked object's (x, y[, angle]) after each stroke."""
    from afm_core.physics.pushing import push_along_path

    track = []
    objs = {o.id: o for o in sample.movable}
    for stroke in strokes:
        if stroke.contact:
            push_along_path(
                sample,
                np.array([stroke.start[0], stroke.end[0]]),
                np.array([stroke.start[1], stroke.end[1]]),
                1e-3,
                contact_params,
            )
        if track_id is not None:
            o = objs[track_id]
            track.append((o.x, o.y, o.angle) if hasattr(o, "angle") else (o.x, o.y))
    return track


def predict_particle(plan: PushPlan, contact_params=None, start=None) -> list[np.ndarray]:
    """The particle's centre after each stroke of `plan` in the pushing model, starting at
    `start` (default: the plan's estimate)."""
    from afm_core.physics.sample import Sample, Sphere

    c0 = plan.particle if start is None else _point("start", start)
    sample = Sample(spheres=[Sphere(0, float(c0[0]), float(c0[1]), plan.particle_radius)])
    track = simulate_strokes(
        sample, plan.strokes, _contact_params(contact_params, plan.tip_radius), 0
    )
    return [np.array(p) for p in track]


# --------------------------------------------------------------------------------------------
# Centre pushing (baseline)
# --------------------------------------------------------------------------------------------


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
    est = _particle(particle, particle_radius)
    c0, g = est.xy, _point("goal", goal)
    u, dist = _axis(c0, g, _positive("max_distance", max_distance))
    _positive("tip_radius", tip_radius)
    for name, value in (("push", push), ("back", back), ("approach", approach)):
        _positive(name, value)
    if back >= push:
        raise ValueError(
            f"back={back:.4e} m: must be < push={push:.4e} m (each step must advance)"
        )
    D = est.radius + tip_radius
    s0 = -(D + approach)
    final = dist - D
    strokes: list[Stroke] = []
    if single:
        ends = [(s0, final)]
    else:
        adv = push - back
        if steps is None:
            steps = max(1, int(math.ceil((final - (s0 + push)) / adv - 1e-9)) + 1)
        if not (isinstance(steps, (int, np.integer)) and steps >= 1):
            raise ValueError(f"steps={steps}: must be an integer >= 1")
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
    for a, b in ends:
        strokes.append(Stroke(c0 + a * u, c0 + b * u, True, "centre"))
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


# --------------------------------------------------------------------------------------------
# The virtual nano-hand zigzag
# --------------------------------------------------------------------------------------------


def _lead(D: float, e: float) -> float:
    return math.sqrt(max(D * D - e * e, 0.0))


def _zigzag_strokes(
    c0,
    u,
    n_left,
    params: NanoHandParams,
    D: float,
    steps: int,
    trim: float,
    last_extra: float,
    first_left: bool,
) -> tuple[list[Stroke], tuple[float, float]]:
    """The zigzag's strokes; the last one is `last_extra` longer and moved `trim` sideways."""
    a = 0.5 * params.h
    s = -(_lead(D, a) + params.initial_h)
    strokes = []
    for k in range(steps):
        left = (k % 2 == 0) == first_left
        lat = (a if left else -a) + (trim if k == steps - 1 else 0.0)
        push = params.push(k) + (last_extra if k == steps - 1 else 0.0)
        strokes.append(
            Stroke(
                c0 + s * u + lat * n_left,
                c0 + (s + push) * u + lat * n_left,
                True,
                "left" if left else "right",
            )
        )
        s = s + params.push(k) - params.back(k)
    return strokes, (a, -a)


def nominal_reach(params: NanoHandParams, D: float, steps: int) -> float:
    """Along displacement of the particle after `steps` zigzag steps, neglecting its sideways
    slide: L_push - L_initial_h + (steps - 1) L_step."""
    return params.left_push - params.initial_h + (steps - 1) * params.step


def nano_hand_plan(
    particle,
    goal,
    params: NanoHandParams | None = None,
    *,
    tip_radius: float = DEFAULT_TIP_RADIUS,
    particle_radius: float | None = None,
    steps: int | None = None,
    aim: bool = True,
    first_side: str = "left",
    contact_params=None,
    limits: ScannerLimits | None = None,
    max_distance: float = DEFAULT_MAX_DISTANCE,
    aim_iterations: int = 6,
) -> PushPlan:
    """The virtual nano-hand zigzag from the estimated centre towards the goal (module docstring).

    params: NanoHandParams (default: Table 7.6, NanoHandParams.book()). steps: number of pushes
    (default: of the counts whose nominal reach is nearest the distance and its two neighbours,
    the one aimed best). aim: adjust the last
    push's length and move its path sideways (at most h/4) with the pushing model so the predicted
    end is the goal; plan.extra["predicted_error"] = (along, lateral) of what remains (aiming an
    odd count can leave several nm). aim=False: the literal geometry, e.g. the book's 13-step
    experiment; the predicted end is still reported. contact_params: the model's sim ContactParams (default: its defaults with
    this tip_radius).
    """
    est = _particle(particle, particle_radius)
    params = NanoHandParams.book() if params is None else params
    params.validate()
    c0, g = est.xy, _point("goal", goal)
    u, dist = _axis(c0, g, _positive("max_distance", max_distance))
    _positive("tip_radius", tip_radius)
    if first_side not in ("left", "right"):
        raise ValueError(f"first_side={first_side!r}: must be 'left' or 'right'")
    D = est.radius + tip_radius
    if 0.5 * params.h >= D:
        raise ValueError(
            f"params.h/2={0.5 * params.h:.4e} m: must be < R_P + R_T = {D:.4e} m, or the paths "
            f"never touch the particle"
        )
    if steps is None:
        # the count whose nominal reach is nearest, and its neighbours: aim each, keep the best
        # (how well the end can be put on the goal depends on how much contact the last push has)
        nominal = max(1, int(round((dist - nominal_reach(params, D, 1)) / params.step)) + 1)
        best = None
        for n in sorted({max(1, nominal - 1), nominal, nominal + 1}):
            try:
                cand = nano_hand_plan(
                    est,
                    g,
                    params,
                    tip_radius=tip_radius,
                    steps=n,
                    aim=aim,
                    first_side=first_side,
                    contact_params=contact_params,
                    max_distance=max_distance,
                    aim_iterations=aim_iterations,
                )
            except ValueError:
                continue
            if best is None or (
                np.hypot(*cand.extra.get("predicted_error", (0, 0)))
                < np.hypot(*best.extra.get("predicted_error", (0, 0))) - 1e-12
            ):
                best = cand
        if best is None:
            raise ValueError(
                f"goal: {dist:.4e} m: no step count around {nominal} gives a push plan with these params"
            )
        if limits is not None:
            check_plan_limits(best, limits)
        return best
    if not (isinstance(steps, (int, np.integer)) and steps >= 1):
        raise ValueError(f"steps={steps}: must be an integer >= 1")
    n_left = np.array([-u[1], u[0]])
    first_left = first_side == "left"
    a = 0.5 * params.h
    min_last = params.initial_h + 0.25 * params.step  # the last push must still reach the particle
    cp = _contact_params(contact_params, tip_radius)

    def build(x: np.ndarray) -> PushPlan:
        extra, trim = float(x[0]), float(x[1])
        strokes, offsets = _zigzag_strokes(
            c0, u, n_left, params, D, steps, trim, extra, first_left
        )
        plan = PushPlan(
            "nano_hand",
            strokes,
            c0,
            g,
            u,
            est.radius,
            tip_radius,
            path_offsets=offsets,
            params=params,
            extra={
                "steps": steps,
                "last_push_extra": extra,
                "last_path_trim": trim,
                "first_side": first_side,
            },
        )
        track = predict_particle(plan, cp)
        plan.predicted_track, plan.predicted = track, track[-1]
        err = plan.predicted - g
        plan.extra["predicted_error"] = (float(err @ u), float(err @ n_left))  # (along, lateral)
        return plan

    x = np.array([dist - nominal_reach(params, D, steps) if aim else 0.0, 0.0])
    lo = np.array([min_last - params.push(steps - 1), -0.5 * a])
    hi = np.array([x[0] + 2 * params.step, 0.5 * a])
    if aim and x[0] < lo[0]:
        raise ValueError(
            f"goal: {dist:.4e} m is too short for steps={steps} with these params (the last push "
            f"would be {params.push(steps - 1) + x[0]:.4e} m, below {min_last:.4e} m)"
        )
    plan = best = build(x)
    # Aiming: damped Newton steps on (last push's extra length, last path's sideways trim) with a
    # finite-difference Jacobian, bounded (the trim to +-a/2, so the last path stays on its side of
    # the particle), keeping the best plan seen.
    fd = np.array([2 * NM, 2 * NM])
    for _ in range(aim_iterations if aim else 0):
        e = np.array(plan.extra["predicted_error"])
        if np.all(np.abs(e) < 0.1 * NM):
            break
        jac = np.empty((2, 2))
        for col in range(2):
            xp = x.copy()
            xp[col] += fd[col] if xp[col] + fd[col] <= hi[col] else -fd[col]
            jac[:, col] = (np.array(build(xp).extra["predicted_error"]) - e) / (xp[col] - x[col])
        try:
            dx = -np.linalg.solve(jac, e)
        except np.linalg.LinAlgError:
            dx = -e * np.array([1.0, 0.0])
        limit = 2 * params.step
        if np.hypot(*dx) > limit:
            dx *= limit / np.hypot(*dx)
        for damping in (1.0, 0.5, 0.25):
            trial = build(np.clip(x + damping * dx, lo, hi))
            if np.hypot(*trial.extra["predicted_error"]) < np.hypot(*e):
                break
        else:
            break
        x, plan = np.clip(x + damping * dx, lo, hi), trial
        if np.hypot(*plan.extra["predicted_error"]) < np.hypot(*best.extra["predicted_error"]):
            best = plan
    plan = best
    if limits is not None:
        check_plan_limits(plan, limits)
    return plan


def _slide(D: float, e: float, travel: float) -> float:
    """Frictionless sideways slide of a particle pushed `travel` past contact at offset e."""
    t0 = math.asin(min(e / D, 1.0))
    t1 = min(2 * math.atan(math.tan(t0 / 2) * math.exp(travel / D)), math.pi / 2)
    return D * (math.sin(t1) - math.sin(t0))


def choose_nano_hand_params(
    particle_sigma: float,
    particle_radius: float = DEFAULT_PARTICLE_RADIUS,
    tip_radius: float = DEFAULT_TIP_RADIUS,
    *,
    tip_sigma: float = 0.0,
    confidence: float = 3.0,
    margin: float = 10 * NM,
) -> NanoHandParams:
    """The zigzag geometry for the current uncertainties (rules in the module docstring):
    sigma = hypot(particle_sigma, tip_sigma) is the centre's uncertainty relative to the tip.
    Gives Table 7.6 (within 5 nm) for sigma 10 nm, R_P 100 nm, R_T 50 nm."""
    if not (math.isfinite(particle_sigma) and particle_sigma >= 0):
        raise ValueError(f"particle_sigma={particle_sigma}: must be finite and >= 0 m")
    if not (math.isfinite(tip_sigma) and tip_sigma >= 0):
        raise ValueError(f"tip_sigma={tip_sigma}: must be finite and >= 0 m")
    _positive("particle_radius", particle_radius)
    _positive("tip_radius", tip_radius)
    _positive("confidence", confidence, unit="")
    if not (math.isfinite(margin) and margin >= 0):
        raise ValueError(f"margin={margin}: must be finite and >= 0 m")
    sigma = math.hypot(particle_sigma, tip_sigma)
    D = particle_radius + tip_radius
    ks = confidence * sigma
    lo, hi = ks + margin, D - ks - margin
    if lo > hi:
        raise ValueError(
            f"particle_sigma={particle_sigma:.4e} m (relative sigma {sigma:.4e} m): the uncertainty "
            f"region (+-{ks:.4e} m) is too wide for R_P + R_T = {D:.4e} m; the limit is "
            f"sigma <= {(D / 2 - margin) / confidence:.4e} m: localise the tip/particle better first"
        )
    a = min(max(0.4 * D, lo), hi)
    # L_step: slide at offset a <= a / 4 (closed form inverted)
    t0 = math.asin(a / D)
    t1 = math.asin(min((a + 0.25 * a) / D, 1.0))
    step = D * math.log(math.tan(t1 / 2) / math.tan(t0 / 2))
    delta = _slide(D, a, step)
    initial = 2 * ks + (_lead(D, max(a - ks, 0.0)) - _lead(D, a)) + margin
    back = initial + ks + (_lead(D, max(a - delta, 0.0)) - _lead(D, min(a + delta, D)))
    push = back + step
    return NanoHandParams(push, push, back, back, initial, 2 * a, step)


# --------------------------------------------------------------------------------------------
# Rod-like hand
# --------------------------------------------------------------------------------------------


def _wrap_half_turn(angle: float) -> float:
    """Angle difference folded into (-pi/2, pi/2] (a rod's axis has no head)."""
    return (angle + 0.5 * math.pi) % math.pi - 0.5 * math.pi


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

    rod: anything with x, y, angle, length, radius (a sim Rod or a tube Landmark converted).
    Two pushing points at +-grip * length/2 are pushed alternately across the axis (at most
    `step` deep per stroke, from `clearance` outside the rod); the greedy choice runs on the
    pushing model until the predicted axis points are within `tolerance` of the goal's lines
    (or max_strokes). Motion along the rod's own axis is not controlled unless axial=True, which
    also pushes an end cap along the axis when that error is the largest: on a thin tube that push
    is as unstable as centre pushing a sphere (a tip a few nm off the axis slides off the cap and
    turns the tube), so it is off by default; plan goals across the axis plus a rotation."""
    from afm_core.physics.sample import Electrode, Rod, Sample

    for name in ("x", "y", "angle", "length", "radius"):
        if not hasattr(rod, name):
            raise ValueError(f"rod: needs x, y, angle, length, radius (missing {name})")
    rx, ry = _point("rod", (rod.x, rod.y))
    ang = float(rod.angle)
    if not math.isfinite(ang):
        raise ValueError(f"rod.angle={ang}: must be finite")
    length = _positive("rod.length", rod.length)
    radius = _positive("rod.radius", rod.radius)
    try:
        gx, gy, ga = (float(v) for v in goal_pose)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"goal_pose={goal_pose!r}: must be (x, y, angle)") from exc
    if not all(math.isfinite(v) for v in (gx, gy, ga)):
        raise ValueError(f"goal_pose={goal_pose!r}: must be finite")
    _positive("tip_radius", tip_radius)
    _positive("step", step)
    _positive("tolerance", tolerance)
    if not 0 < grip <= 1:
        raise ValueError(f"grip={grip}: must be within (0, 1]")
    dist = math.hypot(gx - rx, gy - ry)
    dang = _wrap_half_turn(ga - ang)
    if dist > max_distance:
        raise ValueError(
            f"goal_pose: {dist:.4e} m from the rod, beyond max_distance={max_distance:.4e} m"
        )
    if dist < tolerance and abs(dang) * 0.5 * length * grip < tolerance:
        raise ValueError("goal_pose: the rod is already there (within tolerance): nothing to push")
    ga = ang + dang
    walls = [
        Electrode(1000 + i, e.x0, e.y0, e.x1, e.y1, e.thickness) for i, e in enumerate(electrodes)
    ]
    model_rod = Rod(0, rx, ry, ang, length, radius, getattr(rod, "kind", "rod"))
    sample = Sample(rods=[model_rod], electrodes=walls)
    cp = _contact_params(contact_params, tip_radius)
    reach = tip_radius + radius
    strokes: list[Stroke] = []
    track = []
    g_t = np.array([math.cos(ga), math.sin(ga)])
    last_point = None
    for _ in range(max_strokes):
        c = np.array([model_rod.x, model_rod.y])
        t = np.array([math.cos(model_rod.angle), math.sin(model_rod.angle)])
        n = np.array([-t[1], t[0]])
        # goal angle relative to the current one (keep the material orientation)
        g_dir = g_t if g_t @ t >= 0 else -g_t
        options = []
        for label, sp in (("rod+", grip * 0.5 * length), ("rod-", -grip * 0.5 * length)):
            here = c + sp * t
            there = np.array([gx, gy]) + sp * g_dir
            r = float((there - here) @ n)
            options.append((abs(r), label, sp, r))
        if axial:
            along = float((np.array([gx, gy]) - c) @ t)
            options.append((abs(along), "axial", 0.0, along))
        worst = max(options, key=lambda o: o[0])
        if worst[0] < tolerance:
            break
        # alternate the two points when both are off (the rod-like hand), never the same twice
        # in a row unless it is the only one left
        normal_opts = sorted(
            [o for o in options if o[1] != "axial" and o[0] >= tolerance], key=lambda o: -o[0]
        )
        if worst[1] != "axial" and len(normal_opts) == 2 and normal_opts[0][1] == last_point:
            worst = normal_opts[1]
        _, label, sp, r = worst
        depth = min(abs(r), step)
        sign = 1.0 if r > 0 else -1.0
        if label == "axial":
            # push the rear end cap along the axis
            tip_end = c - sign * (0.5 * length) * t
            d = sign * t
            start = tip_end - (reach + clearance) * d
            end = tip_end - reach * d + depth * d
        else:
            point = c + sp * t
            d = sign * n
            start = point - (reach + clearance) * d
            end = point - reach * d + depth * d
        stroke = Stroke(start, end, True, label)
        simulate_strokes(sample, [stroke], cp)
        strokes.append(stroke)
        track.append((model_rod.x, model_rod.y, model_rod.angle))
        last_point = label
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


# --------------------------------------------------------------------------------------------
# Arc-shaped hand: gathering particles onto a ring
# --------------------------------------------------------------------------------------------


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
    from scipy.optimize import linear_sum_assignment

    from afm_core.physics.sample import Sample, Sphere

    ests = [_particle(p, None) for p in particles]
    if not ests:
        raise ValueError("particles: empty; nothing to gather")
    c = _point("centre", centre)
    _positive("radius", radius)
    n_slots = len(ests) if slots is None else slots
    if not (isinstance(n_slots, (int, np.integer)) and n_slots >= len(ests)):
        raise ValueError(
            f"slots={slots}: must be an integer >= the number of particles ({len(ests)})"
        )
    if not math.isfinite(phase):
        raise ValueError(f"phase={phase}: must be finite")
    chord = 2 * radius * math.sin(math.pi / n_slots) if n_slots > 1 else math.inf
    widest = 2 * max(e.radius for e in ests)
    if chord < widest:
        raise ValueError(
            f"radius={radius:.4e} m: {n_slots} slots are {chord:.4e} m apart, closer than a particle's "
            f"diameter {widest:.4e} m"
        )
    angles = phase + 2 * math.pi * np.arange(n_slots) / n_slots
    slot_xy = c + radius * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    cost = np.array([[np.hypot(*(e.xy - s)) for s in slot_xy] for e in ests])
    rows, cols = linear_sum_assignment(cost)
    assignment = {int(r): slot_xy[cc] for r, cc in zip(rows, cols)}
    order = sorted(assignment, key=lambda i: cost[i, cols[list(rows).index(i)]])
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
    simulate_strokes(sample, strokes, _contact_params(contact_params, tip_radius))
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


def path_blocker(start, goal, radius: float, tip_radius: float, others):
    """The first of `others` (objects with x, y, radius: landmarks) a particle of `radius` would
    run into on its way from `start` to `goal` ((2,) m): the corridor it sweeps (its radius plus
    the other's) and the tip's approach behind it. None when the way is clear."""
    start, goal = np.asarray(start, float), np.asarray(goal, float)
    axis = goal - start
    length = float(np.hypot(*axis))
    if length == 0:
        return None
    u = axis / length
    hits = []
    for other in others:
        rel = np.array([other.x, other.y]) - start
        along = float(rel @ u)
        across = abs(float(rel[0] * u[1] - rel[1] * u[0]))
        if (
            -(radius + 2 * tip_radius) < along < length + radius + other.radius
            and across < radius + other.radius
        ):
            hits.append((along, other))
    return min(hits, key=lambda h: h[0])[1] if hits else None
