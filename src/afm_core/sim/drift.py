"""Thermal drift: the sample moves against the scanner with a slowly wandering velocity.

Each axis' velocity is an Ornstein-Uhlenbeck process: it wanders around a mean with a
stationary spread and a correlation time, so over minutes it is nearly constant (what
drift compensation assumes) and over hours it changes (the book's Fig. 7.9 statistics over
hours: v_x ~ N(-0.004, 0.027) nm/s, v_y ~ N(0.099, 0.209) nm/s). Velocity knots are drawn
in time order from the seed, so the same seed gives the same drift whatever is queried
when; between knots the velocity is linear and the offset its exact integral.

Ramped drift: after a temperature change (a lamp switched on, the stage warming up) the
drift speeds up steadily for a while. A constant acceleration a per axis adds a t to the
velocity and 0.5 a t^2 to the offset (t from the instrument's power-on), on top of the
wandering velocity above; zero (the default) leaves the drift exactly as without it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import signal


@dataclass
class DriftParams:
    enabled: bool = True
    mean_velocity_x: float = -0.004e-9  # m/s (book Fig. 7.9)
    mean_velocity_y: float = 0.099e-9  # m/s
    sigma_velocity_x: float = 0.027e-9  # m/s, stationary spread
    sigma_velocity_y: float = 0.209e-9  # m/s
    correlation_time: float = 1800.0  # s, how long the velocity stays about the same
    knot_interval: float = 1.0  # s between velocity knots
    acceleration_x: float = 0.0  # m/s^2, ramped drift: velocity grows by a t, offset by 0.5 a t^2
    acceleration_y: float = 0.0  # m/s^2

    def __post_init__(self):
        # checked when the configuration is read, so a bad file fails before a session starts
        self.validate()

    def validate(self) -> None:
        for name in ("mean_velocity_x", "mean_velocity_y", "acceleration_x", "acceleration_y"):
            value = getattr(self, name)
            try:
                finite = not isinstance(value, bool) and math.isfinite(value)
            except TypeError:
                finite = False
            if not finite:
                raise ValueError(f"drift.{name}={value!r}: must be a finite number (m/s or m/s^2)")
        if not self.correlation_time > 0:
            raise ValueError(f"drift.correlation_time={self.correlation_time}: must be > 0 s")
        if not self.knot_interval > 0:
            raise ValueError(f"drift.knot_interval={self.knot_interval}: must be > 0 s")
        if self.sigma_velocity_x < 0 or self.sigma_velocity_y < 0:
            raise ValueError("drift.sigma_velocity_x/y: must be >= 0 m/s")
        if not (math.isfinite(self.sigma_velocity_x) and math.isfinite(self.sigma_velocity_y)):
            raise ValueError("drift.sigma_velocity_x/y: must be finite (m/s)")


class ThermalDrift:
    def __init__(self, params: DriftParams, seed: int):
        params.validate()
        self.params = params
        self.rng = np.random.default_rng(seed)
        self.mean = np.array([params.mean_velocity_x, params.mean_velocity_y])
        self.sigma = np.array([params.sigma_velocity_x, params.sigma_velocity_y])
        # None when there is no ramp, so the default drift is computed exactly as without it
        self.acceleration = (
            np.array([params.acceleration_x, params.acceleration_y])
            if params.acceleration_x or params.acceleration_y
            else None
        )
        first = self.mean + self.sigma * self.rng.normal(size=2)
        # knots at t = 0, dt, 2 dt, ...: arrays grown by doubling, so a long session's queries
        # stay linear in the knots they add
        self._velocity = np.empty((1024, 2))
        self._offset = np.empty((1024, 2))
        self._velocity[0], self._offset[0] = first, 0.0
        self._count = 1

    def _extend_to(self, t_max: float) -> None:
        p = self.params
        needed = int(np.ceil(t_max / p.knot_interval)) + 1
        if needed <= self._count:
            return
        if needed > len(self._velocity):
            capacity = max(needed, 2 * len(self._velocity))
            for name in ("_velocity", "_offset"):
                grown = np.empty((capacity, 2))
                grown[: self._count] = getattr(self, name)[: self._count]
                setattr(self, name, grown)
        decay = np.exp(-p.knot_interval / p.correlation_time)
        spread = self.sigma * np.sqrt(1.0 - decay**2)
        new = needed - self._count
        innovations = spread * self.rng.normal(size=(new, 2))
        # the Ornstein-Uhlenbeck recursion v_k - mean = decay (v_{k-1} - mean) + spread e_k
        previous = self._velocity[self._count - 1] - self.mean
        deviation = signal.lfilter(
            [1.0], [1.0, -decay], innovations, axis=0, zi=decay * previous[None, :]
        )[0]
        velocity = self.mean + deviation
        before = np.vstack([self._velocity[self._count - 1], velocity[:-1]])
        offsets = self._offset[self._count - 1] + np.cumsum(
            0.5 * (before + velocity) * p.knot_interval, axis=0
        )
        self._velocity[self._count : needed] = velocity
        self._offset[self._count : needed] = offsets
        self._count = needed

    def _interval(self, t: np.ndarray):
        if np.any(t < 0):
            raise ValueError("drift is defined from t = 0 s on")
        self._extend_to(float(np.max(t, initial=0.0)) + self.params.knot_interval)
        k = np.minimum((t // self.params.knot_interval).astype(int), self._count - 2)
        tau = t - k * self.params.knot_interval
        return k, tau[..., None], self._velocity[k], self._velocity[k + 1]

    def offset(self, t) -> np.ndarray:
        """Sample displacement (m) against the scanner at times t (s): shape t.shape + (2,)."""
        t = np.asarray(t, dtype=float)
        if not self.params.enabled:
            return np.zeros(t.shape + (2,))
        k, tau, v0, v1 = self._interval(t)
        slope = (v1 - v0) / self.params.knot_interval
        offset = self._offset[k] + v0 * tau + 0.5 * slope * tau**2
        if self.acceleration is not None:
            offset = offset + 0.5 * self.acceleration * (t**2)[..., None]
        return offset

    def velocity(self, t) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        if not self.params.enabled:
            return np.zeros(t.shape + (2,))
        _k, tau, v0, v1 = self._interval(t)
        velocity = v0 + (v1 - v0) * tau / self.params.knot_interval
        if self.acceleration is not None:
            velocity = velocity + self.acceleration * t[..., None]
        return velocity
