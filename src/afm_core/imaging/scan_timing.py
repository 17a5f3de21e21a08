"""When each pixel of a raster scan was acquired (the per-line time model of the drift
methods), and the checks that a scan, or a pair of scans of the same area, carries what the
drift methods need.

A scan's lines start at its line_start_times (from start_time); a line's trace takes the first
half of the line period, so pixel k of n along the fast axis is taken (k + 0.5) / n of it
later. Fractional lines are interpolated between line starts, and extrapolated beyond the
first and last line.
"""

from __future__ import annotations

import math

import numpy as np

from afm_core import checks
from afm_core.instrument import RasterScanData


def extrapolating_interp(x, fp):
    """Linear interpolation of fp (given at 0, 1, ..., n - 1) at x, extrapolated beyond."""
    x = np.asarray(x, float)
    n = len(fp)
    i = np.clip(np.floor(x).astype(int), 0, n - 2)
    return fp[i] + (fp[i + 1] - fp[i]) * (x - i)


def pixel_times(scan: RasterScanData, rows, cols):
    """Instrument-clock time (s) at which (fractional) pixel (row, col) was acquired: the line's
    start plus the trace time to the pixel (the trace is the first half of the line period)."""
    ny, nx = np.shape(scan.height)
    rows, cols = np.broadcast_arrays(np.asarray(rows, float), np.asarray(cols, float))
    line, k, n_fast = (rows, cols, nx) if scan.scan_angle_deg == 0.0 else (cols, rows, ny)
    t_line = extrapolating_interp(line, np.asarray(scan.line_start_times, float))
    return scan.start_time + t_line + (k + 0.5) * 0.5 * scan.line_period / n_fast


def check_scan(name: str, scan: RasterScanData) -> None:
    """A complete 0 or 90 deg scan with one finite start time per line (errors name the field)."""
    h = np.asarray(scan.height)
    if h.ndim != 2 or min(h.shape) < 16:
        raise ValueError(
            f"{name}.height: shape {h.shape}; need a 2-D image of at least 16 x 16 pixels"
        )
    bad = int(np.count_nonzero(~np.isfinite(h)))
    if bad:
        raise ValueError(
            f"{name}.height: {bad} NaN/inf pixels (incomplete scan?); drift compensation needs "
            f"a complete image"
        )
    if scan.scan_angle_deg not in (0.0, 90.0):
        raise ValueError(f"{name}.scan_angle_deg={scan.scan_angle_deg}: must be 0 or 90")
    lines = h.shape[0] if scan.scan_angle_deg == 0.0 else h.shape[1]
    times = np.asarray(scan.line_start_times, float)
    if times.shape != (lines,) or not np.all(np.isfinite(times)):
        raise ValueError(f"{name}.line_start_times: need {lines} finite times (one per line)")
    for attr, unit in (("pixel_size_x", "m"), ("pixel_size_y", "m"), ("line_period", "s")):
        checks.positive(f"{name}.{attr}", getattr(scan, attr), unit)
    for attr, unit in (("origin_x", "m"), ("origin_y", "m"), ("start_time", "s")):
        checks.finite(f"{name}.{attr}", getattr(scan, attr), unit)


def check_same_area(a: RasterScanData, b: RasterScanData, name_b: str) -> None:
    """Scan b has scan a's pixels over the same area (errors name b's field)."""
    if np.shape(a.height) != np.shape(b.height):
        raise ValueError(
            f"{name_b}.height: shape {np.shape(b.height)} differs from {np.shape(a.height)}; "
            f"both scans must have the same pixels"
        )
    for attr in ("pixel_size_x", "pixel_size_y"):
        if not math.isclose(getattr(a, attr), getattr(b, attr), rel_tol=1e-6):
            raise ValueError(
                f"{name_b}.{attr}={getattr(b, attr):.6e}: differs from {getattr(a, attr):.6e}; "
                f"both scans must cover the same area"
            )
    for attr, pix in (("origin_x", a.pixel_size_x), ("origin_y", a.pixel_size_y)):
        if abs(getattr(a, attr) - getattr(b, attr)) > 1e-3 * pix:
            raise ValueError(
                f"{name_b}.{attr}={getattr(b, attr):.6e}: differs from {getattr(a, attr):.6e}; "
                f"both scans must cover the same area"
            )
