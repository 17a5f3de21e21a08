"""Drift velocity statistics (book 5.3.3, 7.2.2, eq. 5.32-5.36, Fig. 7.9): frame-up /
frame-down image pairs of a particle area, apart in time; each pair gives one drift velocity.
The same frames give the map error and the scan-region error (map_errors.py).
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from afm_core import checks
from afm_core.imaging.frame_up_down import up_down_observations, up_down_velocity
from afm_core.imaging.landmarks import scan_landmarks
from afm_core.instrument import ScanRequest
from afm_core.localization.calibration.experiment import (
    MAX_LINE_RATE,
    Experiment,
    StepProgress,
    check_box,
    range_centre,
    wait,
)

# The default particle area: its lower corner from the range centre, its width and height (m)
AREA = np.array([-0.9e-6, -1.15e-6, 2.0e-6, 3.0e-6])


def _particle_area(instrument, area) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = np.asarray(area[:2], float), np.asarray(area[:2], float) + np.asarray(area[2:], float)
    check_box(
        "drift area",
        instrument,
        lo,
        hi,
        "pass the area (x, y, width, height) of at least two particles within the range: afm "
        "calibrate --set drift.area=X,Y,W,H",
    )
    if not np.all(hi > lo):
        raise ValueError(f"area={area}: width and height must be > 0")
    return lo, hi


# the frame-up/down pairs measure_drift takes: one pair gives no spread
PAIRS = (2, 100000)


def check_pairs(pairs) -> int:
    """`pairs` checked against PAIRS (also by `afm calibrate` before any experiment runs)."""
    return checks.count("pairs", pairs, *PAIRS)


def measure_drift(
    instrument,
    *,
    area=None,
    pairs: int = 20,
    pixel: float = 15.625e-9,
    frame_time: float = 256.0,
    interval: float = 3600.0,
    search: float = 6e-6,
    settle: float = 300.0,
    progress=None,
) -> Experiment:
    """Drift velocity statistics (book 5.3.3, 7.2.2, Fig. 7.9): `pairs` frame-up / frame-down
    image pairs of an area with at least two particles on different lines, a pair starting
    every `interval` s (the drift velocity wanders slowly; samples closer than its
    correlation time are not independent, so the mean and sigma of a few close pairs say
    little). Each pair gives one velocity (afm_core.imaging.frame_up_down.velocity_from_up_down,
    eq. 5.35-5.36), timed at the pair's middle; it averages the velocity over the stretches of
    the two frames where the particles are imaged (about a minute each, ~280 s before and
    after the middle with the defaults), not over the whole pair, and the moments are kept per pair
    (data["particle_times"]: [t_up, t_down] lists) so it can be compared with a known drift
    (afm_core.imaging.frame_up_down.sampled_velocity). Its scale is the frames' image scale (the
    package doc, "The image frame": the compensated scanner's small-move gain).

    Before each pair a quick `search`-wide image finds the particles again (the sample
    drifts micrometres over hours), the frames are centred on them and the tip rests
    `settle` s at the frame's start: creep after a move of a few micrometres (2 % of it,
    the slowest part with a 50 s time constant) would otherwise look like a drift of tenths
    of nm/s. For the same reason the frame reaches well beyond the particles along the slow
    axis (area's height): the slow axis' own creep lag settles while the margin is scanned.
    The tip rests `settle` s before the frame down too (see there).
    The frame time is a compromise: slow frames make the particles' time separation
    T'_u + T'_d long, so the per-pair error (centroid noise / T') stays well below the
    spread being measured, but a pair averages the velocity over its length, which lowers
    the measured spread by about T_pair / (6 x correlation time) (5 % for 512 s pairs and
    1800 s). The frames are kept for the map error and scan-region error (`map_errors`).
    area (x, y, width, height; m) defaults to AREA's offset from the range centre (the
    default simulator's particles: 54.1, 53.85 um on its 110 um scanner), on any range."""
    limits = instrument.limits
    if area is None:
        area = (*(range_centre(instrument) + AREA[:2]), *AREA[2:])
    lo, hi = _particle_area(instrument, area)
    pairs = check_pairs(pairs)
    pixel = checks.positive("pixel", pixel, "m", upper=1e-6)
    frame_time = checks.positive("frame_time", frame_time, "s", upper=86400.0)
    interval = checks.positive("interval", interval, "s")
    size = hi - lo
    _frame_raster(limits, size, pixel, frame_time)  # the frame without drift must fit
    centre = 0.5 * (lo + hi)
    velocities, moments, frames, particle_times = [], [], [], []
    steps = StepProgress(progress, "drift", "frame pair", pairs, instrument)
    for k in range(pairs):
        if k:  # pairs done so far (the wait for the next pair counts to the one before)
            steps.step(k)
        start = float(instrument.time)
        centre = _find_particle_cluster(instrument, centre, search, size)
        if k == 0:  # nothing measured yet: the frame as given, unless the particles leave it
            estimate, spread = np.zeros(2), np.zeros(2)
        else:
            # the next pair's velocity is off the mean so far by the pairs' spread (once three
            # pairs show it)
            estimate = np.mean(velocities, axis=0)
            spread = np.std(velocities, axis=0, ddof=1) if k >= 3 else np.zeros(2)
        try:
            up, down, observations = _measured_pair(
                instrument, centre, size, estimate, spread, (pixel, frame_time, settle)
            )
        except ValueError:
            if k:
                raise
            # the first pair lost its particles: the drift over it, from where the search
            # finds them now, frames the pair again
            searched = float(instrument.time)
            later = _find_particle_cluster(instrument, centre, search, size)
            estimate = (later - centre) / max(searched - start, 1.0)
            spread = np.full(2, np.sqrt(2.0) * search / SEARCH_PIXELS) / (searched - start)
            centre = later
            up, down, observations = _measured_pair(
                instrument, centre, size, estimate, spread, (pixel, frame_time, settle)
            )
        velocities.append(up_down_velocity(observations))
        particle_times.append([observations.t_up.tolist(), observations.t_down.tolist()])
        moments.append(0.5 * (up.start_time + float(instrument.time)))
        frames.extend([up, down])
        if k < pairs - 1:
            wait(instrument, start + interval - float(instrument.time))
    v = np.array(velocities)
    errors = [mean_error(v[:, axis]) for axis in range(2)]
    parameters = {
        "mean_velocity": v.mean(axis=0).tolist(),
        # the spread with the pairs' correlation allowed for (mean_error), and as sampled
        "sigma_velocity": [e["sigma"] for e in errors],
        "sigma_velocity_interval95": [e["sigma_interval95"] for e in errors],
        "sample_sigma_velocity": v.std(axis=0, ddof=1).tolist(),
        "pairs": pairs,
        # the mean's sampling error with the pairs' correlation allowed for (mean_error)
        "mean_velocity_sigma": [e["standard_error"] for e in errors],
        "mean_velocity_interval95": [e["interval95"] for e in errors],
        "lag1_correlation": [e["lag1_correlation"] for e in errors],
    }
    return Experiment(
        parameters,
        {
            "time": moments,
            "velocity": v.tolist(),
            "particle_times": particle_times,
            "frames": frames,
        },
    )


# The particles move by the drift over a pair (two rests and two frames, ~1100 s with the
# defaults: 1.1 um at 1 nm/s, half the frame's width; issue 37: "only 1 particle matches").
# The frame is centred where they are at the pair's middle and widened by how far they go,
# with the velocity as measured so far: the mean of the pairs before (it wanders by their
# spread; DRIFT_Z of it, a 0.27 % chance per axis that the wander outruns the margin for a
# Gaussian velocity). The first pair has the frame as given; if its particles left it, the
# pair is taken again, framed with the drift from two search images before and after it.
DRIFT_Z = 3.0


def _measured_pair(instrument, centre, size, velocity, spread, raster) -> tuple:
    """A frame-up / frame-down pair (`_up_down_pair`) framed for the drift (`_drifting_frame`)
    and its matched particles; ValueError when fewer than two particles match."""
    pixel, frame_time, settle = raster
    limits = instrument.limits
    lo, frame = _drifting_frame(limits, centre, size, velocity, spread, settle, frame_time)
    pixels, line_rate = _frame_raster(limits, frame, pixel, frame_time)
    up, down = _up_down_pair(instrument, lo, frame, pixels, line_rate, settle)
    return up, down, up_down_observations(up, down)


def _drifting_frame(limits, centre, size, velocity, spread, settle, frame_time) -> tuple:
    """(lower corner, size) of a pair's frames: `size` widened by the particles' travel over
    the pair (|velocity| + DRIFT_Z spread, per axis) and centred where the drift puts them at
    the pair's middle, kept inside the range."""
    pair_time = 2.0 * (settle + frame_time)
    velocity, spread = np.asarray(velocity, float), np.asarray(spread, float)
    frame = np.asarray(size, float) + (np.abs(velocity) + DRIFT_Z * spread) * pair_time
    frame = np.minimum(frame, [limits.range_x, limits.range_y])
    middle = np.asarray(centre, float) + velocity * (settle + frame_time)
    lo = np.clip(middle - frame / 2, 0.0, [limits.range_x - frame[0], limits.range_y - frame[1]])
    return lo, frame


def _frame_raster(limits, size, pixel: float, frame_time: float) -> tuple[np.ndarray, float]:
    """Pixels (x, y) and line rate (Hz) of a frame of `size` (m), or ValueError when the
    instrument cannot scan it in `frame_time`."""
    pixels = np.maximum(16, np.round(size / pixel)).astype(int)
    if pixels.max() > limits.max_pixels:
        raise ValueError(
            f"pixel={pixel:.3g} m: the frame needs {pixels.max()} pixels, "
            f"above max_pixels {limits.max_pixels}"
        )
    line_rate = pixels[1] / frame_time
    if 2.0 * size[0] * line_rate > limits.max_speed or line_rate > limits.max_line_rate:
        raise ValueError(
            f"frame_time={frame_time} s: {pixels[1]} lines of {size[0]:.3g} m would exceed the "
            f"slew limit {limits.max_speed} m/s or max_line_rate {limits.max_line_rate} Hz"
        )
    return pixels, line_rate


def _up_down_pair(instrument, lo, size, pixels, line_rate, settle: float) -> tuple:
    """A frame up and a frame down of the box at `lo`, each after resting `settle` s at its
    first line."""
    limits = instrument.limits
    # rest at the middle of the first line: the fast axis then oscillates about where its
    # creep has settled (resting at the line's start, the slow creep would follow the line
    # mean for the first minutes of the frame and look like drift along x)
    instrument.move_tip(
        float(lo[0] + 0.5 * size[0]),
        float(lo[1] + 0.5 * size[1] / pixels[1]),
        0.1 * limits.max_speed,
    )
    wait(instrument, settle)
    request = dict(
        origin_x=float(lo[0]),
        origin_y=float(lo[1]),
        size_x=float(size[0]),
        size_y=float(size[1]),
        pixels_x=int(pixels[0]),
        pixels_y=int(pixels[1]),
        line_rate=float(line_rate),
    )
    up = instrument.raster_scan(ScanRequest(slow_scan_up=True, **request))
    # rest again before the frame down: it then starts from a settled creep state as the
    # frame up did, and the slow axis' creep lag builds up alike in both (mirror images),
    # so its effect on the particles' separations is the same in both frames and cancels
    # (reversing at once, the lag would swing from -L to +L during the frame down)
    instrument.move_tip(
        float(lo[0] + 0.5 * size[0]),
        float(lo[1] + size[1] - 0.5 * size[1] / pixels[1]),
        0.1 * limits.max_speed,
    )
    wait(instrument, settle)
    down = instrument.raster_scan(ScanRequest(slow_scan_up=False, **request))
    return up, down


SEARCH_PIXELS = 128  # per side of a search image (at its first, smallest size)


def _find_particle_cluster(instrument, centre, search: float, frame) -> np.ndarray:
    """Centre of the particles in a quick search image around `centre` (the middle of their
    bounding box); the search area doubles (three times at most) while none is found, and
    `centre` itself is returned when still none is."""
    limits = instrument.limits
    for attempt in range(4):
        reach = search * 2**attempt
        size = np.array([min(reach, limits.range_x), min(reach, limits.range_y)])
        lo = np.clip(
            np.asarray(centre) - size / 2,
            0.0,
            [limits.range_x - size[0], limits.range_y - size[1]],
        )
        rate = min(MAX_LINE_RATE, limits.max_line_rate, 0.95 * limits.max_speed / (2.0 * size[0]))
        pixels = int(min(limits.max_pixels, SEARCH_PIXELS * 2**attempt))
        scan = instrument.raster_scan(
            ScanRequest(
                float(lo[0]),
                float(lo[1]),
                float(size[0]),
                float(size[1]),
                pixels,
                pixels,
                line_rate=rate,
            )
        )
        marks = scan_landmarks(scan, min_height=30e-9)
        if marks:
            break
    if not marks:
        return np.asarray(centre, float)
    points = np.array([[m.x, m.y] for m in marks])
    # the cluster: the particles within a frame's reach of the one nearest the old centre
    first = points[np.argmin(np.linalg.norm(points - centre, axis=1))]
    near = points[np.all(np.abs(points - first) < np.asarray(frame) * 0.8, axis=1)]
    return 0.5 * (near.min(axis=0) + near.max(axis=0))


# The correlation of neighbouring pairs is estimated from the pairs themselves, and a few pairs
# make it small: E[r1] = rho - (1 + 4 rho) / n for an AR(1) series with an unknown mean
# (Marriott & Pope 1954, to first order in 1/n), so r1 + (1 + 4 r1) / n is used; MAX_RHO keeps
# the inflation finite when the pairs cannot tell a trend from a mean.
MAX_RHO = 0.95


def mean_error(velocities) -> dict:
    """The sampling error of the mean of `velocities` (one axis, in time order, a pair every
    `interval`), allowing for the correlation of neighbouring pairs: the drift velocity wanders
    with a correlation time (book Fig. 7.9: hours), so pairs closer than it are not
    independent and sigma / sqrt(n) understates the error (issue 37: a mean 3.9 such errors
    off the configured one). With an AR(1) model of the pairs (lag-1 correlation rho,
    bias-corrected, see MAX_RHO) the variance of the mean is s^2 f / n with
    f = 1 + 2 sum_k (1 - k/n) rho^k, the sample variance is low by (1 - (f - 1)/(n - 1)),
    and the 95 % interval uses Student's t with n/f - 1 degrees of freedom.
    Coverage of the configured mean, measured on the simulator's drift (1500 seeds x 2 axes,
    pair velocities over 560 s, correlation time 1800 s): 6 pairs 1800 s apart 0.90 (sigma /
    sqrt(n) with a normal quantile: 0.73), 3600 s apart 0.95, 20 pairs 0.93-0.96; pairs half
    a correlation time apart are under-covered, 0.82-0.85 (0.55).
    The velocity's own spread is corrected alike (`sigma`: the sample variance divided by
    that shrink), with a chi-square 95 % interval on the n/f - 1 effective degrees of freedom
    (`sigma_interval95`, [low, high]): 6 correlated pairs hold about 3 independent values.
    Returns {"standard_error", "interval95", "lag1_correlation" (the corrected rho),
    "sigma", "sigma_interval95"}."""
    v = np.asarray(velocities, float)
    n = v.size
    deviation = v - v.mean()
    spread = float(np.sum(deviation**2))
    if n < 3 or spread <= 0.0:
        sigma = float(np.std(v, ddof=1)) if n > 1 else float("nan")
        error = sigma / np.sqrt(n)
        return {
            "standard_error": error,
            "interval95": 1.96 * error,
            "lag1_correlation": 0.0,
            "sigma": sigma,
            "sigma_interval95": [float("nan"), float("nan")],
        }
    r1 = float(np.sum(deviation[1:] * deviation[:-1]) / spread)
    rho = float(np.clip(r1 + (1.0 + 4.0 * r1) / n, 0.0, MAX_RHO))
    lags = np.arange(1, n)
    inflation = 1.0 + 2.0 * float(np.sum((1.0 - lags / n) * rho**lags))
    # the sample variance about the sample mean misses the mean's own wander; floored so a
    # strongly correlated handful of pairs still gives a finite error
    shrink = max(1.0 - (inflation - 1.0) / (n - 1), 0.2)
    variance = spread / (n - 1) / shrink
    error = float(np.sqrt(variance * inflation / n))
    dof = max(n / inflation - 1.0, 1.0)
    sigma = float(np.sqrt(variance))
    return {
        "standard_error": error,
        "interval95": float(stats.t.ppf(0.975, dof)) * error,
        "lag1_correlation": rho,
        "sigma": sigma,
        "sigma_interval95": [
            sigma * float(np.sqrt(dof / stats.chi2.ppf(0.975, dof))),
            sigma * float(np.sqrt(dof / stats.chi2.ppf(0.025, dof))),
        ],
    }
