"""A normal-work session recorded ROS-free, as the graph records it in ordinary work.

Labs rarely record the diagnostic protocol (`afm_core.sim2real.protocol`); what they have is
what the manipulation graph publishes while they work. `record_work_session` runs that on a
`SimulatedAfm` wrapped by `RecordingInstrument` (the MCAP file is what the driver publishes):

1. a 0/90 deg raster pair of the work area (the map, `pair_id` "area");
2. the particles mapped from the 0 deg image (`extract_landmarks`), a local image around one
   of them (a lab zooms in before it pushes);
3. a localization of the tip on a particle (the core `Localizer`'s scan lines);
4. `pushes` pushes through `afm_core.manipulation.push_procedure.PushProcedure` (control pits,
   the before image, localization, the strategy's strokes -- the graph's default, the closed
   loop: legs of strokes with local scan lines between them; or the open-loop nano-hand --,
   the after image, verification), each
   particle a distance `push_distance` along a direction the seed picks among those that stay
   clear of the other particles;
5. the 0/90 pair of the area again (the rescan a lab takes at the end).

A push the procedure refuses or cannot finish is part of ordinary work: it is recorded as it
ran and counted in the summary, never retried. The lab's calibration (the Localizer's and the
procedure's scanner matrix) is measured on a quiet copy of `config` (no drift, creep or
positioning noise), as a calibration of that instrument finds it.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from afm_core import checks
from afm_core.evaluation import image_frame_matrix
from afm_core.instrument import ScanRequest
from afm_core.localization.calibration.simulator_comparison import simulator_calibration

# The pushes' strategy by default: the graph's (the closed loop), as labs record in normal
# work; "nano_hand" records the open-loop baseline. The diagnosis handles both: what the closed
# loop's legs leave the re-simulation unable to reproduce (correction strokes on a particle
# beyond the last stroke's end, the levels of lines over a pushed particle) is left out with
# its reason (exclusions.py).
from afm_core.manipulation.push_parameters import DEFAULT_STRATEGY
from afm_core.sim.config import SimConfig, merge

# Spheres of the work sample (m): a loose cluster around the scanner centre, 0.9-1.5 um apart,
# so a push of a few hundred nm has a clear path in at least one direction.
WORK_SPHERES = [
    (54.1e-6, 54.2e-6),
    (55.3e-6, 54.0e-6),
    (56.1e-6, 55.1e-6),
    (54.6e-6, 55.7e-6),
    (55.7e-6, 56.3e-6),
]
AREA_MARGIN = 0.6e-6  # m around the spheres: the area image shows each whole with substrate
AREA_PIXEL = 25e-9  # m: the protocol's cluster images' resolution (23 nm), a bit coarser
AREA_LINE_RATE = 4.0  # Hz
LOCAL_SIZE, LOCAL_PIXELS, LOCAL_LINE_RATE = 1.0e-6, 64, 4.0
PUSH_DISTANCE = 300e-9  # m
CLEARANCE = 350e-9  # m: a goal this close to another particle's centre is not chosen
MAX_PUSHES = 10
INITIAL_SIGMA = 50e-9  # m: the tip's uncertainty when a localization starts (the map's)
DIRECTIONS = ((1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0))


@dataclass
class WorkSummary:
    """What the session did (operation counts by kind, the pushes' outcomes)."""

    path: Path
    operations: dict = field(default_factory=dict)  # kind -> count
    pushes: list = field(default_factory=list)  # {particle, goal, ran, success, message}
    particles: int = 0  # mapped from the first area image
    seconds: float = 0.0  # instrument time of the session


def work_config(base: SimConfig | None = None) -> SimConfig:
    """The work sample (spheres at WORK_SPHERES, r = 100 nm) on `base` (default config)."""
    from afm_core.sim.config import load_config

    base = base if base is not None else load_config()
    spheres = [{"x": x, "y": y, "radius": 100e-9} for x, y in WORK_SPHERES]
    return merge(base, {"sample": {"spheres": spheres, "random_spheres": 0}})


def _area_request(spheres, limits, angle: float) -> ScanRequest:
    points = np.asarray(spheres, float)
    lo, hi = points.min(axis=0) - AREA_MARGIN, points.max(axis=0) + AREA_MARGIN
    size = float(max(hi - lo))
    pixels = int(min(limits.max_pixels, math.ceil(size / AREA_PIXEL)))
    centre = 0.5 * (lo + hi)
    return ScanRequest(
        float(centre[0] - size / 2),
        float(centre[1] - size / 2),
        size,
        size,
        pixels,
        pixels,
        scan_angle_deg=angle,
        line_rate=AREA_LINE_RATE,
    )


def _scan_pair(recording, spheres):
    """The 0/90 deg images of the area; the 0 deg one."""
    first = None
    for angle in (0.0, 90.0):
        scan = recording.raster_scan(
            _area_request(spheres, recording.limits, angle), pair_id="area"
        )
        first = scan if first is None else first
    return first


def _map(scan) -> dict:
    from afm_core.imaging.landmarks import scan_landmarks

    marks = scan_landmarks(scan)
    return {m.id: m for m in marks}


def _goal(mark, marks: dict, rng, distance: float):
    """A goal `distance` from `mark` along a seeded direction that stays clear of the others
    (None: no direction does)."""
    here = np.array([mark.x, mark.y])
    others = [np.array([m.x, m.y]) for m in marks.values() if m.id != mark.id]
    for k in rng.permutation(len(DIRECTIONS)):
        goal = here + distance * np.array(DIRECTIONS[k])
        # the path and the goal keep clear: the nearest point of the segment to each other one
        clear = True
        for other in others:
            t = np.clip((other - here) @ (goal - here) / distance**2, 0.0, 1.0)
            if np.hypot(*(here + t * (goal - here) - other)) < CLEARANCE:
                clear = False
        if clear:
            return goal
    return None


def _local_image(recording, mark) -> None:
    half = 0.5 * LOCAL_SIZE
    recording.raster_scan(
        ScanRequest(
            mark.x - half,
            mark.y - half,
            LOCAL_SIZE,
            LOCAL_SIZE,
            LOCAL_PIXELS,
            LOCAL_PIXELS,
            line_rate=LOCAL_LINE_RATE,
        )
    )


def _fresh_localizer(recording, calibration):
    """The localization callable, each call on a Localizer started at the current command with
    the map's 50 nm uncertainty (as bench_pushing's procedure runs start one per push): a
    Localizer carried across the area images' long moves gates out its next lines."""
    from afm_core.localization import Localizer
    from afm_core.manipulation import localize_with

    def localize(particle, should_stop):
        localizer = Localizer(
            recording,
            calibration,
            np.array(recording.commanded_position()),
            np.diag([INITIAL_SIGMA**2] * 2),
        )
        return localize_with(localizer)(particle, should_stop)

    return localize


def _push_all(
    recording, procedure, marks: dict, rng, pushes: int, distance: float, strategy: str
) -> list:
    from afm_core.manipulation import PushFailed, PushRefused

    outcomes = []
    order = [list(marks)[k] for k in rng.permutation(len(marks))]
    for particle in order[:pushes]:
        mark = marks[particle]
        goal = _goal(mark, marks, rng, distance)
        if goal is None:
            outcomes.append({"particle": particle, "ran": False, "message": "no clear path"})
            continue
        try:
            result = procedure.push(particle, goal, strategy=strategy)
            outcome = {"ran": True, "success": bool(result.success), "message": result.message}
        except (PushFailed, PushRefused) as exc:
            outcome = {"ran": isinstance(exc, PushFailed), "success": False, "message": str(exc)}
        outcomes.append({"particle": particle, "goal": goal.tolist(), **outcome})
    return outcomes


def record_work_session(
    path: str | os.PathLike,
    config: SimConfig,
    *,
    seed: int = 0,
    pushes: int = 2,
    push_distance: float = PUSH_DISTANCE,
    spheres=None,
    truth: bool = True,
    strategy: str = DEFAULT_STRATEGY,
) -> WorkSummary:
    """Record a normal-work session (module docstring) on SimulatedAfm(config) to a new MCAP
    file `path`. seed: the choices (which particles, which directions); the instrument's own
    randomness is config.seed. spheres: where the area is (m; default: config's spheres).
    strategy: the pushes' (default the graph's, DEFAULT_STRATEGY: the closed loop; "nano_hand"
    the open loop). The summary says what ran."""
    from afm_core.manipulation import PushProcedure
    from afm_core.manipulation.push_parameters import STRATEGIES
    from afm_core.sim.instrument import SimulatedAfm
    from afm_core.sim2real.session_writer import RecordingInstrument

    seed = checks.count("seed", seed)
    pushes = checks.count("pushes", pushes, 0, MAX_PUSHES)
    push_distance = checks.positive("push_distance", push_distance, "m", upper=2e-6)
    if strategy not in STRATEGIES:  # a refused push is recorded as ordinary work: refuse here
        raise ValueError(f"strategy={strategy!r}: must be one of {list(STRATEGIES)}")
    if spheres is None:
        spheres = [(s["x"], s["y"]) for s in config.sample.spheres]
    spheres = [checks.point(f"spheres[{k}]", p) for k, p in enumerate(spheres)]
    if not spheres:
        raise ValueError("spheres=[]: the work area needs at least one particle (m)")
    rng = np.random.default_rng([seed, 3571])
    calibration = simulator_calibration(
        config,
        image_frame_matrix(config),
        "work session: measured on a quiet copy of the instrument's config",
    )
    recording = RecordingInstrument(SimulatedAfm(config), path, truth=truth)
    summary = WorkSummary(path=Path(path))
    try:
        t0 = recording.time
        marks = _map(_scan_pair(recording, spheres))
        summary.particles = len(marks)
        if marks:
            first = marks[list(marks)[int(rng.integers(len(marks)))]]
            _local_image(recording, first)
            localize = _fresh_localizer(recording, calibration)
            localize(first, lambda: False)
            procedure = PushProcedure(
                recording,
                localize,
                lambda: marks,
                scanner_matrix=calibration.scanner_matrix,
                on_moved=lambda moved: marks.__setitem__(moved.id, moved),
            )
            summary.pushes = _push_all(
                recording, procedure, marks, rng, pushes, push_distance, strategy
            )
        _scan_pair(recording, spheres)
        summary.seconds = float(recording.time - t0)
    finally:
        recording.close()
    summary.path = recording.path
    summary.operations = _count_kinds(recording.path)
    return summary


def _count_kinds(path) -> dict:
    from afm_core.sim2real.session_reader import read_operations

    counts: dict = {}
    with read_operations(path) as stream:
        for op in stream:
            counts[op.kind] = counts.get(op.kind, 0) + 1
    return counts
