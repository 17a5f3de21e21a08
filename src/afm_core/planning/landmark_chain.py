"""The cheapest chain of landmark observations from the tip to a task point (book 6.2.2, Fig. 6.9).

Nodes: the start, every landmark, the task. Edges (eq. 6.11-6.12, see landmark_paths): start ->
landmark (expected cost of observing it from the start's Gaussian), landmark -> landmark
(observation distance), landmark -> task (distance from its spot nearest the task; only if the
predicted sigma at the task is within `required_sigma`, when given), start -> task only when
`required_sigma` is given and met without any observation.

The search is Dijkstra's, but an edge's cost (two observation plans) is worked out only when it
could still matter. Every observation edge u -> j costs at least |p - c_j| + R_T + R_j, p the
point the tip leaves from (the start, or one of u's localization spots) and c_j, R_j the
particle's centre and radius: scan count >= 1, and the expected travel is at least the approach
plus the first line, which runs through the centre and ends R_T + R_j past it. These bounds are
one numpy expression over the whole map; a node's edges wait in the queue in the order of their
bounds and are computed when the queue reaches them, so edges that cannot beat what is already
known are never computed. The result is the same chain as with the full (n + 2)^2 matrix, which
took minutes and gigabytes for a few thousand landmarks.
"""

from __future__ import annotations

import heapq
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from afm_core import checks
from afm_core.localization.motion_noise import MotionNoise
from afm_core.planning import limits
from afm_core.planning._checks import covariance_matrix, noise_model, point_copy, sigma_pair
from afm_core.planning.landmark_paths import (
    SPOTS,
    LandmarkRoute,
    Waypoint,
    _localized_covariance,
    _observation_cost,
    _pair_cost,
    _Site,
    _sites,
    nearest_spot,
    plan_landmark_route,
)

CHUNK = 64  # candidate edges of a settled node kept ranked at a time


@dataclass(frozen=True)
class LandmarkChain:
    """Cheapest chain of landmark observations from the start to the task (Dijkstra, Fig. 6.9)."""

    landmark_ids: tuple[int, ...]
    cost: float  # m, sum of the chain's edge weights
    # (n + 2) x (n + 2), indexed [i, j]: start, the landmarks in input order, task; inf: no edge.
    # Computed on first access (the search computes only the edges it needs).
    weights: ChainWeights
    route: LandmarkRoute
    meets_required: bool  # the route's final sigma is within required_sigma (True when none given)
    edges_computed: int = 0  # observation edges the search worked out


class ChainWeights:
    """The weight matrix of eq. 6.12 without building it: w[i, j] is computed on first access."""

    def __init__(self, search: _ChainSearch):
        self._search = search
        self.shape = (search.n + 2, search.n + 2)

    def __getitem__(self, key) -> float:
        i, j = key
        return self._search.weight(int(i), int(j))


class _ChainSearch:
    def __init__(self, start, cov, sites: list[_Site], task, tip_radius, noise, required):
        self.start, self.cov, self.sites, self.task = start, cov, sites, task
        self.tip_radius, self.noise, self.required = tip_radius, noise, required
        self.n = len(sites)
        self.centres = np.array([s.center for s in sites]).reshape(-1, 2)
        self.reach = tip_radius + np.array([s.radius for s in sites])
        self.cache: dict[tuple[int, int], float] = {}
        self.edges_computed = 0
        self.max_edges = limits.MAX_CHAIN_EDGES
        self.deadline = time.monotonic() + limits.MAX_CHAIN_SECONDS
        self.points: dict[int, np.ndarray] = {}  # node -> where the tip leaves it from
        self.done_landmarks = np.zeros(self.n, dtype=bool)

    def meets(self, c: np.ndarray) -> bool:
        return self.required is None or bool((np.sqrt(np.diag(c)) <= self.required).all())

    def weight(self, i: int, j: int) -> float:
        """Edge i -> j of eq. 6.12 (0: start, 1..n: landmarks, n + 1: task), inf: no edge."""
        task = self.n + 1
        if not (0 <= i <= task and 0 <= j <= task):
            raise IndexError(f"node ({i}, {j}) outside [0, {task}]")
        if i == j or j == 0 or i == task:
            return math.inf
        cached = self.cache.get((i, j))
        if cached is None:
            cached = self.cache[(i, j)] = self._compute(i, j)
        return cached

    def _compute(self, i: int, j: int) -> float:
        if j == self.n + 1:
            return self._to_task(i)
        self.edges_computed += 1
        self.check_limits()
        site = self.sites[j - 1]
        if i == 0:
            return _observation_cost(self.start, self.cov, site, self.tip_radius, self.noise)
        return _pair_cost(self.sites[i - 1], site, self.tip_radius, self.noise)

    def check_limits(self) -> None:
        over_time = time.monotonic() > self.deadline
        if self.edges_computed > self.max_edges or over_time:
            what = (
                f"more than {limits.MAX_CHAIN_SECONDS:g} s"
                if over_time
                else f"more than {self.max_edges} observation edges"
            )
            raise ValueError(
                f"landmarks: the chain search needs {what} (the limit) among the {self.n} "
                "landmarks; plan to a nearer target first, or give fewer landmarks near the route"
            )

    def _to_task(self, i: int) -> float:
        d = self.task - self.start
        if i == 0:
            ok = self.required is not None and self.meets(self.noise.predict(self.cov, *d))
            return float(np.hypot(*d)) if ok else math.inf
        site = self.sites[i - 1]
        spot = nearest_spot(
            site.center, site.radius, self.tip_radius, self.task, site.observation_sigma
        )
        try:
            localized, position = _localized_covariance(site, spot, self.tip_radius, self.noise)
        except ValueError:
            return math.inf
        d = self.task - position
        return float(np.hypot(*d)) if self.meets(self.noise.predict(localized, *d)) else math.inf

    def lower_bounds(self, u: int) -> np.ndarray:
        """A lower bound of every edge u -> landmark (see the module docstring), inf: none."""
        points = self.points.get(u)
        if points is None:
            points = self.points[u] = self._departures(u)
        if not len(points):
            return np.full(self.n, math.inf)
        gaps = np.hypot(
            self.centres[:, None, 0] - points[None, :, 0],
            self.centres[:, None, 1] - points[None, :, 1],
        ).min(axis=1)
        bounds = (gaps + self.reach) * (1 - 1e-9)  # rounding of the plans' sums
        if u:
            bounds[u - 1] = math.inf
        bounds[self.done_landmarks] = math.inf  # already settled: no edge into them can matter
        return bounds

    def _departures(self, u: int) -> np.ndarray:
        """Where the tip leaves node u from: the start, or the landmark's localization spots."""
        if u == 0:
            return self.start[None, :]
        self.check_limits()
        site, points = self.sites[u - 1], []
        for spot in SPOTS:
            try:
                points.append(_localized_covariance(site, spot, self.tip_radius, self.noise)[1])
            except ValueError:
                pass  # the tip cannot localize there: no edge leaves from that spot
        return np.array(points).reshape(-1, 2)

    def chunk(self, u: int, after: tuple[float, int] | None = None):
        """u's next CHUNK candidate edges in the order (bound, index), those after `after`, or
        None. Only a chunk is kept per node (the whole ranking of a 20000-landmark map for each
        of thousands of settled nodes took 700 MB); the next is ranked when the queue reaches
        it, without the landmarks settled meanwhile."""
        bounds = self.lower_bounds(u)
        if after is not None:
            last, index = after
            earlier = bounds < last
            earlier[: index + 1] |= bounds[: index + 1] == last
            bounds[earlier] = math.inf
        order = np.argsort(bounds, kind="stable")[:CHUNK]
        bounds = bounds[order]
        finite = np.isfinite(bounds)
        if not finite.any():
            return None
        return order[finite], bounds[finite], 0

    def run(self) -> tuple[list[int], float]:
        """Dijkstra with edges computed when the queue reaches their lower bound."""
        task = self.n + 1
        dist, previous, done = {0: 0.0}, {}, set()
        queue: list = [(0.0, 0, 0, None)]  # (key, tie, node, pending edges or None)
        tie = 1
        while queue:
            key, _, u, pending = heapq.heappop(queue)
            if pending is not None:  # the next of u's edges, in the order of their bounds
                order, bounds, k = pending
                following = (
                    (order, bounds, k + 1)
                    if k + 1 < len(order)
                    else (
                        self.chunk(u, (bounds[k], int(order[k]))) if len(order) == CHUNK else None
                    )
                )
                if following is not None:
                    key = dist[u] + following[1][following[2]]
                    heapq.heappush(queue, (key, tie, u, following))
                    tie += 1
                v = int(order[k]) + 1
                targets = () if v in done else (v,)
            elif u in done:
                continue
            else:
                done.add(u)
                if u == task:
                    break
                if u:
                    self.done_landmarks[u - 1] = True
                pending = self.chunk(u)
                if pending is not None:
                    heapq.heappush(queue, (dist[u] + pending[1][0], tie, u, pending))
                    tie += 1
                targets = (task,)
            for v in targets:
                new = dist[u] + self.weight(u, v)
                if new < dist.get(v, math.inf):
                    dist[v], previous[v] = new, u
                    heapq.heappush(queue, (new, tie, v, None))
                    tie += 1
        if task not in done:
            raise ValueError("no chain of known edges leads from the start to the task")
        path = [task]
        while path[-1] != 0:
            path.append(previous[path[-1]])
        path.reverse()
        return path, float(sum(self.weight(a, b) for a, b in zip(path, path[1:])))


def plan_landmark_chain(
    start_mean,
    start_covariance,
    landmarks: Sequence,
    task_point,
    tip_radius: float,
    noise: MotionNoise,
    required_sigma=None,
    observation_sigma=None,
) -> LandmarkChain:
    """Cheapest chain of landmark observations from the tip's Gaussian to the task point (6.2.2).

    Nodes and edges: see the module docstring. Dijkstra picks the chain; the route through it is
    built landmark by landmark (each localized at the spot nearest the next landmark, the last at
    the spot nearest the task). Raises ValueError for bad input, duplicate or no landmarks, when
    no chain reaches the task, and when the search would compute more than
    limits.MAX_CHAIN_EDGES observation edges or run longer than limits.MAX_CHAIN_SECONDS.
    """
    start = point_copy("start_mean", start_mean)
    cov = covariance_matrix("start_covariance", start_covariance)
    task = point_copy("task_point", task_point)
    tip_radius = checks.non_negative("tip_radius", tip_radius)
    noise = noise_model("noise", noise)
    required = None if required_sigma is None else sigma_pair("required_sigma", required_sigma)
    sites = _sites(landmarks, observation_sigma)
    if not sites:
        raise ValueError("landmarks: need at least one landmark")
    search = _ChainSearch(start, cov, sites, task, tip_radius, noise, required)
    try:
        path, cost = search.run()
    except ValueError as exc:
        if not str(exc).startswith("no chain"):
            raise
        raise ValueError(
            "task_point: no chain of landmark observations reaches it"
            + ("" if required is None else f" within required_sigma={required.tolist()} m")
        ) from None
    chain = [sites[k - 1] for k in path[1:-1]]
    route = _chain_route(start, cov, chain, task, tip_radius, noise)
    met = required is None or bool((route.final_sigma <= required * (1 + 1e-12)).all())
    return LandmarkChain(
        tuple(s.id for s in chain), cost, ChainWeights(search), route, met, search.edges_computed
    )


def _chain_route(start, cov, chain: list[_Site], task, tip_radius, noise) -> LandmarkRoute:
    waypoints, plans, modes, spots = [], [], [], []
    length = expected = 0.0
    position, covariance = start, cov
    for k, site in enumerate(chain):
        aim = chain[k + 1].center if k + 1 < len(chain) else task
        route = plan_landmark_route(
            position,
            covariance,
            site,
            tip_radius,
            noise,
            task_point=task if k + 1 == len(chain) else None,
            spot=nearest_spot(site.center, site.radius, tip_radius, aim, site.observation_sigma),
            observation_sigma=site.observation_sigma,
        )
        waypoints += route.waypoints
        plans += route.observations
        modes += route.modes
        spots += route.spots
        length += route.length
        expected += route.expected_cost
        position, covariance = route.waypoints[-1].position, route.waypoints[-1].covariance
    if not chain:
        d = task - start
        waypoints.append(Waypoint(task, noise.predict(cov, d[0], d[1]), "task", -1))
        length = expected = float(np.hypot(*d))
    return LandmarkRoute(
        start,
        cov,
        tuple(waypoints),
        length,
        expected,
        tuple(s.id for s in chain),
        tuple(modes),
        tuple(spots),
        tuple(plans),
    )
