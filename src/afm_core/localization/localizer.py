"""Tip localization on an instrument, ROS-free: what the localization node calls (book 5.2-5.4).

`Localizer` keeps the motion model (`MotionModel`) and the Kalman filter (`TipFilter`) in step
with an `Instrument`: every command it sends is predicted with the time the instrument says
it took; `observe_landmark` plans local scan lines through a landmark's predicted position,
runs them, and applies each line's observation at its crossing time x_kp, then carries the
estimate to the line's end with the motion model (eq. 5.16-5.21).

Frames: the estimate, targets and landmarks are in the task frame (sample-fixed, m); the
instrument takes commanded scanner positions. The command for a task-frame target is the
motion model inverted about the current estimate (`MotionModel.command_for`).

Errors: bad inputs (non-finite values, covariances that are not positive semi-definite,
targets whose command falls outside the scanner range, a line that would claim no noise) raise
ValueError naming the field and the limit, before anything moves. A lost landmark, a gated-out
or ambiguous observation, a cancel (`should_stop`) or an instrument error during a line is
reported in the result; the estimate then still carries every motion that happened (the
localizer re-reads the instrument's command and clock).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from afm_core import checks
from afm_core.instrument import (
    Instrument,
    LineRequest,
    ScannerLimits,
    check_in_range,
    check_speed,
)
from afm_core.localization.calibration.model import Calibration
from afm_core.localization.filter import GATE, HISTORY_SECONDS, TipFilter, UpdateResult
from afm_core.localization.landmark_observation import (
    DEFAULT_THRESHOLD_FRACTION,
    LineObservation,
    MapLandmark,
    as_map_landmark,
    line_variance,
    observe_line,
)
from afm_core.localization.motion import MotionModel, MotionStep
from afm_core.parameters import Parameter, ParameterTable

LINE_SPEED = Parameter(
    "line_speed",
    1e-6,
    "Tip speed along a local scan line.",
    unit="m/s",
    minimum=0.0,
    above_minimum=True,
    maximum=ScannerLimits().max_speed,
    runtime=True,
)
MOVE_SPEED = Parameter(
    "move_speed",
    2e-6,
    "Tip speed of the free moves to a line's start.",
    unit="m/s",
    minimum=0.0,
    above_minimum=True,
    maximum=ScannerLimits().max_speed,
    runtime=True,
)
SAMPLE_SPACING = Parameter(
    "sample_spacing",
    1e-9,
    "Distance between samples of a local scan line.",
    unit="m",
    minimum=0.0,
    above_minimum=True,
    runtime=True,
)
THRESHOLD_FRACTION = Parameter(
    "threshold_fraction",
    DEFAULT_THRESHOLD_FRACTION,
    "Height threshold of a line's crossings, as a fraction of the landmark's height (book eq. "
    "5.10).",
    minimum=0.0,
    maximum=1.0,
    above_minimum=True,
    below_maximum=True,
    runtime=True,
)
MARGIN = Parameter(
    "margin",
    50e-9,
    "Substrate a line covers beyond 3 sigma and the landmark's extent, each side.",
    unit="m",
    minimum=0.0,
    runtime=True,
)
# What a Localizer takes besides its instrument, calibration and initial estimate; the
# localizer node declares these as its parameters.
LOCALIZER_PARAMETERS = ParameterTable(
    GATE, LINE_SPEED, MOVE_SPEED, SAMPLE_SPACING, THRESHOLD_FRACTION, MARGIN, HISTORY_SECONDS
)
DEFAULT_TIP_ALLOWANCE = (
    30e-9  # m, lateral tip broadening when the landmark's apparent half-width is unknown
)
# A line that misses its landmark is followed by a search (observe_landmark): parallel lines
# offset across it by one apparent half-width (the landmark then lies within half a
# half-width of one of them, where its profile still rises well above the threshold), out to
# SEARCH_SIGMAS standard deviations of the tip's and the landmark's uncertainty across the
# line, each SEARCH_LENGTH_FACTOR times as long as the first; at most MAX_SEARCH_LINES lines,
# so a landmark that is not there costs a bounded time.
# The book's order (horizontal line first, Fig. 5.11) is kept unless its first line risks
# passing beside the landmark with more than this probability and the vertical-first order
# risks less (after a long move the tip's y is often the worse known: drift is larger in y).
FIRST_LINE_RISK = 0.01
StopCheck = Callable[[], bool]
SEARCH_SIGMAS = 3.0
SEARCH_LENGTH_FACTOR = 2.0
MAX_SEARCH_LINES = 8


@dataclass
class LineResult:
    """One local scan line of a landmark observation."""

    axis: str  # "x" (horizontal line) or "y" (vertical line)
    # "accepted" | "gated_out" | "ambiguous" | "lost" | "too_old" | "instrument_error" |
    # "not_run" | "cancelled"
    status: str
    reason: str = ""
    request: LineRequest | None = None
    observation: LineObservation | None = None
    update: UpdateResult | None = None
    innovation: float = math.nan  # m, map value - predicted tip position along u at x_kp
    innovation_sigma: float = math.nan  # m, sqrt(S)
    mahalanobis: float = math.nan
    mean_at_crossing: np.ndarray | None = None  # estimate at x_kp after the update (or prediction)
    covariance_at_crossing: np.ndarray | None = None
    search: str = ""  # after a missed first try: the search lines run and what they found

    def describe(self) -> str:
        text = f"{self.axis} line {self.status}" + (f" ({self.reason})" if self.reason else "")
        return text + (f" [{self.search}]" if self.search else "")

    @property
    def accepted(self) -> bool:
        return self.status == "accepted"

    @property
    def gated_out(self) -> bool:
        return self.status == "gated_out"

    @property
    def lost(self) -> bool:
        return self.status == "lost"


@dataclass
class ObservationResult:
    """A landmark observation: its lines, and the pose after the last line's end."""

    landmark_id: int
    lines: list = field(default_factory=list)
    mean: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    covariance: np.ndarray = field(default_factory=lambda: np.full((2, 2), np.nan))
    time: float = math.nan
    instrument_error: str = ""

    @property
    def accepted(self) -> bool:
        """At least one line updated the estimate."""
        return any(line.accepted for line in self.lines)

    @property
    def all_accepted(self) -> bool:
        return bool(self.lines) and all(line.accepted for line in self.lines)

    @property
    def gated_out(self) -> bool:
        return any(line.gated_out for line in self.lines)

    @property
    def lost(self) -> bool:
        return any(line.lost for line in self.lines)

    @property
    def cancelled(self) -> bool:
        return any(line.status == "cancelled" for line in self.lines)

    def summary(self) -> str:
        """One phrase per line: its axis, verdict, reason and any search."""
        return "; ".join(line.describe() for line in self.lines)


@dataclass
class MoveOutcome:
    command: tuple  # m, commanded end point
    mean: np.ndarray  # estimate after the move
    covariance: np.ndarray
    time: float
    completed: bool


class Localizer:
    def __init__(
        self,
        instrument: Instrument,
        calibration: Calibration,
        initial_mean,
        initial_cov,
        *,
        gate: float = GATE.default,
        line_speed: float = LINE_SPEED.default,
        move_speed: float = MOVE_SPEED.default,
        sample_spacing: float = SAMPLE_SPACING.default,
        threshold_fraction: float = THRESHOLD_FRACTION.default,
        margin: float = MARGIN.default,
        history_seconds: float = HISTORY_SECONDS.default,
    ):
        """initial_mean / initial_cov: the tip's position (task frame, m) and covariance (m^2)
        now, with the instrument at rest at its current command (creep settled)."""
        self.line_speed = LINE_SPEED.validate(line_speed)
        self.move_speed = MOVE_SPEED.validate(move_speed)
        for name, value in (("line_speed", self.line_speed), ("move_speed", self.move_speed)):
            check_speed(name, value, instrument.limits)
        self.sample_spacing = SAMPLE_SPACING.validate(sample_spacing)
        self.margin = MARGIN.validate(margin)
        self.threshold_fraction = THRESHOLD_FRACTION.validate(threshold_fraction)
        self.instrument = instrument
        self.calibration = calibration
        self.model = MotionModel(calibration, instrument.commanded_position(), instrument.time)
        self.filter = TipFilter(
            initial_mean,
            initial_cov,
            instrument.time,
            gate=gate,
            history_seconds=history_seconds,
            extrapolate=self._extrapolate,
            drift_sigma=calibration.drift_sigma_velocity,
        )
        self.steps: list[MotionStep] = []  # every motion predicted (for inspection)

    # -- estimate ---------------------------------------------------------------------------------
    @property
    def mean(self) -> np.ndarray:
        return self.filter.mean

    @property
    def covariance(self) -> np.ndarray:
        return self.filter.covariance

    @property
    def time(self) -> float:
        return self.filter.time

    def at(self, time: float) -> tuple[np.ndarray, np.ndarray]:
        """Estimate (mean, covariance) at any time: history, or a hold predicted from now on."""
        return self.filter.at(time)

    def _extrapolate(self, from_time: float, to_time: float):
        trial = self.model.copy()
        if abs(trial.time - from_time) > 1e-9:
            return np.zeros(2), np.zeros((2, 2))
        step = trial.hold(to_time - from_time)
        return step.mean, step.covariance

    def _apply(self, step: MotionStep) -> None:
        self.steps.append(step)
        self.filter.predict(step.end_time, step.mean, step.covariance)

    def sync(self) -> None:
        """Predict whatever the instrument did since the last prediction: a hold if the
        command is unchanged, otherwise a free move to the new command over the elapsed time."""
        now = float(self.instrument.time)
        command = self.instrument.commanded_position()
        elapsed = max(0.0, now - self.model.time)
        if command != self.model.command:
            self._apply(self.model.move(command[0], command[1], elapsed, "move"))
        elif elapsed > 0:
            self._apply(self.model.hold(elapsed))

    def predict_command(
        self,
        kind: str,
        start,
        end,
        start_time: float,
        end_time: float,
        extra_variance: float = 0.0,
    ) -> bool:
        """Predict a command someone else sent the instrument (a driver reports every one it
        executes): hold until it starts, a free move to its start if the tip was commanded
        elsewhere, then the command itself ("line" along a scan line, "raster" an image, "move"
        otherwise) over its duration. An "indent" is reported at its spot (start = end) with a
        duration that includes the lifted approach from wherever the tip was commanded: it is
        predicted as a move there over that duration, never as a jump in no time.
        extra_variance (m^2, each axis): what the motion model cannot predict about this
        command, e.g. the path-dependent hysteresis residue of a raster image, which the model
        sees only as its net displacement. A command
        ending no later than the estimate's time is already accounted for (our own, or reported
        twice): skipped, returns False."""
        if kind not in ("move", "line", "indent", "raster"):
            raise ValueError(f"kind={kind!r}: must be 'move', 'line', 'indent' or 'raster'")
        start, end = checks.point("start", start), checks.point("end", end)
        if kind == "indent":
            start, kind = np.asarray(self.model.command, dtype=float), "move"
        if not (math.isfinite(start_time) and math.isfinite(end_time) and end_time >= start_time):
            raise ValueError(
                f"start_time={start_time}, end_time={end_time}: need finite times, "
                "end >= start (s)"
            )
        if not (math.isfinite(extra_variance) and extra_variance >= 0):
            raise ValueError(f"extra_variance={extra_variance}: must be finite and >= 0 (m^2)")
        if end_time <= self.model.time:
            return False
        if start_time > self.model.time:
            self._apply(self.model.hold(start_time - self.model.time))
        if tuple(start) != tuple(self.model.command):
            self._apply(self.model.move(start[0], start[1], 0.0, "move"))
        self._apply(self.model.move(end[0], end[1], max(0.0, end_time - self.model.time), kind))
        if extra_variance > 0:
            self.filter.predict(self.model.time, np.zeros(2), np.eye(2) * extra_variance)
        return True

    # -- moves -----------------------------------------------------------------------------------
    def _speed(self, speed: float | None) -> float:
        speed = self.move_speed if speed is None else float(speed)
        if not (math.isfinite(speed) and 0 < speed <= self.instrument.limits.max_speed):
            raise ValueError(
                f"speed={speed}: must be > 0 and at most the slew limit "
                f"{self.instrument.limits.max_speed:.3e} m/s"
            )
        return speed

    def command_for(self, x: float, y: float, speed: float | None = None) -> tuple[float, float]:
        """The command that brings the tip (as estimated now) to task-frame (x, y)."""
        target = checks.point("target", (x, y))
        command = self.model.command_for(target - self.mean, self._speed(speed))
        check_in_range("target command", command[0], command[1], self.instrument.limits)
        return command

    def move_command(
        self, x: float, y: float, speed: float | None = None, should_stop: StopCheck | None = None
    ) -> MoveOutcome:
        """Command the scanner to (x, y) (scanner frame) and predict the move (as far as it
        went when should_stop ends it)."""
        speed = self._speed(speed)
        checks.point("command", (x, y))
        check_in_range("command", x, y, self.instrument.limits)
        self.sync()
        try:
            result = (
                self.instrument.move_tip(float(x), float(y), speed)
                if should_stop is None
                else self.instrument.move_tip(float(x), float(y), speed, should_stop=should_stop)
            )
            completed = result.completed
        finally:
            self.sync()
        return MoveOutcome(self.model.command, self.mean, self.covariance, self.time, completed)

    def move_to(self, x: float, y: float, speed: float | None = None) -> MoveOutcome:
        """Move the tip to task-frame (x, y): the command is the motion model inverted about the
        current estimate (creep still to come and drift included)."""
        self.sync()
        command = self.command_for(x, y, speed)
        return self.move_command(command[0], command[1], speed)

    def indent_here(self, force: float, dwell: float):
        """Punch a pit where the tip is commanded now; predicts the time it takes."""
        self.sync()
        x, y = self.model.command
        try:
            return self.instrument.indent(x, y, force, dwell)
        finally:
            self.sync()

    # -- landmark observation -------------------------------------------------------------------
    def _line_half_length(self, landmark: MapLandmark, u: np.ndarray) -> float:
        sigma = math.sqrt(max(0.0, float(u @ (self.covariance + landmark.covariance) @ u)))
        extent = (
            landmark.half_width
            if landmark.half_width > 0
            else landmark.radius + DEFAULT_TIP_ALLOWANCE
        )
        return 3.0 * sigma + extent + self.margin

    def _check_noise(self, landmark: MapLandmark) -> None:
        """Refuse, before anything moves, a line whose observation would claim no noise at all:
        the filter refuses it after the line has run (a zero variance), which left the line
        reported as never run and the estimate mid-line."""
        if line_variance(landmark, self.calibration) > 0:
            return
        if float(np.linalg.eigvalsh(landmark.covariance).min()) > 0:
            return
        raise ValueError(
            f"landmark.covariance={landmark.covariance.tolist()} is singular and the "
            "calibration's scan_region_sigma and line_deflection_sigma_deg are 0: a line "
            "across it would be an observation without noise (m^2)"
        )

    def plan_line(
        self,
        landmark,
        axis: str,
        sign: float = 1.0,
        before: float | None = None,
        after: float | None = None,
        across: float = 0.0,
    ) -> tuple[LineRequest, np.ndarray, float]:
        """A line along task-frame axis `axis` ("x" or "y") through the landmark's map position,
        in the direction `sign`, long enough to start and end clear of it with 3 sigma of the
        tip's and the landmark's uncertainty: it starts `before` and ends `after` metres (task
        frame) from the landmark (default both: 3 sigma + the landmark's apparent half-width
        + margin), `across` metres beside it (a search line; + is the other axis's positive
        direction). Returns (request, true direction, default half length)."""
        landmark = as_map_landmark(landmark)
        if axis not in ("x", "y"):
            raise ValueError(f"axis={axis!r}: must be 'x' or 'y'")
        self._check_noise(landmark)
        d = np.array([1.0, 0.0]) if axis == "x" else np.array([0.0, 1.0])
        d = d * (1.0 if sign >= 0 else -1.0)
        half = self._line_half_length(landmark, d)
        before = half if before is None else float(before)
        after = half if after is None else float(after)
        for name, value in (("before", before), ("after", after)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name}={value}: must be finite and > 0 m")
        beside = float(checks.finite("across", across)) * (
            np.array([0.0, 1.0]) if axis == "x" else np.array([1.0, 0.0])
        )
        start_target = landmark.position + beside - before * d
        start = self.model.command_for(start_target - self.mean, self.move_speed)
        # the end: where the model (creep still to come included) puts the tip (before + after) * d
        # further along, trying the approach move on a copy first
        trial = self.model.copy()
        approach = trial.move(
            start[0], start[1], math.dist(start, trial.command) / self.move_speed, "move"
        )
        start_predicted = self.mean + approach.mean
        end = trial.command_for(
            landmark.position + beside + after * d - start_predicted, self.line_speed, "line"
        )
        step = np.subtract(end, start)
        limits = self.instrument.limits
        check_in_range(f"{axis} line start", start[0], start[1], limits)
        check_in_range(f"{axis} line end", end[0], end[1], limits)
        length = float(np.hypot(*step))
        samples = int(
            min(limits.max_line_samples, max(16, math.ceil(length / self.sample_spacing) + 1))
        )
        request = LineRequest(start[0], start[1], end[0], end[1], samples, self.line_speed)
        request.validate(limits)
        return request, self.model.line_direction(*step), half

    def observe_line(
        self,
        landmark,
        axis: str,
        sign: float = 1.0,
        before: float | None = None,
        after: float | None = None,
        across: float = 0.0,
        should_stop: StopCheck | None = None,
    ) -> LineResult:
        """One local scan line across the landmark (see plan_line) and its update at the
        crossing point, carried to the line's end (eq. 5.9-5.21). should_stop (polled by the
        instrument) ends the approach or the line where it is: status "cancelled", no update,
        the motion up to there predicted."""
        landmark = as_map_landmark(landmark)
        self.sync()
        request, direction, _ = self.plan_line(landmark, axis, sign, before, after, across)
        stopped = should_stop if should_stop is not None else (lambda: False)
        try:
            self.move_command(request.start_x, request.start_y, self.move_speed, should_stop)
            if stopped():
                return LineResult(axis, "cancelled", "cancelled before the line", request)
            data = (
                self.instrument.local_scan(request)
                if should_stop is None
                else self.instrument.local_scan(request, should_stop=should_stop)
            )
        except ValueError as exc:
            self.sync()
            return LineResult(axis, "instrument_error", f"instrument: {exc}", request)
        if stopped():  # a line cut short: its crossing, if any, is not where it was planned
            self.sync()
            return LineResult(axis, "cancelled", "cancelled during the line", request)
        # up to the first sample the command stayed at the line start (the scan's own approach is
        # a zero-length move now); do not sync(): the instrument is already at the line's end
        start_time = float(data.start_time)
        if self.model.time < start_time:
            self._apply(self.model.hold(start_time - self.model.time))
        times = np.asarray(data.times, dtype=float)
        line_start = (float(data.x[0]), float(data.y[0]))
        if line_start != self.model.command:  # the scan's own approach, not through move_tip
            self._apply(self.model.move(line_start[0], line_start[1], 0.0, "move"))
        expected = self._expected_index(landmark, request, direction)
        obs = observe_line(
            data, landmark, self.calibration, direction, self.threshold_fraction, expected
        )
        end = (float(data.x[-1]), float(data.y[-1]))
        end_time = start_time + float(times[-1])
        result = LineResult(axis, "lost", obs.reason, request, obs)
        if obs.ok:
            kp_time = obs.time
            self._apply(
                self.model.move(obs.command[0], obs.command[1], kp_time - self.model.time, "line")
            )
            # the map position is part of the key: a landmark re-mapped or moved since (same
            # id) has another map error, not the one the state may hold for it
            key = (landmark.id, landmark.x, landmark.y)
            # only a line that crossed other features can be ambiguous and need undoing
            saved = self.filter.snapshot() if obs.alternatives else None
            update = self.filter.update_axis(
                kp_time,
                obs.value,
                obs.line_variance,
                obs.direction,
                landmark=key,
                map_covariance=landmark.covariance,
            )
            result.update = update
            result.innovation, result.mahalanobis = update.innovation, update.mahalanobis
            result.innovation_sigma = (
                math.sqrt(update.innovation_variance)
                if update.innovation_variance >= 0
                else math.nan
            )
            result.status = (
                "accepted" if update.accepted else ("gated_out" if update.gated_out else "too_old")
            )
            result.reason = update.reason
            ambiguity = self._ambiguity(obs, update) if update.accepted and saved else ""
            if ambiguity:
                self.filter.restore(saved)
                result.status, result.reason = "ambiguous", ambiguity
            result.mean_at_crossing, result.covariance_at_crossing = self.mean, self.covariance
        # carry the estimate to the line's end (eq. 5.20-5.21), then whatever time is left
        self._apply(self.model.move(end[0], end[1], max(0.0, end_time - self.model.time), "line"))
        self.sync()
        return result

    def _ambiguity(self, obs: LineObservation, update: UpdateResult) -> str:
        """Why the accepted crossing cannot be told from another on the same line ("" if it
        can): another crossing pair the gate would also accept. Particles closer together than
        the tip's uncertainty both pass the gate, and the one nearer the prediction is the
        landmark only by luck: a neighbour 300 nm away, the tip 160 nm off at a 100 nm sigma,
        was taken and left the estimate 300 nm off at a 9 nm sigma."""
        d2 = update.mahalanobis**2
        for alternative in obs.alternatives:
            step = self.model.matrix @ np.subtract(alternative, obs.command)
            along = float(obs.direction @ step)  # the tip is that much further at it
            d2_other = (update.innovation - along) ** 2 / update.innovation_variance
            if d2_other <= self.filter.gate:
                return (
                    f"ambiguous: another crossing {abs(along) * 1e9:.0f} nm along the line is "
                    f"within the gate too (squared Mahalanobis distances {d2:.3g} and "
                    f"{d2_other:.3g}, gate {self.filter.gate:.3g}): particles closer together "
                    "than the tip's uncertainty"
                )
        return ""

    def _expected_index(
        self, landmark: MapLandmark, request: LineRequest, direction: np.ndarray
    ) -> float:
        """Fractional sample index at which the tip is predicted to pass the landmark."""
        start = self.mean  # estimate at the line start (we are there now)
        along = float((landmark.position - start) @ direction)
        true_length = float(
            np.hypot(
                *(
                    self.model.matrix
                    @ np.array([request.end_x - request.start_x, request.end_y - request.start_y])
                )
            )
        )
        return (request.samples - 1) * along / true_length

    def _across(self, landmark: MapLandmark, axis: str) -> tuple[float, float]:
        """For a line along `axis`: the sigma of the tip's and the map's error across it, and
        the landmark's apparent half-width (the error across it up to which the line finds it)."""
        across = np.array([0.0, 1.0]) if axis == "x" else np.array([1.0, 0.0])
        sigma = math.sqrt(
            max(0.0, float(across @ (self.covariance + landmark.covariance) @ across))
        )
        extent = (
            landmark.half_width
            if landmark.half_width > 0
            else landmark.radius + DEFAULT_TIP_ALLOWANCE
        )
        return sigma, extent

    def _first_line_risk(self, landmark: MapLandmark, axis: str) -> float:
        """Probability that a first line along `axis` passes beside the landmark: its error
        across the line (Gaussian) beyond the landmark's apparent half-width. The second line's
        across-axis is the first one's measured axis, so only the first risks it."""
        sigma, extent = self._across(landmark, axis)
        return math.erfc(extent / (sigma * math.sqrt(2.0))) if sigma > 0 else 0.0

    def search_offsets(self, landmark: MapLandmark, axis: str) -> list[float]:
        """Offsets across a missed `axis` line for the search lines, nearest first (see
        SEARCH_SIGMAS): one apparent half-width apart out to SEARCH_SIGMAS sigma, the first
        line's own track (offset 0) again but longer, at most MAX_SEARCH_LINES in all."""
        sigma, spacing = self._across(landmark, axis)
        reach = max(SEARCH_SIGMAS * sigma, spacing)
        offsets = [0.0]
        k = 1
        while k * spacing <= reach and len(offsets) < MAX_SEARCH_LINES:
            offsets += [k * spacing, -k * spacing]
            k += 1
        return offsets[:MAX_SEARCH_LINES]

    def _search(
        self,
        landmark: MapLandmark,
        missed: LineResult,
        sign: float,
        after,
        should_stop: StopCheck | None = None,
    ) -> LineResult:
        """A missed line's bounded search (SEARCH_SIGMAS): longer parallel lines beside its
        track until one finds the landmark and the gate accepts it; that line (or the last
        failure) is the result, its `search` field says what was run. A crossing the gate
        rejects is not taken for the landmark, so the search goes on past it: a line can cross
        a particle the map does not hold (one cut by the image's edge, or come since) and pass
        beside the landmark. Rejecting a good crossing costs one more line at the gate's
        false-alarm rate (0.1 % at the default gate)."""
        d = np.array([1.0, 0.0]) if missed.axis == "x" else np.array([0.0, 1.0])
        half = SEARCH_LENGTH_FACTOR * self._line_half_length(landmark, d)
        offsets = self.search_offsets(landmark, missed.axis)
        if not offsets:
            return missed
        line, run, offset, rejected, gated = missed, 0, 0.0, 0, None
        for offset in offsets:
            try:
                line = self.observe_line(
                    landmark,
                    missed.axis,
                    sign,
                    before=half,
                    after=max(half, after or 0.0),
                    across=offset,
                    should_stop=should_stop,
                )
            except ValueError as exc:  # the search left the scanner range: stop there
                line.search = f"search stopped after {run} line(s): {exc}"
                return line
            if line.status == "cancelled":
                line.search = f"first try missed ({missed.reason}); cancelled after {run} line(s)"
                return line
            run += 1
            if not (line.lost or line.gated_out):
                break
            rejected += line.gated_out
            gated = gated or (line if line.gated_out else None)
        found = not (line.lost or line.gated_out)
        if not found and gated is not None:
            line = gated  # something was crossed and rejected: the more telling failure
        first = f"first try missed ({missed.reason})"
        where = f"{offset * 1e9:+.0f} nm across" if offset else "on its track"
        passed = (
            f", after {rejected} crossing(s) the gate rejected (gated out)" if rejected else ""
        )
        line.search = (
            f"{first}; search line {run} of up to {len(offsets)}, "
            f"{2 * half * 1e9:.0f} nm long, {where}{passed}: {line.status}"
            if found
            else f"{first}; {run} search line(s) up to "
            f"{max(abs(o) for o in offsets) * 1e9:.0f} nm across found nothing the gate "
            f"accepts ({rejected} gated out)"
        )
        return line

    def plan_observation(
        self, landmark, both_axes: bool = True, toward=None
    ) -> list[tuple[str, float, float | None]]:
        """The lines observe_landmark runs, as (axis, sign, after) for observe_line, each checked
        against the scanner range from the estimate of now (ValueError naming the line).

        Horizontal, then vertical local scan line through the landmark (Fig. 5.11); vertical
        first when the horizontal line would risk passing beside it (FIRST_LINE_RISK). A tube or
        rod is observed by one line across it (the position along its axis is not
        observable); both_axes=False: the horizontal line only (sphere).

        toward: a task-frame point the tip goes to next. The last line then runs in its
        direction and goes on past the landmark up to the point's coordinate along the line
        (when that is beyond the line's usual end): scan-line motion after the update carries
        the estimate with the line's small error, where a free move to the point would add
        positioning noise growing with its length (sigma^2 = a d + b)."""
        landmark = as_map_landmark(landmark)
        if landmark.elongated:
            # the task axis closer to the tube's normal
            normal = np.array([-math.sin(landmark.orientation), math.cos(landmark.orientation)])
            lines = [("y", 1.0, None)] if abs(normal[1]) >= abs(normal[0]) else [("x", 1.0, None)]
        else:
            lines = [("x", 1.0, None), ("y", -1.0, None)] if both_axes else [("x", 1.0, None)]
            if both_axes and self._first_line_risk(landmark, "x") > max(
                FIRST_LINE_RISK, self._first_line_risk(landmark, "y")
            ):
                lines.reverse()
        if toward is not None:
            toward = np.asarray(toward, dtype=float)
            if toward.shape != (2,) or not np.all(np.isfinite(toward)):
                raise ValueError(
                    f"toward={toward.tolist()}: must be a finite task-frame point (x, y) in m"
                )
            axis, sign, _ = lines[-1]
            k = 0 if axis == "x" else 1
            along = float(toward[k] - landmark.position[k])
            half = self._line_half_length(landmark, np.eye(2)[k])
            lines[-1] = (
                axis,
                math.copysign(1.0, along) if along else sign,
                abs(along) if abs(along) > half else None,
            )  # None: the usual end
        for axis, sign, after in lines:
            self.plan_line(landmark, axis, sign, after=after)
        return lines

    def observe_landmark(
        self,
        landmark,
        both_axes: bool = True,
        toward=None,
        should_stop: StopCheck | None = None,
    ) -> ObservationResult:
        """Run the lines of plan_observation (every one checked before anything moves; each
        re-planned from the estimate of its moment) and update on each. should_stop (a
        cancelled Localize goal) is polled between lines and by the instrument within them: the
        observation ends where it is, with a "cancelled" line, no update from a cut line and
        the motion so far predicted (a search of up to MAX_SEARCH_LINES lines would otherwise
        run to its end)."""
        landmark = as_map_landmark(landmark)
        self.sync()
        lines = self.plan_observation(landmark, both_axes, toward)
        result = ObservationResult(landmark.id)
        for axis, sign, after in lines:
            if should_stop is not None and should_stop():
                result.lines.append(LineResult(axis, "cancelled", "cancelled before the line"))
                break
            try:
                line = self.observe_line(
                    landmark, axis, sign, after=after, should_stop=should_stop
                )
            except ValueError as exc:  # the re-planned line left the scanner range
                line = LineResult(axis, "not_run", f"line not run: {exc}")
            # a search only looks for a landmark where the model says it may be: once a line
            # found it where it was planned and gated it out, the disagreement is beyond the
            # model, not a miss (a line that missed and searched goes on past crossings the
            # gate rejects: _search)
            searchable = line.observation is not None and line.request is not None
            if line.lost and searchable and not result.gated_out:
                line = self._search(landmark, line, sign, after, should_stop)
            result.lines.append(line)
            if line.status == "instrument_error":
                result.instrument_error = line.reason
            if line.status in ("instrument_error", "not_run", "cancelled"):
                break
        result.mean, result.covariance, result.time = self.mean, self.covariance, self.time
        return result
