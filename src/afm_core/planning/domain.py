"""Landmark domain and dynamic landmark configuration (book 6.4.1, eq. 6.13-6.15, Fig. 6.14-6.16).

A tip localized at a spot P_l beside a landmark has variance Var(P_l) per axis. Moving from
there to a task point P_t adds Var(d_l,t) (MotionNoise: K_h1 |dx| + K_v2 |dy| + offset in x,
K_h2 |dx| + K_v1 |dy| + offset in y). The task point is in the landmark's domain when, per axis,

    Var_x(d_l,t) + Var_x(P_l) <= Var_x(P_t)        (eq. 6.14)
    Var_y(d_l,t) + Var_y(P_l) <= Var_y(P_t)        (eq. 6.15)

with Var(P_t) the variance the task allows. Around one spot the two linear constraints in
|dx|, |dy| cut out a convex, centrally symmetric polygon (a box when the cross slopes are
0, a diamond when they equal the main slopes). The book localizes the tip on a circle of
radius R_n,t around the particle (Fig. 6.15c); the route planner uses four spots on it
(left / right / down / up, at R_P + R_T + 3 sigma_localized), so the domain here is the union
of the four spots' polygons.

Dynamic configuration (6.4, Fig. 6.13 / 6.14): when no landmark's domain holds the task
point, push the movable landmark that needs the shortest push along the straight line
towards the task point until its domain holds it (the push itself is the virtual nano-hand's
job, afm_core's pushing code; this module only says which particle and where to).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from afm_core import checks
from afm_core.localization.motion_noise import MotionNoise
from afm_core.planning._checks import noise_model, point_copy, sigma_pair
from afm_core.planning.landmark_paths import SPOTS, landmark_site


@dataclass(frozen=True)
class LandmarkDomain:
    """Where a tip localized at one of the landmark's four spots can reach within the required
    variance."""

    landmark_id: int
    center: np.ndarray  # (2,) m, landmark centre
    spots: np.ndarray  # (4, 2) m: left, right, down, up
    localized_variance: np.ndarray  # (2,) m^2, Var(P_l) per axis
    required_variance: np.ndarray  # (2,) m^2, Var(P_t) per axis
    noise: MotionNoise

    def slack(self, points) -> np.ndarray:
        """Per point, the largest over the spots of the smaller per-axis margin (m^2):
        Var_req - Var_l - Var(move). >= 0 inside the domain."""
        p = np.atleast_2d(np.asarray(points, dtype=float))
        if p.shape[-1] != 2 or not np.isfinite(p).all():
            raise ValueError(f"points: must be finite (x, y) pairs in metres, got shape {p.shape}")
        n = self.noise
        d = np.abs(p[:, None, :] - self.spots[None, :, :])  # (points, spots, 2)
        moved = (d > 0).any(axis=-1)
        var_x = n.k_h1 * d[..., 0] + n.k_v2 * d[..., 1] + np.where(moved, n.offset_x, 0.0)
        var_y = n.k_h2 * d[..., 0] + n.k_v1 * d[..., 1] + np.where(moved, n.offset_y, 0.0)
        margin_x = self.required_variance[0] - self.localized_variance[0] - var_x
        margin_y = self.required_variance[1] - self.localized_variance[1] - var_y
        return np.minimum(margin_x, margin_y).max(axis=1)

    def contains(self, points) -> np.ndarray:
        return self.slack(points) >= 0

    def half_extents(self) -> np.ndarray:
        """Reach (m) from a spot along x and along y alone (the polygon's axis half-widths)."""
        n = self.noise
        bx = self.required_variance[0] - self.localized_variance[0] - n.offset_x
        by = self.required_variance[1] - self.localized_variance[1] - n.offset_y
        if bx < 0 or by < 0:
            return np.zeros(2)
        reach_x = min(
            bx / n.k_h1 if n.k_h1 > 0 else math.inf, by / n.k_h2 if n.k_h2 > 0 else math.inf
        )
        reach_y = min(
            bx / n.k_v2 if n.k_v2 > 0 else math.inf, by / n.k_v1 if n.k_v1 > 0 else math.inf
        )
        return np.array([reach_x, reach_y])


@dataclass(frozen=True)
class LandmarkConfiguration:
    """Which landmarks' domains hold the task point, or which particle to push where first."""

    covering_ids: tuple[int, ...]  # landmarks whose domain holds the task point now
    push_landmark_id: int | None  # None when some landmark already covers it
    push_from: np.ndarray | None  # (2,) m, the particle's centre now
    push_to: np.ndarray | None  # (2,) m, where its centre must go
    push_distance: float  # m, 0 when no push is needed


def _variance_pair(sigma, name) -> np.ndarray:
    return sigma_pair(name, sigma) ** 2


def landmark_domain(
    landmark, required_sigma, tip_radius: float, noise: MotionNoise, localized_sigma=None
) -> LandmarkDomain:
    """Domain of one landmark (eq. 6.13-6.15). `localized_sigma`: sigma of a tip localized beside
    it (default: the landmark's observation sigma, i.e. its map error, else the book's 5.0 /
    4.5 nm); `required_sigma`: sigma the task allows, one number or (x, y)."""
    noise = noise_model("noise", noise)
    tip_radius = checks.non_negative("tip_radius", tip_radius)
    site = landmark_site(landmark, localized_sigma)
    required = _variance_pair(required_sigma, "required_sigma")
    return _domain(site, required, tip_radius, noise)


def _domain(site, required, tip_radius, noise) -> LandmarkDomain:
    localized = site.observation_sigma**2
    offsets = site.radius + tip_radius + 3 * site.observation_sigma
    spots = np.repeat(site.center[None, :], 4, axis=0)
    for row, (axis, sign) in enumerate(SPOTS.values()):
        spots[row, axis] += sign * offsets[axis]
    return LandmarkDomain(site.id, site.center, spots, localized, required, noise)


def covering_landmarks(
    task_point,
    landmarks: Sequence,
    required_sigma,
    tip_radius: float,
    noise: MotionNoise,
    localized_sigma=None,
) -> list[int]:
    """Ids of the landmarks whose domain holds the task point, best (largest slack) first."""
    task = point_copy("task_point", task_point)
    noise = noise_model("noise", noise)
    tip_radius = checks.non_negative("tip_radius", tip_radius)
    required = _variance_pair(required_sigma, "required_sigma")
    slack = []
    for i, lm in enumerate(landmarks):
        domain = _domain(
            landmark_site(lm, localized_sigma, f"landmarks[{i}]"), required, tip_radius, noise
        )
        s = float(domain.slack(task)[0])
        if s >= 0:
            slack.append((s, domain.landmark_id))
    return [lid for _, lid in sorted(slack, key=lambda t: -t[0])]


def plan_landmark_configuration(
    task_point,
    landmarks: Sequence,
    required_sigma,
    tip_radius: float,
    noise: MotionNoise,
    movable_ids: Sequence[int] | None = None,
    localized_sigma=None,
    keep_clear: float = 0.0,
    resolution: int = 400,
) -> LandmarkConfiguration:
    """Covering landmarks of the task point; if there are none, the push that makes one (6.4).

    A candidate is pushed straight towards the task point; its centre stops once the task point
    is in its domain (searched on `resolution` steps, then refined by bisection), and never
    closer to the task point than R_P + R_T + keep_clear (the particle must not sit on the task
    point). The candidate with the shortest push wins. `movable_ids`: landmarks that may be
    pushed (default: all). Raises ValueError when the required sigma is below what a
    localization gives (no domain can exist), for unknown movable ids, or when no push works.
    """
    task = point_copy("task_point", task_point)
    noise = noise_model("noise", noise)
    tip_radius = checks.non_negative("tip_radius", tip_radius)
    keep_clear = checks.non_negative("keep_clear", keep_clear)
    required = _variance_pair(required_sigma, "required_sigma")
    if not (isinstance(resolution, int) and resolution >= 2):
        raise ValueError(f"resolution={resolution!r}: must be an integer >= 2")
    sites = [
        landmark_site(lm, localized_sigma, f"landmarks[{i}]") for i, lm in enumerate(landmarks)
    ]
    if not sites:
        raise ValueError("landmarks: need at least one landmark")
    ids = [s.id for s in sites]
    if movable_ids is not None:
        unknown = sorted(set(int(i) for i in movable_ids) - set(ids))
        if unknown:
            raise ValueError(f"movable_ids: unknown landmark id(s) {unknown}; known ids are {ids}")
    for s in sites:
        if (s.observation_sigma**2 > required).any():
            raise ValueError(
                f"required_sigma={np.sqrt(required).tolist()} m: below the localized sigma "
                f"{s.observation_sigma.tolist()} m of landmark {s.id}; no landmark domain can "
                "hold it"
            )
    covering = covering_landmarks(
        task, landmarks, np.sqrt(required), tip_radius, noise, localized_sigma
    )
    if covering:
        return LandmarkConfiguration(tuple(covering), None, None, None, 0.0)
    movable = set(ids) if movable_ids is None else set(int(i) for i in movable_ids)
    best = None
    for site in sites:
        if site.id not in movable:
            continue
        offset = task - site.center
        distance = float(np.hypot(*offset))
        closest = site.radius + tip_radius + keep_clear
        if distance <= closest:
            continue
        direction = offset / distance

        def inside(travel: float) -> bool:
            moved = type(site)(
                site.id, site.center + direction * travel, site.radius, site.observation_sigma
            )
            return bool(_domain(moved, required, tip_radius, noise).contains(task)[0])

        travels = np.linspace(0.0, distance - closest, resolution)
        hits = [t for t in travels if inside(float(t))]
        if not hits:
            continue
        lo_index = int(np.searchsorted(travels, hits[0])) - 1
        lo, hi = (float(travels[lo_index]), float(hits[0])) if lo_index >= 0 else (0.0, 0.0)
        for _ in range(60):  # shortest push: bisect between the last miss and the first hit
            if hi - lo <= 1e-12:
                break
            mid = 0.5 * (lo + hi)
            lo, hi = (lo, mid) if inside(mid) else (mid, hi)
        if best is None or hi < best[0]:
            best = (hi, site, site.center + direction * hi)
    if best is None:
        raise ValueError(
            f"task_point={task.tolist()}: no movable landmark can be pushed so that its domain "
            f"holds it within required_sigma={np.sqrt(required).tolist()} m"
        )
    travel, site, target = best
    return LandmarkConfiguration((), site.id, site.center.copy(), target, float(travel))


__all__ = [
    "LandmarkDomain",
    "LandmarkConfiguration",
    "landmark_domain",
    "covering_landmarks",
    "plan_landmark_configuration",
]
