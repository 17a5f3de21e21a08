"""The whole push of book 7.3 on any Instrument, ROS-free: what the nano-hand node runs.

`PushProcedure.push` strings the manipulation algorithms together for one particle:

1. refuse what cannot work, before anything moves (`PushRefused`): unknown particle, goal
   off-range or not finite, unknown strategy or one that does not fit the particle's kind,
   negative or non-finite tolerance, another particle in the way;
2. punch control pits in the rescan's corners and scan the area ("before"): pits and image
   first, since moving the tip there after localizing would spend the localization (a raster
   leaves the tip tens of nm from where the model says);
3. localize the tip on the particle (the `localize` callable: in the graph the localizer's
   Localize action, ROS-free `localize_with(Localizer)`), or trust the current estimate;
4. plan the strokes (nano-hand zigzag chosen from the particle's and the tip's uncertainty,
   centre pushing, or the rod hand) and execute them stroke by stroke, commands linearised
   about the localized tip through the calibrated scanner matrix; or, strategy "closed_loop"
   (the default, `DEFAULT_STRATEGY`), in legs with local scan lines across a static landmark
   and the particle between them, re-planned until the particle is within tolerance with
   2-sigma confidence (`afm_core.manipulation.closed_loop`); a tube or rod goes to a goal pose
   (position and `goal_angle`) by the rod hand, open loop ("rod_hand") or closed loop (the
   default: `afm_core.manipulation.rod_loop`, the tube observation model between legs);
5. rescan ("after"), verify the particle's position with the pits (and the other particles)
   as control points, and judge it in the maps' frame with its uncertainty
   (`afm_core.manipulation.verdict`: within, outside, or cannot tell at this tolerance; a
   tube's or rod's turn too: `PushResult.achieved_angle`, `angle_error`).

Progress goes to a callback (`Progress`: phase, step, the particle's and the tip's estimates,
peak forces, the planned strokes once); `should_stop` is polled during the pits and scans,
after localizing and before every stroke. A push that started and could not finish, or was
cancelled, raises `PushFailed` saying what happened and where the tip and the particle are;
a cancelled one lifts the tip clear of the particle first.

`PushProcedure.assemble` pushes many particles to many goals, in the order a callable gives
(the planner's sequencing) or as given, each as above; a failure stops the assembly and the
result says which particles reached their goals.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace

import numpy as np

from afm_core.imaging.landmarks import Landmark
from afm_core.instrument import (
    Instrument,
    InstrumentUnavailable,
    RasterScanData,
    ScanRequest,
    check_in_range,
)
from afm_core.localization.calibration.model import Calibration
from afm_core.manipulation.closed_loop import PushCost, closed_loop_push, report_fields
from afm_core.manipulation.execute import (
    PREDICTED,
    ExecutionResult,
    clear_point,
    execute_plan,
    pushed_object_after,
)
from afm_core.manipulation.nano_hand import choose_nano_hand_params
from afm_core.manipulation.particle_observation import TipTrack
from afm_core.manipulation.plans import PushPlan, path_blocker
from afm_core.manipulation.push_parameters import (
    DEFAULT_STRATEGY,
    PUSH_PARAMETERS,
    STRATEGIES,
)
from afm_core.manipulation.push_results import (
    AssemblyResult,
    Progress,
    PushFailed,
    PushRefused,
    PushResult,
)
from afm_core.manipulation.push_steps import (
    Localization,
    TipEstimate,
    ZigzagOverrides,
    check_sphere_not_there,
    control_pit_sites,
    find_particle,
    in_maps_frame,
    largest_sigma,
    nearest_particle,
    plan_push,
    rescan_request,
    sphere_distance_within,
    task_to_command,
    zigzag_reach,
)
from afm_core.manipulation.rod_loop import (
    ROD_STRATEGIES,
    RodGoal,
    check_rod_goal,
    rescan_margin,
    rod_closed_loop_push,
    rod_goal_for,
    rod_pose_verified,
    swept_radius,
)
from afm_core.manipulation.verdict import drift_prior, push_verdict, reversed_scan
from afm_core.manipulation.verify import VerificationResult, verify_push

PIT_DWELL = 0.1  # s


def _never() -> bool:
    return False


def _ignore(_progress: Progress) -> None:
    return None


class PushProcedure:
    """Pushes on `instrument` (module docstring).

    localize(particle, should_stop) -> Localization: observe the tip on the particle.
    landmarks() -> {id: Landmark}: the current map (task frame; the graph's /afm/landmarks).
    scanner_matrix: the calibration's (true displacement per commanded one, 2x2): it maps
        task-frame strokes to commands (default: the calibration's).
    settings: values of PUSH_PARAMETERS, validated (the rest their defaults), kept in
        `self.settings`, which each step reads when it needs a value: a change there (a
        node's run-time parameter) reaches the next step that uses it.
    tip_estimate() -> TipEstimate | None: the newest estimate from elsewhere (the graph's
        /afm/tip_pose), used when localize_first is false and reported while pushing.
    on_moved(landmark): a pushed particle, where the rescan found it (e.g. publish the map).
    on_lost(landmark): a particle whose push failed after its strokes: not where the map holds it.
    calibration: the localization calibration (motion model of the closed loop's tip track;
        its scanner matrix unless scanner_matrix is given; default: the book's defaults).
    map_time() -> when the map passed a point of it (s, maps' frame; e.g.
        partial(verify.scan_time, map_scan)) for a map that is one image, whose own drift
        stretches it (verdict.map_stretch), or None for a drift-corrected map (the default).
    """

    def __init__(
        self,
        instrument: Instrument,
        localize: Callable[[Landmark, Callable[[], bool]], Localization],
        landmarks: Callable[[], Mapping[int, Landmark]],
        *,
        scanner_matrix=None,
        settings: Mapping | None = None,
        tip_estimate: Callable[[], TipEstimate | None] = lambda: None,
        on_moved: Callable[[Landmark], None] = lambda _landmark: None,
        on_lost: Callable[[Landmark], None] = lambda _landmark: None,
        calibration: Calibration | None = None,
        map_time: Callable[[], Callable[[np.ndarray], float] | None] = lambda: None,
    ):
        self.instrument = instrument
        self.map_time = map_time
        self.localize = localize
        self.landmarks = landmarks
        self.calibration = calibration or Calibration()
        self.scanner_matrix = np.array(
            self.calibration.scanner_matrix if scanner_matrix is None else scanner_matrix
        )
        self.settings = {
            **PUSH_PARAMETERS.defaults(),
            **PUSH_PARAMETERS.validate(dict(settings or {})),
        }
        self.tip_estimate = tip_estimate
        self.on_moved, self.on_lost = on_moved, on_lost

    def maps_frame(self, particle: Landmark) -> tuple[Landmark, float]:
        """The particle and the tip's radius with the radii in the maps' frame, where the
        strokes are placed (push_steps.in_maps_frame): the contact distances of every plan."""
        return in_maps_frame(particle, self.settings["tip_radius"], self.calibration.lateral_scale)

    # -- refusals ----------------------------------------------------------------------------
    def particle(self, particle_id: int, position=None) -> Landmark:
        return find_particle(
            dict(self.landmarks()), particle_id, position, self.settings["match_radius"]
        )

    def check_goal(
        self, particle: Landmark, goal, strategy: str, tolerance: float, *, blockers: bool = True
    ) -> None:
        """ValueError when the push cannot work (module docstring, step 1). blockers=False
        leaves out the other particles (an assembly's first check: the pushes before this one
        move them)."""
        if strategy not in STRATEGIES:
            raise ValueError(
                f"strategy={strategy!r}: must be one of {list(STRATEGIES)} "
                "(arc_hand: use Assemble)"
            )
        if not np.all(np.isfinite(goal)):
            raise ValueError("goal: must be finite (m)")
        check_in_range("goal", goal[0], goal[1], self.instrument.limits)
        if not (math.isfinite(tolerance) and tolerance >= 0):
            raise ValueError(f"tolerance={tolerance}: must be finite and >= 0 (m)")
        if strategy == "rod_hand" and particle.kind not in ("tube", "rod"):
            raise ValueError(
                f"strategy='rod_hand': landmark {particle.id} is a {particle.kind}, "
                "not a tube or rod"
            )
        if strategy not in ROD_STRATEGIES and particle.kind != "sphere":
            raise ValueError(
                f"strategy={strategy!r}: landmark {particle.id} is a {particle.kind}; "
                f"use one of {list(ROD_STRATEGIES)}"
            )
        start = np.array([particle.x, particle.y])
        s = self.settings
        rescan_request(
            start,
            goal,
            rescan_margin(particle, s["rescan_margin"]),
            s["rescan_pixel"],
            s["rescan_line_rate"],
            self.instrument.limits,
        )
        if strategy == "nano_hand" and particle.kind == "sphere":
            # the open loop plans with the map's sigma (and the localized tip's, which can only
            # add to it): one too wide for any zigzag is refused before the pits are made
            maps_particle, tip_radius = self.maps_frame(particle)
            choose_nano_hand_params(
                largest_sigma(particle.covariance), maps_particle.radius, tip_radius
            )
        if not blockers:
            return
        others = [m for m in self.landmarks().values() if m.id != particle.id]
        tip_radius = self.settings["tip_radius"]
        blocker = path_blocker(
            start,
            goal,
            swept_radius(particle),
            tip_radius,
            others,
            zigzag_reach(particle, strategy, tip_radius),
        )
        if blocker is not None:
            raise ValueError(
                f"path blocked: landmark {blocker.id} at ({blocker.x * 1e9:.0f} nm, "
                f"{blocker.y * 1e9:.0f} nm) lies in the way from particle {particle.id} to the "
                "goal"
            )

    def check_overrides(self, particle: Landmark, goal, strategy: str, overrides) -> None:
        """ValueError naming the field when a goal's zigzag fields cannot work: each field's
        limits, then (any field set) the plan they give for a perfectly localized tip must stay
        in the scanner; before anything moves."""
        if not overrides.any():
            return
        if particle.kind != "sphere":
            raise ValueError(
                "push_length, back_length, lateral_offset, step_length, max_steps: the "
                f"zigzag's, not for the rod hand; landmark {particle.id} is a {particle.kind} "
                "(leave them 0)"
            )
        if strategy not in ("nano_hand", "closed_loop"):
            raise ValueError(
                f"push_length, back_length, lateral_offset, step_length, max_steps: only for "
                f"strategy 'nano_hand' or 'closed_loop', not {strategy!r} (leave them 0)"
            )
        sigma = largest_sigma(particle.covariance)
        # the zigzag's lengths are the maps' frame's, as the strokes they place
        particle, tip_radius = self.maps_frame(particle)
        overrides.check(particle.radius, tip_radius, sigma)
        try:
            limits = self.instrument.limits
            plan_push(particle, goal, strategy, np.zeros((2, 2)), overrides, tip_radius, limits)
        except ValueError as exc:
            raise ValueError(f"the zigzag these fields give cannot be run: {exc}") from exc

    # -- one push ----------------------------------------------------------------------------
    def push(
        self,
        particle_id: int,
        goal,
        *,
        position=None,
        strategy: str = "",
        tolerance: float = 0.0,
        overrides: ZigzagOverrides = ZigzagOverrides(),
        progress: Callable[[Progress], None] | None = None,
        should_stop: Callable[[], bool] | None = None,
        goal_angle: float | None = None,
        angle_tolerance: float = 0.0,
    ) -> PushResult:
        """Push landmark `particle_id` (-1: the one nearest `position`) to `goal` (task frame,
        m). strategy "" is DEFAULT_STRATEGY; tolerance 0 is default_tolerance. A tube or rod:
        goal_angle (rad, task frame; None: keep its orientation), angle_tolerance (rad, 0:
        default_angle_tolerance); refused for a sphere. PushRefused before anything moved,
        PushFailed after (module docstring)."""
        try:
            particle = self.particle(particle_id, position)
            target = np.array([goal[0], goal[1]], dtype=float)
            strategy = strategy or DEFAULT_STRATEGY
            tolerance = tolerance or self.settings["default_tolerance"]
            rod = rod_goal_for(
                particle,
                goal_angle,
                angle_tolerance or self.settings["default_angle_tolerance"],
            )
            self.check_goal(particle, target, strategy, tolerance)
            check_sphere_not_there(particle, target, tolerance)
            self.check_overrides(particle, target, strategy, overrides)
            check_rod_goal(particle, target, rod, tolerance)
        except ValueError as exc:
            raise PushRefused(str(exc)) from exc
        return self.run(
            particle,
            target,
            strategy,
            tolerance,
            overrides,
            progress or _ignore,
            should_stop or _never,
            rod,
        )

    def run(
        self,
        particle: Landmark,
        target: np.ndarray,
        strategy: str,
        tolerance: float,
        overrides: ZigzagOverrides,
        progress: Callable[[Progress], None],
        should_stop: Callable[[], bool],
        rod: RodGoal | None = None,
    ) -> PushResult:
        """The push of a checked goal: scan, localize, plan, execute, rescan, verify. rod: a
        tube's or rod's goal angle (None: keep its orientation)."""
        cost, planned = PushCost(), []

        def progress_watched(p: Progress) -> None:
            # the first "pushing" report comes once a plan stands, before its first stroke:
            # from then on the particle may have moved (a refused plan touched nothing)
            if p.phase == "pushing":
                planned.append(True)
            progress(p)

        if rod is None and particle.kind != "sphere":
            rod = rod_goal_for(particle, None, self.settings["default_angle_tolerance"])
        try:
            start_xy = np.array([particle.x, particle.y])
            request, before, started = self._scan_before(
                particle, start_xy, target, progress, should_stop
            )
            tip = self._localized(particle, start_xy, progress, should_stop)
            # the particle in scanner coordinates (the images') by the localized tip: the map's is
            # off by the drift since the map, hundreds of nm late in an assembly
            start_in_scan = task_to_command(
                tip.mean, np.array(self.instrument.commanded_position()), self.scanner_matrix
            )(start_xy)
            if strategy == "closed_loop":
                plan, execution, cost = self._closed_loop(
                    particle, target, tip, tolerance, overrides, progress_watched, should_stop, rod
                )
            else:
                plan, execution = self._execute(
                    particle, target, strategy, tip, overrides, progress_watched, should_stop, rod
                )
                cost.legs = 1
                cost.slid = sum(
                    float(np.hypot(*(np.asarray(s.end) - s.start)))
                    for s in plan.strokes
                    if s.contact
                )
            verification, seen_before = self._verify(
                particle,
                target,
                plan,
                execution,
                tip,
                (request, before, start_in_scan),
                progress,
                should_stop,
            )
            pose = rod_pose_verified(
                rod, particle, before, seen_before, verification, self.calibration.image_matrix
            )
            verdict = push_verdict(
                verification, self.calibration, start_xy, target, tolerance, self.map_time()
            )
        except (ValueError, InstrumentUnavailable, PushFailed) as exc:
            if not planned:
                if isinstance(exc, PushFailed):
                    raise
                raise PushFailed(str(exc)) from exc
            # failed or cancelled after strokes: the map's place is stale (the graph drops it),
            # which the next push by id or position would otherwise meet as "unknown"
            self.on_lost(particle)
            raise PushFailed(
                f"{exc}; particle {particle.id}'s place is no longer known: scan the area before "
                "pushing it again",
                getattr(exc, "execution", None),
            ) from exc
        achieved, error = verdict.achieved, verdict.error
        cost.duration = self.instrument.time - started
        moved = replace(particle, x=float(achieved[0]), y=float(achieved[1]))
        self.on_moved(moved if rod is None else replace(moved, orientation=pose.achieved_angle))
        used = sum(1 for c in verification.control_points if c.used)
        message = verdict.message(strategy, particle.id, tolerance, pose.text, used)
        return PushResult(
            particle.id,
            target,
            achieved,
            error,
            tolerance,
            sum(1 for s in plan.strokes if s.contact),
            message,
            plan,
            execution,
            verification,
            cost,
            pose.goal_angle,
            pose.achieved_angle,
            pose.angle_error,
            pose.angle_tolerance,
            verdict,
        )

    def _report(self, progress, phase: str, particle: Landmark, estimate, **fields) -> None:
        progress(
            Progress(
                phase, particle.id, estimate, particle.covariance, self.instrument.time, **fields
            )
        )

    def _scan_before(
        self, particle, start_xy, target, progress, should_stop
    ) -> tuple[ScanRequest, RasterScanData, float]:
        """The control pits, then the before image (module docstring, step 2); a report
        before each of them, so a listener that joined late still sees the phase. Also when the
        first started: a backend that hears others' commands late (the graph's nano-hand) may
        not know the time when the goal arrives, so the push's cost counts from there."""
        s = self.settings
        request = rescan_request(
            start_xy,
            target,
            rescan_margin(particle, s["rescan_margin"]),
            s["rescan_pixel"],
            s["rescan_line_rate"],
            self.instrument.limits,
        )
        pits = control_pit_sites(request, start_xy, target, s["control_pits"])
        first_start = None
        for done, pit in enumerate(pits):
            self._report(
                progress, "scanning", particle, start_xy, step=done, steps_total=len(pits) + 1
            )
            pitted = self.instrument.indent(
                pit[0], pit[1], s["pit_force"], PIT_DWELL, should_stop=should_stop
            )
            if first_start is None:
                first_start = pitted.trace.start_time
        self._report(
            progress, "scanning", particle, start_xy, step=len(pits), steps_total=len(pits) + 1
        )
        before = self.instrument.raster_scan(request, should_stop=should_stop)
        if should_stop() or not before.complete:
            raise PushFailed("cancelled before pushing; nothing was pushed")
        return request, before, before.start_time if first_start is None else first_start

    def _localized(self, particle, start_xy, progress, should_stop) -> TipEstimate:
        self._report(progress, "localizing", particle, start_xy)
        if not self.settings["localize_first"]:
            tip = self.tip_estimate()
            if tip is None:
                raise PushFailed("no tip estimate on /afm/tip_pose; is the localizer running?")
            return tip
        localization = self.localize(particle, should_stop)
        if should_stop():
            raise PushFailed("cancelled while localizing; nothing was pushed")
        if not localization.success:
            raise PushFailed(
                f"localization on particle {particle.id} failed, nothing was pushed: "
                f"{localization.message}"
            )
        return localization.estimate

    def _execute(
        self, particle, target, strategy, tip: TipEstimate, overrides, progress, should_stop, rod
    ) -> tuple[PushPlan, ExecutionResult]:
        """Plan the strokes and run them, commands linearised about the localized tip."""
        start_xy = np.array([particle.x, particle.y])
        commanded = np.array(self.instrument.commanded_position())
        to_instrument = task_to_command(tip.mean, commanded, self.scanner_matrix)
        maps_particle, tip_radius = self.maps_frame(particle)
        plan = plan_push(
            maps_particle,
            target,
            strategy,
            tip.covariance,
            overrides,
            tip_radius,
            self.instrument.limits,
            goal_angle=None if rod is None else rod.angle,
        )
        total = len(plan.strokes)
        self._report(
            progress, "pushing", particle, start_xy, steps_total=total, tip=tip, plan=plan
        )

        def on_step(report):
            estimate, _, _ = pushed_object_after(plan, report.index + 1)
            current = self.tip_estimate()
            self._report(
                progress,
                "pushing",
                particle,
                estimate,
                step=report.index + 1,
                steps_total=report.total,
                tip=current if current is not None else tip,
                peak_lateral_force=float(report.peak_lateral_force),
                peak_normal_force=float(report.peak_normal_force),
                belief=PREDICTED,
            )

        execution = execute_plan(
            self.instrument,
            plan,
            speed=self.settings["push_speed"],
            on_step=on_step,
            should_stop=should_stop,
            to_instrument=to_instrument,
        )
        if execution.cancelled:
            lifted = execution.lift_position
            estimate = (
                execution.predicted_particle
                if execution.predicted_particle is not None
                else start_xy
            )
            raise PushFailed(
                f"cancelled after {execution.strokes_done} of {total} strokes; tip lifted "
                f"clear to ({lifted[0] * 1e9:.1f} nm, {lifted[1] * 1e9:.1f} nm) in afm_scanner; "
                f"particle {particle.id} predicted at ({estimate[0] * 1e9:.1f} nm, "
                f"{estimate[1] * 1e9:.1f} nm) in afm_task (not verified)",
                execution,
            )
        return plan, execution

    def _closed_loop(
        self, particle, target, tip: TipEstimate, tolerance, overrides, progress, should_stop, rod
    ) -> tuple[PushPlan, ExecutionResult, PushCost]:
        """The closed-loop strategy (afm_core.manipulation.closed_loop; a tube's or rod's:
        rod_loop) from the localized tip; the plan returned holds every stroke run and the last
        estimate as its prediction."""
        # the push's frame is the particle's map position (the goal's displacement from it is
        # what is asked): the map's error of the particle, in the localization's covariance, is
        # common to the start and the goal
        relative = tip.covariance - np.asarray(particle.covariance, float)
        w, v = np.linalg.eigh(0.5 * (relative + relative.T))
        relative = v @ np.diag(np.maximum(w, (1e-9) ** 2)) @ v.T
        track = TipTrack(
            self.calibration, self.instrument, tip.mean, relative, self.scanner_matrix
        )
        t0, loop = self.instrument.time, {}

        def report(kind, **f):
            current = loop["state"].particle if "state" in loop else particle
            phase, estimate, fields = report_fields(kind, f, particle, current)
            tip_now = TipEstimate(track.mean.copy(), track.covariance.copy(), self.instrument.time)
            self._report(progress, phase, particle, estimate, tip=tip_now, **fields)

        settings = {**self.settings, "tolerance": tolerance}
        if rod is not None:
            settings["angle_tolerance"] = rod.angle_tolerance
            state = rod_closed_loop_push(
                track,
                particle,
                target,
                rod.angle,
                dict(self.landmarks()),
                settings,
                report,
                should_stop,
                loop,
            )
        else:
            state = closed_loop_push(
                track,
                particle,
                target,
                dict(self.landmarks()),
                overrides,
                settings,
                report,
                should_stop,
                loop,
            )
        if not state.plans:  # the rod hand found nothing to push: the map's pose is the goal's
            raise ValueError("goal: the rod is already there (within tolerance): nothing to push")
        strokes = [st for p in state.plans for st in p.strokes][: len(state.reports)]
        final = np.array([state.particle.x, state.particle.y])
        plan = replace(state.plans[-1], strokes=strokes, predicted=final)
        execution = ExecutionResult(
            not state.cancelled,
            state.cancelled,
            len(state.reports),
            state.reports,
            predicted_particle=final,
            duration=self.instrument.time - t0,
        )
        state.cost.lines = track.lines
        if state.cancelled:
            here = np.array(self.instrument.commanded_position(), float)
            distance = particle.radius + self.settings["tip_radius"] + 50e-9
            target_cmd = clear_point(
                track.to_command(final), -plan.axis, distance, self.instrument.limits
            )
            self.instrument.move_tip(
                *map(float, target_cmd), self.instrument.limits.max_speed / 10
            )
            lifted = self.instrument.commanded_position()
            execution.lift_position = (float(lifted[0]), float(lifted[1]))  # as the open loop
            raise PushFailed(
                f"cancelled after {len(state.reports)} strokes (closed loop, leg "
                f"{state.cost.legs}); tip lifted clear from ({here[0] * 1e9:.1f} nm, "
                f"{here[1] * 1e9:.1f} nm) to ({lifted[0] * 1e9:.1f} nm, {lifted[1] * 1e9:.1f} nm) "
                f"in afm_scanner; particle {particle.id} estimated at ({final[0] * 1e9:.1f} nm, "
                f"{final[1] * 1e9:.1f} nm) in afm_task (not verified)",
                execution,
            )
        return plan, execution, state.cost

    def _verify(
        self, particle, target, plan, execution, tip, images, progress, should_stop
    ) -> tuple[VerificationResult, np.ndarray]:
        """The after image and the particle's position by control points (module docstring,
        step 5); also where the before image had it. images: (the rescan's request, the before
        image, the particle's start in the images' coordinates as the localized tip has it)."""
        request, before, start_in_scan = images
        start_xy = np.array([particle.x, particle.y])
        total = len(plan.strokes)
        predicted = plan.predicted if plan.predicted is not None else target
        self._report(
            progress, "verifying", particle, predicted, step=total, steps_total=total, tip=tip
        )
        # the rescan sees the particle in scan coordinates; its position before the push in the
        # same scan ties it to the map (task frame); control points remove drift between scans
        before_particle = nearest_particle(before, start_in_scan)
        if before_particle is None or np.hypot(*(before_particle - start_in_scan)) > 2 * (
            swept_radius(particle)
        ):
            raise PushFailed(
                f"not verified: the before image shows no particle within two radii of where "
                f"the localized tip puts particle {particle.id} ({start_in_scan[0] * 1e9:.1f} nm, "
                f"{start_in_scan[1] * 1e9:.1f} nm in afm_scanner): it was cut off or drifted "
                "out of the image (a wider rescan_margin)",
                execution,
            )
        map_to_scan = before_particle - start_xy
        # the particle may end far from the plan (a centre push slides it off): look anywhere
        reach = float(np.hypot(*(target - start_xy))) + 2 * particle.radius + 100e-9
        # a cancel is honoured until the result is sent: the strokes can be done before a cancel
        # sent on their first report arrives, and the rescan takes longer than all of them
        after = self.instrument.raster_scan(reversed_scan(request), should_stop=should_stop)
        if should_stop() or not after.complete:
            raise PushFailed(
                f"cancelled while verifying, after all {total} strokes; tip lifted off the "
                f"particle for the rescan, which was stopped; particle {particle.id} predicted at "
                f"({predicted[0] * 1e9:.1f} nm, {predicted[1] * 1e9:.1f} nm) in afm_task "
                "(not verified)",
                execution,
            )
        verification = verify_push(
            self.instrument,
            request,
            target + map_to_scan,
            after=after,
            expected=predicted + map_to_scan,
            start=before_particle,
            before=before,
            particle_radius=particle.radius,
            particle_match_radius=reach,
            drift_prior=drift_prior(self.calibration),
        )
        return verification, before_particle

    # -- many pushes -------------------------------------------------------------------------
    def assemble(
        self,
        particle_ids: Sequence[int],
        goals: Sequence,
        *,
        strategy: str = "",
        tolerance: float = 0.0,
        order: Callable[[list[int]], list[int]] | None = None,
        progress: Callable[[Progress], None] | None = None,
        should_stop: Callable[[], bool] | None = None,
    ) -> AssemblyResult:
        """Push each particle to its goal (one per particle), in the order `order(ids)` gives
        (None: as given); each push as `push` with the planner's zigzag. PushRefused before
        anything moved; a push that fails or is refused ends the assembly (the result says
        which particles got where)."""
        progress, should_stop = progress or _ignore, should_stop or _never
        ids = [int(pid) for pid in particle_ids]
        strategy = strategy or DEFAULT_STRATEGY
        tolerance = tolerance or self.settings["default_tolerance"]
        try:
            targets, particles = self._check_assembly(ids, goals, strategy, tolerance)
            sequence = list(ids) if order is None else [int(pid) for pid in order(ids)]
        except (ValueError, InstrumentUnavailable) as exc:
            raise PushRefused(str(exc)) from exc
        pushes: dict[int, PushResult] = {}
        settled: dict[int, np.ndarray] = {}  # already within tolerance: left where they are
        messages = []
        for index, pid in enumerate(sequence):

            def report(p: Progress, index=index) -> None:
                progress(replace(p, index=index))

            try:
                particle = self.particle(pid)  # where the last pushes left it
                if sphere_distance_within(particle, targets[pid], tolerance) is not None:
                    settled[pid] = np.array([particle.x, particle.y])
                    messages.append(f"particle {pid}: already within tolerance, not pushed")
                    continue
                self.check_goal(particle, targets[pid], strategy, tolerance)
                # no per-push overrides: the planner chooses the zigzag
                pushes[pid] = self.run(
                    particle,
                    targets[pid],
                    strategy,
                    tolerance,
                    ZigzagOverrides(),
                    report,
                    should_stop,
                )
            except (ValueError, PushFailed) as exc:
                messages.append(f"particle {pid}: {exc}")
                break
            messages.append(pushes[pid].message)
        return AssemblyResult(
            ids,
            sequence,
            [
                pushes[pid].achieved if pid in pushes else settled.get(pid, np.array([p.x, p.y]))
                for pid, p in particles.items()
            ],
            [
                pushes[pid].error
                if pid in pushes
                else float(np.hypot(*(settled[pid] - targets[pid])))
                if pid in settled
                else math.nan
                for pid in ids
            ],
            len(pushes) + len(settled) == len(sequence)
            and all(p.success for p in pushes.values()),
            "; ".join(messages),
            [pushes[pid] for pid in sequence if pid in pushes],
        )

    def _check_assembly(self, ids: list[int], goals, strategy: str, tolerance: float):
        """The goals by particle id and the particles as mapped now; ValueError naming what
        cannot work."""
        if len(ids) != len(goals) or not ids:
            raise ValueError(
                f"particle_ids ({len(ids)}) and goals ({len(goals)}): "
                "need one goal per particle, at least one"
            )
        if len(set(ids)) != len(ids):
            raise ValueError("particle_ids: each particle once")
        targets = {pid: np.array([g[0], g[1]]) for pid, g in zip(ids, goals)}
        particles = {pid: self.particle(pid) for pid in ids}
        for pid in ids:
            if not (math.isfinite(targets[pid][0]) and math.isfinite(targets[pid][1])):
                raise ValueError(f"goal of particle {pid}: must be finite (m)")
            check_in_range(
                f"goal of particle {pid}", targets[pid][0], targets[pid][1], self.instrument.limits
            )
            if strategy not in STRATEGIES:
                raise ValueError(f"strategy={strategy!r}: must be one of {list(STRATEGIES)}")
            try:
                self.check_goal(particles[pid], targets[pid], strategy, tolerance, blockers=False)
            except ValueError as exc:
                raise ValueError(f"particle {pid}: {exc}") from exc
        return targets, particles
