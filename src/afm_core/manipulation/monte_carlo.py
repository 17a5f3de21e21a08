"""The Monte Carlo stochastic pushing model (book 6.4.3, Fig. 6.18; SPEC section 5).

The particle's true centre is uncertain: draw `samples` centres (default 500) from a normal
distribution about the plan's estimate (sigma 10 nm per axis by default, or a full 2x2
covariance), push every one of them with the plan's strokes through the project's pushing
physics (afm_core.physics.pushing.push_along_path, one single-sphere
afm_core.physics.sample.Sample per draw, moved in place), and describe where they end:

- mean, sigma across the push axis (lateral) and along it;
- share_left / share_right: fraction that ended more than `split_threshold` (default 3 sigma)
  left / right of the intended line (the line through the goal parallel to the push axis);
  split_fraction = share_left + share_right (the share that slid off to either side);
  bimodal: both shares >= 10 % (the distribution split in two, Fig. 6.18b-c), with Sarle's
  bimodality coefficient of the lateral coordinate reported as well (> 5/9 suggests two modes);
- between_paths: fraction whose lateral coordinate lies between the plan's two push paths
  (nano-hand plans: the corridor at the end);
- success_probability: fraction that ended within `tolerance` of the goal;
- touched: fraction the tip touched at all (Fig. 6.18: with short centre pushes some draws are
  never reached).

Optionally `tip_sigma` adds an independent random offset per stroke (the instrument's
positioning error of each move). Seeded and deterministic: the same seed gives the same draws.

Speed: each contact stroke first tests all draws at once (vectorised distance from every
centre to the stroke segment); only the draws the tip can reach go through push_along_path,
which costs ~1.5 ms per stroke in contact (about 20 mechanics steps of 5 nm). 500 draws x 6
strokes take 1.3-2.4 s on one core, 500 x 13 strokes ~4 s (bench/bench_pushing.py, 2026-11-21).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from afm_core.manipulation.plans import PushPlan, model_contact_params


@dataclass
class MonteCarloResult:
    initial: np.ndarray  # (N, 2) sampled true start centres
    final: np.ndarray  # (N, 2) centres after the plan
    goal: np.ndarray  # (2,)
    axis: np.ndarray  # (2,) push axis u
    mean: np.ndarray  # (2,) mean final centre
    sigma_lateral: float  # m, std across the axis
    sigma_along: float  # m, std along the axis
    lateral: np.ndarray  # (N,) final lateral coordinate relative to the goal line (+ left)
    along: np.ndarray  # (N,) final along coordinate relative to the goal
    share_left: float
    share_right: float
    split_fraction: float
    bimodal: bool
    bimodality_coefficient: float
    between_paths: float | None  # fraction between the plan's two paths (None: no paths)
    success_probability: float
    tolerance: float
    split_threshold: float
    touched: float  # fraction touched by at least one stroke
    strokes_applied: int
    samples: int
    seconds: float  # wall time of the pushing

    def summary(self) -> dict:
        nm = 1e9
        return {
            "samples": self.samples,
            "strokes": self.strokes_applied,
            "mean_offset_from_goal_nm": [float(v) for v in (self.mean - self.goal) * nm],
            "sigma_lateral_nm": self.sigma_lateral * nm,
            "sigma_along_nm": self.sigma_along * nm,
            "share_left": self.share_left,
            "share_right": self.share_right,
            "split_fraction": self.split_fraction,
            "bimodal": self.bimodal,
            "bimodality_coefficient": self.bimodality_coefficient,
            "between_paths": self.between_paths,
            "success_probability": self.success_probability,
            "tolerance_nm": self.tolerance * nm,
            "touched": self.touched,
            "seconds": self.seconds,
        }


def bimodality_coefficient(x: np.ndarray) -> float:
    """Sarle's sample bimodality coefficient (g^2 + 1) / (k + 3 (n-1)^2 / ((n-2)(n-3)))."""
    x = np.asarray(x, float)
    n = x.size
    if n < 4 or np.std(x) == 0:
        return 0.0
    from scipy.stats import kurtosis, skew

    g = skew(x, bias=False)
    k = kurtosis(x, bias=False)
    return float((g * g + 1) / (k + 3 * (n - 1) ** 2 / ((n - 2) * (n - 3))))


def monte_carlo_push(
    plan: PushPlan,
    *,
    samples: int = 500,
    sigma: float = 10e-9,
    covariance=None,
    seed: int = 0,
    tolerance: float = 20e-9,
    split_threshold: float | None = None,
    tip_sigma: float = 0.0,
    contact_params=None,
    max_strokes: int | None = None,
) -> MonteCarloResult:
    """Push `samples` draws of the particle's centre with `plan` (module docstring).
    max_strokes: apply only the first that many contact strokes (e.g. "after 6 pushes")."""
    if not (isinstance(samples, (int, np.integer)) and 1 <= samples <= 100_000):
        raise ValueError(f"samples={samples}: must be an integer within [1, 100000]")
    for name, value in (("sigma", sigma), ("tolerance", tolerance), ("tip_sigma", tip_sigma)):
        if not (math.isfinite(value) and value >= 0):
            raise ValueError(f"{name}={value}: must be finite and >= 0 m")
    if tolerance == 0:
        raise ValueError("tolerance=0: must be > 0 m")
    if covariance is None:
        cov = np.eye(2) * sigma * sigma
    else:
        cov = np.asarray(covariance, float)
        if (
            cov.shape != (2, 2)
            or not np.all(np.isfinite(cov))
            or np.any(np.linalg.eigvalsh(0.5 * (cov + cov.T)) < 0)
        ):
            raise ValueError(
                "covariance: must be a finite, symmetric positive semi-definite 2x2 matrix (m^2)"
            )
    threshold = (
        3 * math.sqrt(max(np.max(np.linalg.eigvalsh(cov)), 0.0))
        if split_threshold is None
        else float(split_threshold)
    )
    if not (math.isfinite(threshold) and threshold >= 0):
        raise ValueError(f"split_threshold={split_threshold}: must be finite and >= 0 m")

    from afm_core.physics.pushing import push_along_path
    from afm_core.physics.sample import Sample, Sphere

    cp = model_contact_params(contact_params, plan.tip_radius)
    rng = np.random.default_rng(seed)
    initial = (
        rng.multivariate_normal(plan.particle, cov, size=samples, method="cholesky")
        if np.any(cov)
        else np.tile(plan.particle, (samples, 1))
    )
    strokes = [s for s in plan.strokes if s.contact]
    if max_strokes is not None:
        if not (isinstance(max_strokes, (int, np.integer)) and max_strokes >= 0):
            raise ValueError(f"max_strokes={max_strokes}: must be an integer >= 0")
        strokes = strokes[:max_strokes]
    jitter = (
        rng.normal(0.0, tip_sigma, size=(len(strokes), samples, 2))
        if tip_sigma > 0
        else np.zeros((len(strokes), samples, 2))
    )
    spheres = [Sphere(0, float(x), float(y), plan.particle_radius) for x, y in initial]
    worlds = [Sample(spheres=[s]) for s in spheres]
    pos = initial.copy()
    touched = np.zeros(samples, dtype=bool)
    reach = plan.particle_radius + cp.tip_radius
    t0 = time.perf_counter()
    for k, stroke in enumerate(strokes):
        a = stroke.start + jitter[k]  # per draw
        b = stroke.end + jitter[k]
        rel = pos - a
        ab = b - a
        denom = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300)
        t = np.clip(np.einsum("ij,ij->i", rel, ab) / denom, 0.0, 1.0)
        dist = np.hypot(*(rel - t[:, None] * ab).T)
        hit = np.flatnonzero(dist < reach)
        for i in hit:
            push_along_path(
                worlds[i], np.array([a[i, 0], b[i, 0]]), np.array([a[i, 1], b[i, 1]]), 1e-3, cp
            )
            sp = spheres[i]
            if sp.x != pos[i, 0] or sp.y != pos[i, 1]:
                touched[i] = True
                pos[i] = (sp.x, sp.y)
    seconds = time.perf_counter() - t0
    return summarize(plan, initial, pos, tolerance, threshold, touched, len(strokes), seconds)


def summarize(
    plan: PushPlan,
    initial: np.ndarray,
    final: np.ndarray,
    tolerance: float,
    threshold: float,
    touched: np.ndarray,
    strokes_applied: int,
    seconds: float,
) -> MonteCarloResult:
    u = plan.axis
    n = plan.normal
    rel = final - plan.goal
    lateral = rel @ n
    along = rel @ u
    share_left = float(np.mean(lateral > threshold))
    share_right = float(np.mean(lateral < -threshold))
    between = None
    if plan.path_offsets is not None and plan.path_offsets[0] != plan.path_offsets[1]:
        lat_start = plan.lateral(final)  # relative to the estimated start line, like the offsets
        lo, hi = sorted(plan.path_offsets)
        between = float(np.mean((lat_start >= lo) & (lat_start <= hi)))
    dist = np.hypot(*rel.T)
    return MonteCarloResult(
        initial=initial,
        final=final,
        goal=plan.goal.copy(),
        axis=u.copy(),
        mean=final.mean(axis=0),
        sigma_lateral=float(np.std(lateral)),
        sigma_along=float(np.std(along)),
        lateral=lateral,
        along=along,
        share_left=share_left,
        share_right=share_right,
        split_fraction=share_left + share_right,
        bimodal=bool(share_left >= 0.1 and share_right >= 0.1),
        bimodality_coefficient=bimodality_coefficient(lateral),
        between_paths=between,
        success_probability=float(np.mean(dist <= tolerance)),
        tolerance=tolerance,
        split_threshold=threshold,
        touched=float(np.mean(touched)),
        strokes_applied=strokes_applied,
        samples=len(final),
        seconds=seconds,
    )
