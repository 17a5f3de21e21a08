"""The scanner matrix (book 7.2.2): a grid of pits at commanded offsets, rescanned; the affine
map commanded -> imaged displacement, in normal (compensated) operation.
"""

from __future__ import annotations

import numpy as np

from afm_core import checks
from afm_core.localization.calibration.experiment import (
    Experiment,
    check_box,
    indent_force,
    punch_at,
    range_centre,
    range_scale,
    rescan,
    wait,
)
from afm_core.localization.calibration.matching import match_points
from afm_core.localization.calibration.pits import find_pits

# On REFERENCE_RANGE (experiment.range_scale): the grid's first pit from the range centre (m),
# its spacing, and how far beyond its far corner the tip comes from (BEYOND_CHECKED: that,
# checked against the range with a margin)
SITE = np.array([-20e-6, 20e-6])
SPACING = 1e-6
MIN_SPACING = 0.25e-6
BEYOND = 4e-6
BEYOND_CHECKED = 5e-6


def measure_scanner_matrix(
    instrument,
    *,
    site=None,
    grid: int = 5,
    spacing: float | None = None,
    pixel: float = 10e-9,
    force: float | None = None,
    settle: float = 300.0,
) -> Experiment:
    """Imaged displacement per commanded displacement in normal (compensated) operation: a
    grid x grid pattern of pits `spacing` apart, punched row by row (serpentine, moves as
    short as the localizer's), rescanned; the affine fit image = M command + b gives M.

    What M can show: a rescan uses the same scanner, so a coupling or rotation common to all
    motion (the tube's x/y coupling, its rotation against the sample) is in the image as well
    and cancels; M measures the motion against the image frame, the frame the localizer's maps
    are in (gain differences between moves and raster lines, e.g. the compensation residual
    of short moves). The absolute coupling and rotation need an external reference (a
    calibration grating of known orientation).

    settle (s): the rest at the first pit before the pattern is punched (see below).
    site (offset of the first pit from the range centre) and spacing default to SITE and
    SPACING on a 110 um scanner, the same fractions of a smaller one's range (experiment.
    range_scale; the spacing not below MIN_SPACING, a few pit widths)."""
    limits = instrument.limits
    scale = range_scale(instrument)
    site = SITE * scale if site is None else site
    if spacing is None:
        spacing = max(MIN_SPACING, SPACING * min(1.0, scale))
    grid = checks.count("grid", grid, 2, 20)
    spacing = checks.positive("spacing", spacing, "m", upper=10e-6)
    force = indent_force(instrument, force)
    origin = range_centre(instrument) + np.asarray(site, float)
    commands = np.array(
        [
            origin + spacing * np.array([i if j % 2 == 0 else grid - 1 - i, j])
            for j in range(grid)
            for i in range(grid)
        ]
    )
    check_box(
        "scanner-matrix grid",
        instrument,
        commands.min(axis=0) - 0.5e-6,
        commands.max(axis=0) + BEYOND_CHECKED * scale,
        f"pass a site nearer the centre (now {site[0]:.3g}, {site[1]:.3g} m) or a smaller grid "
        f"x spacing ({grid} x {spacing:.3g} m): afm calibrate --set scanner_matrix.spacing=VALUE",
    )
    # Come from beyond the far corner, so every move of the pattern is a short move after a
    # reversal, as in manipulation (the compensated gain of a short move after a reversal
    # differs from that of a long monotone run by the model error of the feed-forward).
    beyond = commands.max(axis=0) + BEYOND * scale
    instrument.move_tip(float(beyond[0]), float(beyond[1]), 0.5 * limits.max_speed)
    # Then to the first pit and rest there: the creep of the moves before (the approach, the
    # earlier experiments' full-range cycles) still runs while the rows are punched one after
    # another along y, and shifts the later rows along the last long move: issue 37's y gains
    # of 0.92-0.95 in full runs (creep 1.5-3x). Simulator, creep 3x, a 45 um move before: y
    # 0.967 from above, 1.026 from below; after settle 300 s at the first pit 0.987 from
    # either (creep 1.5x: 0.991 -> 0.996); the rest is the grid's own steps' creep.
    instrument.move_tip(float(commands[0][0]), float(commands[0][1]), 0.1 * limits.max_speed)
    wait(instrument, checks.finite("settle", settle))
    for x, y in commands:
        punch_at(instrument, float(x), float(y), 0.1 * limits.max_speed, force)
    # Imaged with the slow axis up and then down, positions averaged: the slow axis of one
    # pass is stretched by whatever moves the sample against the scanner while it runs (the
    # creep of the moves before it, the drift), and a rescan of the 5 um grid takes minutes;
    # the down pass is stretched the other way, so the mean cancels the part linear in time
    # (simulator, a 45 um move before the grid: y gain 0.938 -> 0.968 with creep 3x, 0.989 ->
    # 0.998 with 1x; x 1.00).
    images = []
    for slow_up in (True, False):
        scan = rescan(
            instrument,
            commands.min(axis=0) - 0.5e-6,
            commands.max(axis=0) + 0.5e-6,
            pixel,
            slow_axis=1,
            slow_up=slow_up,
        )
        detected = find_pits(scan)
        found = np.array([[p.x, p.y] for p in detected]).reshape(-1, 2)
        index = match_points(commands, found, 0.3 * spacing)
        placed = np.full(commands.shape, np.nan)
        placed[index >= 0] = found[index[index >= 0]]
        images.append(placed)
    imaged = np.mean(images, axis=0)
    ok = np.all(np.isfinite(imaged), axis=1)
    if ok.sum() < 4:
        raise RuntimeError(
            f"scanner matrix: only {int(ok.sum())} of {len(commands)} pits found in both rescans"
        )
    design = np.hstack([commands[ok] - origin, np.ones((int(ok.sum()), 1))])
    solution, *_ = np.linalg.lstsq(design, imaged[ok] - origin, rcond=None)
    matrix = solution[:2].T
    residual = imaged[ok] - origin - design @ solution
    # standard errors of the matrix entries: per output axis s^2 (X^T X)^-1, s^2 the residual
    # variance of that axis per degree of freedom (three parameters per axis)
    dof = max(1, int(ok.sum()) - 3)
    unscaled = np.diag(np.linalg.pinv(design.T @ design))[:2]
    sigma = np.sqrt(np.outer(np.sum(residual**2, axis=0) / dof, unscaled))
    return Experiment(
        {
            "scanner_matrix": matrix.tolist(),
            "scanner_matrix_sigma": sigma.tolist(),
            "rms_residual": float(np.sqrt(np.mean(residual**2))),
            # the longest commanded displacement the fit covers (MotionModel: M's reach)
            "span": float(np.max(np.ptp(commands[ok], axis=0))),
        },
        {
            "commanded": commands[ok].tolist(),
            "imaged": imaged[ok].tolist(),
            "imaged_per_rescan": [image[ok].tolist() for image in images],
        },
    )
