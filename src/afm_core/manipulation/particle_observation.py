"""Where the tip and a pushed particle are between strokes, from local scan lines (book 2.2.3,
5.2.3, 7.3): the observation half of closed-loop pushing (`afm_core.manipulation.closed_loop`).

`TipTrack` follows the tip in the task frame through every command the closed loop sends, with
the calibrated motion model (`afm_core.localization.motion.MotionModel` on the images' gain,
`Calibration.image_matrix`, creep, mean drift; free moves add the positioning noise
sigma^2 = a d + b per axis, book eq. 5.5, a local scan line only its deflection error). It
starts from the tip's localization on the particle and is corrected by scan lines across a
landmark that did not move (`observe_particle`).

Why a static landmark: a free move's positioning error is persistent, so the particle, pushed
by the tip, carries the tip's accumulated error, and a scan line across the particle alone sees
the particle where the commands put it: the error cancels. Only a landmark that stayed where
the map has it ties the tip back to the task frame. The observation is therefore a chain of
local scan lines, each starting where the last ended (a line is a ramp, not a repositioning:
the only free moves are of zero length): across the anchor in x and y, a transit line to the
particle, across the particle in x and y. The crossings of the anchor correct the track (a
Kalman update at the crossing's moment, carried to now by the known motion since); the
particle's centre is the track at the particle's crossings. Without an anchor in reach the
particle lines still run, and the estimate keeps the track's uncertainty (the stop rule then
cannot claim more than it knows).

The crossing of a line (eq. 5.10): the midpoint of the rising and falling half-height
crossings (`find_crossings`); its variance: the line's height noise over the profile's slope at
each crossing, halved by the midpoint, plus the calibration's scan-region error.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from afm_core.instrument import Instrument, LineRequest, check_in_range
from afm_core.localization.calibration.model import Calibration
from afm_core.localization.landmark_observation import (
    DEFAULT_THRESHOLD_FRACTION,
    MIN_EDGE_SAMPLES,
    MapLandmark,
    find_crossings,
    line_noise,
    line_threshold,
)
from afm_core.localization.localizer import LINE_SPEED, MOVE_SPEED, SAMPLE_SPACING
from afm_core.localization.motion import MotionModel

# a line reaches this far beyond the landmark's dilated edge plus 3 sigma of where the tip and
# the landmark may be: the line's first and last 10 % must lie on the substrate (its level)
LINE_MARGIN = 50e-9  # m
LINE_SIGMAS = 3.0
# an anchor farther than this from the particle is not used: the transit line's deflection
# and creep errors grow with its length, and a far landmark is as likely to have been moved
ANCHOR_REACH = 3e-6  # m


@dataclass
class TipTrack:
    """The tip's task-frame estimate (mean, covariance) now, carried through every motion the
    instrument made since the fix by the motion model. `lines`: local scan lines run."""

    calibration: Calibration
    instrument: Instrument
    mean: np.ndarray
    covariance: np.ndarray
    # true displacement per commanded one for aiming a stroke (the calibration's scanner
    # matrix: short moves after a reversal); None: the calibration's
    aim_matrix: np.ndarray | None = None
    model: MotionModel = field(init=False)
    lines: int = 0

    def __post_init__(self):
        self.mean = np.asarray(self.mean, float).copy()
        self.covariance = np.asarray(self.covariance, float).copy()
        aim = self.calibration.scanner_matrix if self.aim_matrix is None else self.aim_matrix
        self.aim_inverse = np.linalg.inv(np.asarray(aim, float))
        # the track's positions are the chain's (observe_particle): reached through the
        # reversals of local scan lines, they sit on the images' hysteresis branch, so its
        # displacements have the images' gain, not the short move's after a reversal (the
        # scanner matrix: 1.4 % more in y on the simulated instrument, which put every 500 nm
        # push's observed displacement ~8 nm beyond the truth in the maps' frame)
        frame = replace(self.calibration, scanner_matrix=self.calibration.image_matrix)
        self.model = MotionModel(frame, self.instrument.commanded_position(), self.instrument.time)

    @property
    def sigma(self) -> float:
        return float(math.sqrt(max(np.linalg.eigvalsh(self.covariance).max(), 0.0)))

    def _step(self, kind: str, command, until: float, systematic: bool = False) -> None:
        if until > self.model.time and tuple(command) == self.model.command:
            kind = "hold"
        step = self.model.move(command[0], command[1], max(0.0, until - self.model.time), kind)
        self.mean = self.mean + step.mean
        if not systematic:
            self.covariance = self.covariance + step.covariance

    def to_command(self, point) -> np.ndarray:
        """The command that brings the tip to task point `point`, linearised about now."""
        here = np.array(self.instrument.commanded_position(), float)
        return here + self.aim_inverse @ (np.asarray(point, float) - self.mean)

    def move(self, command, speed: float, contact: bool = False, should_stop=None):
        """A free move (`Instrument.move_tip`), tracked."""
        started = self.instrument.time
        self._step("hold", self.model.command, started)
        result = self.instrument.move_tip(
            float(command[0]), float(command[1]), speed, contact=contact, should_stop=should_stop
        )
        self._step("move", self.instrument.commanded_position(), self.instrument.time)
        return result

    def ramp(self, command, speed: float | None = None, samples: int = 2, should_stop=None):
        """A local scan line from the current command to `command` (tracked; no positioning
        noise but its deflection error). Returns the ScanLineData, or None for no distance."""
        here = self.instrument.commanded_position()
        if math.hypot(command[0] - here[0], command[1] - here[1]) < 1e-12:
            return None
        check_in_range("line end", float(command[0]), float(command[1]), self.instrument.limits)
        speed = LINE_SPEED.default if speed is None else speed
        request = LineRequest(
            here[0], here[1], float(command[0]), float(command[1]), samples, speed
        )
        self._step("hold", self.model.command, self.instrument.time)
        line = self.instrument.local_scan(request, should_stop=should_stop)
        self.lines += 1
        # a ramp's deflection error is the scanner's rotation and coupling, the same for every
        # ramp along the same way: it cancels between the anchor's measurement from the particle
        # and the way back (observe_particle adds what is left, over the displacement)
        self._step("line", (request.end_x, request.end_y), self.instrument.time, systematic=True)
        return line

    def at_line_sample(self, line, index: float) -> tuple[np.ndarray, np.ndarray, float]:
        """The estimate (mean, covariance, time) at fractional sample `index` of the line just
        run (the track is at its end): the motion model re-run on a copy from the line's start."""
        samples = np.arange(len(line.x))
        command = (
            float(np.interp(index, samples, line.x)),
            float(np.interp(index, samples, line.y)),
        )
        time = float(line.start_time + np.interp(index, samples, line.times))
        end_time = float(line.start_time + line.times[-1])
        whole = (float(line.x[-1]), float(line.y[-1]))
        # the line's own step from its start, and to the sample: the difference is what the
        # track must take back
        full, part = self._line_start.copy(), self._line_start.copy()
        full_step = full.move(*whole, max(0.0, end_time - full.time), "line")
        part_step = part.move(*command, max(0.0, time - part.time), "line")
        # the line's deflection is systematic (scan): the covariance is the end's
        return self.mean - full_step.mean + part_step.mean, self.covariance.copy(), time

    def scan(self, start, end, should_stop=None):
        """A measuring line from `start` to `end` (commands): a ramp to its start, then the
        line with samples every SAMPLE_SPACING; the model's state at the line's start is kept
        for `at_line_sample`."""
        self.ramp(start, MOVE_SPEED.default, should_stop=should_stop)
        length = math.hypot(end[0] - start[0], end[1] - start[1])
        samples = int(
            min(self.instrument.limits.max_line_samples, length / SAMPLE_SPACING.default)
        )
        self._step("hold", self.model.command, self.instrument.time)
        self._line_start = self.model.copy()
        check_in_range("line end", float(end[0]), float(end[1]), self.instrument.limits)
        request = LineRequest(
            float(start[0]),
            float(start[1]),
            float(end[0]),
            float(end[1]),
            max(samples, 16),
            LINE_SPEED.default,
        )
        line = self.instrument.local_scan(request, should_stop=should_stop)
        self.lines += 1
        # a measuring line is a ramp of the same shape at every observation (see ramp)
        self._step("line", (request.end_x, request.end_y), self.instrument.time, systematic=True)
        return line

    def reset(self, axis: int, value: float, variance: float, at_mean, at_cov) -> None:
        """The tip's `axis` coordinate was `value` (variance) when the estimate was (at_mean,
        at_cov): the estimate then is replaced on that axis, and carried to now (the motion
        since is independent of it). A reset, not a Kalman update: the anchor's error is the
        same at every observation, so fusing it with the track as if it were fresh would let
        the track's error leak into every later estimate."""
        shift = np.zeros(2)
        shift[axis] = value - float(at_mean[axis])
        self.mean = self.mean + shift
        then = np.array(at_cov, float)
        then[axis, :] = then[:, axis] = 0.0
        then[axis, axis] = variance
        self.covariance = self.covariance - np.asarray(at_cov, float) + then


@dataclass
class Crossing:
    ok: bool
    reason: str = ""
    index: float = math.nan
    variance: float = math.nan  # m^2, of the centre's position along the line


def crossing(
    line, landmark: MapLandmark, scan_region_sigma: float, margin: float | None = None
) -> Crossing:
    """Where the line passed the landmark's centre (module docstring). margin: the Schmitt
    trigger's (`find_crossings`; None: its default)."""
    h = np.asarray(line.height, float)
    n = h.size
    if not line.complete or n < 2 * MIN_EDGE_SAMPLES + 2 or not np.isfinite(h).all():
        return Crossing(False, "the line was not completed or has no usable samples")
    _, threshold = line_threshold(h, landmark.apparent_height, DEFAULT_THRESHOLD_FRACTION)
    pairs, reason = find_crossings(h, threshold, margin=margin)
    if not pairs:
        return Crossing(False, reason)
    rising, falling = pairs[0]
    spacing = float(np.hypot(line.x[1] - line.x[0], line.y[1] - line.y[0]))
    slope = np.abs(np.gradient(h, spacing))
    noise = line_noise(h)
    variance = scan_region_sigma**2
    for index in (rising, falling):
        s = max(float(np.interp(index, np.arange(n), slope)), 1e-3)
        variance += 0.25 * (noise / s) ** 2
    return Crossing(True, "", 0.5 * (rising + falling), variance)


def line_half_length(track: TipTrack, mark: MapLandmark, tip_radius: float) -> float:
    spread = math.sqrt(max(np.linalg.eigvalsh(mark.covariance).max(), 0.0))
    return mark.radius + tip_radius + LINE_SIGMAS * math.hypot(track.sigma, spread) + LINE_MARGIN


def scan_across(track: TipTrack, mark: MapLandmark, axis: int, sign: float, tip_radius, stop):
    """A line across `mark` along `axis` (sign: its direction); (Crossing, estimate and
    covariance of the tip at the crossing)."""
    e = np.eye(2)[axis] * sign * line_half_length(track, mark, tip_radius)
    start, end = track.to_command(mark.position - e), track.to_command(mark.position + e)
    line = track.scan(start, end, stop)
    found = crossing(line, mark, track.calibration.scan_region_sigma)
    if not found.ok:
        return found, None, None
    mean, cov, _ = track.at_line_sample(line, found.index)
    return found, mean, cov


def measure_anchor(
    track: TipTrack, anchor: MapLandmark, towards, tip_radius: float, should_stop=None
) -> MapLandmark | None:
    """The anchor where the track (fresh from the localization on the particle) sees it: the
    reference later observations reset the track to. Relative to the particle's own start, the
    map's error of the anchor and the chain's systematic errors cancel in the displacement.
    None when a line missed it."""
    away = np.sign(np.asarray(towards, float) - anchor.position)
    away[away == 0] = 1.0
    position, variances = anchor.position.copy(), [0.0, 0.0]
    for axis in (0, 1):
        found, mean, cov = scan_across(
            track, anchor, axis, float(away[axis]), tip_radius, should_stop
        )
        if not found.ok:
            return None
        position[axis] = float(mean[axis])
        variances[axis] = float(cov[axis, axis]) + found.variance
    return MapLandmark(
        float(position[0]),
        float(position[1]),
        np.diag(variances),
        anchor.radius,
        anchor.kind,
        anchor.height,
        anchor.orientation,
        anchor.half_width,
        anchor.id,
    )


@dataclass
class ParticleObservation:
    ok: bool
    mean: np.ndarray  # (2,) task frame
    covariance: np.ndarray  # (2, 2)
    anchor_id: int  # -1: no anchor (the track alone placed the particle)
    note: str  # what was observed, for the feedback


def choose_anchor(
    landmarks: Mapping[int, object], particle_id: int, near, goal, half_length: float
) -> MapLandmark | None:
    """The sphere in the map nearest `near` (the particle's predicted centre) within
    ANCHOR_REACH whose lines stay clear of the particle and its goal; None: no anchor."""
    best, best_d = None, ANCHOR_REACH
    for mark in landmarks.values():
        if mark.id == particle_id or mark.kind != "sphere":
            continue
        centre = np.array([mark.x, mark.y])
        clear = half_length + 2 * mark.radius
        if min(np.hypot(*(centre - near)), np.hypot(*(centre - goal))) < clear:
            continue
        d = float(np.hypot(*(centre - near)))
        if d < best_d:
            best, best_d = mark, d
    return None if best is None else MapLandmark.from_landmark(best)


def reset_on_anchor(
    track: TipTrack, anchor: MapLandmark | None, towards, tip_radius: float, should_stop=None
) -> list[str]:
    """Lines across the anchor (from the side away from `towards`), each resetting the track's
    axis to where `measure_anchor` saw it; the notes say which lines were seen."""
    notes: list[str] = []
    if anchor is None:
        return notes
    away = np.sign(np.asarray(towards, float) - anchor.position)
    away[away == 0] = 1.0
    for axis in (0, 1):
        found, mean, cov = scan_across(
            track, anchor, axis, float(away[axis]), tip_radius, should_stop
        )
        if not found.ok:
            notes.append(f"anchor {anchor.id} {'xy'[axis]} line lost ({found.reason})")
            continue
        variance = float(anchor.covariance[axis, axis]) + found.variance
        track.reset(axis, float(anchor.position[axis]), variance, mean, cov)
        notes.append(f"anchor {anchor.id} {'xy'[axis]}")
    return notes


def observe_particle(
    track: TipTrack,
    particle: MapLandmark,
    anchor: MapLandmark | None,
    tip_radius: float,
    should_stop=None,
    displacement: float = 0.0,
) -> ParticleObservation:
    """Anchor lines (if any: the anchor as `measure_anchor` saw it), then lines across the
    particle's predicted centre (module docstring); the track is reset by the anchor and ends
    at the particle. displacement: how far the particle is from where the anchor was measured
    (m): the ramps' systematic deflection error over it is added to the estimate's variance."""
    notes = reset_on_anchor(track, anchor, particle.position, tip_radius, should_stop)
    deflection = math.radians(track.calibration.line_deflection_sigma_deg) * displacement
    estimate, variances, ok = particle.position.copy(), [math.nan, math.nan], True
    for axis in (0, 1):
        found, mean, cov = scan_across(track, particle, axis, 1.0, tip_radius, should_stop)
        if not found.ok:
            notes.append(f"particle {'xy'[axis]} line lost ({found.reason})")
            ok = False
            continue
        estimate[axis] = float(mean[axis])
        variances[axis] = float(cov[axis, axis]) + found.variance + deflection**2
        notes.append(f"particle {'xy'[axis]}")
    covariance = np.diag([v if math.isfinite(v) else 1e-12 for v in variances])
    return ParticleObservation(
        ok, estimate, covariance, -1 if anchor is None else anchor.id, ", ".join(notes)
    )
