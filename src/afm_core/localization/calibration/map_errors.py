"""Map error (book Fig. 7.10) and scan-region error (Fig. 7.11) from repeated images of the same
particles (the drift experiment's frames, drift_statistics.py).
"""

from __future__ import annotations

import numpy as np

from afm_core.imaging.landmarks import extract_landmarks
from afm_core.instrument import RasterScanData
from afm_core.localization.calibration.experiment import Experiment


def map_errors(
    frames: list[RasterScanData], lines: int = 11, min_height: float = 30e-9
) -> Experiment:
    """Map error (book Fig. 7.10) and scan-region error (Fig. 7.11) from repeated images of
    the same particles.

    Map error: in each image the particles' centres (afm_core.imaging.landmarks, centre of
    gravity over height thresholds); the image is registered on the first particle P1 (its
    centre is the control point) and the spread of P2's position relative to it over the
    images is the map sigma, per axis. Scan-region error: in each image, `lines` rows (and
    columns) through P2 within +-0.5 of its apparent radius stand in for real-time local scan
    lines; on each the particle centre is the midpoint of the two half-height crossings
    (eq. 5.10); the spread of those against the image's own centre of P2, pooled over rows
    and columns, is the scan-region sigma."""
    if len(frames) < 3:
        raise ValueError(f"frames: {len(frames)} images; need at least 3")
    relative, region = [], []
    reference = None
    for scan in frames:
        height = np.asarray(scan.height, float)
        marks = extract_landmarks(
            height,
            scan.pixel_size_x,
            scan.pixel_size_y,
            scan.origin_x,
            scan.origin_y,
            min_height=min_height,
        )
        if len(marks) < 2:
            continue
        # relative to the frame's centre: the frames follow the drifting particles, so that is
        # where the same particle is found again
        frame_centre = [
            scan.origin_x + 0.5 * height.shape[1] * scan.pixel_size_x,
            scan.origin_y + 0.5 * height.shape[0] * scan.pixel_size_y,
        ]
        points = np.array([[m.x, m.y] for m in marks]) - frame_centre
        if reference is None:
            reference = points[:2].copy()
        nearest = [int(np.argmin(np.linalg.norm(points - r, axis=1))) for r in reference]
        if nearest[0] == nearest[1]:
            continue
        p1, p2 = marks[nearest[0]], marks[nearest[1]]
        relative.append([p2.x - p1.x, p2.y - p1.y])
        level = np.median(height)
        top = level + 0.5 * p2.height
        row0 = (p2.y - scan.origin_y) / scan.pixel_size_y - 0.5
        col0 = (p2.x - scan.origin_x) / scan.pixel_size_x - 0.5
        reach_rows = 0.5 * p2.half_width / scan.pixel_size_y
        reach_cols = 0.5 * p2.half_width / scan.pixel_size_x
        for offset in np.linspace(-1.0, 1.0, lines):
            row = int(round(row0 + offset * reach_rows))
            col = int(round(col0 + offset * reach_cols))
            if 0 <= row < height.shape[0]:
                mid = _crossing_midpoint(height[row], top, col0)
                if mid is not None:
                    region.append((mid - col0) * scan.pixel_size_x)
            if 0 <= col < height.shape[1]:
                mid = _crossing_midpoint(height[:, col], top, row0)
                if mid is not None:
                    region.append((mid - row0) * scan.pixel_size_y)
    relative = np.array(relative)
    if len(relative) < 3:
        raise ValueError(f"frames: two particles found in only {len(relative)} images; need 3")
    region = np.array(region)
    return Experiment(
        {
            "map_sigma": relative.std(axis=0, ddof=1).tolist(),
            "scan_region_sigma": float(region.std(ddof=1)) if len(region) > 1 else float("nan"),
        },
        {"relative_position": relative.tolist(), "region_offsets": region.tolist()},
    )


def _crossing_midpoint(profile: np.ndarray, level: float, near: float) -> float | None:
    """Midpoint (fractional index) of the two crossings of `level` around index `near`
    (eq. 5.10)."""
    above = profile > level
    centre = int(round(near))
    if not (0 <= centre < profile.size) or not above[centre]:
        return None
    left = centre
    while left > 0 and above[left - 1]:
        left -= 1
    right = centre
    while right < profile.size - 1 and above[right + 1]:
        right += 1
    if left == 0 or right == profile.size - 1:
        return None
    # linear interpolation of each crossing between the pixel below and the one above the level
    x_left = left - 1 + (level - profile[left - 1]) / (profile[left] - profile[left - 1])
    x_right = right + (profile[right] - level) / (profile[right] - profile[right + 1])
    return 0.5 * (x_left + x_right)
