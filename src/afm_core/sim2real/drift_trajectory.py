"""The recorded drift trajectory D(t): the drift that puts the configured particles where the
recording saw them.

Drift and the random walk of the tip position move the particles by up to microns over a
session; a re-simulation with the model's mean drift would cross them elsewhere (other widths,
heights), or miss them. A replay without imaging gives, per measurement, where the model's
scanner truly was (hysteresis, creep, coupling, rotation: `ScannerMap`), so D = true scanner
position - the particle's configured position (stage A; stage B corrects those observations by
what the imaged reference at their drift still differs from the recording). `drift_trajectory`
smooths them into D(t) and says how far the true offset may be from it (`geometry_mismatch`).
"""

from __future__ import annotations

import math

import numpy as np

from afm_core.sim.config import SimConfig
from afm_core.sim2real.features import POSITION_GROUPS
from afm_core.sim2real.protocol import TrajectoryDrift, deterministic, replay

POSITION_PRECISION = 2e-9  # m, how well a measured position pins the drift trajectory


def nominal_drift(config: SimConfig, t: np.ndarray) -> np.ndarray:
    """(N, 2) drift offset of the model's deterministic drift (mean velocity and ramp) at t."""
    t = np.asarray(t, float)
    d = config.drift
    if not d.enabled:
        return np.zeros(t.shape + (2,))
    v = np.array([d.mean_velocity_x, d.mean_velocity_y])
    a = np.array([d.acceleration_x, d.acceleration_y])
    return v * t[..., None] + 0.5 * a * (t**2)[..., None]


class ScannerMap:
    """The model's scanner along every recorded position measurement: a replay without imaging
    gives, for each scan line and raster, where the scanner truly was at each commanded sample
    (hysteresis, creep, coupling, rotation). A particle at sample position P with drift offset
    D is measured where the true path passes P + D, so the map predicts every position
    feature for any drift (`predict`), exactly also where a re-simulation would miss the
    particle, and tells which configured particle each measurement saw and what drift offset
    it implies (`observations`: stage A of the drift trajectory)."""

    def __init__(self, ops, f_rec: dict, config: SimConfig, anchors: np.ndarray):
        by_index = {op.index: op for op in ops}
        # each operation's time span (s): a long image's one observation sits at its particles'
        # mean time, and the drift goes on over the whole image (drift_trajectory)
        self.spans = {
            op.index: (op.start_time, op.start_time + op.duration)
            for op in ops
            if np.isfinite(op.duration)
        }
        drives: dict = {}
        self.moves = replay(ops, deterministic(config), imaging=False, drives=drives).moves
        self.anchors = anchors
        self.items: dict = {}
        self.obs = [[], []]
        feats = sorted(
            (f for f in f_rec.values() if f.group in POSITION_GROUPS), key=lambda f: f.time
        )
        last = [None, None]
        per_raster: dict = {}
        for f in feats:
            op = by_index.get(f.key[0])
            if op is None:
                continue
            axis = 0 if abs(f.u[0]) >= abs(f.u[1]) else 1
            if op.kind == "scan_line":
                indices = (op.index, op.index + 1) if f.group == "line.pos" else (op.index,)
                paths = [self._line_path(drives.get(i), f.u) for i in indices]
                if any(p is None for p in paths):
                    continue
                item = {"kind": "line", "axis": axis, "paths": paths}
            elif op.kind == "raster":
                grid = self._raster_grid(drives.get(op.index), op.request)
                if grid is None:
                    continue
                item = {"kind": "raster", "axis": axis, "grid": grid}
            else:
                continue
            # where the model's scanner truly was when it measured the particle
            true_point = self._true_at(item, np.array([f.x, f.y]))
            if f.group.startswith("raster.") and f.conditions.get("particle", "") != "":
                j = int(f.conditions["particle"])
            else:
                guess = true_point - np.array(
                    [
                        self._current(config, last, 0, f.time),
                        self._current(config, last, 1, f.time),
                    ]
                )
                j = int(np.argmin(np.hypot(*(anchors - guess).T)))
            item["anchor"] = j
            self.items[f.key] = item
            value = float(true_point[axis] - anchors[j, axis])
            if op.kind == "raster":
                # a raster's particles give one offset per axis (their mean): a drift trajectory
                # is a function of time, and particles in the same lines differ by distortion,
                # not drift
                per_raster.setdefault((op.index, axis), []).append((f.time, value, f.key))
                continue
            self.obs[axis].append((f.time, value, [f.key]))
            last[axis] = value
        for (_, axis), values in per_raster.items():
            self.obs[axis].append(
                (
                    float(np.mean([v[0] for v in values])),
                    float(np.mean([v[1] for v in values])),
                    [v[2] for v in values],
                )
            )

    def refined(self, f_rec: dict, f_ref: dict) -> list:
        """Stage B: the observations corrected by what the imaged reference at their drift
        still differs from the recording (the imaging's own offsets: tip, creep during the
        line), through each feature's sensitivity."""
        out = [[], []]
        for axis in (0, 1):
            for t, value, keys in self.obs[axis]:
                corrections = []
                for key in keys:
                    if key in f_ref and key in self.items:
                        gain = self.sensitivity([key], [np.zeros(2)])[0, axis]
                        if abs(gain) > 0.2:
                            corrections.append((f_rec[key].value - f_ref[key].value) / gain)
                out[axis].append(
                    (t, value + (float(np.mean(corrections)) if corrections else 0.0), keys)
                )
        return out

    @staticmethod
    def _current(config, last, axis, t):
        if last[axis] is None:
            return float(nominal_drift(config, np.array([t]))[0, axis])
        return last[axis]

    @staticmethod
    def _line_path(drive_calls, u):
        """(commanded coordinate along |u| sorted, true x, true y, |u|) of a line's own drive."""
        if not drive_calls:
            return None
        _, cx, cy, tx, ty = drive_calls[-1]
        if cx.size < 3:
            return None
        axis_u = np.abs(np.asarray(u, float))
        c = cx * axis_u[0] + cy * axis_u[1]
        order = np.argsort(c)
        if np.ptp(c) == 0:
            return None
        return c[order], tx[order], ty[order], cx[order], cy[order], axis_u

    @staticmethod
    def _raster_grid(drive_calls, request):
        """Commanded and true positions of a raster's trace samples, (lines, pixels) each."""
        from afm_core.sim.instrument import LINES_PER_CHUNK

        if not drive_calls or request is None:
            return None
        n_lines, n_fast = request.lines, request.pixels_per_line
        calls = drive_calls[-int(math.ceil(n_lines / LINES_PER_CHUNK)) :]
        cx = np.concatenate([c[1] for c in calls])
        if cx.size != n_lines * 2 * n_fast or n_lines < 3 or n_fast < 3:
            return None
        arrays = [
            np.concatenate([c[k] for c in calls]).reshape(n_lines, 2 * n_fast)[:, :n_fast]
            for k in (1, 2, 3, 4)
        ]
        return arrays

    @staticmethod
    def _true_at(item, point) -> np.ndarray:
        """The true scanner position at a commanded point of the measurement."""
        if item["kind"] == "line":
            out = []
            for c, tx, ty, cx, cy, axis_u in item["paths"]:
                q = point @ axis_u
                out.append(
                    [np.interp(q, c, tx - cx) + point[0], np.interp(q, c, ty - cy) + point[1]]
                )
            return np.mean(out, axis=0)
        cx, cy, tx, ty = item["grid"]
        k, j = np.unravel_index(
            int(np.argmin((cx - point[0]) ** 2 + (cy - point[1]) ** 2)), cx.shape
        )
        return point + np.array([tx[k, j] - cx[k, j], ty[k, j] - cy[k, j]])

    @staticmethod
    def _line_predict(path, q):
        """Commanded coordinate along |u| where the line's true path passes closest to q."""
        c, tx, ty, _, _, _ = path
        tangent = np.array([tx[-1] - tx[0], ty[-1] - ty[0]])
        tangent /= max(float(np.hypot(*tangent)), 1e-30)
        f = (tx - q[0]) * tangent[0] + (ty - q[1]) * tangent[1]  # increasing along c
        slope = (f[-1] - f[0]) / (c[-1] - c[0])
        if f[0] > 0:
            return float(c[0] - f[0] / slope)
        if f[-1] < 0:
            return float(c[-1] - f[-1] / slope)
        return float(np.interp(0.0, f, c))

    @staticmethod
    def _raster_predict(grid, q):
        cx, cy, tx, ty = grid
        n_lines, n_fast = cx.shape
        k, j = np.unravel_index(int(np.argmin((tx - q[0]) ** 2 + (ty - q[1]) ** 2)), cx.shape)
        j0, j1 = max(0, j - 1), min(n_fast - 1, j + 1)
        k0, k1 = max(0, k - 1), min(n_lines - 1, k + 1)
        C = np.array(
            [
                [cx[k, j1] - cx[k, j0], cx[k1, j] - cx[k0, j]],
                [cy[k, j1] - cy[k, j0], cy[k1, j] - cy[k0, j]],
            ]
        )
        T = np.array(
            [
                [tx[k, j1] - tx[k, j0], tx[k1, j] - tx[k0, j]],
                [ty[k, j1] - ty[k, j0], ty[k1, j] - ty[k0, j]],
            ]
        )
        G = T @ np.linalg.inv(C)
        return np.array([cx[k, j], cy[k, j]]) + np.linalg.solve(
            G, q - np.array([tx[k, j], ty[k, j]])
        )

    def predict(self, key, offset) -> float:
        """The feature's predicted value (commanded coordinate, m) for a drift offset (2,)."""
        item = self.items[key]
        q = self.anchors[item["anchor"]] + np.asarray(offset, float)
        if item["kind"] == "line":
            return float(np.mean([self._line_predict(p, q) for p in item["paths"]]))
        return float(self._raster_predict(item["grid"], q)[item["axis"]])

    def predict_all(self, keys, offsets) -> np.ndarray:
        return np.array(
            [self.predict(k, d) if k in self.items else np.nan for k, d in zip(keys, offsets)]
        )

    def sensitivity(self, keys, offsets, eps: float = 1e-9) -> np.ndarray:
        """(N, 2): d feature / d drift offset (NaN rows for features without a map)."""
        base = self.predict_all(keys, offsets)
        out = []
        for axis in (0, 1):
            step = np.zeros(2)
            step[axis] = eps
            out.append((self.predict_all(keys, np.asarray(offsets) + step) - base) / eps)
        return np.stack(out, axis=1)


def _covered_degree(t: np.ndarray) -> int:
    """The highest polynomial degree (at most 3) the sorted observation times `t` support: k
    when each of k + 1 equal parts of their span holds an observation. A cubic through two
    stretches (a long image's one observation, then a push's lines within 30 s, 200 s later)
    is set by each stretch's local slope and swung 150 nm within the image between them."""
    span = float(np.ptp(t)) if t.size else 0.0
    for degree in (3, 2, 1):
        if span > 0:
            parts = np.minimum(np.floor((t - t[0]) / span * (degree + 1)), degree)
            if np.unique(parts).size == degree + 1:
                return degree
    return 0


def _observed_span(keys, spans, t: float) -> tuple[float, float]:
    """(start, end) s of the operations an observation's feature keys come from; (t, t)
    without spans."""
    found = [spans[k[0]] for k in keys if spans and k[0] in spans]
    if not found:
        return t, t
    return min(a for a, _ in found), max(b for _, b in found)


def drift_trajectory(
    obs, config: SimConfig, t_end: float, moves=(), step: float = 0.5, spans=None
) -> TrajectoryDrift:
    """D(t) per axis, on a grid of `step` s: a polynomial in time fitted to the observations (the
    smooth drift; cubic where they cover their span, `_covered_degree`; back to the start of
    the first observed operation at their mean velocity, `spans`: operation index -> (start,
    end) s; held beyond) plus the residual of the observation expected to be
    closest to D(t): the one with the least positioning-walk variance (moves) between, plus the
    drift's wander over the time between (0.1 nm/s); the model's drift where an axis has no
    observation."""
    grid = np.arange(0.0, max(t_end, step) + step, step)
    out = nominal_drift(config, grid)
    s = config.scanner
    if moves and s.positioning_noise_enabled:
        move_t = np.array([m[0] for m in moves])
        var = (
            s.positioning_noise_slope * np.array([m[1] for m in moves])
            + s.positioning_noise_offset
        )
        order = np.argsort(move_t)
        move_t, cum = move_t[order], np.concatenate([[0.0], np.cumsum(var[order])])
        walk = lambda t: cum[np.searchsorted(move_t, t, side="right")]  # noqa: E731
    else:
        walk = lambda t: np.zeros(np.shape(t))  # noqa: E731
    wander = (0.1e-9) ** 2
    choice = np.full((grid.size, 2), -1)
    mismatch = np.full((grid.size, 2), np.inf)
    for axis in (0, 1):
        if not obs[axis]:
            continue
        t = np.array([o[0] for o in obs[axis]])
        d = np.array([o[1] for o in obs[axis]])
        order = np.argsort(t)
        t, d = t[order], d[order]
        degree = min(int(max(0, np.unique(np.round(t)).size - 1)), _covered_degree(t))
        scale = max(float(np.ptp(t)), 1.0)
        coef = np.polyfit((t - t[0]) / scale, d, degree) if degree > 0 else np.array([d.mean()])
        # back over the first observed operation at the observations' mean velocity (not held:
        # a 256 s image's one observation sits at its particles' mean time, and its first
        # particles were imaged a minute before it); held before it and after the last one
        velocity = np.polyfit(t - t[0], d, 1)[0] if degree > 0 else 0.0
        first = min(obs[axis], key=lambda o: o[0])[2]
        lo = min(_observed_span(first, spans, t[0])[0], t[0])

        def smooth(x, t=t, coef=coef, scale=scale, velocity=velocity, lo=lo):
            end = np.clip(x, t[0], t[-1])
            return np.polyval(coef, (end - t[0]) / scale) + velocity * (
                np.clip(x, lo, t[0]) - t[0]
            )

        resid = d - smooth(t)
        cost = (
            np.abs(walk(grid)[:, None] - walk(t)[None, :])
            + wander * (grid[:, None] - t[None, :]) ** 2
        )
        best = np.argmin(cost, axis=1)
        out[:, axis] = smooth(grid) + resid[best]
        choice[:, axis] = np.searchsorted(np.sort(t), t[best])  # an id of the observation used
        mismatch[:, axis] = cost[np.arange(grid.size), best] + POSITION_PRECISION**2
    trajectory = TrajectoryDrift(grid, out)
    trajectory.choice, trajectory.mismatch = choice, mismatch
    return trajectory


def geometry_mismatch(trajectory: TrajectoryDrift, t: np.ndarray):
    """Per time and axis: (id of the observation the trajectory follows there, variance of how
    far the true offset may be from it)."""
    k = np.clip(
        np.round(np.asarray(t, float) / (trajectory.times[1] - trajectory.times[0])).astype(int),
        0,
        trajectory.times.size - 1,
    )
    return trajectory.choice[k], trajectory.mismatch[k]
