"""Control points from the substrate: the before and after images registered band by band.

`verify_push` fits the offset between the images as c + v * elapsed (the drift's velocity v
times the time between the two images' passes), which needs control points whose elapsed times
differ. The corner pits are chosen farthest from the push's way: for a push along the fast axis
both lie on the same rows (elapsed times 2-5 s apart), so v is not measured, and a pit next to a
static particle is not found at all. The particle is then seen ~50 s later than the control
points: at the default drift's 0.5 nm/s excursions that is 20 nm in y (default instrument,
seed 6, 700 nm along -x), at 1 nm/s 55 nm.

The substrate is a control point everywhere the push did not pass: its roughness (0.3 nm rms,
20 nm correlation on the simulator) registers a band of rows of the before image in the after
image to ~1 nm. `substrate_controls` cuts the before image into bands of `band_rows` rows,
leaves out every particle of either image (within `particle_margin` of its centre, the pushed
one's start and end included), and finds each band's shift in the after image by least squares
over integer shifts within `search` pixels of a predicted shift, refined by a parabola through
the neighbours. A band with less than half its pixels left, or whose best shift is on the search
window's edge or not a clear minimum, gives no control point. Each band is one ControlPoint of
kind "substrate" (never pushed) at its centre.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from afm_core.instrument import RasterScanData

BAND_ROWS = 16  # rows per band: 4 s of the before image at 4 lines/s, 128 nm at 8 nm pixels
SEARCH = 6  # pixels either way of the predicted shift
CLIP = 3e-9  # m: heights beyond this about the line's median (particles, pit floors) clipped
MIN_VALID = 0.5  # share of a band's pixels left after the particles are left out


def _levelled(scan: RasterScanData) -> np.ndarray:
    height = np.asarray(scan.height, float)
    height = height - np.median(height, axis=1, keepdims=True)
    return np.clip(height, -CLIP, CLIP)


def _free(scan: RasterScanData, particles: np.ndarray, margin: float) -> np.ndarray:
    """True where no particle (centres (n, 2), m) is within margin."""
    ny, nx = np.shape(scan.height)
    x = scan.origin_x + (np.arange(nx) + 0.5) * scan.pixel_size_x
    y = scan.origin_y + (np.arange(ny) + 0.5) * scan.pixel_size_y
    free = np.ones((ny, nx), bool)
    for px, py in np.asarray(particles, float).reshape(-1, 2):
        free &= np.hypot(x[None, :] - px, y[:, None] - py) > margin
    return free


def _vertex(c_minus: float, c0: float, c_plus: float) -> float | None:
    curvature = c_minus - 2 * c0 + c_plus
    if not np.isfinite(curvature) or curvature <= 0:
        return None
    return 0.5 * (c_minus - c_plus) / curvature


def band_shift(
    before: np.ndarray,
    after: np.ndarray,
    free_before: np.ndarray,
    free_after: np.ndarray,
    rows: slice,
    predicted: tuple[int, int],
    search: int = SEARCH,
) -> np.ndarray | None:
    """(dx, dy) pixels that move the band `rows` of `before` onto `after` (levelled images of
    the same grid; free_*: the pixels to compare), searched within `search` of `predicted`
    (dx, dy), or None (too few pixels, or no clear minimum inside the window)."""
    ny, nx = before.shape
    inner = slice(search + abs(predicted[0]), nx - search - abs(predicted[0]))
    if inner.stop - inner.start < 16:
        return None
    band, band_free = before[rows, inner], free_before[rows, inner]
    if band_free.mean() < MIN_VALID:
        return None
    cost = {}
    for dy in range(predicted[1] - search, predicted[1] + search + 1):
        lo, hi = rows.start + dy, rows.stop + dy
        if lo < 0 or hi > ny:
            continue
        for dx in range(predicted[0] - search, predicted[0] + search + 1):
            cols = slice(inner.start + dx, inner.stop + dx)
            valid = band_free & free_after[lo:hi, cols]
            if valid.mean() < MIN_VALID:
                continue
            diff = band[valid] - after[lo:hi, cols][valid]
            cost[(dx, dy)] = float(np.mean((diff - diff.mean()) ** 2))
    if not cost:
        return None
    dx, dy = min(cost, key=cost.get)
    best = cost[(dx, dy)]
    sx = _vertex(cost.get((dx - 1, dy), np.nan), best, cost.get((dx + 1, dy), np.nan))
    sy = _vertex(cost.get((dx, dy - 1), np.nan), best, cost.get((dx, dy + 1), np.nan))
    if sx is None or sy is None:
        return None  # on the window's edge, or flat: no clear minimum
    return np.array([dx + sx, dy + sy])


def substrate_controls(
    before: RasterScanData,
    after: RasterScanData,
    particles_before: np.ndarray,
    particles_after: np.ndarray,
    predicted: Callable[[np.ndarray], np.ndarray],
    particle_margin: float,
    band_rows: int = BAND_ROWS,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """The bands' control points (module docstring): [(centre in the before image, where the
    after image has it)] (m). predicted(centre) -> the expected after - before shift (m) there.
    Nothing when the images' grids differ."""
    b, a = np.asarray(before.height), np.asarray(after.height)
    same = (
        b.shape == a.shape
        and before.scan_angle_deg == after.scan_angle_deg == 0.0
        and np.isclose(before.pixel_size_x, after.pixel_size_x)
        and np.isclose(before.pixel_size_y, after.pixel_size_y)
        and np.isclose(before.origin_x, after.origin_x)
        and np.isclose(before.origin_y, after.origin_y)
    )
    if not same:
        return []
    lb, la = _levelled(before), _levelled(after)
    fb = _free(before, particles_before, particle_margin)
    fa = _free(after, particles_after, particle_margin)
    ny, nx = b.shape
    pixel = np.array([before.pixel_size_x, before.pixel_size_y])
    out = []
    for r0 in range(0, ny - band_rows + 1, band_rows):
        rows = slice(r0, r0 + band_rows)
        centre = np.array(
            [
                before.origin_x + 0.5 * nx * pixel[0],
                before.origin_y + (r0 + 0.5 * band_rows) * pixel[1],
            ]
        )
        guess = np.asarray(predicted(centre), float) / pixel
        shift = band_shift(lb, la, fb, fa, rows, (int(round(guess[0])), int(round(guess[1]))))
        if shift is not None:
            out.append((centre, centre + shift * pixel))
    return out
