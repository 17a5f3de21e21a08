"""Effects outside the sim2real library, injected into recorded operations after the fact
(post-processing the measurements), so the diagnosis cannot know how they were made. Each
returns new operations; the truth is the function and its arguments."""

from __future__ import annotations

import dataclasses
import math

import numpy as np


def _raster_pixels(data):
    """(times s, x m, y m) of every pixel of a raster (the trace half of each line period)."""
    h = np.asarray(data.height)
    ny, nx = h.shape
    fast_is_x = data.scan_angle_deg == 0.0
    n_fast = nx if fast_is_x else ny
    dt = 0.5 * data.line_period / n_fast
    starts = np.nan_to_num(np.asarray(data.line_start_times, float))
    rows, cols = np.mgrid[0:ny, 0:nx]
    line, fast = (rows, cols) if fast_is_x else (cols, rows)
    t = data.start_time + starts[line] + fast * dt
    x = data.origin_x + (cols + 0.5) * data.pixel_size_x
    y = data.origin_y + (rows + 0.5) * data.pixel_size_y
    return t, x, y


def add_to_heights(ops, offset):
    """Every measured height (rasters, scan lines) plus offset(t, x, y) (m)."""
    out = []
    for op in ops:
        data = op.data
        if op.kind == "raster" and data is not None:
            t, x, y = _raster_pixels(data)
            height = (np.asarray(data.height, float) + offset(t, x, y)).astype(np.float32)
            op = dataclasses.replace(op, data=dataclasses.replace(data, height=height))
        elif op.kind == "scan_line" and data is not None:
            t = data.start_time + np.asarray(data.times, float)
            x, y = np.asarray(data.x, float), np.asarray(data.y, float)
            height = np.asarray(data.height, float) + offset(t, x, y)
            op = dataclasses.replace(op, data=dataclasses.replace(data, height=height))
        out.append(op)
    return out


def add_to_torsion(ops, offset):
    """Every push trace's torsion plus offset(t, x, y) (rad)."""
    out = []
    for op in ops:
        data = op.data
        if op.kind == "push" and data is not None:
            t = data.start_time + np.asarray(data.times, float)
            torsion = np.asarray(data.lateral_torsion, float) + offset(
                t, np.asarray(data.commanded_x, float), np.asarray(data.commanded_y, float)
            )
            op = dataclasses.replace(op, data=dataclasses.replace(data, lateral_torsion=torsion))
        out.append(op)
    return out


def thermal_bending(rate):
    """The cantilever bends slowly as it warms: the whole z signal moves by rate (m/s) x t."""
    return lambda t, x, y: rate * np.asarray(t, float)


def z_pickup_with_x(amplitude, period, phase=0.0):
    """A pickup on the z sensor periodic in the scanner's x position."""
    return lambda t, x, y: amplitude * np.sin(2 * math.pi * np.asarray(x, float) / period + phase)


def z_settling(level, time_constant):
    """The cantilever settles thermally after power-on: the whole z signal moves by
    level (1 - exp(-t / time_constant)) (m)."""
    return lambda t, x, y: level * (1 - np.exp(-np.asarray(t, float) / time_constant))


def z_jump(size, at):
    """The z signal jumps by `size` at time `at` (a tip picking up debris, a cable moved)."""
    return lambda t, x, y: size * (np.asarray(t, float) >= at)


def torsion_drift(rate):
    """The torsion signal's zero drifts linearly in time (rad/s)."""
    return lambda t, x, y: rate * np.asarray(t, float)


def map_heights(ops, transform):
    """Every measured height h (rasters, scan lines) replaced by transform(h) (m): a z sensor
    whose reading is not linear in the height."""
    out = []
    for op in ops:
        data = op.data
        if op.kind in ("raster", "scan_line") and data is not None:
            height = np.asarray(data.height)
            moved = transform(np.asarray(height, float)).astype(height.dtype)
            op = dataclasses.replace(op, data=dataclasses.replace(data, height=moved))
        out.append(op)
    return out


def z_offset_by_scan_direction(ops, size):
    """Every local scan line scanned along +x (+y for a line closer to y) reads size / 2 (m)
    higher, every one scanned back size / 2 lower: trace and retrace differ by `size`
    (feedback lag on a tilt, a tilted tip). Images keep their heights (they record the trace
    only, where the offset is one constant)."""
    out = []
    for op in ops:
        data = op.data
        if op.kind == "scan_line" and data is not None:
            dx, dy = op.end[0] - op.start[0], op.end[1] - op.start[1]
            forward = (dx if abs(dx) >= abs(dy) else dy) > 0
            height = np.asarray(data.height, float) + (0.5 if forward else -0.5) * size
            op = dataclasses.replace(op, data=dataclasses.replace(data, height=height))
        out.append(op)
    return out
