"""Normal-work sessions for the suite: what the graph records while a lab works (a 0/90 scan
pair of the area, a local image, a localization, pushes through the core PushProcedure with
their pits, images, localizations and rescans, the pair again at the end).

`record(path, config, seed, spheres, pushes)` uses the core's
`afm_core.sim2real.work_session.record_work_session` when the installed core has it, else the
minimal recorder here (the same steps, the graph's calibration file for the localizer and the
scanner matrix), so the suite runs before and after that module is merged.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

CALIBRATION = (
    Path(__file__).resolve().parents[1] / "afm_localization" / "config" / "sim_calibration.yaml"
)
AREA_MARGIN, AREA_PIXEL, LINE_RATE = 0.6e-6, 25e-9, 4.0  # m, m, Hz
PUSH_DISTANCE, CLEARANCE = 300e-9, 350e-9  # m
DIRECTIONS = ((1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0))


def core_recorder():
    """The core's record_work_session, or None when this core does not have it."""
    try:
        from afm_core.sim2real.work_session import record_work_session
    except ImportError:
        return None
    return record_work_session


def record(path, config, *, seed: int, spheres, pushes: int = 2) -> str:
    """Record a normal-work session on SimulatedAfm(config) to `path`; which recorder ran."""
    recorder = core_recorder()
    if recorder is not None:
        recorder(path, config, seed=seed, pushes=pushes, spheres=spheres)
        return "afm_core.sim2real.work_session"
    _record_minimal(path, config, seed, spheres, pushes)
    return "bench/sim2real_work.py"


def _area(spheres, angle: float):
    from afm_core.instrument import ScanRequest

    points = np.asarray(spheres, float)
    lo, hi = points.min(axis=0) - AREA_MARGIN, points.max(axis=0) + AREA_MARGIN
    size = float(max(hi - lo))
    pixels = int(math.ceil(size / AREA_PIXEL))
    centre = 0.5 * (lo + hi)
    return ScanRequest(
        float(centre[0] - size / 2),
        float(centre[1] - size / 2),
        size,
        size,
        pixels,
        pixels,
        scan_angle_deg=angle,
        line_rate=LINE_RATE,
    )


def _goal(mark, marks, rng):
    here = np.array([mark.x, mark.y])
    others = [np.array([m.x, m.y]) for m in marks.values() if m.id != mark.id]
    for k in rng.permutation(len(DIRECTIONS)):
        goal = here + PUSH_DISTANCE * np.array(DIRECTIONS[k])
        if all(
            np.hypot(*(here + t * (goal - here) - o)) >= CLEARANCE
            for o in others
            for t in (np.clip((o - here) @ (goal - here) / PUSH_DISTANCE**2, 0.0, 1.0),)
        ):
            return goal
    return None


def _record_minimal(path, config, seed: int, spheres, pushes: int) -> None:
    from afm_core.imaging.landmarks import extract_landmarks
    from afm_core.instrument import ScanRequest
    from afm_core.localization import Localizer
    from afm_core.localization.calibration.model import load_calibration
    from afm_core.manipulation import PushFailed, PushProcedure, PushRefused, localize_with
    from afm_core.sim.instrument import SimulatedAfm
    from afm_core.sim2real.session_writer import RecordingInstrument

    rng = np.random.default_rng([seed, 3571])
    calibration = load_calibration(CALIBRATION)
    recording = RecordingInstrument(SimulatedAfm(config), path)
    try:
        scans = [recording.raster_scan(_area(spheres, a), pair_id="area") for a in (0.0, 90.0)]
        first = scans[0]
        marks = {
            m.id: m
            for m in extract_landmarks(
                np.asarray(first.height, float),
                first.pixel_size_x,
                first.pixel_size_y,
                first.origin_x,
                first.origin_y,
            )
        }
        if marks:
            mark = marks[list(marks)[int(rng.integers(len(marks)))]]
            recording.raster_scan(
                ScanRequest(mark.x - 0.5e-6, mark.y - 0.5e-6, 1e-6, 1e-6, 64, 64, line_rate=4.0)
            )
            localize = localize_with(
                Localizer(
                    recording,
                    calibration,
                    np.array(recording.commanded_position()),
                    np.diag([(50e-9) ** 2] * 2),
                )
            )
            localize(mark, lambda: False)
            procedure = PushProcedure(
                recording,
                localize,
                lambda: marks,
                scanner_matrix=calibration.scanner_matrix,
                on_moved=lambda moved: marks.__setitem__(moved.id, moved),
            )
            for particle in [list(marks)[k] for k in rng.permutation(len(marks))][:pushes]:
                goal = _goal(marks[particle], marks, rng)
                if goal is None:
                    continue
                try:  # a failed push is part of ordinary work: recorded as it ran
                    procedure.push(particle, goal)
                except (PushFailed, PushRefused):
                    pass
        for angle in (0.0, 90.0):
            recording.raster_scan(_area(spheres, angle), pair_id="area")
    finally:
        recording.close()
