"""Where and when each height sample of a raster was taken: the commanded place of the pixel's
centre, on the instrument clock. Apart so the modules that read samples (generic_forms.py,
height_spectrum.py) share it without importing each other's machinery (an import cycle
otherwise: the reference session collects the samples as the recording streams past)."""

from __future__ import annotations

import numpy as np


def raster_samples(data) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, x, y) of every pixel of a RasterScanData, shaped like its height: the commanded
    place of the pixel's centre, at start_time + line_start_times[line] + (k + 1) dt, k its
    index along the fast axis, dt = line_period / (2 pixels along it) (the simulator's trace:
    the first half of the line period)."""
    rows, columns = np.asarray(data.height).shape
    fast_is_x = data.scan_angle_deg == 0.0
    n_fast = columns if fast_is_x else rows
    dt = data.line_period / (2 * n_fast)
    r, c = np.meshgrid(np.arange(rows), np.arange(columns), indexing="ij")
    line, k = (r, c) if fast_is_x else (c, r)
    t = data.start_time + np.asarray(data.line_start_times, float)[line] + (k + 1) * dt
    x = data.origin_x + (c + 0.5) * data.pixel_size_x
    y = data.origin_y + (r + 0.5) * data.pixel_size_y
    return t, x, y
