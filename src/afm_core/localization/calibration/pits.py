"""Indentation pits in a raster image: where the tip punched them, to sub-pixel precision.

The calibration experiments of book 7.2.2 record where the tip was by punching a pit
(Fig. 7.6a, 7.7a, 7.12a) and find the pits again in a rescan. A pit is a small depression
(the simulator's: a paraboloid dent about as wide as the tip apex, ~40 nm radius, up to
20 nm deep), so the detector works on the depth below the local substrate:

1. Substrate: per-line median first (line offsets of the 1/f height noise), then a grey
   closing (a maximum then a minimum filter) wider than a pit: it fills depressions
   narrower than its window and leaves the substrate, so depth = closing - height >= 0.
2. Pits: connected regions (8-neighbour) deeper than max(min_depth, 6 robust sigmas of
   the depth noise) of at least MIN_PIT_PIXELS pixels; regions touching the image border (part
   of the pit outside, centre biased) or wider than max_radius (not a pit: an edge of a
   particle, a scratch) are left out.
3. Centre: a rotationally symmetric paraboloid z = a + b x + c y + d (x^2 + y^2) fitted by
   linear least squares to the pixels deeper than a third of the pit's depth; near its
   bottom the imaged pit is the pit itself (the apex is sharper than the dent), which is a
   paraboloid, so the fit has no model bias; x0 = -b / (2 d), y0 = -c / (2 d). With fewer
   than 5 such pixels (coarse images) the depth-weighted centroid is used instead.

Coordinates are the image's, i.e. the commanded scanner frame of the rescan (pixel centres at
origin + (index + 0.5) * pixel size): the calibration compares them with the commands that
punched the pits. `time` is when the rescan imaged the pit's centre (instrument clock).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from afm_core import checks
from afm_core.imaging.scan_timing import pixel_times
from afm_core.instrument import RasterScanData

NOISE_SIGMAS = 6.0  # detection threshold in robust sigmas of the depth noise
FIT_DEPTH_FRACTION = (
    1 / 3
)  # paraboloid fitted to the pixels deeper than this fraction of the pit's depth
MIN_FIT_PIXELS = 5
MIN_PIT_PIXELS = (
    3  # smaller regions are noise (a pit spans several pixels at the pixel sizes used)
)


@dataclass(frozen=True)
class DetectedPit:
    x: float  # m, image (commanded scanner) frame
    y: float  # m
    depth: float  # m, below the local substrate
    time: float  # s, instrument clock when the rescan imaged the centre
    pixels: int  # pixels above the detection threshold
    fitted: bool  # True: paraboloid fit; False: depth-weighted centroid (coarse image)


def _check(scan: RasterScanData, min_depth: float, max_radius: float) -> np.ndarray:
    height = np.asarray(scan.height, dtype=float)
    if height.ndim != 2 or min(height.shape) < 3:
        raise ValueError(
            f"scan.height: shape {height.shape}; need a 2-D image of at least 3 x 3 pixels"
        )
    bad = int(np.count_nonzero(~np.isfinite(height)))
    if bad:
        raise ValueError(
            f"scan.height: {bad} NaN/inf pixels (incomplete scan?); pit detection needs a "
            "complete image"
        )
    for name in ("pixel_size_x", "pixel_size_y"):
        checks.positive(f"scan.{name}", getattr(scan, name), "m")
    checks.non_negative("min_depth", min_depth, "m")
    checks.positive("max_radius", max_radius, "m")
    return height


def depth_map(scan: RasterScanData, max_radius: float = 150e-9) -> np.ndarray:
    """Depth below the local substrate (m, >= 0): grey closing minus the line-levelled height."""
    height = _check(scan, 0.0, max_radius)
    fast_axis = 1 if scan.scan_angle_deg == 0.0 else 0
    levelled = height - np.median(height, axis=fast_axis, keepdims=True)
    window = (
        2 * int(math.ceil(max_radius / scan.pixel_size_y)) + 1,
        2 * int(math.ceil(max_radius / scan.pixel_size_x)) + 1,
    )
    return ndimage.grey_closing(levelled, size=window) - levelled


def find_pits(
    scan: RasterScanData, min_depth: float = 5e-9, max_radius: float = 150e-9
) -> list[DetectedPit]:
    """Pits in `scan`, sorted by time of imaging. min_depth (m): shallower depressions are not
    pits; max_radius (m): a larger apparent radius is not a pit (the closing window is twice
    it)."""
    height = _check(scan, min_depth, max_radius)
    depth = depth_map(scan, max_radius)
    noise = 1.4826 * float(np.median(np.abs(depth - np.median(depth))))
    threshold = max(min_depth, NOISE_SIGMAS * noise)
    labels, count = ndimage.label(depth > threshold, structure=np.ones((3, 3), dtype=bool))
    px, py = scan.pixel_size_x, scan.pixel_size_y
    max_pixels = math.pi * (max_radius / px) * (max_radius / py)
    rows_total, cols_total = height.shape
    pits = []
    for index, region in enumerate(ndimage.find_objects(labels), start=1):
        if region is None:
            continue
        rows, cols = region
        if (
            rows.start == 0
            or cols.start == 0
            or rows.stop == rows_total
            or cols.stop == cols_total
        ):
            continue
        mask = labels[region] == index
        if not MIN_PIT_PIXELS <= mask.sum() <= max_pixels:
            continue
        part = np.where(mask, depth[region], 0.0)
        deepest = float(part.max())
        rr, cc = np.nonzero(part > FIT_DEPTH_FRACTION * deepest)
        rr, cc = rr + rows.start, cc + cols.start
        row, col, fitted = (
            _paraboloid_centre(height, rr, cc, px, py)
            if rr.size >= MIN_FIT_PIXELS
            else (None, None, False)
        )
        if row is None:
            weights = np.clip(part - 0.5 * threshold, 0.0, None)
            r_all, c_all = np.mgrid[rows, cols]
            row = float((weights * r_all).sum() / weights.sum())
            col = float((weights * c_all).sum() / weights.sum())
        pits.append(
            DetectedPit(
                x=scan.origin_x + (col + 0.5) * px,
                y=scan.origin_y + (row + 0.5) * py,
                depth=deepest,
                time=float(pixel_times(scan, row, col)),
                pixels=int(mask.sum()),
                fitted=fitted,
            )
        )
    return sorted(pits, key=lambda pit: pit.time)


def _paraboloid_centre(height, rr, cc, px, py):
    """(row, col) of the bottom of z = a + b x + c y + d (x^2 + y^2) fitted to the pixels, in
    physical units so unequal pixel sizes keep the pit round; None when it is no bowl or the
    bottom falls outside the fitted pixels (then the centroid is the safer answer)."""
    unit = max(px, py)  # lengths in pixels of about 1, heights in nm: a well-scaled system
    x, y = (cc - cc.mean()) * (px / unit), (rr - rr.mean()) * (py / unit)
    design = np.stack([np.ones_like(x), x, y, x * x + y * y], axis=1)
    (a, b, c, d), *_ = np.linalg.lstsq(design, height[rr, cc] * 1e9, rcond=None)
    if not d > 0:
        return None, None, False
    col = cc.mean() - b / (2 * d) * (unit / px)
    row = rr.mean() - c / (2 * d) * (unit / py)
    if not (cc.min() - 0.5 <= col <= cc.max() + 0.5 and rr.min() - 0.5 <= row <= rr.max() + 0.5):
        return None, None, False
    return float(row), float(col), True
