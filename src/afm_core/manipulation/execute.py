"""Execute a push plan on an Instrument (simulator, DAQ hardware or replay: the same calls).

For every stroke: move_tip(start, contact=False) (lifted) and then move_tip(end, contact=
stroke.contact); so the tip is lifted between strokes. After each stroke `on_step` receives a
StepReport (index, peak lateral and normal force of the stroke's force trace, the object the
instrument says it pushed, where the command ended). `should_stop` is polled before each
stroke: when it returns True the stroke in progress has already finished (cancel stops after
the current stroke, never in the middle of a push), and the tip is lifted clear of the
particle: a lifted move to a point `clear_distance` = particle radius + tip radius + margin
from the particle's predicted centre (after the strokes done), behind it along the push axis
(or, if that point is outside the scanner range, the first of the other directions around the
particle that is inside). The report says where.

Before anything moves, every commanded point (stroke ends, the plan's goal, the speeds) is
checked against the instrument's `limits`: a plan that would leave the scanner range is
refused with ValueError naming the stroke and the limit, and the instrument is not touched.

Forces: the ForceTraceData gives lateral torsion (rad) and vertical deflection (m); the normal
force is deflection x normal_spring_constant, the lateral force torsion x
lateral_spring_constant / tip_height (tip_height, the lever arm of the lateral force, is not in
the trace: 10 um by default, the simulator's value).

Frames: plans are in the afm_task frame; `to_instrument` maps a task point to the instrument's
commanded frame (default: the identity, i.e. the caller has already put the plan in instrument
coordinates, or the localization says the two frames coincide).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from afm_core.instrument import Instrument, check_in_range, check_speed
from afm_core.manipulation.plans import PushPlan, predict_particle


@dataclass
class StepReport:
    index: int  # stroke index in the plan (0-based)
    total: int  # strokes in the plan
    label: str
    contact: bool
    end: tuple[float, float]  # commanded end (instrument frame, m)
    completed: bool  # the instrument finished the move
    peak_lateral_force: float  # N (0 for lifted strokes)
    peak_normal_force: float  # N
    object_id: int = -1  # what the instrument says it pushed (-1: nothing / unknown)

    @classmethod
    def of_move(cls, index: int, total: int, stroke, move, tip_height: float) -> StepReport:
        """The report of one executed stroke: its move's end and, in contact, the peak forces
        of its force trace."""
        lateral, normal = force_summary(move.trace, tip_height) if stroke.contact else (0.0, 0.0)
        return cls(
            index,
            total,
            stroke.label,
            stroke.contact,
            (move.end_x, move.end_y),
            move.completed,
            lateral,
            normal,
            move.trace.object_id if move.trace is not None else -1,
        )


@dataclass
class ExecutionResult:
    completed: bool  # every stroke done
    cancelled: bool
    strokes_done: int
    steps: list[StepReport] = field(default_factory=list)
    lift_position: tuple[float, float] | None = (
        None  # where the tip was lifted clear to (instrument frame)
    )
    predicted_particle: np.ndarray | None = (
        None  # model's particle centre after the strokes done (task)
    )
    duration: float = 0.0  # s of instrument time


# m, the lateral force's lever arm (module docstring) when none is given
TIP_HEIGHT = 10e-6
# What a progress report's particle estimate is (push_procedure.Progress.belief): the push
# model's prediction after the strokes done, or what local scan lines observed
PREDICTED, OBSERVED = "predicted", "observed"


def cantilever_forces(
    lateral_torsion,
    vertical_deflection,
    lateral_spring_constant: float,
    normal_spring_constant: float,
    tip_height: float = TIP_HEIGHT,
) -> tuple[np.ndarray, np.ndarray]:
    """(lateral, normal) force in N per sample: torsion x lateral spring constant / tip height
    (the lever arm), deflection x normal spring constant."""
    lateral = np.asarray(lateral_torsion, float) * lateral_spring_constant / tip_height
    normal = np.asarray(vertical_deflection, float) * normal_spring_constant
    return lateral, normal


def force_summary(trace, tip_height: float = TIP_HEIGHT) -> tuple[float, float]:
    """(peak lateral force, peak normal force) in N of a ForceTraceData (0, 0 for None)."""
    if trace is None or len(trace.lateral_torsion) == 0:
        return 0.0, 0.0
    lateral, normal = cantilever_forces(
        trace.lateral_torsion,
        trace.vertical_deflection,
        trace.lateral_spring_constant,
        trace.normal_spring_constant,
        tip_height,
    )
    return float(np.max(np.abs(lateral))), float(np.max(normal))


def _identity(p: np.ndarray) -> np.ndarray:
    return np.asarray(p, float)


def clear_point(particle: np.ndarray, axis: np.ndarray, distance: float, limits) -> np.ndarray:
    """A point `distance` from the particle, behind it (along -axis), or else the first of the
    directions turned by +-45, +-90, +-135, 180 deg from there that is inside the scanner range."""
    for turn_deg in (180, 135, 225, 90, 270, 45, 315, 0):
        t = math.radians(turn_deg)
        c, s = math.cos(t), math.sin(t)
        d = np.array([c * axis[0] - s * axis[1], s * axis[0] + c * axis[1]])
        p = np.asarray(particle, float) + distance * d
        if 0 <= p[0] <= limits.range_x and 0 <= p[1] <= limits.range_y:
            return p
    raise ValueError(f"no point {distance:.4e} m from the particle is inside the scanner range")


def pushed_object_after(
    plan: PushPlan, strokes_done: int, contact_params=None
) -> tuple[np.ndarray, float, np.ndarray]:
    """(predicted centre of what the last done stroke pushed, its radius, the stroke's direction)
    in the task frame: the particle (centre and nano-hand plans: the pushing model on the done
    strokes); for rod and arc plans the contact point ahead of the last stroke's end."""
    done = plan.strokes[:strokes_done]
    last = done[-1]
    d = np.asarray(last.end, float) - np.asarray(last.start, float)
    d = d / np.hypot(*d) if np.hypot(*d) > 0 else plan.axis
    if plan.kind in ("centre", "nano_hand"):
        track = predict_particle(replace(plan, strokes=done), contact_params)
        return track[-1], plan.particle_radius, d
    reach = plan.particle_radius + plan.tip_radius
    return np.asarray(last.end, float) + reach * d, plan.particle_radius, d


def execute_plan(
    instrument: Instrument,
    plan: PushPlan,
    *,
    speed: float = 0.5e-6,
    lift_speed: float | None = None,
    on_step: Callable[[StepReport], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    margin: float = 50e-9,
    tip_height: float = 10e-6,
    to_instrument: Callable[[np.ndarray], np.ndarray] = _identity,
    contact_params=None,
) -> ExecutionResult:
    """Run `plan` on `instrument` (module docstring). speed: pushing speed (m/s); lift_speed:
    lifted moves (default 10 x speed, at most the slew limit). margin: extra clearance of the
    lift-clear point beyond particle radius + tip radius (cover the particle's uncertainty)."""
    limits = instrument.limits
    check_speed("speed", speed, limits)
    lift_speed = min(10 * speed, limits.max_speed) if lift_speed is None else lift_speed
    check_speed("lift_speed", lift_speed, limits)
    if not (math.isfinite(margin) and margin >= 0):
        raise ValueError(f"margin={margin}: must be finite and >= 0 m")
    if not (math.isfinite(tip_height) and tip_height > 0):
        raise ValueError(f"tip_height={tip_height}: must be finite and > 0 m")
    commands = []
    check_in_range("plan.goal", *map(float, to_instrument(plan.goal)), limits)
    for i, stroke in enumerate(plan.strokes):
        a, b = to_instrument(stroke.start), to_instrument(stroke.end)
        check_in_range(f"strokes[{i}].start", float(a[0]), float(a[1]), limits)
        check_in_range(f"strokes[{i}].end", float(b[0]), float(b[1]), limits)
        commands.append((a, b))
    t0 = instrument.time
    result = ExecutionResult(completed=False, cancelled=False, strokes_done=0)
    for i, (stroke, (a, b)) in enumerate(zip(plan.strokes, commands)):
        if should_stop is not None and should_stop():
            result.cancelled = True
            break
        instrument.move_tip(float(a[0]), float(a[1]), lift_speed, contact=False)
        move = instrument.move_tip(float(b[0]), float(b[1]), speed, contact=stroke.contact)
        report = StepReport.of_move(i, len(plan.strokes), stroke, move, tip_height)
        result.steps.append(report)
        result.strokes_done = i + 1
        if on_step is not None:
            on_step(report)
        if not move.completed:
            result.cancelled = True
            break
    else:
        result.completed = True
    if result.cancelled:
        tip = np.array(instrument.commanded_position(), float)
        result.lift_position = (
            float(tip[0]),
            float(tip[1]),
        )  # lifted where it is unless too close
        if result.strokes_done:
            obj, radius, direction = pushed_object_after(plan, result.strokes_done, contact_params)
            result.predicted_particle = obj
            distance = radius + plan.tip_radius + margin
            here = to_instrument(obj)
            if np.hypot(*(tip - here)) < distance:
                target = clear_point(here, direction, distance, limits)
                instrument.move_tip(float(target[0]), float(target[1]), lift_speed, contact=False)
                result.lift_position = (float(target[0]), float(target[1]))
    result.duration = instrument.time - t0
    return result
