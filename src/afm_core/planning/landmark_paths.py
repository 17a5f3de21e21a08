"""Tip paths through landmark observations (book 6.2: Guidelines 6.1 / 6.2, eq. 6.11-6.12).

Single landmark (6.2.1, Fig. 6.4 / 6.7). The tip observes a particle with two local scan
lines, one along x (updates x) and one along y (updates y), and ends at one of four
localization spots around it: left / right (on the particle's horizontal centre line) or
down / up (vertical centre line), R_P + R_T + 3 sigma from its centre.
- Guideline 6.1: the spot is the one nearest the task point.
- Guideline 6.2: of the ways to get there, the shortest (expected) path.
A scan mode (Table 6.2) is two letters: the axis of the first line, then the axis on which
the final spot lies ("h": left/right, "v": down/up). "hv" and "vh" end where their second
line ends; "hh" (h line, v line, then round to left/right) and "vv" (v, h, round to down/up)
take an extra leg but scan the first line from the side the tip comes from.

Waypoints carry the predicted covariance (afm_core.localization.MotionNoise for every move,
the shared model of the Kalman filter) and, at each observation, the Kalman update of the
observed axis with the observation noise sigma (default: the landmark's map error, or the
book's 5.0 nm in x / 4.5 nm in y, Fig. 7.10). The update happens where the line crosses the
particle's centre and the rest of the line is predicted from there (eq. 5.16-5.21). Moves
between lines go round the particle's corners, so no move cuts through the clearance.

Many landmarks (6.2.2). The observation distance w_ij (eq. 6.11) is the cost of observing
landmark j from the localization spot of landmark i nearest to j, with the covariance of a
tip localized there: scan count x expected travel (the ObservationPlan's approach plus
expected scan lines, eq. 6.10), the book's "scantimes" factor, which makes an observation
that needs several lines (after a long, uncertain move) dearer than its travel alone. The
book's Dist / Dr term is the approach, kept in metres here. Pairs whose observation cannot
be planned (the tip would be too uncertain for the particle) have no edge. The matrix
(eq. 6.12) with a start node and a task node is searched for the cheapest chain of
observations (Fig. 6.9) by landmark_chain.plan_landmark_chain, which computes only the edges
that can matter; `cheapest_chain` searches a given matrix with scipy.sparse.csgraph.dijkstra.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from afm_core import checks
from afm_core.localization.motion_noise import MotionNoise
from afm_core.planning._checks import covariance_matrix, noise_model, point_copy, sigma_pair
from afm_core.planning.observation_plan import ObservationPlan, line_end_distance, plan_observation

BOOK_OBSERVATION_SIGMA = (5.0e-9, 4.5e-9)  # m, map error sigma x / y (Fig. 7.10)
SPOTS = {"left": (0, -1.0), "right": (0, 1.0), "down": (1, -1.0), "up": (1, 1.0)}
MODES = {"hh": (0, 0), "hv": (0, 1), "vh": (1, 0), "vv": (1, 1)}  # (first line axis, spot axis)
ROLES = ("move", "observe_h", "observe_v", "task")


@dataclass(frozen=True)
class Waypoint:
    position: np.ndarray  # (2,) m, afm_task frame
    covariance: np.ndarray  # 2x2 m^2 on arrival (after the update for an observation)
    role: str  # "move" | "observe_h" | "observe_v" | "task"
    landmark_id: int  # -1 when the waypoint belongs to no landmark


@dataclass(frozen=True)
class LandmarkRoute:
    """A planned tip route: waypoints from `start` (not itself a waypoint) to the end."""

    start: np.ndarray
    start_covariance: np.ndarray
    waypoints: tuple[Waypoint, ...]
    length: float  # m, nominal travel (each landmark found on its first line)
    expected_cost: float  # m, travel with each observation line at its expected cost (eq. 6.10)
    landmark_ids: tuple[int, ...]
    modes: tuple[str, ...]  # scan mode per landmark
    spots: tuple[str, ...]  # localization spot per landmark
    observations: tuple[ObservationPlan, ...]

    @property
    def final_covariance(self) -> np.ndarray:
        return self.waypoints[-1].covariance

    @property
    def final_sigma(self) -> np.ndarray:
        return np.sqrt(np.diag(self.final_covariance))


@dataclass(frozen=True)
class _Site:
    id: int
    center: np.ndarray
    radius: float
    observation_sigma: np.ndarray
    covariance = None  # the observation sigma above already holds the map error

    @property
    def x(self) -> float:
        return float(self.center[0])

    @property
    def y(self) -> float:
        return float(self.center[1])


def landmark_site(landmark, observation_sigma=None, name: str = "landmark") -> _Site:
    """A landmark's planning data from an imaging Landmark (id, x, y, radius, covariance) or any
    object with those attributes. The observation sigma is `observation_sigma` if given, else the
    landmark's own map error (sqrt of its covariance diagonal), else the book's 5.0 / 4.5 nm."""
    try:
        lid, x, y, radius = int(landmark.id), landmark.x, landmark.y, landmark.radius
    except (AttributeError, TypeError, ValueError):
        raise ValueError(
            f"{name}: needs id, x, y and radius (an afm_core.imaging.landmarks.Landmark), "
            f"got {landmark!r}"
        ) from None
    center = point_copy(f"{name} {lid} centre (x, y)", (x, y))
    r = checks.positive(f"{name} {lid} radius", radius)
    if observation_sigma is not None:
        sigma = sigma_pair("observation_sigma", observation_sigma)
    elif getattr(landmark, "covariance", None) is not None:
        cov = covariance_matrix(f"{name} {lid} covariance", landmark.covariance)
        sigma = np.sqrt(np.diag(cov))
        sigma = sigma_pair(f"{name} {lid} covariance diagonal sqrt", sigma)
    else:
        sigma = np.array(BOOK_OBSERVATION_SIGMA)
    return _Site(lid, center, r, sigma)


def _kalman_axis_update(cov: np.ndarray, axis: int, sigma: float) -> np.ndarray:
    """Covariance after observing one axis with noise sigma: P - P h^T (h P h^T + r^2)^-1 h P."""
    gain = cov[:, axis] / (cov[axis, axis] + sigma * sigma)
    updated = cov - np.outer(gain, cov[axis, :])
    return 0.5 * (updated + updated.T)


def _continue(noise: MotionNoise, cov: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Prediction for the rest of a move already under way: its settling offset was counted at
    its start."""
    if not d.any():
        return cov
    added = noise.added_covariance(d[0], d[1]) - np.diag([noise.offset_x, noise.offset_y])
    return cov + added


def _clear_distance(cov: np.ndarray, axis: int, site: _Site, tip_radius: float) -> float:
    return 3.0 * math.sqrt(cov[axis, axis]) + tip_radius + site.radius


class _Builder:
    def __init__(self, start, cov, noise):
        self.position, self.cov, self.noise = start.copy(), cov.copy(), noise
        self.waypoints: list[Waypoint] = []
        self.length = 0.0
        self.expected = 0.0

    def move(self, target, role="move", landmark_id=-1, counted=True):
        d = np.asarray(target, float) - self.position
        if d.any():
            self.cov = self.noise.predict(self.cov, d[0], d[1])
            step = float(np.hypot(*d))
            self.length += step
            if counted:
                self.expected += step
            self.position = np.asarray(target, float).copy()
        self.waypoints.append(Waypoint(self.position.copy(), self.cov.copy(), role, landmark_id))

    def observe(self, plan: ObservationPlan, site: _Site, tip_radius: float):
        """Approach and scan the plan's first line (nominal: found there), updating at the
        crossing.

        Once the particle is seen the along position is known to the observation sigma, so the
        line ends where 3 sigma (updated, grown to the end) + R_T + R_P clears the particle (eq.
        6.2 with the posterior) instead of the planned end, which allowed for the prior."""
        axis = 0 if plan.direction == "h" else 1
        line = plan.lines[0]
        self.move(line.start, "move", site.id, counted=False)
        crossing = line.start.copy()
        crossing[axis] = site.center[axis]
        to_crossing = crossing - line.start
        self.cov = self.noise.predict(self.cov, to_crossing[0], to_crossing[1])
        self.cov = _kalman_axis_update(self.cov, axis, float(site.observation_sigma[axis]))
        slope = self.noise.k_h1 if axis == 0 else self.noise.k_v1
        end = crossing.copy()
        end[axis] += math.copysign(
            line_end_distance(self.cov[axis, axis], slope, 0.0, tip_radius + site.radius),
            line.end[axis] - crossing[axis],
        )
        rest = end - crossing
        self.cov = _continue(self.noise, self.cov, rest)
        scanned = float(np.hypot(*to_crossing) + np.hypot(*rest))
        self.length += scanned
        self.expected += (
            plan.expected_cost - line.length + scanned
        )  # approach + expected lines (eq. 6.10)
        self.position = end
        self.waypoints.append(
            Waypoint(
                self.position.copy(),
                self.cov.copy(),
                "observe_h" if axis == 0 else "observe_v",
                site.id,
            )
        )


def _localize(
    builder: _Builder,
    site: _Site,
    first_axis: int,
    spot: str,
    second_sign: float,
    tip_radius: float,
) -> list[ObservationPlan]:
    """Two lines (first_axis, then the other) ending at `spot`; second_sign: side the second line
    starts on."""
    noise = builder.noise
    spot_axis, spot_sign = SPOTS[spot]
    second_axis = 1 - first_axis
    plans = []
    plan = plan_observation(
        builder.position,
        builder.cov,
        site.center,
        site.radius,
        tip_radius,
        noise,
        "h" if first_axis == 0 else "v",
    )
    builder.observe(plan, site, tip_radius)
    plans.append(plan)
    # round the corner: out along the second axis beside the particle, then to its centre line
    corner = builder.position.copy()
    for _ in range(
        2
    ):  # the corner's distance from the particle is the second line's start distance
        corner[second_axis] = site.center[second_axis] + second_sign * _clear_distance(
            noise.predict(builder.cov, *(corner - builder.position)), second_axis, site, tip_radius
        )
        trial = plan_observation(
            corner,
            noise.predict(builder.cov, *(corner - builder.position)),
            site.center,
            site.radius,
            tip_radius,
            noise,
            "h" if second_axis == 0 else "v",
        )
        corner[second_axis] = trial.lines[0].start[second_axis]
    builder.move(corner, "move", site.id)
    plan = plan_observation(
        builder.position,
        builder.cov,
        site.center,
        site.radius,
        tip_radius,
        noise,
        "h" if second_axis == 0 else "v",
    )
    builder.observe(plan, site, tip_radius)
    plans.append(plan)
    if spot_axis == first_axis:  # "hh" / "vv": round the next corner to the spot on the first axis
        target = site.center.copy()
        target[spot_axis] += spot_sign * _clear_distance(builder.cov, spot_axis, site, tip_radius)
        corner = builder.position.copy()
        corner[spot_axis] = target[spot_axis]
        builder.move(corner, "move", site.id)
        target[spot_axis] = site.center[spot_axis] + spot_sign * _clear_distance(
            builder.cov, spot_axis, site, tip_radius
        )
        builder.move(target, "move", site.id)
    return plans


def _spot_point(site: _Site, spot: str, tip_radius: float) -> np.ndarray:
    axis, sign = SPOTS[spot]
    p = site.center.copy()
    p[axis] += sign * (site.radius + tip_radius + 3 * float(site.observation_sigma[axis]))
    return p


def nearest_spot(
    site_center,
    site_radius: float,
    tip_radius: float,
    toward,
    observation_sigma=BOOK_OBSERVATION_SIGMA,
    allowed: Sequence[str] = tuple(SPOTS),
) -> str:
    """Guideline 6.1: the localization spot (of `allowed`) nearest the point `toward`."""
    site = _Site(
        -1,
        point_copy("site_center", site_center),
        checks.positive("site_radius", site_radius),
        sigma_pair("observation_sigma", observation_sigma),
    )
    toward = point_copy("toward", toward)
    return min(
        allowed, key=lambda s: float(np.linalg.norm(_spot_point(site, s, tip_radius) - toward))
    )


def _single(start, cov, site, tip_radius, noise, mode, spot, second_sign):
    builder = _Builder(start, cov, noise)
    plans = _localize(builder, site, MODES[mode][0], spot, second_sign, tip_radius)
    return builder, plans


def plan_landmark_route(
    start_mean,
    start_covariance,
    landmark,
    tip_radius: float,
    noise: MotionNoise,
    task_point=None,
    mode: str | None = None,
    spot: str | None = None,
    observation_sigma=None,
) -> LandmarkRoute:
    """Route from the tip's Gaussian through one landmark's localization to the task point.

    `landmark`: an imaging Landmark (or an object with id, x, y, radius[, covariance]).
    Spot: `spot` if given, else the one nearest the task point (Guideline 6.1; nearest the
    start when there is no task point), among those the mode allows. Mode: `mode` if given,
    else of the modes that end at that spot the one with the least expected cost (6.2).
    The last waypoint is the task point (role "task") when one is given, else the spot.
    Raises ValueError naming the argument for bad input or an unknown mode / spot, or when
    the observation cannot be planned (the tip is too uncertain for the particle).
    """
    start = point_copy("start_mean", start_mean)
    cov = covariance_matrix("start_covariance", start_covariance)
    tip_radius = checks.non_negative("tip_radius", tip_radius)
    noise = noise_model("noise", noise)
    site = landmark_site(landmark, observation_sigma)
    task = None if task_point is None else point_copy("task_point", task_point)
    if mode is not None and mode not in MODES:
        raise ValueError(f"mode={mode!r}: must be one of {sorted(MODES)}")
    if spot is not None and spot not in SPOTS:
        raise ValueError(f"spot={spot!r}: must be one of {sorted(SPOTS)}")
    if mode is not None and spot is not None and SPOTS[spot][0] != MODES[mode][1]:
        raise ValueError(
            f"spot={spot!r} is not reachable in mode={mode!r}: mode {mode!r} ends on the "
            f"{'left/right' if MODES[mode][1] == 0 else 'down/up'} spots"
        )
    if spot is None:
        allowed = [s for s in SPOTS if mode is None or SPOTS[s][0] == MODES[mode][1]]
        spot = nearest_spot(
            site.center,
            site.radius,
            tip_radius,
            task if task is not None else start,
            site.observation_sigma,
            allowed,
        )
    spot_axis, spot_sign = SPOTS[spot]
    modes = (
        [mode]
        if mode is not None
        else [m for m, (_, end_axis) in MODES.items() if end_axis == spot_axis]
    )
    best = None
    for m in modes:
        first_axis = MODES[m][0]
        # natural modes: the second line must end on the spot's side; otherwise try both sides
        signs = (-spot_sign,) if first_axis != spot_axis else (-1.0, 1.0)
        for sign in signs:
            builder, plans = _single(start, cov, site, tip_radius, noise, m, spot, sign)
            if task is not None:
                builder.move(task, "task", -1)
            if best is None or builder.expected < best[0].expected - 1e-15:
                best = (builder, plans, m)
    builder, plans, m = best
    return LandmarkRoute(
        start,
        cov,
        tuple(builder.waypoints),
        builder.length,
        builder.expected,
        (site.id,),
        (m,),
        (spot,),
        tuple(plans),
    )


# -- many landmarks ------------------------------------------------------------------------
def _observation_cost(position, cov, site: _Site, tip_radius: float, noise: MotionNoise) -> float:
    """Eq. 6.11: scan count x expected travel to observe `site` (the cheaper line direction); inf
    when it cannot be planned. The book multiplies by the number of scans ("scantimes"), so an
    observation that needs several lines costs more than its travel: the reason to hop between
    near landmarks."""
    costs = []
    for direction in ("h", "v"):
        try:
            plan = plan_observation(
                position, cov, site.center, site.radius, tip_radius, noise, direction
            )
            costs.append(len(plan.lines) * plan.expected_cost)
        except ValueError:
            costs.append(math.inf)
    return min(costs)


ARRIVAL_SIGMA_FACTOR = (
    3.0  # arrival sigma assumed when predicting a localization: 3x the observation sigma
)


def _localized_covariance(
    site: _Site, spot: str, tip_radius: float, noise: MotionNoise
) -> tuple[np.ndarray, np.ndarray]:
    """Covariance at `spot` after localizing at the site (both lines, the growth after each
    update and the moves round the particle included), for a tip arriving from the opposite side
    with ARRIVAL_SIGMA_FACTOR times the observation sigma (conservative: the Kalman posterior
    grows with the prior, and a tip hopping between near landmarks arrives better than that).
    Returns (covariance, spot position). The route does not depend on where the particle is, so
    it is kept by radius, sigma and spot (a map of like particles plans it once)."""
    key = (spot, tip_radius, noise, site.radius, tuple(site.observation_sigma))
    cached = _LOCALIZED_CACHE.get(key)
    if cached is None:
        axis, sign = SPOTS[spot]
        arrival = site.center.copy()
        arrival[axis] -= (
            sign * 2 * (site.radius + tip_radius + 10 * float(site.observation_sigma.max()))
        )
        route = plan_landmark_route(
            arrival,
            np.diag((ARRIVAL_SIGMA_FACTOR * site.observation_sigma) ** 2),
            site,
            tip_radius,
            noise,
            spot=spot,
            observation_sigma=site.observation_sigma,
        )
        offset = route.waypoints[-1].position - site.center
        cached = _LOCALIZED_CACHE.setdefault(key, (route.final_covariance, offset))
        if len(_LOCALIZED_CACHE) > 4096:
            _LOCALIZED_CACHE.clear()
    return cached[0], site.center + cached[1]


_LOCALIZED_CACHE: dict = {}


def observation_distance(
    from_landmark, to_landmark, tip_radius: float, noise: MotionNoise, observation_sigma=None
) -> float:
    """Eq. 6.11: scan count x expected travel (m) to observe `to_landmark` from the spot of
    `from_landmark` nearest to it, with the covariance of a tip localized there (see
    _localized_covariance); inf when the observation cannot be planned."""
    tip_radius = checks.non_negative("tip_radius", tip_radius)
    noise = noise_model("noise", noise)
    a = landmark_site(from_landmark, observation_sigma, "from_landmark")
    b = landmark_site(to_landmark, observation_sigma, "to_landmark")
    return _pair_cost(a, b, tip_radius, noise)


def _pair_cost(a: _Site, b: _Site, tip_radius: float, noise: MotionNoise) -> float:
    spot = nearest_spot(a.center, a.radius, tip_radius, b.center, a.observation_sigma)
    try:
        cov, position = _localized_covariance(a, spot, tip_radius, noise)
    except ValueError:
        return math.inf  # the tip cannot even localize at `a` with this noise
    return _observation_cost(position, cov, b, tip_radius, noise)


def _sites(landmarks, observation_sigma) -> list[_Site]:
    sites = [
        landmark_site(lm, observation_sigma, f"landmarks[{i}]") for i, lm in enumerate(landmarks)
    ]
    ids = [s.id for s in sites]
    if len(set(ids)) != len(ids):
        raise ValueError(f"landmarks: ids must be unique, got {ids}")
    return sites


def observation_distance_matrix(
    landmarks: Sequence,
    tip_radius: float,
    noise: MotionNoise,
    observation_sigma=None,
    symmetric: bool = False,
) -> np.ndarray:
    """Eq. 6.12: W[i, j] = observation distance from landmark i to j (eq. 6.11), 0 on the diagonal,
    inf where the observation cannot be planned. `symmetric`: max(W, W^T), for sequencing."""
    tip_radius = checks.non_negative("tip_radius", tip_radius)
    noise = noise_model("noise", noise)
    sites = _sites(landmarks, observation_sigma)
    n = len(sites)
    w = np.zeros((n, n))
    for i in range(n):
        for j in range(n):
            if i != j:
                w[i, j] = _pair_cost(sites[i], sites[j], tip_radius, noise)
    return np.maximum(w, w.T) if symmetric else w


def cheapest_chain(weights, source: int, target: int) -> tuple[list[int], float]:
    """Cheapest path source -> target in a directed weight matrix (inf or NaN: no edge;
    weights >= 0), by scipy.sparse.csgraph.dijkstra. Raises ValueError when the target cannot be
    reached."""
    w = np.array(weights, dtype=float)
    if w.ndim != 2 or w.shape[0] != w.shape[1]:
        raise ValueError(f"weights: must be a square matrix, got shape {w.shape}")
    n = w.shape[0]
    for name, v in (("source", source), ("target", target)):
        if not (isinstance(v, (int, np.integer)) and 0 <= v < n):
            raise ValueError(f"{name}={v!r}: must be a node index in [0, {n})")
    w[np.isnan(w)] = np.inf
    if (w < 0).any():
        raise ValueError("weights: must be >= 0 (Dijkstra); found a negative entry")
    np.fill_diagonal(w, np.inf)
    rows, cols = np.nonzero(np.isfinite(w))
    # csgraph drops explicit zeros in a sparse matrix's structure only if told to; a zero-cost edge
    # is kept by nudging it to the smallest positive float, which changes no sum measurably.
    graph = csr_matrix(
        (np.maximum(w[rows, cols], np.finfo(float).tiny), (rows, cols)), shape=(n, n)
    )
    distances, predecessors = dijkstra(
        graph, directed=True, indices=source, return_predecessors=True
    )
    if not np.isfinite(distances[target]):
        raise ValueError(f"no chain of known edges leads from node {source} to node {target}")
    path = [target]
    while path[-1] != source:
        path.append(int(predecessors[path[-1]]))
    path.reverse()
    return path, float(
        sum(w[a, b] if np.isfinite(w[a, b]) else 0.0 for a, b in zip(path, path[1:]))
    )
