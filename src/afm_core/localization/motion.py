"""The calibrated tip motion model (book eq. 5.3-5.5).

    x_{k+1} = x_k + (c~_{k+1} - c~_k) + (r_{k+1} - r_k) - v_d dt + w,    w ~ N(0, R_k)

- c: the commanded scanner position (m, per axis). The controller's hysteresis feed-forward
  is part of the instrument; what is left of it, the x/y coupling and the scan-line rotation
  are the calibrated `scanner_matrix` M (true displacement per commanded displacement, in the
  frame of the images, measured on short moves after a reversal).
- M's departure from the identity is the residual hysteresis of short moves (the images'
  raster shares the coupling and rotation, which cancel), and a hysteresis offset is bounded:
  the model carries it as a residual r (task frame minus command, per axis) that grows by
  (M - I) dc along a move and saturates at |M - I| times the span M was measured over
  (`Calibration.scanner_matrix_span`). A raster resets r: the image it makes is the frame the
  map is in. Extrapolating M over a 40 um move put the estimate 0.5 um from where the map and
  the tip agree (the simulated default scanner, y gain 1.014), and the first line missed.
  So the mean displacement is dc~ + dr, which is M dc~ for moves within the span.
- c~: the command seen through the calibrated creep operators (book eq. 5.29-5.31,
  `afm_core.pzt.Creep`, one per axis): c~ = a c + sum_i f_i x_i with a = 1 - sum_i f_i, so
  a step is followed by sum_i f_i of it over the creep time constants and a settled tip is
  where it was commanded. Creep is linear, so M applied after it is the same as before it.
  The operators are driven by the command history this model has seen, so the creep still
  to come from earlier moves is predicted in every later move or hold.
- v_d: the calibrated mean drift velocity. Sign convention: `Calibration.drift_mean_velocity`
  is the velocity of the SAMPLE against the scanner (what a feature's apparent motion in
  frame-up/frame-down image pairs measures, Fig. 7.9, and what the simulator's drift is),
  so the tip's position in the sample-fixed task frame changes by DRIFT_SIGN * v_d dt with
  DRIFT_SIGN = -1.
- R_k: a free move (`move_tip`, including the approach to a scan line's start) adds
  `calibration.motion_noise().added_covariance(dx, dy)` (sigma^2 = a d + b per axis); a move
  along a local scan line adds no positioning noise (the piezo is ramped, not repositioned)
  but the line-deflection uncertainty, (sigma_theta L)^2 across the line; a hold adds nothing.
  The drift the mean v_d leaves unmodelled is not noise of each step but a velocity that
  persists for minutes: the Kalman filter carries it as state (`TipFilter` drift_sigma).

State (`MotionState`): time, last command and the creep operators' states: all of it
explicit, copyable and restorable, so a filter can re-run history and the localizer can try
a move on a copy (`command_for`) before making it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from afm_core import checks
from afm_core.localization.calibration.model import Calibration
from afm_core.pzt import Creep

DRIFT_SIGN = -1.0  # task-frame tip displacement per unit of calibrated (sample) drift
RAMP_SAMPLE_TIME = 0.01  # s, creep operators sample a commanded ramp at least this finely
RAMP_MIN_SAMPLES = 8
RAMP_MAX_SAMPLES = 2000

KINDS = ("move", "line", "hold", "raster")


@dataclass
class MotionState:
    """Everything the model remembers (copies; restore with MotionModel.set_state)."""

    time: float  # s, instrument clock
    command: np.ndarray  # (2,) m, last commanded scanner position
    creep: tuple  # per axis: Creep.state array, or None without creep
    residual: np.ndarray  # (2,) m, the feed-forward's residual hysteresis offset r

    def copy(self) -> MotionState:
        return MotionState(
            self.time,
            self.command.copy(),
            tuple(None if s is None else np.array(s, dtype=float) for s in self.creep),
            self.residual.copy(),
        )


@dataclass(frozen=True)
class MotionStep:
    """One predicted motion: what the filter's prediction step needs, and what produced it."""

    kind: str  # "move" | "line" | "hold"
    start_time: float  # s
    end_time: float  # s
    start_command: tuple  # m
    end_command: tuple  # m
    mean: np.ndarray  # (2,) m, predicted true displacement in the task frame
    covariance: np.ndarray  # (2, 2) m^2, covariance the motion adds
    commanded_distance: float  # m

    @property
    def duration(self) -> float:
        return self.end_time - self.start_time


class MotionModel:
    """Predicts the tip's true displacement (and the covariance it adds) for each command."""

    def __init__(self, calibration: Calibration, command=(0.0, 0.0), time: float = 0.0):
        """Starts at rest (creep settled) at `command` at `time`."""
        calibration.validate()
        self.calibration = calibration
        self.matrix = np.array(calibration.scanner_matrix, dtype=float)
        if abs(np.linalg.det(self.matrix)) < 1e-6:
            raise ValueError(
                f"calibration scanner_matrix={calibration.scanner_matrix}: singular, cannot be "
                "inverted"
            )
        self.inverse_matrix = np.linalg.inv(self.matrix)
        self.residual_gain = self.matrix - np.eye(2)
        self.residual_bound = np.abs(self.residual_gain).sum(axis=1) * float(
            calibration.scanner_matrix_span
        )
        self.noise = calibration.motion_noise()
        self.drift_velocity = DRIFT_SIGN * np.array(calibration.drift_mean_velocity, dtype=float)
        self.deflection_sigma = math.radians(calibration.line_deflection_sigma_deg)
        taus = np.array(calibration.creep_time_constants, dtype=float)
        # per axis: (inverse time constants, fractions, direct gain) or None
        self._creep_params = []
        for fractions in (calibration.creep_fractions_x, calibration.creep_fractions_y):
            f = np.array(fractions, dtype=float)
            self._creep_params.append(
                (1.0 / taus, f, 1.0 - float(f.sum())) if taus.size and f.any() else None
            )
        self._creep = [None if p is None else Creep(*p) for p in self._creep_params]
        self.reset(command, time)

    # -- state ---------------------------------------------------------------------------------
    def reset(self, command, time: float) -> None:
        """At rest at `command` (m) at `time` (s): creep settled."""
        cx, cy = (checks.finite("command.x", command[0]), checks.finite("command.y", command[1]))
        self._time = checks.finite("time", time)
        self._command = np.array([cx, cy])
        self._residual = np.zeros(2)
        for creep, c in zip(self._creep, self._command):
            if creep is not None:
                creep.reset(c)

    @property
    def state(self) -> MotionState:
        return MotionState(
            self._time,
            self._command.copy(),
            tuple(None if c is None else c.state for c in self._creep),
            self._residual.copy(),
        )

    def set_state(self, state: MotionState) -> None:
        self._time = float(state.time)
        self._command = np.array(state.command, dtype=float)
        self._residual = np.array(state.residual, dtype=float)
        for creep, s in zip(self._creep, state.creep):
            if creep is not None:
                creep.state = s

    def copy(self) -> MotionModel:
        other = MotionModel.__new__(MotionModel)
        other.__dict__.update(self.__dict__)
        other._creep = [None if p is None else Creep(*p) for p in self._creep_params]
        other.set_state(self.state)
        return other

    @property
    def time(self) -> float:
        return self._time

    @property
    def command(self) -> tuple[float, float]:
        return float(self._command[0]), float(self._command[1])

    @property
    def has_creep(self) -> bool:
        return any(c is not None for c in self._creep)

    def creep_to_come(self) -> np.ndarray:
        """(2,) m: the creep displacement still to come if the command is held from now on
        (command minus c~ per axis; zero once settled), before the scanner matrix."""
        return self._command - self._creep_output()

    # -- prediction ----------------------------------------------------------------------------
    def _creep_output(self) -> np.ndarray:
        """c~ now: a c + sum f_i x_i per axis (the command itself without creep)."""
        out = self._command.copy()
        for i, (creep, params) in enumerate(zip(self._creep, self._creep_params)):
            if creep is not None:
                _, fractions, direct = params
                out[i] = direct * self._command[i] + creep.state[:-1] @ fractions
        return out

    def _drive(self, target: np.ndarray, duration: float) -> None:
        """Advance the creep operators along a linear ramp to `target` taking `duration` s."""
        if duration <= 0.0:
            self._command = target.copy()
            for creep, c in zip(self._creep, target):
                if creep is not None:  # an instantaneous step: seen from the next sample on
                    state = creep.state
                    state[-1] = c
                    creep.state = state
            return
        moving = bool(np.any(target != self._command))
        n = (
            1
            if not moving
            else int(
                min(
                    RAMP_MAX_SAMPLES, max(RAMP_MIN_SAMPLES, math.ceil(duration / RAMP_SAMPLE_TIME))
                )
            )
        )
        fractions = np.arange(1, n + 1) / n
        path = self._command[None, :] + fractions[:, None] * (target - self._command)[None, :]
        path[-1] = target
        for i, creep in enumerate(self._creep):
            if creep is not None:
                creep.apply(path[:, i], duration / n)
        self._command = target.copy()

    def move(self, x: float, y: float, duration: float, kind: str = "move") -> MotionStep:
        """Ramp the command linearly from the last command to (x, y) over `duration` s.

        kind "move": a free move (positioning noise a d + b); "line": along a local scan line
        (deflection noise across the line, no positioning noise); "raster": an image's net
        motion, a free move that leaves the residual r at zero (the image is the map's frame);
        "hold" requires no motion."""
        if kind not in KINDS:
            raise ValueError(f"kind={kind!r}: must be one of {KINDS}")
        target = np.array([checks.finite("x", x), checks.finite("y", y)])
        duration = checks.finite("duration", duration)
        if duration < 0:
            raise ValueError(f"duration={duration}: must be >= 0 s")
        start_command, start_time = self._command.copy(), self._time
        before = self._creep_output()
        self._drive(target, duration)
        self._time = start_time + duration
        after = self._creep_output()
        step = target - start_command
        distance = float(np.hypot(*step))
        if kind == "hold" and distance > 0:
            raise ValueError(f"kind='hold' with a commanded step of {distance:.3e} m")
        if kind == "raster":
            residual = np.zeros(2)
        else:
            residual = np.clip(
                self._residual + self.residual_gain @ step,
                -self.residual_bound,
                self.residual_bound,
            )
        mean = (after - before) + (residual - self._residual) + self.drift_velocity * duration
        self._residual = residual
        true_step = self.matrix @ step
        if kind in ("move", "raster"):
            covariance = self.noise.added_covariance(true_step[0], true_step[1])
        else:
            covariance = np.zeros((2, 2))
            if kind == "line" and distance > 0:
                length = float(np.hypot(*true_step))
                across = np.array([-true_step[1], true_step[0]]) / length
                covariance = covariance + (self.deflection_sigma * length) ** 2 * np.outer(
                    across, across
                )
        return MotionStep(
            kind,
            start_time,
            self._time,
            tuple(start_command),
            tuple(target),
            mean,
            covariance,
            distance,
        )

    def hold(self, duration: float) -> MotionStep:
        """Time passes with the command held: creep still to come, drift."""
        return self.move(self._command[0], self._command[1], duration, "hold")

    # -- planning helpers --------------------------------------------------------------------
    def line_direction(self, dx: float, dy: float) -> np.ndarray:
        """Unit vector (task frame) of the true path of a commanded straight line along
        (dx, dy)."""
        v = self.matrix @ np.array([dx, dy], dtype=float)
        norm = float(np.hypot(*v))
        if norm == 0.0:
            raise ValueError("line direction: zero-length commanded step")
        return v / norm

    def commanded_step_for(self, displacement) -> np.ndarray:
        """The commanded step whose true displacement is `displacement`, creep and drift aside."""
        return self.inverse_matrix @ np.asarray(displacement, dtype=float)

    def command_for(
        self, displacement, speed: float, kind: str = "move", iterations: int = 3
    ) -> tuple[float, float]:
        """The commanded end point of a move (at `speed`, m/s) whose predicted mean true
        displacement, creep still to come and drift included, is `displacement` (m).
        Tried on copies of this model; this model is unchanged."""
        displacement = np.asarray(displacement, dtype=float)
        if displacement.shape != (2,) or not np.isfinite(displacement).all():
            raise ValueError(f"displacement={displacement}: need two finite values (m)")
        if not (math.isfinite(speed) and speed > 0):
            raise ValueError(f"speed={speed}: must be finite and > 0 (m/s)")
        step = self.commanded_step_for(displacement)
        for _ in range(iterations):
            trial = self.copy()
            target = self._command + step
            predicted = trial.move(target[0], target[1], float(np.hypot(*step)) / speed, kind).mean
            step = step + self.inverse_matrix @ (displacement - predicted)
        target = self._command + step
        return float(target[0]), float(target[1])
