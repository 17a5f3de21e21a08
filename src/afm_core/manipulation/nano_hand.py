"""The virtual nano-hand zigzag (book 6.4.3, 7.3: Fig. 6.18f-i, Fig. 7.24, Table 7.6).

The frame of a push (u, n, along, lateral, D = R_P + R_T, lead(e) = sqrt(D^2 - e^2)) is
defined in afm_core.manipulation.plans.

The zigzag: our reading
-----------------------
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
particle ends ~13 nm right of the axis; the experiment: 20 nm). The pushing model of
afm_core.physics.pushing (tip-particle friction bends the motion slightly towards u) gives
503.1 nm and 13.8 nm. On the SimulatedAfm the tip's own displacement errors add to that
(the controller's residual hysteresis ratchets the tip ~20 nm further along u over the 13
zigzag steps, and each move's random positioning error accumulates): 525 +- 12 nm along over
20 seeds, close to the book's measured 530 nm, whose gap to its 507 nm simulation the book
also puts down to the tip's displacement.

Aiming
------
With `aim=True` (default) the planner runs the plan through the pushing model
(afm_core.physics.pushing.push_along_path on one sphere at the estimated centre) and corrects
it until the predicted end is on the goal: the number of steps is the one whose nominal reach
is closest to the distance, the end of the last push is moved along u by the remaining along
error, and the whole corridor is shifted sideways by minus the predicted sideways offset (the
final slide of ~delta away from the last path is planned for, not suffered).

choose_nano_hand_params: the planner's choice from the uncertainties
--------------------------------------------------------------------
With sigma the 1-sigma uncertainty of the particle's centre relative to the tip (particle and
tip localisation combined), k = `confidence` (3) and m = `margin` (10 nm):

- half separation a = L_h / 2: the paths must straddle the uncertainty region,
  a >= k sigma + m, and still touch the particle when it is k sigma beyond a path's side,
  a + k sigma + m <= D. Inside that window we take a = 0.4 D (the book's 60 / 150), clipped
  into the window; an empty window (k sigma + m > D / 2) is an error: localise better first.
- L_step: the largest advance whose sideways slide at offset a (frictionless closed form above,
  an upper bound: friction only reduces it) is at most a / 4, so the particle stays well
  inside the corridor after each push; 37.5 nm for the book's case (Table 7.6: 36).
- L_initial_h = 2 k sigma + (lead(a - k sigma) - lead(a)) + m: the particle may be k sigma
  closer than estimated, the tip itself a further k sigma off, and a particle k sigma nearer
  the path is touched lead(a - k sigma) - lead(a) earlier; 79.5 nm for the book's case
  (Table 7.6: 78).
- L_back = L_initial_h + k sigma + (lead(a - delta) - lead(a + delta)): the next push, on the
  other path, starts at least L_initial_h + k sigma before its nominal contact (the particle
  is delta nearer that path than nominal, hence the lead difference); 122.7 nm
  (Table 7.6: 120).
- L_push = L_back + L_step (160.2 nm; Table 7.6: 156).

The margins are ours, chosen so that the rule gives Table 7.6 for the book's case (sigma 10 nm,
R_P 100 nm, R_T 50 nm); the structure (a window for a, a slide bound for L_step, run-ups for
the approach) is what makes it scale with the uncertainty.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from afm_core.checks import count, non_negative, one_of, point, positive
from afm_core.instrument import ScannerLimits
from afm_core.manipulation.plans import (
    DEFAULT_MAX_DISTANCE,
    DEFAULT_PARTICLE_RADIUS,
    DEFAULT_TIP_RADIUS,
    NM,
    ParticleEstimate,
    PushPlan,
    Stroke,
    check_plan_limits,
    model_contact_params,
    particle_estimate,
    predict_particle,
    push_axis,
)


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
            positive(f"NanoHandParams.{name}", getattr(self, name), "m")
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


def _lead(D: float, e: float) -> float:
    return math.sqrt(max(D * D - e * e, 0.0))


def _slide(D: float, e: float, travel: float) -> float:
    """Frictionless sideways slide of a particle pushed `travel` past contact at offset e."""
    t0 = math.asin(min(e / D, 1.0))
    t1 = min(2 * math.atan(math.tan(t0 / 2) * math.exp(travel / D)), math.pi / 2)
    return D * (math.sin(t1) - math.sin(t0))


def nominal_reach(params: NanoHandParams, steps: int) -> float:
    """Along displacement of the particle after `steps` zigzag steps, neglecting its sideways
    slide: L_push - L_initial_h + (steps - 1) L_step."""
    return params.left_push - params.initial_h + (steps - 1) * params.step


# --------------------------------------------------------------------------------------------
# The plan: step count, the zigzag's strokes, aiming in the model
# --------------------------------------------------------------------------------------------


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
    the one aimed best). aim: adjust the last push's length and move its path sideways (at most
    h/4) with the pushing model so the predicted end is the goal; plan.extra["predicted_error"]
    = (along, lateral) of what remains (aiming an odd count can leave several nm). aim=False:
    the literal geometry, e.g. the book's 13-step experiment; the predicted end is still
    reported. contact_params: the model's afm_core.physics.contact.ContactParams (default: its
    defaults with this tip_radius).
    """
    est = particle_estimate(particle, particle_radius)
    params = NanoHandParams.book() if params is None else params
    params.validate()
    c0, g = est.xy, point("goal", goal)
    u, dist = push_axis(c0, g, positive("max_distance", max_distance, "m"))
    positive("tip_radius", tip_radius, "m")
    one_of("first_side", first_side, ("left", "right"))
    D = est.radius + tip_radius
    if 0.5 * params.h >= D:
        raise ValueError(
            f"params.h/2={0.5 * params.h:.4e} m: must be < R_P + R_T = {D:.4e} m, or the paths "
            f"never touch the particle"
        )
    if steps is None:
        plan = _best_step_count(
            est,
            g,
            params,
            dist,
            tip_radius=tip_radius,
            aim=aim,
            first_side=first_side,
            contact_params=contact_params,
            max_distance=max_distance,
            aim_iterations=aim_iterations,
        )
    else:
        zigzag = _Zigzag(
            c0,
            g,
            u,
            est.radius,
            tip_radius,
            params,
            count("steps", steps, 1),
            first_side,
            model_contact_params(contact_params, tip_radius),
        )
        plan = _aimed(zigzag, dist, aim, aim_iterations)
        missed = float(np.hypot(*plan.extra["predicted_error"]))
        # aiming leaves a few nm (up to ~17 nm on 40 nm pushes with params chosen for the
        # particle); more than two steps means the zigzag does not carry this particle at all
        if aim and missed > 2 * params.step:
            raise ValueError(
                f"params: the aimed zigzag misses the goal by {missed:.4e} m in the pushing model "
                f"(more than two steps, {2 * params.step:.4e} m): they do not suit R_P = "
                f"{est.radius:.4e} m with R_T = {tip_radius:.4e} m (choose_nano_hand_params "
                "gives ones that do)"
            )
    if limits is not None:
        check_plan_limits(plan, limits)
    return plan


def _best_step_count(
    est: ParticleEstimate, g: np.ndarray, params: NanoHandParams, dist: float, **options
) -> PushPlan:
    """The count whose nominal reach is nearest, and its neighbours: aim each, keep the best
    (how well the end can be put on the goal depends on how much contact the last push has)."""
    nominal = max(1, int(round((dist - nominal_reach(params, 1)) / params.step)) + 1)
    best, why = None, ""
    for n in sorted({max(1, nominal - 1), nominal, nominal + 1}):
        try:
            cand = nano_hand_plan(est, g, params, steps=n, **options)
        except ValueError as exc:
            why = f" ({n} steps: {exc})"
            continue
        if best is None or (
            np.hypot(*cand.extra.get("predicted_error", (0, 0)))
            < np.hypot(*best.extra.get("predicted_error", (0, 0))) - 1e-12
        ):
            best = cand
    if best is None:
        raise ValueError(
            f"goal: {dist:.4e} m: no step count around {nominal} gives a push plan with these "
            f"params{why}"
        )
    return best


@dataclass(frozen=True)
class _Zigzag:
    """A zigzag's fixed inputs; build(x) is its plan for x = (the last push's extra length,
    the last path's sideways trim), predicted in the model."""

    start: np.ndarray  # (2,) estimated centre c0
    goal: np.ndarray
    axis: np.ndarray  # u
    particle_radius: float
    tip_radius: float
    params: NanoHandParams
    steps: int
    first_side: str
    contact_params: object

    @property
    def left(self) -> np.ndarray:
        return np.array([-self.axis[1], self.axis[0]])

    def strokes(self, last_extra: float, trim: float) -> list[Stroke]:
        """The zigzag's strokes; the last one is `last_extra` longer and moved `trim`
        sideways."""
        c0, u, n_left, params = self.start, self.axis, self.left, self.params
        first_left = self.first_side == "left"
        a = 0.5 * params.h
        s = -(_lead(self.particle_radius + self.tip_radius, a) + params.initial_h)
        strokes = []
        for k in range(self.steps):
            left = (k % 2 == 0) == first_left
            last = k == self.steps - 1
            lat = (a if left else -a) + (trim if last else 0.0)
            push = params.push(k) + (last_extra if last else 0.0)
            strokes.append(
                Stroke(
                    c0 + s * u + lat * n_left,
                    c0 + (s + push) * u + lat * n_left,
                    True,
                    "left" if left else "right",
                )
            )
            s = s + params.push(k) - params.back(k)
        return strokes

    def build(self, x: np.ndarray) -> PushPlan:
        extra, trim = float(x[0]), float(x[1])
        a = 0.5 * self.params.h
        plan = PushPlan(
            "nano_hand",
            self.strokes(extra, trim),
            self.start,
            self.goal,
            self.axis,
            self.particle_radius,
            self.tip_radius,
            path_offsets=(a, -a),
            params=self.params,
            extra={
                "steps": self.steps,
                "last_push_extra": extra,
                "last_path_trim": trim,
                "first_side": self.first_side,
            },
        )
        track = predict_particle(plan, self.contact_params)
        plan.predicted_track, plan.predicted = track, track[-1]
        err = plan.predicted - self.goal
        # (along, lateral)
        plan.extra["predicted_error"] = (float(err @ self.axis), float(err @ self.left))
        return plan


def _aimed(zigzag: _Zigzag, dist: float, aim: bool, iterations: int) -> PushPlan:
    """Aiming: damped Newton steps on (last push's extra length, last path's sideways trim)
    with a finite-difference Jacobian, bounded (the trim to +-a/2, so the last path stays on
    its side of the particle), keeping the best plan seen. aim=False: the literal geometry."""
    params, steps = zigzag.params, zigzag.steps
    a = 0.5 * params.h
    min_last = params.initial_h + 0.25 * params.step  # the last push must still reach it
    x = np.array([dist - nominal_reach(params, steps) if aim else 0.0, 0.0])
    lo = np.array([min_last - params.push(steps - 1), -0.5 * a])
    hi = np.array([x[0] + 2 * params.step, 0.5 * a])
    if aim and x[0] < lo[0]:
        raise ValueError(
            f"goal: {dist:.4e} m is too short for steps={steps} with these params (the last "
            f"push would be {params.push(steps - 1) + x[0]:.4e} m, below {min_last:.4e} m)"
        )
    plan = best = zigzag.build(x)
    for _ in range(iterations if aim else 0):
        e = np.array(plan.extra["predicted_error"])
        if np.all(np.abs(e) < 0.1 * NM):
            break
        dx = _newton_step(zigzag, x, e, hi)
        for damping in (1.0, 0.5, 0.25):
            trial = zigzag.build(np.clip(x + damping * dx, lo, hi))
            if np.hypot(*trial.extra["predicted_error"]) < np.hypot(*e):
                break
        else:
            break
        x, plan = np.clip(x + damping * dx, lo, hi), trial
        if np.hypot(*plan.extra["predicted_error"]) < np.hypot(*best.extra["predicted_error"]):
            best = plan
    return best


def _newton_step(zigzag: _Zigzag, x: np.ndarray, e: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The Newton step on x for the predicted error e (finite differences of 2 nm, inward at
    the upper bound), at most 2 L_step long."""
    fd = np.array([2 * NM, 2 * NM])
    jac = np.empty((2, 2))
    for col in range(2):
        xp = x.copy()
        xp[col] += fd[col] if xp[col] + fd[col] <= hi[col] else -fd[col]
        error = np.array(zigzag.build(xp).extra["predicted_error"])
        jac[:, col] = (error - e) / (xp[col] - x[col])
    try:
        dx = -np.linalg.solve(jac, e)
    except np.linalg.LinAlgError:
        dx = -e * np.array([1.0, 0.0])
    limit = 2 * zigzag.params.step
    if np.hypot(*dx) > limit:
        dx *= limit / np.hypot(*dx)
    return dx


# --------------------------------------------------------------------------------------------
# The geometry for the current uncertainties
# --------------------------------------------------------------------------------------------


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
    non_negative("particle_sigma", particle_sigma, "m")
    non_negative("tip_sigma", tip_sigma, "m")
    positive("particle_radius", particle_radius, "m")
    positive("tip_radius", tip_radius, "m")
    positive("confidence", confidence)
    non_negative("margin", margin, "m")
    sigma = math.hypot(particle_sigma, tip_sigma)
    D = particle_radius + tip_radius
    ks = confidence * sigma
    lo, hi = ks + margin, D - ks - margin
    if lo > hi:
        raise ValueError(
            f"particle_sigma={particle_sigma:.4e} m (relative sigma {sigma:.4e} m): the "
            f"uncertainty region (+-{ks:.4e} m) is too wide for R_P + R_T = {D:.4e} m; the "
            f"limit is sigma <= {(D / 2 - margin) / confidence:.4e} m: localise the "
            f"tip/particle better first"
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
