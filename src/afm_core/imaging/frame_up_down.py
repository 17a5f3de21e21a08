"""Drift velocity from a frame-up and a frame-down image of the same area (book 5.3.3, eq.
5.32-5.36): the particles' apparent positions differ by the drift between the moments each
frame images them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from afm_core.imaging.particle_matching import (
    feature_windows,
    find_blobs,
    global_shift,
    match_blobs,
)
from afm_core.imaging.scan_timing import check_same_area, check_scan, pixel_times
from afm_core.instrument import RasterScanData


def velocity_from_up_down(
    scan_up: RasterScanData, scan_down: RasterScanData
) -> tuple[float, float]:
    """Drift velocity (vx, vy) in m/s from a frame-up and a frame-down image of the same area at
    the same angle (book 5.3.3).

    A particle at sample position s appears at X = s + D(t), t the moment its centre is imaged.
    For two particles P1, P2 and constant drift v the apparent separations are
        d_up = d + v (t_up(P2) - t_up(P1)),   d_down = d + v (t_down(P2) - t_down(P1)),
    so v = (d_up - d_down) / (T'_u + T'_d) with T'_u, T'_d the times between imaging the two
    particles in each frame (signed; along the slow axis they have opposite signs, so the
    denominator is the sum of the two intervals: eq. 5.35; along the fast axis the same relation
    with the horizontal separations: eq. 5.36). Along the slow axis with line speed V this is the
    stretch V / (V - v) frame up and the compression V / (V + v) frame down:
    v = V (d_up - d_down) / (d_up + d_down). With more than two particles all pairs are used at
    once: X_up(k) - X_down(k) = c + v (t_up(k) - t_down(k)) by least squares (c absorbs a common
    offset between the frames, e.g. the drift between the frames or a scanner offset).

    What it measures: the least-squares slope over the particles' moments, so in a drift that
    wanders it is an average of the velocity over the stretches of the two frames where the
    particles are imaged (`sampled_velocity` gives it for a known D(t)), in the units of the
    images (their pixel size as commanded: a scanner whose small moves go farther than
    commanded makes every image, and the velocity, smaller by the same factor)."""
    return up_down_velocity(up_down_observations(scan_up, scan_down))


@dataclass
class UpDownObservations:
    """The particles matched between a frame-up and a frame-down image: their positions
    (n, 2) as (x, y) in m from the image origin, in image units (commanded pixel size), and
    the instrument-clock moments (n,) their centres were imaged (`pixel_times`)."""

    position_up: np.ndarray
    position_down: np.ndarray
    t_up: np.ndarray
    t_down: np.ndarray


def up_down_observations(scan_up: RasterScanData, scan_down: RasterScanData) -> UpDownObservations:
    """The particles of a frame-up / frame-down pair, matched (see `velocity_from_up_down`)."""
    check_scan("scan_up", scan_up)
    check_scan("scan_down", scan_down)
    if scan_down.scan_angle_deg != scan_up.scan_angle_deg:
        raise ValueError(
            f"scan_down.scan_angle_deg={scan_down.scan_angle_deg}: must equal "
            f"scan_up.scan_angle_deg={scan_up.scan_angle_deg}"
        )
    if not scan_up.slow_scan_up:
        raise ValueError("scan_up.slow_scan_up=False: the frame-up image must be scanned upwards")
    if scan_down.slow_scan_up:
        raise ValueError(
            "scan_down.slow_scan_up=True: the frame-down image must be scanned downwards"
        )
    check_same_area(scan_up, scan_down, "scan_down")
    hu = np.asarray(scan_up.height, float)
    hd = np.asarray(scan_down.height, float)
    blobs_u, threshold = find_blobs(hu)
    blobs_d, _ = find_blobs(hd, threshold)
    blobs_u = feature_windows(blobs_u, hu.shape)
    blobs_d = feature_windows(blobs_d, hd.shape)
    if len(blobs_u) < 2:
        raise ValueError(f"scan_up.height: {len(blobs_u)} particle(s) found; need at least two")
    pairs, _, _ = match_blobs(blobs_u, blobs_d, global_shift(hu, hd))
    if len(pairs) < 2:
        raise ValueError(
            f"scan_down.height: only {len(pairs)} particle(s) match the frame-up image; need two"
        )
    pu = np.array([blobs_u[i].centroid for i, _ in pairs])
    pd = np.array([blobs_d[j].centroid for _, j in pairs])
    tu = pixel_times(scan_up, pu[:, 0], pu[:, 1])
    td = pixel_times(scan_down, pd[:, 0], pd[:, 1])
    if np.ptp(tu - td) <= 0:
        raise ValueError(
            "scan_up.height: the particles were imaged at the same moments; need particles on "
            "different lines"
        )
    scale = np.array([scan_up.pixel_size_x, scan_up.pixel_size_y])
    return UpDownObservations(
        position_up=pu[:, ::-1] * scale, position_down=pd[:, ::-1] * scale, t_up=tu, t_down=td
    )


def up_down_velocity(obs: UpDownObservations) -> tuple[float, float]:
    """(vx, vy) in m/s: X_up(k) - X_down(k) = c + v (t_up(k) - t_down(k)) by least squares."""
    dt = np.asarray(obs.t_up, float) - np.asarray(obs.t_down, float)
    design = np.stack([np.ones_like(dt), dt], axis=1)
    diff = np.asarray(obs.position_up, float) - np.asarray(obs.position_down, float)
    sol, *_ = np.linalg.lstsq(design, diff, rcond=None)
    return float(sol[1, 0]), float(sol[1, 1])


def sampled_velocity(offset, t_up, t_down) -> np.ndarray:
    """The velocity (vx, vy) a frame-up / frame-down pair returns for a drift offset D(t)
    (`offset(t)` -> (..., 2), m) with its particles imaged at t_up, t_down (s): the least
    squares of `up_down_velocity` applied to D(t_up) - D(t_down). For a constant velocity it is
    that velocity; for a wandering one it is the average the pair samples (weighted towards the
    stretches of the two frames where the particles are), which is the truth to compare a
    measured pair velocity with (not the mean velocity over the pair's whole span)."""
    t_up, t_down = np.asarray(t_up, float), np.asarray(t_down, float)
    return np.array(
        up_down_velocity(
            UpDownObservations(
                position_up=np.asarray(offset(t_up), float),
                position_down=np.asarray(offset(t_down), float),
                t_up=t_up,
                t_down=t_down,
            )
        )
    )
