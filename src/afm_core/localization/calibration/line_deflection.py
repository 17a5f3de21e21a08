"""Deflection of local scan lines (book 7.2.2, Fig. 7.12): pits at both ends of local scan
lines, rescanned; the angle between where a line went and where it was sent.
"""

from __future__ import annotations

import math

import numpy as np

from afm_core import checks
from afm_core.instrument import LineRequest
from afm_core.localization.calibration.experiment import (
    Experiment,
    check_box,
    indent_force,
    punch_at,
    range_centre,
    range_scale,
    rescan,
)
from afm_core.localization.calibration.matching import match_points
from afm_core.localization.calibration.pits import find_pits

SITE = np.array([20e-6, -25e-6])  # m on REFERENCE_RANGE (experiment.range_scale)


def _into_range(instrument, points, margin: float) -> np.ndarray:
    """The shift (m) that brings `points` `margin` inside the scanner range where they stick out
    (zero where they do not, or where the block is wider than the range)."""
    limits = instrument.limits
    lo, hi = points.min(axis=0) - margin, points.max(axis=0) + margin
    top = np.array([limits.range_x, limits.range_y])
    shift = np.where(lo < 0.0, -lo, 0.0) + np.where(hi > top, top - hi, 0.0)
    return np.where(hi - lo <= top, shift, 0.0)


def measure_line_deflection(
    instrument,
    *,
    lines: int = 20,
    length: float = 1e-6,
    line_spacing: float = 0.4e-6,
    site=None,
    speed: float = 1e-6,
    pixel: float = 10e-9,
    force: float | None = None,
) -> Experiment:
    """Deflection of local scan lines (book Fig. 7.12): for each line, a pit at its start,
    the local scan, a pit where it ended; half the lines horizontal, half vertical. The angle
    between the pit-to-pit vector and the commanded direction (counter-clockwise positive)
    over all lines gives mean and sigma. As for the scanner matrix, a deflection common to
    lines and raster scans cancels: this is the deflection against the image (the map).
    site (the first line's start from the range centre) defaults to SITE on a 110 um scanner,
    the same fraction of another's range (experiment.range_scale)."""
    limits = instrument.limits
    given = site is not None
    site = SITE * range_scale(instrument) if site is None else np.asarray(site, float)
    lines = checks.count("lines", lines, 2, 200)
    length = checks.positive("length", length, "m", upper=20e-6)
    force = indent_force(instrument, force)
    origin = range_centre(instrument) + np.asarray(site, float)
    starts, ends = [], []
    for k in range(lines):
        if k % 2 == 0:  # horizontal lines, stacked along y
            s = origin + np.array([0.0, (k // 2) * line_spacing])
            e = s + np.array([length, 0.0])
        else:  # vertical lines, to the right of the horizontal block
            s = origin + np.array([length + 1e-6 + (k // 2) * line_spacing, 0.0])
            e = s + np.array([0.0, length])
        starts.append(s)
        ends.append(e)
    starts, ends = np.array(starts), np.array(ends)
    if not given:  # on a small range the block (a few um) is moved inside it, if it fits
        shift = _into_range(instrument, np.vstack([starts, ends]), 0.5e-6)
        starts, ends = starts + shift, ends + shift
    everything = np.vstack([starts, ends])
    check_box(
        "line-deflection site",
        instrument,
        everything.min(axis=0) - 0.5e-6,
        everything.max(axis=0) + 0.5e-6,
        f"pass a site nearer the centre (now {site[0]:.3g}, {site[1]:.3g} m), fewer lines or a "
        f"smaller line_spacing ({lines} x {line_spacing:.3g} m): afm calibrate --set "
        "line_deflection.site=X,Y",
    )
    samples = max(
        2, int(round(length / 10e-9))
    )  # 10 nm per sample: the line is not what is measured
    for s, e in zip(starts, ends):
        punch_at(instrument, float(s[0]), float(s[1]), 0.1 * limits.max_speed, force)
        instrument.local_scan(
            LineRequest(float(s[0]), float(s[1]), float(e[0]), float(e[1]), samples, speed)
        )
        x, y = instrument.commanded_position()
        instrument.indent(x, y, force, 0.0)
    scan = rescan(
        instrument,
        everything.min(axis=0) - 0.4e-6,
        everything.max(axis=0) + 0.4e-6,
        pixel,
        slow_axis=1,
    )
    detected = np.array([[p.x, p.y] for p in find_pits(scan)]).reshape(-1, 2)
    index = match_points(everything, detected, 0.3 * line_spacing)
    n = len(starts)
    angles = []
    for k in range(n):
        i, j = index[k], index[n + k]
        if i < 0 or j < 0:
            continue
        measured = detected[j] - detected[i]
        commanded = ends[k] - starts[k]
        angle = math.atan2(
            commanded[0] * measured[1] - commanded[1] * measured[0], float(commanded @ measured)
        )
        angles.append(math.degrees(angle))
    if len(angles) < 2:
        raise RuntimeError(f"line deflection: only {len(angles)} of {n} lines measured")
    angles = np.array(angles)
    return Experiment(
        {"mean_deg": float(angles.mean()), "sigma_deg": float(angles.std(ddof=1))},
        {"angles_deg": angles.tolist(), "length": length},
    )
