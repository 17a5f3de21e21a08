"""The tip-position Kalman filter (book eq. 5.16-5.21) on filterpy's KalmanFilter.

State: the tip's 2-D position x in the task frame (m), augmented with the drift velocity w the
motion model leaves unmodelled (m/s, 2-D: the deviation from the calibrated mean drift) and
the map errors b of the MAP_ERROR_SLOTS landmarks observed last (m, 2-D each): covariance P.
Prediction over
dt: the motion model's mean displacement as the control input (B = [I; 0; ...], u = mean) and
its added covariance (the calibrated positioning noise of each move, see
`afm_core.localization.motion`) as process noise on x; x also moves by w integrated over dt,
and w is an Ornstein-Uhlenbeck velocity (spread `drift_sigma`, the calibration's
drift_sigma_velocity; correlation time `drift_correlation_time`), with the exact transition
and process noise of the integrated OU process. A drift velocity stays about the same for
minutes, so its position error grows as sigma_v t, not as the square root of the number of
steps time is cut into (adding (sigma_v dt)^2 per step did that: 60 s in 30 steps counted a
fifth of the drift's 12 nm in y); observations of a landmark at different times learn w. b is
constant. Update: one scalar
observation z = u . (x + b) (a local scan line measures the position along one direction u,
a horizontal line x, a vertical line y, relative to the landmark, whose map position is off by
b), measurement variance R from the observation model without the map error, which is b's.
Carrying b makes a second line across the same landmark (the y line after the x line of a
particle, a tube crossed twice, the nano-hand's repeated localizations on one particle) use
the map error once, as it is: one error shared by every line across that landmark; treating
it as fresh noise on each line made the filter overconfident (mean NEES 1.7 for a tube
crossed twice). A landmark observed for the first time (or forgotten) takes a slot with its
error (mean 0, covariance its map covariance, uncorrelated); when every slot is taken, the
least recently observed landmark's error is forgotten and its correlation dropped. An update
without a landmark leaves b out (z = u . x).

Gating (eq. 5.18): the squared Mahalanobis distance d^2 = nu^2 / S of the innovation nu
(S = u P u^T + R) must not exceed `gate` (robot_localization's *_rejection_threshold is the
same test on d). Default chi2.ppf(0.999, 1) = 10.83, i.e. |nu| at most 3.29 sigma: a
consistent filter then rejects 0.1 % of good observations. The 99 % value (6.63, 2.58 sigma,
GATE_CHI2_1DOF_99) rejected ~1 % of good lines in the Table 7.1/7.2 experiment, and a falsely
rejected landmark leaves the tip at its broad prior (a 60 nm error at 2.7 sigma of 24 nm),
far costlier than letting through an outlier between 2.6 and 3.3 sigma; a wrong landmark (a
neighbouring particle, hundreds of nm away) is still rejected. A rejected observation leaves
the state as it was.

Time: every prediction ends at a timestamp (the instrument clock) and every observation
carries the time it applies to (the crossing time t_kp). The filter keeps a history of
states and steps (`history_seconds`, like robot_localization's smoothing lag): an
observation older than the latest step is inserted at its time (a prediction step that spans
it is split in proportion to time, exact for the drift terms and for a constant-speed ramp
without creep, linear interpolation otherwise) and everything after it is re-applied,
observations re-gated. An observation older than the history is rejected with that reason.
"""

from __future__ import annotations

import copy
import math
from bisect import bisect_right
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import KalmanFilter

from afm_core.localization.landmark_observation import check_covariance
from afm_core.parameters import Parameter

DRIFT_CORRELATION_TIME = (
    1800.0  # s, how long a drift velocity stays about the same (the simulator's default)
)

GATE_CHI2_1DOF_99 = 6.634896601021214  # scipy.stats.chi2.ppf(0.99, 1)
GATE_CHI2_1DOF_999 = 10.827566170662733  # scipy.stats.chi2.ppf(0.999, 1): the default gate
GATE = Parameter(
    "gate",
    GATE_CHI2_1DOF_999,
    "Mahalanobis gate: squared distance above which an observation is rejected (chi-square, "
    "1 dof; 10.83 = 99.9 %, 6.63 = 99 %).",
    minimum=0.0,
    above_minimum=True,
    runtime=True,
)
HISTORY_SECONDS = Parameter(
    "history_seconds",
    120.0,
    "Filter history kept to re-apply an out-of-order observation.",
    unit="s",
    minimum=0.0,
    runtime=True,
)
AXES = {"x": (1.0, 0.0), "y": (0.0, 1.0), 0: (1.0, 0.0), 1: (0.0, 1.0)}
# The map errors of this many landmarks observed last stay in the state, each with its
# correlation to the tip: a session that returns to a landmark (two particles observed in
# turn, hours of localizations in one area) meets the same map error again, and a fresh,
# independent one each time made the filter overconfident (two landmarks in turn with 100 nm
# moves between: mean NEES 3.3, 3 % of estimates outside 3 sigma). Beyond it the least
# recently observed one is forgotten (its correlation dropped, as for every landmark before).
MAP_ERROR_SLOTS = 8
TIP, DRIFT = slice(0, 2), slice(2, 4)
STATE_SIZE = 4 + 2 * MAP_ERROR_SLOTS


def _slot(i: int) -> slice:
    """The state's part that holds the map error in landmark slot i."""
    return slice(4 + 2 * i, 6 + 2 * i)


@dataclass(frozen=True)
class _Slots:
    """Which landmark's map error each slot holds (None: empty), and the slots from the least
    to the most recently observed."""

    keys: tuple = (None,) * MAP_ERROR_SLOTS
    recent: tuple = ()

    def find(self, landmark) -> int | None:
        return self.keys.index(landmark) if landmark in self.keys else None

    def place(self, landmark) -> int:
        """A slot for a landmark not held: an empty one, else the least recently observed."""
        return self.keys.index(None) if None in self.keys else self.recent[0]

    def used(self, i: int, landmark) -> _Slots:
        keys = self.keys[:i] + (landmark,) + self.keys[i + 1 :]
        return _Slots(keys, tuple(k for k in self.recent if k != i) + (i,))


Extrapolate = Callable[
    [float, float], tuple
]  # (from_time, to_time) -> (mean increment (2,), added covariance)


@dataclass(frozen=True)
class UpdateResult:
    accepted: bool
    reason: str  # "" when accepted; why not otherwise ("gated_out: ...", "too_old: ...")
    time: float  # s, when the observation applies
    innovation: float  # m, z - u . x(t)^-
    innovation_variance: float  # m^2, S = u P u^T + R
    mahalanobis: float  # sqrt(nu^2 / S), dimensionless

    @property
    def gated_out(self) -> bool:
        return self.reason.startswith("gated_out")


@dataclass
class _Entry:
    kind: str  # "start" | "predict" | "update"
    time: float  # s, time of the state after this entry
    mean: np.ndarray  # state after the entry: tip, drift velocity, landmarks' map errors
    covariance: np.ndarray  # (STATE_SIZE, STATE_SIZE)
    slots: _Slots | None = None  # the landmarks whose map errors the state holds after it
    increment: np.ndarray | None = None  # predict
    process: np.ndarray | None = None
    start_time: float = math.nan  # predict: when the step began
    value: float = math.nan  # update
    variance: float = math.nan
    direction: np.ndarray | None = None
    map_covariance: np.ndarray | None = None  # update: the landmark's (None: no landmark)
    landmark: object = None  # update: the key of the landmark observed


def _direction(axis) -> np.ndarray:
    if isinstance(axis, (str, int)) and not isinstance(axis, bool) and axis in AXES:
        u = np.array(AXES[axis])
    else:
        need = f"axis={axis!r}: need 'x', 'y', 0, 1 or a finite non-zero 2-vector"
        try:
            u = np.asarray(axis, dtype=float)
        except (TypeError, ValueError):  # 'X', or a string of numbers
            raise ValueError(need) from None
        if u.shape != (2,) or not np.isfinite(u).all() or not np.hypot(*u) > 0:
            raise ValueError(need)
        u = u / np.hypot(*u)
    return u


class TipFilter:
    """2-D tip position, timestamped predict / one-axis update with gating and a history."""

    def __init__(
        self,
        mean,
        covariance,
        time: float = 0.0,
        gate: float = GATE.default,
        history_seconds: float = HISTORY_SECONDS.default,
        extrapolate: Extrapolate | None = None,
        drift_sigma=(0.0, 0.0),
        drift_correlation_time: float = DRIFT_CORRELATION_TIME,
    ):
        m = np.asarray(mean, dtype=float)
        if m.shape != (2,) or not np.isfinite(m).all():
            raise ValueError(f"initial_mean={mean}: need two finite values (m)")
        p = check_covariance("initial_cov", covariance)
        if not (math.isfinite(time)):
            raise ValueError(f"time={time}: must be finite")
        sigma_w = np.asarray(drift_sigma, dtype=float)
        if sigma_w.shape != (2,) or not (np.isfinite(sigma_w).all() and (sigma_w >= 0).all()):
            raise ValueError(f"drift_sigma={drift_sigma}: need two finite values >= 0 (m/s)")
        if not (math.isfinite(drift_correlation_time) and drift_correlation_time > 0):
            raise ValueError(
                f"drift_correlation_time={drift_correlation_time}: must be finite and > 0 s"
            )
        self.gate = GATE.validate(gate)
        self.history_seconds = HISTORY_SECONDS.validate(history_seconds)
        self.extrapolate = extrapolate
        self.drift_sigma, self.drift_correlation_time = sigma_w, float(drift_correlation_time)
        self._kf = KalmanFilter(dim_x=STATE_SIZE, dim_z=1)
        self._kf.B = np.vstack([np.eye(2), np.zeros((STATE_SIZE - 2, 2))])
        mean0, cov0 = np.zeros(STATE_SIZE), np.zeros((STATE_SIZE, STATE_SIZE))
        mean0[TIP], cov0[TIP, TIP] = m, p
        cov0[DRIFT, DRIFT] = np.diag(sigma_w**2)
        self._set(mean0, cov0, _Slots())
        self._history = [_Entry("start", float(time), mean0, cov0, _Slots())]

    # -- state -------------------------------------------------------------------------------
    def _set(self, mean, covariance, slots: _Slots) -> None:
        self._kf.x = np.asarray(mean, dtype=float).reshape(STATE_SIZE, 1).copy()
        self._kf.P = np.asarray(covariance, dtype=float).copy()
        self._slots = slots

    def _state(self) -> tuple[np.ndarray, np.ndarray]:
        return self._kf.x[:, 0].copy(), self._kf.P.copy()

    @property
    def mean(self) -> np.ndarray:
        return self._kf.x[:2, 0].copy()

    @property
    def covariance(self) -> np.ndarray:
        return self._kf.P[:2, :2].copy()

    @property
    def time(self) -> float:
        return self._history[-1].time

    @property
    def oldest_time(self) -> float:
        return self._history[0].time

    # -- the two steps -------------------------------------------------------------------------
    def _transition(self, dt: float, process) -> tuple[np.ndarray, np.ndarray]:
        """(F, Q) over dt: x += w integrated over dt, w decays as an OU process (exact integrated
        OU terms, per axis), the motion's process noise on x."""
        tau = self.drift_correlation_time
        phi = math.exp(-dt / tau)
        var = self.drift_sigma**2
        f, q = np.eye(STATE_SIZE), np.zeros((STATE_SIZE, STATE_SIZE))
        f[TIP, DRIFT] = tau * (1.0 - phi) * np.eye(2)
        f[DRIFT, DRIFT] = phi * np.eye(2)
        q[TIP, TIP] = np.asarray(process) + np.diag(
            var * tau * tau * max(0.0, 2 * dt / tau - 3 + 4 * phi - phi * phi)
        )
        q[TIP, DRIFT] = q[DRIFT, TIP] = np.diag(var * tau * (1.0 - phi) ** 2)
        q[DRIFT, DRIFT] = np.diag(var * (1.0 - phi * phi))
        return f, q

    def _predict(self, increment, process, dt: float) -> None:
        f, q = self._transition(dt, process)
        self._kf.predict(u=np.asarray(increment, dtype=float).reshape(2, 1), F=f, Q=q)

    def _predict_entry(self, time: float, increment, process, start_time: float) -> _Entry:
        self._predict(increment, process, time - start_time)
        return _Entry(
            "predict",
            float(time),
            *self._state(),
            self._slots,
            increment,
            process,
            start_time=start_time,
        )

    def predict(self, time: float, increment, process) -> None:
        """Motion from the latest time to `time`: mean += increment, P += process."""
        increment = np.asarray(increment, dtype=float)
        if increment.shape != (2,) or not np.isfinite(increment).all():
            raise ValueError(f"increment={increment}: need two finite values (m)")
        process = check_covariance("process", process)
        if not math.isfinite(time) or time < self.time:
            raise ValueError(
                f"time={time}: predictions must come in time order (latest {self.time})"
            )
        self._history.append(
            self._predict_entry(time, increment.copy(), process.copy(), self.time)
        )
        self._prune()

    def _try_update(
        self, time: float, value: float, variance: float, u: np.ndarray, landmark, map_covariance
    ) -> UpdateResult:
        """Gate and (if accepted) apply to the current state; filterpy does the algebra on a copy
        that replaces the filter only when the observation passes the gate. A landmark whose
        map error the state does not hold takes a slot (MAP_ERROR_SLOTS) with its map error,
        uncorrelated with the rest."""
        trial = copy.deepcopy(self._kf)
        h = np.zeros((1, STATE_SIZE))
        h[0, TIP] = u
        slots = self._slots
        if landmark is not None:
            i = slots.find(landmark)
            if i is None:
                i = slots.place(landmark)
                b = _slot(i)
                trial.x[b] = 0.0
                trial.P[b, :] = 0.0
                trial.P[:, b] = 0.0
                trial.P[b, b] = map_covariance
            h[0, _slot(i)] = u
            slots = slots.used(i, landmark)
        trial.update(np.array([[value]]), R=np.array([[variance]]), H=h)
        innovation = float(trial.y[0, 0])
        s = float(trial.S[0, 0])
        distance = float(trial.mahalanobis)
        if not distance**2 <= self.gate:
            return UpdateResult(
                False,
                f"gated_out: squared Mahalanobis distance {distance**2:.3g} > gate "
                f"{self.gate:.3g}",
                time,
                innovation,
                s,
                distance,
            )
        self._kf, self._slots = trial, slots
        return UpdateResult(True, "", time, innovation, s, distance)

    def _update_entry(self, time, value, variance, u, landmark, map_covariance) -> _Entry:
        return _Entry(
            "update",
            time,
            *self._state(),
            self._slots,
            value=value,
            variance=variance,
            direction=u,
            map_covariance=map_covariance,
            landmark=landmark,
        )

    def update_axis(
        self,
        time: float,
        value: float,
        variance: float,
        axis="x",
        landmark=None,
        map_covariance=None,
    ) -> UpdateResult:
        """One scalar observation z = u . (x(time) + b) + v, v ~ N(0, variance); axis "x", "y" or
        a unit vector u. landmark: a hashable key of the landmark the line crossed and
        map_covariance its 2x2 map covariance (m^2; b's, not counted in `variance`); without a
        landmark, z = u . x(time) + v. Returns whether it was accepted and its Mahalanobis
        distance."""
        u = _direction(axis)
        for name, v in (("time", time), ("value", value), ("variance", variance)):
            if not math.isfinite(v):
                raise ValueError(f"{name}={v}: must be finite")
        if landmark is not None:
            map_covariance = check_covariance("map_covariance", map_covariance)
        elif map_covariance is not None:
            raise ValueError("map_covariance given without the landmark it belongs to")
        # with a landmark, its map error may be all the noise there is (a perfect line)
        if not (
            variance > 0 or (variance == 0 and landmark is not None and u @ map_covariance @ u > 0)
        ):
            raise ValueError(
                f"variance={variance}: must be > 0 m^2 (or 0 with a landmark whose map error "
                "along the line is > 0)"
            )
        time, value, variance = float(time), float(value), float(variance)
        if time < self.oldest_time:
            return UpdateResult(
                False,
                f"too_old: t={time:.6g} s is before the history's start "
                f"{self.oldest_time:.6g} s (history {self.history_seconds:g} s)",
                time,
                math.nan,
                math.nan,
                math.nan,
            )
        if time >= self.time:
            if time > self.time:
                self._extend_to(time)
            result = self._try_update(time, value, variance, u, landmark, map_covariance)
            if result.accepted:
                self._history.append(
                    self._update_entry(time, value, variance, u, landmark, map_covariance)
                )
            return result
        return self._insert_past(time, value, variance, u, landmark, map_covariance)

    def _extend_to(self, time: float) -> None:
        """An observation after the latest prediction: carry the state there first."""
        if self.extrapolate is None:
            self.predict(time, np.zeros(2), np.zeros((2, 2)))
        else:
            increment, process = self.extrapolate(self.time, time)
            self.predict(time, increment, process)

    def _insert_past(
        self, time: float, value: float, variance: float, u: np.ndarray, landmark, map_covariance
    ) -> UpdateResult:
        history = self._history
        times = [e.time for e in history]
        k = bisect_right(times, time)  # entries [0, k) end at or before `time`
        later = history[k:]
        if later and later[0].kind == "predict" and later[0].start_time < time:
            step = later[0]  # split the step that spans `time`
            f = (time - step.start_time) / (step.time - step.start_time)
            first = _Entry(
                "predict",
                time,
                None,
                None,
                None,
                f * step.increment,
                f * step.process,
                start_time=step.start_time,
            )
            second = _Entry(
                "predict",
                step.time,
                None,
                None,
                None,
                (1 - f) * step.increment,
                (1 - f) * step.process,
                start_time=time,
            )
            head, later = [first], [second] + later[1:]
        else:
            head = []
        base = history[:k]
        saved_kf, saved_slots, saved_history = copy.deepcopy(self._kf), self._slots, history
        self._set(base[-1].mean, base[-1].covariance, base[-1].slots)
        new_history = list(base)
        for entry in head:
            new_history.append(
                self._predict_entry(entry.time, entry.increment, entry.process, entry.start_time)
            )
        result = self._try_update(time, value, variance, u, landmark, map_covariance)
        if not result.accepted:  # leave everything as it was
            self._kf, self._slots, self._history = saved_kf, saved_slots, saved_history
            return result
        new_history.append(self._update_entry(time, value, variance, u, landmark, map_covariance))
        for entry in later:
            if entry.kind == "predict":
                new_history.append(
                    self._predict_entry(
                        entry.time, entry.increment, entry.process, entry.start_time
                    )
                )
            elif entry.kind == "update":
                replay = self._try_update(
                    entry.time,
                    entry.value,
                    entry.variance,
                    entry.direction,
                    entry.landmark,
                    entry.map_covariance,
                )
                if replay.accepted:
                    new_history.append(
                        self._update_entry(
                            entry.time,
                            entry.value,
                            entry.variance,
                            entry.direction,
                            entry.landmark,
                            entry.map_covariance,
                        )
                    )
        self._history = new_history
        return result

    def _prune(self) -> None:
        """Keep the states of the last history_seconds (at least the latest one)."""
        horizon = self.time - self.history_seconds
        k = 0
        while k < len(self._history) - 1 and self._history[k + 1].time <= horizon:
            k += 1
        if k:
            oldest = self._history[k]
            self._history = [
                _Entry("start", oldest.time, oldest.mean, oldest.covariance, oldest.slots)
            ] + self._history[k + 1 :]

    def snapshot(self) -> tuple:
        """Everything an update changes, for `restore` (the history's entries are never changed
        in place, so a copy of the list keeps them)."""
        return copy.deepcopy(self._kf), self._slots, list(self._history)

    def restore(self, snapshot: tuple) -> None:
        """Back to a `snapshot`: an update the caller found it should not have made."""
        kf, self._slots, history = snapshot
        self._kf, self._history = copy.deepcopy(kf), list(history)

    # -- queries ---------------------------------------------------------------------------------
    def at(self, time: float) -> tuple[np.ndarray, np.ndarray]:
        """(mean, covariance) at `time`: inside the history, the state then (a prediction step
        interpolated in proportion to time); after the latest step, extrapolated with
        `extrapolate` (the motion model holding still: creep still to come and the mean drift)
        and the unmodelled drift velocity, which alone carries it without `extrapolate`."""
        if not math.isfinite(time):
            raise ValueError(f"time={time}: must be finite")
        if time >= self.time:
            if time == self.time:
                return self.mean, self.covariance
            increment, process = (
                (np.zeros(2), np.zeros((2, 2)))
                if self.extrapolate is None
                else self.extrapolate(self.time, time)
            )
            return self._carried(self._history[-1], increment, process, time - self.time)
        if time < self.oldest_time:
            raise ValueError(f"time={time}: before the history's start {self.oldest_time} s")
        times = [e.time for e in self._history]
        k = bisect_right(times, time)
        entry = self._history[k]
        before = self._history[k - 1]
        if entry.kind != "predict" or entry.start_time >= time:
            return before.mean[:2].copy(), before.covariance[:2, :2].copy()
        f = (time - entry.start_time) / (entry.time - entry.start_time)
        return self._carried(
            before, f * entry.increment, f * entry.process, time - entry.start_time
        )

    def _carried(
        self, entry: _Entry, increment, process, dt: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """(mean, covariance) of the tip: `entry`'s state predicted over dt (not stored)."""
        f, q = self._transition(dt, process)
        mean = f @ entry.mean
        mean[:2] += np.asarray(increment, dtype=float)
        covariance = f @ entry.covariance @ f.T + q
        return mean[TIP], covariance[TIP, TIP]
