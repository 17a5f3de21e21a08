"""The steps of a push (book 7.3) as functions, for `afm_core.manipulation.push_procedure`:
which landmark a goal means, where the control pits go, the rescan's area, task-frame points as
scanner commands about the localized tip, the particle in an image, the strokes for a strategy,
and the localization callable over a core Localizer.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from types import SimpleNamespace

import numpy as np

from afm_core import checks
from afm_core.imaging.landmarks import Landmark
from afm_core.instrument import RasterScanData, ScannerLimits, ScanRequest
from afm_core.manipulation.centre_push import centre_push_plan
from afm_core.manipulation.nano_hand import NanoHandParams, choose_nano_hand_params, nano_hand_plan
from afm_core.manipulation.plans import ParticleEstimate, PushPlan
from afm_core.manipulation.rod_hand import rod_hand_plan
from afm_core.manipulation.verify import find_particles


@dataclass(frozen=True)
class TipEstimate:
    mean: np.ndarray  # (2,) task frame, m
    covariance: np.ndarray  # (2, 2) m^2
    time: float  # s, instrument clock of the estimate


@dataclass(frozen=True)
class Localization:
    """What a localization callable returns: the estimate after observing the particle, and
    whether the observation was accepted (the message says why not)."""

    success: bool
    estimate: TipEstimate | None
    message: str = ""


# the most zigzag steps a goal may ask for: the book's smallest advance per step (Table 7.6,
# 36 nm) across the whole scanner range; more steps would push the particle out of it
MAX_PUSH_STEPS = math.ceil(ScannerLimits().range_x / NanoHandParams.book().step)
ZIGZAG_LENGTHS = ("push_length", "back_length", "lateral_offset", "step_length")


@dataclass(frozen=True)
class ZigzagOverrides:
    """Lengths of the nano-hand zigzag a goal may fix (m; 0: the planner chooses)."""

    push_length: float = 0.0
    back_length: float = 0.0
    lateral_offset: float = 0.0  # half-distance between the left and right push paths
    step_length: float = 0.0  # advance per step
    max_steps: int = 0

    def any(self) -> bool:
        return any(getattr(self, name) != 0 for name in (*ZIGZAG_LENGTHS, "max_steps"))

    def check(self, particle_radius: float, tip_radius: float, particle_sigma: float) -> None:
        """ValueError naming the field and its limit when the zigzag these fields fix cannot
        work on this particle (what can be known before the tip moves: the map's particle and
        uncertainty, the tip radius; the planner's own choice, for a perfectly localized tip,
        stands in for the fields left 0)."""
        for name in ZIGZAG_LENGTHS:
            checks.non_negative(name, getattr(self, name), "m (0: the planner chooses)")
        checks.count("max_steps", self.max_steps, 0, MAX_PUSH_STEPS)
        reach = particle_radius + tip_radius
        if not self.lateral_offset < reach:
            raise ValueError(
                f"lateral_offset={self.lateral_offset:.4e} m: must be < the particle's radius + "
                f"tip_radius = {reach:.4e} m, or the push paths never touch the particle"
            )
        chosen = choose_nano_hand_params(particle_sigma, particle_radius, tip_radius)
        push = self.push_length or chosen.left_push
        if self.back_length and self.step_length:
            if abs(push - self.back_length - self.step_length) > 1e-12:
                raise ValueError(
                    f"step_length={self.step_length:.4e} m: must be push_length - back_length "
                    f"= {push - self.back_length:.4e} m (or leave one of them 0)"
                )
        back = self.back_length or (push - self.step_length if self.step_length else None)
        back = chosen.left_back if back is None else back
        if not back > 0:
            raise ValueError(
                f"step_length={self.step_length:.4e} m: must be < push_length={push:.4e} m "
                "(fields left 0 are the planner's), or the tip never backs off"
            )
        if not push > back:
            raise ValueError(
                f"push_length={push:.4e} m: must exceed back_length={back:.4e} m (fields left 0 "
                "are the planner's), or the zigzag never advances"
            )
        if not push > chosen.initial_h:
            raise ValueError(
                f"push_length={push:.4e} m: must exceed the approach before first contact, "
                f"{chosen.initial_h:.4e} m for this particle's uncertainty, or no push touches it"
            )


def find_particle(
    known: Mapping[int, Landmark], particle_id: int, position, match_radius: float
) -> Landmark:
    """The landmark `particle_id`, or (particle_id < 0) the one nearest `position` within
    `match_radius`; ValueError saying which is missing."""
    if particle_id >= 0 or position is None:
        if particle_id not in known:
            raise ValueError(
                f"particle_id={particle_id}: unknown (known ids: {sorted(known) or 'none yet'})"
            )
        return known[particle_id]
    point = np.array([position[0], position[1]])
    if not np.all(np.isfinite(point)):
        raise ValueError("particle_position: must be finite (m)")
    if not known:
        raise ValueError("no landmark known yet (nothing on /afm/landmarks)")
    nearest = min(known.values(), key=lambda m: math.hypot(m.x - point[0], m.y - point[1]))
    if math.hypot(nearest.x - point[0], nearest.y - point[1]) > match_radius:
        raise ValueError(
            f"particle_position: no particle within match_radius={match_radius * 1e9:.0f} nm"
        )
    return nearest


def control_pit_sites(request: ScanRequest, start, goal, count: int) -> list:
    """Up to `count` indentation sites in the rescan's corners, inset by a quarter of the
    margin, farthest from the push's way: control points the before and after images share
    (book 7.3), away from what is pushed."""
    lo = np.array([request.origin_x, request.origin_y])
    inset = 0.15 * request.size_x
    corners = [
        lo + np.array([dx, dy])
        for dx in (inset, request.size_x - inset)
        for dy in (inset, request.size_y - inset)
    ]
    axis = goal - start
    length = float(np.hypot(*axis)) or 1.0

    def clearance(p):
        t = np.clip((p - start) @ axis / length**2, 0.0, 1.0)
        return float(np.hypot(*(p - (start + t * axis))))

    return sorted(corners, key=clearance, reverse=True)[: max(0, int(count))]


def rescan_request(a, b, margin: float, pixel: float, line_rate: float, limits) -> ScanRequest:
    """The square image around a and b with `margin` (square, so the 0 deg scan's pixels are
    square), in commanded scanner coordinates: the map is an image in them. A way too long for
    the image is a ValueError about the distance, naming the farthest goal that fits."""
    lo, hi = np.minimum(a, b) - margin, np.maximum(a, b) + margin
    size = float(max(hi - lo))
    widest = limits.max_speed / (2.0 * line_rate)  # trace in half a line period at the slew limit
    if size > widest:
        raise ValueError(
            f"goal: {float(np.hypot(*(np.asarray(b) - np.asarray(a)))) * 1e6:.2f} um from the "
            f"particle; the before/after images around both ({size * 1e6:.2f} um square) can be "
            f"at most {widest * 1e6:.2f} um at rescan_line_rate={line_rate:g} Hz (slew limit "
            f"{limits.max_speed * 1e6:g} um/s), so the goal may be at most "
            f"{(widest - 2 * margin) * 1e6:.2f} um along an axis (lower rescan_line_rate, or "
            "push in shorter legs)"
        )
    pixels = int(min(limits.max_pixels, math.ceil(size / pixel)))
    request = ScanRequest(
        float(lo[0]), float(lo[1]), size, size, pixels, pixels, line_rate=line_rate
    )
    try:
        request.validate(limits)
    except ValueError as exc:
        if not (np.all(lo >= 0) and hi[0] <= limits.range_x and hi[1] <= limits.range_y):
            raise ValueError(
                f"goal: the before/after images around the particle and the goal "
                f"({lo[0] * 1e6:.3f} .. {hi[0] * 1e6:.3f} um, {lo[1] * 1e6:.3f} .. "
                f"{hi[1] * 1e6:.3f} um with their {margin * 1e9:.0f} nm margin) would leave "
                f"the scanner range [0, {limits.range_x * 1e6:g}] x [0, {limits.range_y * 1e6:g}] "
                "um: a goal, or a particle, farther from the edge (or a smaller rescan_margin)"
            ) from exc
        raise
    return request


def task_to_command(tip_mean, commanded, scanner_matrix):
    """Task-frame point -> scanner command, linearised about the localized tip: the command that
    moves the tip from where it is estimated by the wanted displacement."""
    inverse = np.linalg.inv(scanner_matrix)

    def to_instrument(xy):
        return commanded + inverse @ (np.asarray(xy, float) - tip_mean)

    return to_instrument


def nearest_particle(scan: RasterScanData, near) -> np.ndarray | None:
    """The particle of `scan` nearest `near` (None: the scan shows none)."""
    found = find_particles(scan)
    if not found:
        return None
    best = min(found, key=lambda m: math.hypot(m.x - near[0], m.y - near[1]))
    return np.array([best.x, best.y])


def in_maps_frame(
    particle: Landmark, tip_radius: float, lateral_scale: float
) -> tuple[Landmark, float]:
    """The particle and the tip's radius with their radii (metres: the particle's from its
    height) in the maps' lateral frame (`Calibration.lateral_scale`, m per map unit), the frame
    the strokes are placed in: every planner's contact distance (radius + tip radius) is then
    where the tip meets the particle there. Taken as metres on the simulator, whose images are
    ~6 % small, every centre stroke stopped ~8.5 nm before the particle's goal (150 nm against
    141.5 nm). A rod's length is measured in the image, in the maps' frame already."""
    return (
        replace(particle, radius=float(particle.radius) / lateral_scale),
        float(tip_radius) / lateral_scale,
    )


def largest_sigma(covariance) -> float:
    """The standard deviation along the covariance's most uncertain axis of x and y (m): what
    the zigzag is chosen for."""
    return float(math.sqrt(max(np.max(np.diag(covariance)), 0.0)))


def plan_push(
    particle: Landmark,
    target: np.ndarray,
    strategy: str,
    tip_cov: np.ndarray,
    overrides: ZigzagOverrides,
    tip_radius: float,
    limits: ScannerLimits,
    goal_angle: float | None = None,
) -> PushPlan:
    """The strokes for `strategy`; the nano-hand's zigzag is chosen from the particle's (map)
    and the tip's (localization) uncertainty unless `overrides` fix its lengths. goal_angle:
    the rod hand's goal axis (rad; None: the rod's orientation kept)."""
    sigma, tip_sigma = largest_sigma(particle.covariance), largest_sigma(tip_cov)
    estimate = ParticleEstimate(
        particle.x, particle.y, particle.radius, math.hypot(sigma, tip_sigma)
    )
    if strategy in ("center", "centre"):
        return centre_push_plan(estimate, target, tip_radius=tip_radius, limits=limits)
    if strategy == "rod_hand":
        rod = SimpleNamespace(
            x=particle.x,
            y=particle.y,
            angle=particle.orientation,
            length=particle.length,
            radius=particle.radius,
        )
        angle = particle.orientation if goal_angle is None else goal_angle
        return rod_hand_plan(
            rod, (target[0], target[1], angle), tip_radius=tip_radius, limits=limits
        )
    chosen = choose_nano_hand_params(sigma, particle.radius, tip_radius, tip_sigma=tip_sigma)
    o = overrides
    push = o.push_length or chosen.left_push
    back = o.back_length or (push - o.step_length if o.step_length else chosen.left_back)
    params = NanoHandParams(
        push,
        push,
        back,
        back,
        chosen.initial_h,
        2 * o.lateral_offset if o.lateral_offset else chosen.h,
        push - back,
    )
    return nano_hand_plan(
        estimate,
        target,
        params,
        tip_radius=tip_radius,
        limits=limits,
        steps=int(o.max_steps) or None,
    )


def localize_with(localizer) -> Callable[[Landmark, Callable[[], bool]], Localization]:
    """The localization callable over a core `afm_core.localization.Localizer` on the same
    instrument: local scan lines through the particle (what the graph's Localize action runs)."""
    from afm_core.localization import MapLandmark

    def localize(particle: Landmark, should_stop: Callable[[], bool]) -> Localization:
        observation = localizer.observe_landmark(MapLandmark.from_landmark(particle))
        lines = observation.summary()
        estimate = TipEstimate(observation.mean, observation.covariance, observation.time)
        return Localization(observation.all_accepted, estimate, lines or "no line run")

    return localize


def sphere_distance_within(particle: Landmark, goal, tolerance: float) -> float | None:
    """The map's distance from a sphere to its goal when it is within tolerance already (None
    otherwise, and for a tube or rod, whose angle counts too)."""
    if particle.kind != "sphere":
        return None
    distance = float(np.hypot(goal[0] - particle.x, goal[1] - particle.y))
    return distance if distance <= tolerance else None


def check_sphere_not_there(particle: Landmark, goal, tolerance: float) -> None:
    """ValueError for a sphere already within tolerance of its goal: no stroke can be planned
    for it, and finding that out after the control pits and the rescan cost the sample two
    pits and the lab half a minute."""
    distance = sphere_distance_within(particle, goal, tolerance)
    if distance is not None:
        raise ValueError(
            f"goal: {distance * 1e9:.1f} nm from particle {particle.id}, within the "
            f"tolerance {tolerance * 1e9:.1f} nm: already there, nothing to push"
        )


def zigzag_reach(particle: Landmark, strategy: str, tip_radius: float) -> float:
    """How far beside the push line the zigzag's tip centre runs (h/2, as plan_push chooses it
    for the map's sigma; the localized tip's own sigma can only widen it): 0 for a push that
    keeps the tip on the line, or when no zigzag fits (the plan is refused then)."""
    if particle.kind != "sphere" or strategy not in ("nano_hand", "closed_loop"):
        return 0.0
    sigma = largest_sigma(particle.covariance)
    try:
        return choose_nano_hand_params(sigma, particle.radius, tip_radius).h / 2
    except ValueError:
        return 0.0
