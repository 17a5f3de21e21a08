"""Closed-loop rod and tube pushing to a goal pose (book 2.2.3, 7.3, Fig. 2.11, 7.26),
ROS-free: the "closed_loop" strategy of `PushProcedure` for a landmark of kind tube or rod.

The rod hand (`rod_hand_plan`) pushes two points of the rod alternately across its axis; open
loop its strokes carry every free move's positioning error and the model's error of the rod's
turning. The closed loop runs the rod hand in legs and looks between them, as the sphere's
(`afm_core.manipulation.closed_loop`):

1. a leg: the rod hand's strokes from the pose as last observed to the goal pose (an end cap
   pushed along the axis too when that error is the largest: the observation after the leg
   corrects the turn such a push may cause), ended early by the force trace or the track's
   added uncertainty (`run_leg`); a way along the axis (beyond AXIAL_LIMIT, now or at the
   goal's angle) is made across it instead: the rod turned across its way in place (on the
   way, when it is nearly across already), pushed across, then turned to the goal's angle at
   the goal (`leg_target`);
2. observe (`observe_rod`, the tube observation model): lines across a static anchor (as the
   sphere's loop), then two lines across the rod's predicted axis at +-CROSS_FRACTION of its
   half length and one along the axis they measured. A line across a tube meets it
   symmetrically about the axis, so each cross line's crossing is a point of the axis: the two
   give the axis's angle and its position across; the line along the axis rises at one end cap
   and falls at the other, the midpoint is the centre along the axis;
3. stop when the position and the angle are both within tolerance with CONFIDENCE_SIGMAS
   confidence, or what is left of each is within the observation's own error, or the rod hand
   finds nothing left to push, or after rod_max_iterations legs; else re-plan from the
   observation.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from types import SimpleNamespace

import numpy as np

from afm_core.imaging.landmarks import Landmark, scan_landmarks
from afm_core.localization.landmark_observation import MapLandmark, line_noise
from afm_core.manipulation.closed_loop import (
    CONFIDENCE_SIGMAS,
    LoopState,
    calibrate_chain,
    run_leg,
)
from afm_core.manipulation.particle_observation import (
    LINE_MARGIN,
    LINE_SIGMAS,
    TipTrack,
    choose_anchor,
    crossing,
    reset_on_anchor,
)
from afm_core.manipulation.push_steps import in_maps_frame
from afm_core.manipulation.rod_hand import _wrap_half_turn, rod_hand_plan

# the cross lines meet the axis at +-this share of the half length: far apart, since the
# angle's error is the crossings' over their distance, and inside the end caps with room for
# the along-axis error of the estimate (3 sigma of a few 10 nm on a rod of some 100 nm)
CROSS_FRACTION = 0.6
# the Schmitt margin of the line along the axis (most of it lies on the rod, so the default,
# from the profile's median, would be 0): 3 sigma of the line's noise, at most this share of
# the rod's apparent height
AXIAL_MARGIN_SHARE = 0.25
# a way along the rod's axis longer than this is not pushed at its end caps (a push there
# slides off a thin tube and turns it; bench_push_rods' first run: the 5 of 30 pushes that
# missed were those with most of their way along the axis, each stuck after all its legs):
# the rod is turned across the way, pushed across, and turned to the goal's angle at the goal
# (leg_target). Two of the rod hand's strokes (2 x 40 nm): what a few cap pushes still do
AXIAL_LIMIT = 80e-9  # m
# a failed observation (a line missed the rod: the strokes moved it farther than the model)
# is repeated once with the prediction's uncertainty this many times wider
RETRY_WIDENING = 3.0
# the rod hand's own stop, at its pushing points: a fraction of the push's tolerance, so the
# model's error is what is left for the observation to judge
PLAN_TOLERANCE_SHARE = 0.25


# a rescan's blob whose second moments differ less than this (sqrt of their ratio) has no
# axis to measure; above it the moments' axis of a tip-broadened short tube (50-160 nm,
# elongation 2-4.5) was within 2 deg of the simulator's, frame rotation included
AXIS_ELONGATION = 1.5
# the verification's particle search's lowest height (verify.find_particles)
VERIFY_MIN_HEIGHT = 10e-9

# the strategies a tube or rod may be pushed with: the closed loop (the default) and the open-
# loop rod hand
ROD_STRATEGIES = ("closed_loop", "rod_hand")


@dataclass(frozen=True)
class RodGoal:
    """A tube's or rod's goal axis (task frame) and how close to it is close enough."""

    angle: float  # rad
    angle_tolerance: float  # rad


@dataclass(frozen=True)
class PoseCheck:
    """The verified angle of a push (NaN for a sphere) and its text for the result message."""

    goal_angle: float = math.nan
    achieved_angle: float = math.nan
    angle_error: float = math.nan  # rad
    angle_tolerance: float = math.nan  # rad
    text: str = ""


def rod_goal_for(particle, goal_angle: float | None, angle_tolerance: float) -> RodGoal | None:
    """The goal axis of a push (None for a sphere); ValueError naming the field when a goal
    angle is not finite or given for a sphere, or the tolerance is not positive."""
    if particle.kind not in ("tube", "rod"):
        if goal_angle is not None:
            raise ValueError(
                f"goal_angle: only for a tube or rod; landmark {particle.id} is a "
                f"{particle.kind} (leave use_goal_angle false)"
            )
        return None
    if goal_angle is not None and not math.isfinite(goal_angle):
        raise ValueError(f"goal_angle={goal_angle}: must be finite (rad)")
    if not (math.isfinite(angle_tolerance) and 0 < angle_tolerance < 0.5 * math.pi):
        raise ValueError(f"angle_tolerance={angle_tolerance}: must be in (0, pi/2) rad")
    angle = particle.orientation if goal_angle is None else float(goal_angle)
    # the axis has no head: the goal within a half turn of the rod's own angle
    return RodGoal(
        particle.orientation + wrap_angle(angle - particle.orientation), angle_tolerance
    )


def check_rod_goal(particle, target, rod: RodGoal | None, tolerance: float) -> None:
    """ValueError when a tube's or rod's goal pose is where the map has it already."""
    if rod is None:
        return
    distance = math.hypot(target[0] - particle.x, target[1] - particle.y)
    turn = abs(wrap_angle(rod.angle - particle.orientation))
    if distance <= tolerance and turn <= rod.angle_tolerance:
        raise ValueError(
            f"goal and goal_angle: the {particle.kind} is already there ({distance * 1e9:.1f} nm "
            f"and {math.degrees(turn):.2f} deg away, within tolerance): nothing to push"
        )


def swept_radius(particle) -> float:
    """How far from its centre a pushed particle reaches: a sphere's radius, half a rod."""
    if particle.kind in ("tube", "rod"):
        return 0.5 * float(particle.length) + float(particle.radius)
    return float(particle.radius)


def rescan_margin(particle, margin: float) -> float:
    """The before/after images' margin around the start and the goal: `margin` beyond the
    particle (a rod's ends, which the image must hold to find its axis)."""
    return margin + swept_radius(particle) - float(particle.radius)


def rod_pose_verified(
    rod: RodGoal | None, particle, before, seen_before, verification, scanner_matrix
) -> PoseCheck:
    """The axis's turn between the before and after images (commanded scanner coordinates,
    each direction made true through the scanner matrix), added to the map's orientation."""
    if rod is None:
        return PoseCheck()
    from afm_core.manipulation.verify import find_particles

    found = find_particles(before)
    if not found or verification.particle is None:
        raise ValueError("rescan: the rod was not found in the before or the after image")
    first = min(found, key=lambda m: math.hypot(m.x - seen_before[0], m.y - seen_before[1]))
    axes = (_axis_seen(before, first), _axis_seen(verification.after, verification.particle))
    if None in axes:
        # the map keeps its angle (a NaN there would refuse every later push of the rod)
        text = (
            f", axis not measured: the rescan shows the {particle.kind} nearly round "
            f"(elongation below {AXIS_ELONGATION:g}), its angle cannot be told"
        )
        return PoseCheck(
            rod.angle, float(particle.orientation), math.nan, rod.angle_tolerance, text
        )
    matrix = np.asarray(scanner_matrix, float)

    def true_angle(angle: float) -> float:
        d = matrix @ np.array([math.cos(angle), math.sin(angle)])
        return math.atan2(d[1], d[0])

    turn = wrap_angle(true_angle(axes[1]) - true_angle(axes[0]))
    achieved = float(particle.orientation) + turn
    error = abs(wrap_angle(achieved - rod.angle))
    text = (
        f", axis {math.degrees(achieved):.2f} deg, {math.degrees(error):.2f} deg from the goal's "
        f"(tolerance {math.degrees(rod.angle_tolerance):.2f} deg)"
    )
    return PoseCheck(rod.angle, achieved, error, rod.angle_tolerance, text)


def _axis_seen(scan, mark) -> float | None:
    """The axis angle of a rescan's landmark `mark` (None: nearly round). A short rod is
    imaged broadened by the tip and may fall below the maps' tube elongation and be found as
    a sphere, whose orientation (0) is no axis; its axis is measured again at AXIS_ELONGATION."""
    if mark.kind != "sphere":
        return float(mark.orientation)
    if scan is None:
        return None
    marks = scan_landmarks(scan, min_height=VERIFY_MIN_HEIGHT, tube_elongation=AXIS_ELONGATION)
    if not marks:
        return None
    near = min(marks, key=lambda m: math.hypot(m.x - mark.x, m.y - mark.y))
    return None if near.kind == "sphere" else float(near.orientation)


@dataclass
class RodObservation:
    ok: bool
    mean: np.ndarray  # (2,) centre, task frame, m
    covariance: np.ndarray  # (2, 2) m^2
    angle: float  # rad, the axis (within a half turn of the prediction)
    angle_variance: float  # rad^2
    anchor_id: int  # -1: the track alone
    note: str


def wrap_angle(angle: float) -> float:
    """A rod's angle difference folded into (-pi/2, pi/2] (its axis has no head)."""
    return _wrap_half_turn(angle)


def _line(track: TipTrack, mark: MapLandmark, centre, direction, half: float, stop, axial=False):
    """A measuring line through task point `centre` along unit `direction`; (Crossing, the
    tip's estimate and covariance at the crossing). axial: along the rod, most of the line on
    it: the Schmitt margin from the line's own noise (AXIAL_MARGIN_SHARE)."""
    d = np.asarray(direction, float) * half
    start, end = track.to_command(centre - d), track.to_command(centre + d)
    line = track.scan(start, end, stop)
    margin = None
    if axial:
        margin = min(3.0 * line_noise(line.height), AXIAL_MARGIN_SHARE * mark.apparent_height)
    found = crossing(line, mark, track.calibration.scan_region_sigma, margin)
    if not found.ok:
        return found, None, None
    mean, cov, _ = track.at_line_sample(line, found.index)
    return found, mean, cov


def observe_rod(
    track: TipTrack,
    rod: MapLandmark,
    anchor: MapLandmark | None,
    tip_radius: float,
    should_stop=None,
    displacement: float = 0.0,
    *,
    length: float,
    angle_sigma: float = 0.0,
) -> RodObservation:
    """Anchor lines, then the tube observation model (module docstring, 2) about the predicted
    pose `rod` (centre, orientation; covariance: the centre's) of a rod `length` long.
    angle_sigma: the prediction's angle uncertainty (rad), widens the cross lines."""
    notes = reset_on_anchor(track, anchor, rod.position, tip_radius, should_stop)
    deflection = math.radians(track.calibration.line_deflection_sigma_deg) * displacement
    t = np.array([math.cos(rod.orientation), math.sin(rod.orientation)])
    n = np.array([-t[1], t[0]])
    arm = CROSS_FRACTION * 0.5 * length
    spread = math.sqrt(max(np.linalg.eigvalsh(rod.covariance).max(), 0.0))
    wobble = math.hypot(track.sigma, spread, arm * angle_sigma)
    half = rod.radius + tip_radius + LINE_SIGMAS * wobble + LINE_MARGIN
    points, variances, covs = [], [], []
    for sign in (1.0, -1.0):
        found, mean, cov = _line(track, rod, rod.position + sign * arm * t, n, half, should_stop)
        if not found.ok:
            notes.append(f"rod {'+-'[sign < 0]} cross line lost ({found.reason})")
            return _failed(rod, anchor, notes)
        points.append(mean)
        variances.append(found.variance)
        covs.append(cov)
        notes.append(f"rod {'+-'[sign < 0]} across")
    axis = points[0] - points[1]
    span = float(np.hypot(*axis))
    angle = rod.orientation + wrap_angle(math.atan2(axis[1], axis[0]) - rod.orientation)
    t = np.array([math.cos(angle), math.sin(angle)])
    n = np.array([-t[1], t[0]])
    # the track's error common to both lines cancels in the angle; what it gained between
    # them does not
    gained = max(float(n @ (covs[1] - covs[0]) @ n), 0.0)
    angle_variance = (variances[0] + variances[1] + gained + 2 * deflection**2) / span**2
    middle = 0.5 * (points[0] + points[1])
    half_axial = 0.5 * length + rod.radius + tip_radius + LINE_SIGMAS * wobble + LINE_MARGIN
    found, end_mean, end_cov = _line(track, rod, middle, t, half_axial, should_stop, True)
    if not found.ok:
        notes.append(f"rod along-axis line lost ({found.reason})")
        return _failed(rod, anchor, notes)
    notes.append("rod along")
    centre = middle + float((end_mean - middle) @ t) * t
    frame = np.column_stack([t, n])
    own = frame @ np.diag([found.variance, 0.25 * (variances[0] + variances[1])]) @ frame.T
    covariance = end_cov + own + np.eye(2) * deflection**2
    return RodObservation(
        True,
        centre,
        covariance,
        float(angle),
        float(angle_variance),
        -1 if anchor is None else anchor.id,
        ", ".join(notes),
    )


def _failed(rod: MapLandmark, anchor, notes) -> RodObservation:
    return RodObservation(
        False,
        rod.position.copy(),
        np.asarray(rod.covariance, float),
        float(rod.orientation),
        math.nan,
        -1 if anchor is None else anchor.id,
        ", ".join(notes),
    )


def decide_pose(
    observation: RodObservation, goal, goal_angle: float, tolerance: float, angle_tolerance
) -> tuple[bool, str]:
    """Stop or go on (module docstring, 3): (done, why)."""
    if not observation.ok:
        return False, f"rod not found ({observation.note})"
    error = float(np.hypot(*(observation.mean - goal)))
    sigma = math.sqrt(max(np.linalg.eigvalsh(observation.covariance).max(), 0.0))
    turn = abs(wrap_angle(observation.angle - goal_angle))
    angle_sigma = math.sqrt(max(observation.angle_variance, 0.0))
    text = (
        f"{error * 1e9:.1f} nm (sigma {sigma * 1e9:.1f} nm) and "
        f"{math.degrees(turn):.2f} deg (sigma {math.degrees(angle_sigma):.2f} deg) from the goal"
    )
    k = CONFIDENCE_SIGMAS
    if error + k * sigma <= tolerance and turn + k * angle_sigma <= angle_tolerance:
        return True, f"{text}: within tolerance with {k:g}-sigma confidence"
    position_done = error + k * sigma <= tolerance or error <= k * sigma
    angle_done = turn + k * angle_sigma <= angle_tolerance or turn <= k * angle_sigma
    if position_done and angle_done:
        return True, f"{text}: the rest is within the observation's own error"
    return False, f"{text}: re-planning"


def map_angle_sigma(rod: Landmark) -> float:
    """The angle uncertainty (rad) of a rod whose centre the map knows to its covariance: each
    end as uncertain as the centre, over half the length."""
    sigma = math.sqrt(max(np.linalg.eigvalsh(np.asarray(rod.covariance, float)).max(), 0.0))
    return math.sqrt(2.0) * sigma / (0.5 * rod.length)


def leg_target(rod: Landmark, goal, goal_angle: float):
    """The pose the next leg aims at (module docstring, 1): the goal when the way left is
    across both the rod's axis now and the goal's (within AXIAL_LIMIT along either); else,
    with the way along the axis now, the rod turned across it, in place, or on the way to the
    goal when that turn moves its ends at most AXIAL_LIMIT; else (across now, along the goal's
    axis) the goal's position at the rod's angle now, the turn left for the end."""
    centre = np.array([rod.x, rod.y])
    way = np.asarray(goal, float) - centre
    now = np.array([math.cos(rod.orientation), math.sin(rod.orientation)])
    then = np.array([math.cos(goal_angle), math.sin(goal_angle)])
    along_now, along_then = abs(float(way @ now)), abs(float(way @ then))
    if along_now <= AXIAL_LIMIT and along_then <= AXIAL_LIMIT:
        return np.asarray(goal, float), goal_angle
    if along_now > AXIAL_LIMIT:
        across = math.atan2(way[1], way[0]) + 0.5 * math.pi
        turn = wrap_angle(across - rod.orientation)
        if abs(turn) * 0.5 * rod.length <= AXIAL_LIMIT:
            # a rod already nearly across (a push leg turns it a few deg) is turned back by
            # the leg's first strokes on the way: a leg of its own for that would spend
            # every other leg of a long way in place
            return np.asarray(goal, float), rod.orientation + turn
        return centre, rod.orientation + turn
    return np.asarray(goal, float), rod.orientation


def plan_rod_leg(rod: Landmark, goal, goal_angle: float, tip_radius, tolerance, limits):
    """The rod hand from the pose estimated now (None: nothing left for it to push)."""
    pose = SimpleNamespace(
        x=rod.x, y=rod.y, angle=rod.orientation, length=rod.length, radius=rod.radius
    )
    try:
        plan = rod_hand_plan(
            pose,
            (goal[0], goal[1], goal_angle),
            tip_radius=tip_radius,
            tolerance=PLAN_TOLERANCE_SHARE * tolerance,
            axial=True,
            limits=limits,
        )
    except ValueError as exc:
        if "already there" in str(exc):
            return None
        raise
    # run_leg follows the centre: the track's poses without their angles
    centres = [np.asarray(p[:2], float) for p in plan.predicted_track]
    return replace(
        plan, predicted_track=centres, extra={**plan.extra, "poses": plan.predicted_track}
    )


def rod_closed_loop_push(
    track: TipTrack,
    rod: Landmark,
    goal: np.ndarray,
    goal_angle: float,
    landmarks: Mapping[int, Landmark],
    settings: Mapping,
    report: Callable[..., None],
    should_stop: Callable[[], bool],
    holder: dict | None = None,
) -> LoopState:
    """The closed loop for a rod (module docstring). report(kind, **fields) as
    `closed_loop_push`'s; "observed" carries a RodObservation."""
    state = LoopState(rod)
    if holder is not None:
        holder["state"] = state
    tip_radius, tolerance = settings["tip_radius"], settings["tolerance"]
    angle_tolerance = settings["angle_tolerance"]
    limits = track.instrument.limits
    start = np.array([rod.x, rod.y])
    reach = 0.5 * rod.length + rod.radius + tip_radius + LINE_SIGMAS * track.sigma + LINE_MARGIN
    anchor = choose_anchor(landmarks, rod.id, start, goal, reach)
    angle_sigma = map_angle_sigma(rod)

    def observe(tr, mark, anc, radius, stop, displacement=0.0, spread=angle_sigma):
        return observe_rod(
            tr, mark, anc, radius, stop, displacement, length=rod.length, angle_sigma=spread
        )

    # the first look, at the map's pose before any stroke, ties the observations to the map:
    # the anchor as the chain sees it (calibrate_chain) and the angle between the lines' axis
    # and the map's (the map is an image in commanded coordinates, the lines measure true
    # ones: the scanner's rotation and shear), taken out of every later observation
    first: list[RodObservation] = []

    def first_look(*args):
        first.append(observe(*args))
        return first[-1]

    mark = MapLandmark.from_landmark(rod)
    if anchor is not None:
        anchor = calibrate_chain(track, anchor, mark, tip_radius, should_stop, first_look)
        report("anchor", anchor=anchor)
    else:
        first_look(track, mark, None, tip_radius, should_stop)
    angle_offset = 0.0
    if first[0].ok:
        angle_offset = wrap_angle(first[0].angle - rod.orientation)
        # the track into the same frame: where it saw the rod is where the map has it (with
        # an anchor it was reset to the anchor's map position, whose error relative to the rod
        # the calibrated anchor takes out only from the next observation on)
        track.mean = track.mean - (first[0].mean - mark.position)
    for leg in range(int(settings["rod_max_iterations"])):
        aim, aim_angle = leg_target(state.particle, goal, goal_angle)
        # the rod hand's reach (radii) in the maps' frame, where its strokes are placed
        rod_maps, tip_maps = in_maps_frame(
            state.particle, tip_radius, track.calibration.lateral_scale
        )
        plan = plan_rod_leg(rod_maps, aim, aim_angle, tip_maps, tolerance, limits)
        if plan is None:
            break
        state.plans.append(plan)
        state.cost.legs += 1
        report("plan", plan=plan, leg=leg)
        cancelled, why, done = run_leg(
            track,
            plan,
            state,
            settings["push_speed"],
            tolerance,
            anchor is not None and leg + 2 < int(settings["rod_max_iterations"]),
            lambda r, w: report("stroke", step=r, why=w, plan=plan),
            should_stop,
        )
        if cancelled:
            state.cancelled = True
            return state
        x, y, angle = plan.extra["poses"][done - 1] if done else (rod.x, rod.y, rod.orientation)
        sigma = max(track.sigma, 1e-9)
        guess = replace(state.particle, x=float(x), y=float(y), orientation=float(angle))
        mark = replace(MapLandmark.from_landmark(guess), covariance=np.eye(2) * sigma**2)
        # the model's turn is as uncertain as the strokes' positions over the grip's arm
        turned = abs(wrap_angle(angle - state.particle.orientation))
        spread = math.hypot(angle_sigma, 0.5 * turned)
        moved = float(np.hypot(x - start[0], y - start[1])) if anchor is not None else 0.0
        observation = observe(track, mark, anchor, tip_radius, should_stop, moved, spread)
        if not observation.ok and not should_stop():
            wider = replace(mark, covariance=mark.covariance * RETRY_WIDENING**2)
            note = observation.note
            observation = observe(
                track, wider, anchor, tip_radius, should_stop, moved, RETRY_WIDENING * spread
            )
            observation = replace(observation, note=f"{note}; again, wider: {observation.note}")
        observation = replace(observation, angle=observation.angle - angle_offset)
        state.cost.observations += 1
        finished, verdict = decide_pose(observation, goal, goal_angle, tolerance, angle_tolerance)
        state.observations.append(observation)
        report("observed", observation=observation, why=why, verdict=verdict)
        if observation.ok:
            state.particle = replace(
                state.particle,
                x=float(observation.mean[0]),
                y=float(observation.mean[1]),
                orientation=float(observation.angle),
                covariance=observation.covariance,
            )
        if finished or should_stop():
            return state
    return state
