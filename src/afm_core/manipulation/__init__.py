"""Virtual nano-hand manipulation, ROS-free (book ch. 2.3.3, 6.4.2-6.4.3, 7.3; SPEC section 5).

Entry points
------------
Plans: lists of tip strokes in the afm_task frame (the data, the shared inputs and the model as
the planners' predictor: afm_core.manipulation.plans):
- centre_push_plan(particle, goal, ...)      baseline: straight pushes through the estimated
                                             centre (.centre_push)
- nano_hand_plan(particle, goal, params)     the virtual nano-hand zigzag (left/right pushes
                                             along the edges of the uncertainty region);
                                             NanoHandParams.book() is Table 7.6 (.nano_hand)
- choose_nano_hand_params(particle_sigma, particle_radius, tip_radius, ...)   the zigzag for
                                             the current uncertainties (.nano_hand)
- rod_hand_plan(rod, goal_pose)              rod-like hand: translate/rotate a rod or tube
                                             (.rod_hand)
- arc_hand_plan(particles, centre, radius)   arc-shaped hand: gather particles onto a ring
                                             (hexagon) (.arc_hand)

Evaluation (afm_core.manipulation.monte_carlo):
- monte_carlo_push(plan, samples=500, sigma=10e-9, seed=0)   the stochastic pushing model
                                             (Fig. 6.18)

On an instrument (afm_core.manipulation.execute, .verify): through the
afm_core.instrument.Instrument protocol only (simulator, hardware driver, replay):
- execute_plan(instrument, plan, on_step=..., should_stop=...)   lifted between strokes, cancel
                                             after the current stroke and lift clear, limits
                                             checked first
- verify_push(instrument, request, goal, before=...)   rescan, find the particle, remove the
                                             drift between the scans with pits / static
                                             landmarks as control points

The whole push of book 7.3 (afm_core.manipulation.push_procedure; its steps as functions in
.push_steps): control pits and the before image, localization on the particle, the strokes run
one by one, the after image and verification with control points, on any Instrument:
- PushProcedure(instrument, localize, landmarks, scanner_matrix=..., settings=...)
                                            .push(...) / .assemble(...) -> PushResult /
                                            AssemblyResult; PushRefused before anything moved,
                                            PushFailed after; Progress reports;
                                            PUSH_PARAMETERS its settings (.push_parameters)
- localize_with(localizer)                  the localization callable over a core Localizer
- .push(..., goal_angle=..., angle_tolerance=...) on a tube or rod: a goal pose; the closed
                                            loop runs the rod hand in legs observed by the tube
                                            observation model (afm_core.manipulation.rod_loop:
                                            observe_rod, rod_closed_loop_push)

Teleoperation (afm_core.manipulation.teleop, .teleop_model; the teleop node runs them):
- TeleopController(settings, limits, scanner_matrix)   velocity commands -> bounded segments
                                            (speed, acceleration, range, dead-man timeout)
- segment_wrench(...), joy_command(...)     force feedback from a force trace; Joy mapping
- PushPredictor, BelievedTip                the push model along teleoperated contact moves

The pushing physics is afm_core.physics (afm_core.physics.pushing.push_along_path with
afm_core.physics.contact.ContactParams on an afm_core.physics.sample.Sample); the planners use
it as their model, nothing here writes another one.
"""

from afm_core.manipulation.arc_hand import arc_hand_plan
from afm_core.manipulation.centre_push import centre_push_plan
from afm_core.manipulation.execute import ExecutionResult, StepReport, execute_plan, force_summary
from afm_core.manipulation.monte_carlo import MonteCarloResult, monte_carlo_push
from afm_core.manipulation.nano_hand import NanoHandParams, choose_nano_hand_params, nano_hand_plan
from afm_core.manipulation.plans import (
    ParticleEstimate,
    PushPlan,
    Stroke,
    check_plan_limits,
    path_blocker,
    predict_particle,
)
from afm_core.manipulation.push_parameters import DEFAULT_STRATEGY, PUSH_PARAMETERS
from afm_core.manipulation.push_procedure import (
    AssemblyResult,
    Progress,
    PushFailed,
    PushProcedure,
    PushRefused,
    PushResult,
)
from afm_core.manipulation.push_steps import (
    Localization,
    TipEstimate,
    ZigzagOverrides,
    localize_with,
)
from afm_core.manipulation.rod_hand import rod_hand_plan
from afm_core.manipulation.verify import (
    ControlPoint,
    VerificationResult,
    find_particles,
    find_pits,
    verify_push,
)

__all__ = [
    "NanoHandParams",
    "ParticleEstimate",
    "PushPlan",
    "Stroke",
    "arc_hand_plan",
    "centre_push_plan",
    "check_plan_limits",
    "choose_nano_hand_params",
    "nano_hand_plan",
    "path_blocker",
    "predict_particle",
    "rod_hand_plan",
    "MonteCarloResult",
    "monte_carlo_push",
    "ExecutionResult",
    "StepReport",
    "execute_plan",
    "force_summary",
    "ControlPoint",
    "VerificationResult",
    "find_particles",
    "find_pits",
    "verify_push",
    "DEFAULT_STRATEGY",
    "PUSH_PARAMETERS",
    "AssemblyResult",
    "Localization",
    "Progress",
    "PushFailed",
    "PushProcedure",
    "PushRefused",
    "PushResult",
    "TipEstimate",
    "ZigzagOverrides",
    "localize_with",
]
