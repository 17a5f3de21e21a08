"""Closed-loop pushing (book 2.2.3, 7.3: local-scan-based manipulation), ROS-free: the
"closed_loop" strategy of `PushProcedure`.

The open-loop nano-hand runs its whole zigzag after one localization: the particle lands where
the tip's true path put it, which carries every free move's persistent positioning error and
the residual hysteresis. The closed loop runs the strokes in legs and looks between them:

1. a leg: the nano-hand zigzag to the goal (or, for what is left once it is shorter than
   NANO_HAND_MIN_DISTANCE, one centre stroke through the estimated centre), stroke by stroke,
   the tip tracked by the motion model (`TipTrack`); lifted approaches to a stroke's start run
   as local scan lines (ramps: no positioning noise, the motion model's own rule), only the
   contact strokes are free moves;
2. the leg ends early when the force trace disagrees with the model (a stroke the model says
   pushes the particle whose lateral force never rises above the trace's noise: contact lost,
   or rises and falls back before the stroke ends: slip), or when the 2-sigma the strokes added
   to the track since the last observation reaches the tolerance while an anchor can bring it
   back and two legs are left (the rest of the way and a correction); observing sooner cannot
   improve on a track that is still good enough;
3. observe (`observe_particle`): lines across a static anchor landmark, then across the
   particle; the estimate (mean, covariance) replaces the model's;
4. stop when |estimate - goal| + CONFIDENCE_SIGMAS * sigma <= tolerance (within tolerance with
   ~95 % confidence), or when the remaining error is below CONFIDENCE_SIGMAS * sigma (not
   distinguishable from the observation's own error: another stroke would chase noise), or
   after max_iterations legs; otherwise re-plan from the estimate and run the next leg.

Cost per push (`PushCost`): instrument time, local scan lines (measuring and ramps),
observations, and the distance slid in contact.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.stats import norm

from afm_core.imaging.landmarks import Landmark
from afm_core.instrument import check_in_range
from afm_core.localization.landmark_observation import MapLandmark, line_noise
from afm_core.manipulation.centre_push import centre_push_plan
from afm_core.manipulation.execute import OBSERVED, PREDICTED, StepReport, pushed_object_after
from afm_core.manipulation.particle_observation import (
    LINE_MARGIN,
    LINE_SIGMAS,
    ParticleObservation,
    TipTrack,
    choose_anchor,
    observe_particle,
)
from afm_core.manipulation.plans import ParticleEstimate, PushPlan
from afm_core.manipulation.push_steps import ZigzagOverrides, in_maps_frame, plan_push

# stop rule: the estimate's error plus this many sigma within the tolerance (one-sided ~97.7 %
# per axis for a Gaussian estimate; "2-sigma" in the brief's words)
CONFIDENCE_SIGMAS = 2.0
# the docs' limit of aimed nano-hand pushes: shorter ones leave 10-30 nm in the model, so what
# is left below this is pushed by one centre stroke (a short centre push has no room to split)
NANO_HAND_MIN_DISTANCE = 200e-9  # m
# a force sample above the stroke's substrate level by more than the noise quantile at this
# false-alarm rate per stroke (Bonferroni over its samples) counts as contact with the particle
CONTACT_FALSE_ALARM = 1e-3
# the share of a stroke's samples at each end taken as "before contact" and "at the end"
FORCE_EDGE_FRACTION = 0.1
# a stroke the model says moves the particle less than this is not expected to touch it
MODEL_CONTACT_MIN = 1e-9  # m
TIP_HEIGHT = 10e-6  # m, the lever arm of the lateral force (execute.force_summary's default)


@dataclass
class PushCost:
    duration: float = 0.0  # s, instrument time from the push's first command (scans included)
    lines: int = 0  # local scan lines run (measuring lines and ramps)
    observations: int = 0
    slid: float = 0.0  # m, commanded distance in contact
    legs: int = 0


@dataclass
class Contact:
    made: bool
    lost: bool  # made, then back at the substrate level before the stroke's end (slip)


def contact_in_trace(trace) -> Contact | None:
    """Contact with the particle from a stroke's lateral force (module docstring, 2): the
    first FORCE_EDGE_FRACTION of samples is the substrate's level and noise (the run-up before
    the particle); None when the trace is too short to tell."""
    if trace is None or len(trace.lateral_torsion) < 20:
        return None
    t = np.asarray(trace.lateral_torsion, float)
    edge = max(3, int(FORCE_EDGE_FRACTION * t.size))
    f = np.abs(t - float(np.median(t[:edge])))  # the rise above the substrate's level
    level = 0.0
    sigma = max(line_noise(t), 1e-30)
    threshold = level + float(norm.isf(CONTACT_FALSE_ALARM / (2 * f.size))) * sigma
    above = f > threshold
    made = bool(above.any())
    return Contact(made, made and not bool(above[-edge:].any()))


@dataclass
class LoopState:
    particle: Landmark  # the estimate now (task frame)
    plans: list = field(default_factory=list)  # each leg's plan
    cancelled: bool = False
    cost: PushCost = field(default_factory=PushCost)
    reports: list = field(default_factory=list)
    observations: list = field(default_factory=list)


def plan_leg(
    particle: Landmark, target, tip_cov, overrides: ZigzagOverrides, tip_radius, limits, first
) -> PushPlan:
    """The zigzag for the first leg (as the open-loop nano-hand) or a long rest; one centre
    stroke for a short rest."""
    distance = float(np.hypot(target[0] - particle.x, target[1] - particle.y))
    if first or distance >= NANO_HAND_MIN_DISTANCE:
        return plan_push(
            particle,
            target,
            "nano_hand",
            tip_cov,
            overrides if first else ZigzagOverrides(),
            tip_radius,
            limits,
        )
    sigma = math.sqrt(max(np.linalg.eigvalsh(particle.covariance).max(), 0.0))
    tip_sigma = math.sqrt(max(np.linalg.eigvalsh(tip_cov).max(), 0.0))
    spread = math.hypot(sigma, tip_sigma)
    estimate = ParticleEstimate(particle.x, particle.y, particle.radius, spread)
    # the run-up clears the particle's and the tip's uncertainty before contact is due
    approach = LINE_SIGMAS * spread + LINE_MARGIN
    return centre_push_plan(
        estimate, target, tip_radius=tip_radius, single=True, approach=approach, limits=limits
    )


def run_leg(
    track: TipTrack,
    plan: PushPlan,
    state: LoopState,
    speed: float,
    tolerance: float,
    can_observe: bool,
    on_step: Callable[[StepReport, str], None],
    should_stop: Callable[[], bool],
) -> tuple[bool, str, int]:
    """Run the plan's strokes (module docstring, 1-2). Returns (cancelled, why it ended,
    strokes done)."""
    limits = track.instrument.limits
    # the model's particle before and after each stroke (none: assume every contact pushes)
    path = [np.asarray(plan.particle, float), *map(np.asarray, plan.predicted_track)]
    moved = [float(np.hypot(*(b - a))) for a, b in zip(path[:-1], path[1:])]
    lift_speed = min(10 * speed, limits.max_speed)
    floor = track.sigma  # what an observation cannot take away: the added part decides
    for i, stroke in enumerate(plan.strokes):
        if should_stop():
            return True, "cancelled", i
        a, b = track.to_command(stroke.start), track.to_command(stroke.end)
        check_in_range(f"strokes[{i}].start", float(a[0]), float(a[1]), limits)
        check_in_range(f"strokes[{i}].end", float(b[0]), float(b[1]), limits)
        track.ramp(a, lift_speed, should_stop=should_stop)
        move = track.move(b, speed if stroke.contact else lift_speed, stroke.contact, should_stop)
        if stroke.contact:
            state.cost.slid += float(np.hypot(*(b - a)))
        report = StepReport.of_move(i, len(plan.strokes), stroke, move, TIP_HEIGHT)
        state.reports.append(report)
        expected = stroke.contact and (i >= len(moved) or moved[i] > MODEL_CONTACT_MIN)
        contact = contact_in_trace(move.trace) if stroke.contact else None
        why = ""
        if expected and contact is not None and not contact.made:
            why = "contact lost: no lateral force above the trace's noise where the model pushes"
        elif expected and contact is not None and contact.lost:
            why = "slip: the lateral force fell back before the stroke's end"
        elif (
            can_observe
            and 2 * added(track.sigma, floor) >= tolerance
            and i < len(plan.strokes) - 1
        ):
            why = (
                f"the strokes' predicted 2-sigma error {2 * added(track.sigma, floor) * 1e9:.1f} "
                "nm reached the tolerance"
            )
        on_step(report, why)
        if not move.completed:
            return True, "cancelled", i + 1
        if why:
            return False, why, i + 1
    return False, "leg done", len(plan.strokes)


def calibrate_chain(
    track: TipTrack,
    anchor: MapLandmark,
    particle: MapLandmark,
    tip_radius: float,
    should_stop,
    observe: Callable[..., ParticleObservation] = observe_particle,
) -> MapLandmark | None:
    """The anchor as the observation chain sees it: the chain (anchor lines, the way to the
    particle, particle lines) run once before the first stroke, where the particle is where
    the push's frame puts it (its map position). What the chain gets wrong the same way every
    time (the anchor's map error relative to the particle, the hysteresis and creep of the way
    from the anchor, which depend on its direction) is then taken out of every later
    observation. The anchor's variance becomes that observation's without the map's error of
    the anchor (it cancels).
    None: a line missed (no anchor then). observe: how the particle is seen (a rod's:
    `afm_core.manipulation.rod_loop.observe_rod`)."""
    seen = observe(track, particle, anchor, tip_radius, should_stop)
    if not seen.ok:
        return None
    offset = seen.mean - particle.position
    # the anchor's map error is in the offset, not in what the offset is measured with
    own = np.diag(np.maximum(np.diag(seen.covariance - anchor.covariance), (1e-9) ** 2))
    return replace(
        anchor, x=float(anchor.x - offset[0]), y=float(anchor.y - offset[1]), covariance=own
    )


def added(sigma: float, floor: float) -> float:
    return math.sqrt(max(sigma**2 - floor**2, 0.0))


def decide(observation: ParticleObservation, target, tolerance: float) -> tuple[bool, str]:
    """Stop or go on (module docstring, 4): (done, why)."""
    error = float(np.hypot(*(observation.mean - target)))
    sigma = math.sqrt(max(np.linalg.eigvalsh(observation.covariance).max(), 0.0))
    text = f"{error * 1e9:.1f} nm from the goal, sigma {sigma * 1e9:.1f} nm"
    if not observation.ok:
        return False, f"particle not found ({observation.note})"
    if error + CONFIDENCE_SIGMAS * sigma <= tolerance:
        return True, f"{text}: within tolerance with {CONFIDENCE_SIGMAS:g}-sigma confidence"
    if error <= CONFIDENCE_SIGMAS * sigma:
        return True, f"{text}: the rest is within the observation's own error"
    return False, f"{text}: re-planning"


def closed_loop_push(
    track: TipTrack,
    particle: Landmark,
    target: np.ndarray,
    landmarks: Mapping[int, Landmark],
    overrides: ZigzagOverrides,
    settings: Mapping,
    report: Callable[..., None],
    should_stop: Callable[[], bool],
    holder: dict | None = None,
) -> LoopState:
    """The closed loop (module docstring). report(kind, **fields): kind "plan" (a leg's plan),
    "stroke" (StepReport, why), "observed" (ParticleObservation, why, verdict)."""
    state = LoopState(particle)
    if holder is not None:  # the caller's view of the state while it runs
        holder["state"] = state
    tip_radius, tolerance = settings["tip_radius"], settings["tolerance"]
    limits = track.instrument.limits
    start = np.array([particle.x, particle.y])
    mark = MapLandmark.from_landmark(particle)
    half = mark.radius + tip_radius + LINE_SIGMAS * track.sigma + LINE_MARGIN
    anchor = choose_anchor(landmarks, particle.id, start, target, half)
    if anchor is not None:
        anchor = calibrate_chain(
            track, anchor, MapLandmark.from_landmark(particle), tip_radius, should_stop
        )
        report("anchor", anchor=anchor)
    # the chain measures displacements from the start (calibrate_chain): its direction error
    # grows with the distance from there
    for leg in range(int(settings["max_iterations"])):
        particle_maps, tip_maps = in_maps_frame(
            state.particle, tip_radius, track.calibration.lateral_scale
        )
        plan = plan_leg(
            particle_maps, target, track.covariance, overrides, tip_maps, limits, leg == 0
        )
        state.plans.append(plan)
        state.cost.legs += 1
        report("plan", plan=plan, leg=leg)
        cancelled, why, strokes_done = run_leg(
            track,
            plan,
            state,
            settings["push_speed"],
            tolerance,
            # an early observation is worth it only with legs left to use it: the rest of the
            # way and a correction (else the legs run out before the goal)
            anchor is not None and leg + 2 < int(settings["max_iterations"]),
            lambda r, w: report("stroke", step=r, why=w, plan=plan),
            should_stop,
        )
        if cancelled:
            state.cancelled = True
            return state
        model = (
            pushed_object_after(plan, strokes_done)[0]
            if strokes_done
            else np.array([state.particle.x, state.particle.y])
        )
        sigma = max(track.sigma, 1e-9)
        guess = replace(
            state.particle,
            x=float(model[0]),
            y=float(model[1]),
            covariance=np.eye(2) * sigma**2,
        )
        observation = observe_particle(
            track,
            MapLandmark.from_landmark(guess),
            anchor,
            tip_radius,
            should_stop,
            float(np.hypot(*(model - start))) if anchor is not None else 0.0,
        )
        state.cost.observations += 1
        done, verdict = decide(observation, target, tolerance)
        state.observations.append(observation)
        report("observed", observation=observation, why=why, verdict=verdict)
        if observation.ok:
            state.particle = replace(
                state.particle,
                x=float(observation.mean[0]),
                y=float(observation.mean[1]),
                covariance=observation.covariance,
            )
        if done or should_stop():
            return state
    return state


def report_fields(kind: str, f: dict, particle: Landmark, current: Landmark):
    """What a closed_loop_push report becomes as a `Progress`: (phase, the particle's estimate,
    the other fields) for "plan", "stroke", "anchor" and "observed" (closed_loop_push)."""
    if kind == "plan":
        plan = f["plan"]
        here = np.array([current.x, current.y])
        return (
            "pushing",
            here,
            dict(steps_total=len(plan.strokes), plan=plan, note=f"leg {f['leg'] + 1}"),
        )
    if kind == "stroke":
        r, plan = f["step"], f["plan"]
        return (
            "pushing",
            # a rod plan's track is the rod's centre (rod_loop); pushed_object_after gives the
            # contact point for it
            np.asarray(plan.predicted_track[r.index], float)
            if plan.kind == "rod" and r.index < len(plan.predicted_track)
            else pushed_object_after(plan, r.index + 1)[0],
            dict(
                step=r.index + 1,
                steps_total=r.total,
                peak_lateral_force=float(r.peak_lateral_force),
                peak_normal_force=float(r.peak_normal_force),
                note=f["why"],
                belief=PREDICTED,
            ),
        )
    if kind == "anchor":
        a = f["anchor"]
        seen = (
            "no anchor: a line missed it"
            if a is None
            else f"anchor {a.id} at ({a.x * 1e9:.1f} nm, {a.y * 1e9:.1f} nm)"
        )
        note = (
            "reference for the observations: the nearest static landmark, seen from the "
            f"localized tip and the particle's start: {seen}"
        )
        return "observing", np.array([particle.x, particle.y]), dict(note=note)
    o = f["observation"]
    seen = dict(belief=OBSERVED, belief_covariance=np.asarray(o.covariance, float)) if o.ok else {}
    return "observing", o.mean, dict(note=f"{f['why']}; observed {o.note}; {f['verdict']}", **seen)
