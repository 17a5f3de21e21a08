"""Order in which to manipulate many particles (book 6.2.2 and 6.3.2, Table 6.5 / 6.6).

The input is a symmetric matrix of observation distances between particles (eq. 6.11-6.12);
the cost of an order is the sum of the distances between consecutive particles (an open
path: the tip may start at any particle and end at any other). This is the shortest
Hamiltonian path problem, NP-hard in general, so three solvers are offered:

- `ant_colony_order`: the book's ant colony optimisation (Ant System; the book gives no
  parameter values, so the classic ones of Dorigo and Stuetzle are the defaults);
- `exact_order`: Held-Karp dynamic programming over subsets, exact (provably optimal) for
  n <= EXACT_MAX (memory grows as 2^n * n);
- `heuristic_order`: multi-start nearest neighbour, then 2-opt and Or-opt to a local optimum,
  optionally iterated with random double-bridge kicks (iterated local search).

`best_order` picks the exact solver when n <= exact_limit and the heuristic otherwise.

Unknown entries (NaN or +inf) are edges the tip cannot use. An order that needs one has an
infinite cost; when no order avoids them the solvers raise ValueError (the exact solver
proves it; the heuristic says it found none).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

EXACT_MAX = 20  # Held-Karp table: 2^20 * 20 float64 = 168 MB; beyond that, refuse
EXACT_LIMIT = 16  # best_order's default switch to the heuristic (2^16 * 16 table: 8 MB, ~0.1 s)
SYMMETRY_TOLERANCE = 1e-9


@dataclass(frozen=True)
class SequencingResult:
    """An order of particle indices (0-based) and its cost (sum of consecutive distances)."""

    order: tuple[int, ...]
    cost: float
    method: str  # "exact", "heuristic", "ant_colony"
    optimal: bool  # True only when the exact solver proved it


@dataclass(frozen=True)
class AntColonyParameters:
    """Ant System (Dorigo and Stuetzle 2004). The book (6.3.2) uses an ant colony after its
    reference [1] but prints no values, so these are the textbook ones: alpha = 1 (pheromone
    weight), beta = 2 (distance weight), rho = 0.5 (evaporation), one ant per particle,
    initial pheromone = ants / (cost of a nearest-neighbour order)."""

    iterations: int = 200
    ants: int | None = None  # None: one per particle
    alpha: float = 1.0
    beta: float = 2.0
    evaporation: float = 0.5
    deposit: float = 1.0  # Q: pheromone an ant lays, divided by its order's cost


# -- validation --------------------------------------------------------------------------
def validated_distances(matrix, tolerance: float = SYMMETRY_TOLERANCE) -> np.ndarray:
    """The matrix as float64 with unknown entries (NaN, +inf) set to +inf.

    Raises ValueError, naming what is wrong, when it is not a square 2-D array with at least
    one row, has a negative or -inf entry, or is not symmetric within `tolerance` (relative to
    its largest finite entry; an unknown entry must be unknown on both sides).
    """
    try:
        d = np.array(matrix, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"distance matrix: not numeric ({exc})") from None
    if d.ndim != 2 or d.shape[0] != d.shape[1]:
        raise ValueError(f"distance matrix: must be square 2-D, got shape {d.shape}")
    if d.shape[0] == 0:
        raise ValueError("distance matrix: must have at least one particle, got 0 x 0")
    if np.isneginf(d).any() or (d < 0).any():
        i, j = np.argwhere(np.isneginf(d) | (d < 0))[0]
        raise ValueError(
            f"distance matrix: entry [{i}, {j}] = {d[i, j]} is negative; distances must be >= 0"
        )
    d[np.isnan(d)] = np.inf
    unknown = np.isinf(d)
    if (unknown != unknown.T).any():
        i, j = np.argwhere(unknown != unknown.T)[0]
        raise ValueError(
            f"distance matrix: entry [{i}, {j}] = {d[i, j]} but [{j}, {i}] = {d[j, i]}; "
            "an unknown distance must be unknown both ways"
        )
    finite = np.where(unknown, 0.0, d)
    scale = float(finite.max()) or 1.0  # relative: metres and micrometres alike
    asymmetry = np.abs(finite - finite.T)
    if asymmetry.max() > tolerance * scale:
        i, j = np.unravel_index(np.argmax(asymmetry), asymmetry.shape)
        raise ValueError(
            f"distance matrix: not symmetric, [{i}, {j}] = {d[i, j]} vs [{j}, {i}] = {d[j, i]} "
            f"(tolerance {tolerance} x {scale})"
        )
    np.fill_diagonal(d, 0.0)  # staying put is free; the diagonal is never an edge of an order
    return d


def order_cost(matrix, order: Sequence[int]) -> float:
    """Sum of the distances between consecutive particles of `order` (inf if it uses an unknown
    one)."""
    d = np.asarray(matrix, dtype=float)
    idx = np.asarray(order, dtype=int)
    if idx.size < 2:
        return 0.0
    steps = d[idx[:-1], idx[1:]]
    steps = np.where(np.isnan(steps), np.inf, steps)
    return float(steps.sum())


def _result(d: np.ndarray, order, method: str, optimal: bool) -> SequencingResult:
    cost = order_cost(d, order)
    if not math.isfinite(cost):
        raise ValueError(
            f"{method}: found no order that avoids the unknown (NaN/inf) distances"
            + (
                " (none exists)"
                if optimal
                else f" (one may still exist; try the exact solver for n <= {EXACT_MAX:d})"
            )
        )
    return SequencingResult(tuple(int(i) for i in order), cost, method, optimal)


# -- exact: Held-Karp ----------------------------------------------------------------------
def exact_order(matrix) -> SequencingResult:
    """Shortest open path through every particle by Held-Karp dynamic programming.

    best[S, j] = cheapest path that visits exactly the set S and ends at j; best[{j}, j] = 0
    (free start) and best[S, j] = min over i in S - {j} of best[S - {j}, i] + d[i, j]; the
    answer is min_j best[all, j] (free end). Subsets are processed by size, each size as one
    numpy batch per end particle. Exact; O(2^n n^2) time, O(2^n n) memory, n <= EXACT_MAX.
    """
    d = validated_distances(matrix)
    n = d.shape[0]
    if n > EXACT_MAX:
        raise ValueError(
            f"exact_order: {n} particles; the exact solver is limited to {EXACT_MAX} "
            f"(its table needs 2^n * n entries); use heuristic_order"
        )
    if n == 1:
        return SequencingResult((0,), 0.0, "exact", True)
    full = (1 << n) - 1
    best = np.full((1 << n, n), np.inf)
    came_from = np.full((1 << n, n), -1, dtype=np.int8)
    singletons = 1 << np.arange(n)
    best[singletons, np.arange(n)] = 0.0
    masks = np.arange(1 << n)
    popcount = np.zeros(1 << n, dtype=np.int8)
    for bit in range(n):
        popcount += ((masks >> bit) & 1).astype(np.int8)
    for size in range(2, n + 1):
        layer = masks[popcount == size]
        for end in range(n):
            with_end = layer[(layer >> end) & 1 == 1]
            before = with_end ^ (1 << end)
            candidates = best[before] + d[:, end]  # inf where the previous end is not in `before`
            previous = np.argmin(candidates, axis=1)
            best[with_end, end] = candidates[np.arange(len(with_end)), previous]
            came_from[with_end, end] = previous
    end = int(np.argmin(best[full]))
    if not math.isfinite(best[full, end]):
        raise ValueError(
            "exact_order: no order visits every particle using only known distances "
            "(the unknown NaN/inf entries disconnect them)"
        )
    order, mask = [end], full
    while mask != (1 << end):
        previous = int(came_from[mask, end])
        mask ^= 1 << end
        end = previous
        order.append(end)
    return _result(d, order[::-1], "exact", True)


# -- heuristic: nearest neighbour + 2-opt + Or-opt ------------------------------------------
def _search_matrix(d: np.ndarray) -> np.ndarray:
    """Distances with a dummy node n at distance 0 from every particle, so an open path is a
    closed tour through the dummy (cut there). Unknown edges get a penalty larger than any
    order made of known edges, so the search avoids them whenever it can."""
    n = d.shape[0]
    finite = d[np.isfinite(d)]
    penalty = (float(finite.max()) if finite.size else 1.0) * (n + 1) + 1.0
    extended = np.zeros((n + 1, n + 1))
    extended[:n, :n] = np.where(np.isfinite(d), d, penalty)
    return extended


def _nearest_neighbour_tour(e: np.ndarray, start: int) -> np.ndarray:
    size = e.shape[0]
    visited = np.zeros(size, dtype=bool)
    tour = np.empty(size, dtype=int)
    tour[0] = current = start
    visited[start] = True
    for k in range(1, size):
        row = np.where(visited, np.inf, e[current])
        dummy = size - 1
        if not visited[dummy] and k < size - 1:
            row[dummy] = np.inf  # the dummy (path end) goes last, so the path is built greedily
        current = int(np.argmin(row))
        tour[k] = current
        visited[current] = True
    return tour


def _tour_length(e: np.ndarray, tour: np.ndarray) -> float:
    return float(e[tour, np.roll(tour, -1)].sum())


def _two_opt(e: np.ndarray, tour: np.ndarray, eps: float) -> tuple[np.ndarray, bool]:
    """Reverse tour[i+1..j] while that shortens the tour; best j for each i, vectorised over j."""
    size = len(tour)
    improved_any = False
    improved = True
    while improved:
        improved = False
        for i in range(size - 2):
            a, b = tour[i], tour[i + 1]
            js = np.arange(i + 2, size if i > 0 else size - 1)
            if js.size == 0:
                continue
            c, nxt = tour[js], tour[(js + 1) % size]
            delta = e[a, c] + e[b, nxt] - e[a, b] - e[c, nxt]
            k = int(np.argmin(delta))
            if delta[k] < -eps:
                j = int(js[k])
                tour[i + 1 : j + 1] = tour[i + 1 : j + 1][::-1].copy()
                improved = improved_any = True
    return tour, improved_any


def _or_opt(
    e: np.ndarray, tour: np.ndarray, eps: float, max_segment: int = 3
) -> tuple[np.ndarray, bool]:
    """Move a segment of 1-3 consecutive nodes (either way round) to its best other place."""
    size = len(tour)
    improved_any = False
    improved = True
    while improved:
        improved = False
        for length in range(1, max_segment + 1):
            if size - length < 3:
                continue
            i = 0
            while i < size:
                positions = (i + np.arange(length)) % size
                segment = tour[positions]
                before, after = tour[(i - 1) % size], tour[(i + length) % size]
                removal_gain = e[before, segment[0]] + e[segment[-1], after] - e[before, after]
                rest = np.delete(np.roll(tour, -i), np.arange(length))  # starts at `after`
                u, v = rest, np.roll(rest, -1)
                base = e[u, v]
                forward = e[u, segment[0]] + e[segment[-1], v] - base
                backward = e[u, segment[-1]] + e[segment[0], v] - base
                forward[-1] = backward[-1] = np.inf  # (before, after): where it came from
                k_f, k_b = int(np.argmin(forward)), int(np.argmin(backward))
                insert_cost, reverse, k = (
                    (forward[k_f], False, k_f)
                    if forward[k_f] <= backward[k_b]
                    else (backward[k_b], True, k_b)
                )
                if insert_cost - removal_gain < -eps:
                    piece = segment[::-1] if reverse else segment
                    tour = np.concatenate([rest[: k + 1], piece, rest[k + 1 :]])
                    improved = improved_any = True
                i += 1
    return tour, improved_any


def _local_search(e: np.ndarray, tour: np.ndarray, eps: float) -> np.ndarray:
    tour = tour.copy()
    while True:
        tour, _ = _two_opt(e, tour, eps)
        tour, changed_or = _or_opt(e, tour, eps)
        if not changed_or:
            return tour


def _double_bridge(tour: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Cut the tour in four pieces A B C D and rejoin as A C B D: a move 2-opt cannot undo."""
    size = len(tour)
    cuts = np.sort(rng.choice(np.arange(1, size), size=3, replace=False))
    a, b, c = cuts
    return np.concatenate([tour[:a], tour[b:c], tour[a:b], tour[c:]])


def _path_from_tour(tour: np.ndarray, dummy: int) -> np.ndarray:
    k = int(np.flatnonzero(tour == dummy)[0])
    return np.concatenate([tour[k + 1 :], tour[:k]])


def heuristic_order(matrix, starts: int = 8, kicks: int = 0, seed: int = 0) -> SequencingResult:
    """Open path by nearest neighbour from `starts` start particles (spread evenly over the
    particles), each improved to a 2-opt + Or-opt local optimum; then, if kicks > 0, iterated
    local search: `kicks` random double-bridge perturbations of the best, each re-optimised and
    kept when shorter. Deterministic for a given seed. No optimality guarantee."""
    d = validated_distances(matrix)
    if not (isinstance(starts, (int, np.integer)) and starts >= 1):
        raise ValueError(f"heuristic_order: starts={starts!r} must be an integer >= 1")
    if not (isinstance(kicks, (int, np.integer)) and kicks >= 0):
        raise ValueError(f"heuristic_order: kicks={kicks!r} must be an integer >= 0")
    n = d.shape[0]
    if n <= 3:
        return exact_order(d)
    e = _search_matrix(d)
    eps = 1e-12 * max(1.0, float(np.abs(e).max()))
    rng = np.random.default_rng(seed)
    best_tour, best_length = None, np.inf
    for start in np.unique(np.linspace(0, n - 1, min(starts, n)).round().astype(int)):
        tour = _local_search(e, _nearest_neighbour_tour(e, int(start)), eps)
        length = _tour_length(e, tour)
        if length < best_length - eps:
            best_tour, best_length = tour, length
    for _ in range(kicks):
        tour = _local_search(e, _double_bridge(best_tour, rng), eps)
        length = _tour_length(e, tour)
        if length < best_length - eps:
            best_tour, best_length = tour, length
    return _result(d, _path_from_tour(best_tour, n), "heuristic", False)


# -- the book's ant colony --------------------------------------------------------------------
def ant_colony_order(
    matrix, seed: int = 0, parameters: AntColonyParameters = AntColonyParameters()
) -> SequencingResult:
    """Ant System for the open path (book 6.3.2). Each ant starts at a random particle and
    picks the next unvisited one with probability ~ tau^alpha * (1/d)^beta; after all ants
    have built an order, pheromone evaporates by rho and each ant lays deposit / cost on its
    edges (both directions). Returns the best order any ant built. Deterministic per seed;
    all ants of an iteration advance together (vectorised)."""
    d = validated_distances(matrix)
    n = d.shape[0]
    p = parameters
    if p.iterations < 1 or (p.ants is not None and p.ants < 1):
        raise ValueError(f"ant colony: iterations={p.iterations} and ants={p.ants} must be >= 1")
    if not (0 < p.evaporation <= 1) or p.alpha < 0 or p.beta < 0 or p.deposit <= 0:
        raise ValueError(
            f"ant colony: evaporation={p.evaporation} must be in (0, 1], alpha={p.alpha} and "
            f"beta={p.beta} >= 0, deposit={p.deposit} > 0"
        )
    if n <= 2:
        return exact_order(d)
    rng = np.random.default_rng(seed)
    ants = p.ants or n
    known = np.isfinite(d)
    positive = d[known & (d > 0)]
    floor = (
        positive.min() if positive.size else 1.0
    ) * 1e-3  # coincident particles: huge, finite visibility
    visibility = np.where(known, 1.0 / np.maximum(d, floor), 0.0) ** p.beta
    np.fill_diagonal(visibility, 0.0)
    try:
        nn_cost = heuristic_order(d, starts=1).cost if n > 3 else exact_order(d).cost
    except ValueError:
        nn_cost = float(np.nansum(np.where(known, d, 0.0))) / max(n - 1, 1)
    pheromone = np.full((n, n), ants / max(nn_cost, floor))
    rows = np.arange(ants)
    best_order, best_cost = None, np.inf
    for _ in range(p.iterations):
        weight = pheromone**p.alpha * visibility
        orders = np.empty((ants, n), dtype=int)
        orders[:, 0] = current = rng.integers(0, n, ants)
        unvisited = np.ones((ants, n), dtype=bool)
        unvisited[rows, current] = False
        stuck = np.zeros(ants, dtype=bool)
        for step in range(1, n):
            w = weight[current] * unvisited
            total = w.sum(axis=1)
            stuck |= total <= 0  # only unknown edges left: this ant fails
            w[stuck] = unvisited[stuck]  # let it finish anywhere; its cost is inf
            cumulative = np.cumsum(w, axis=1)
            draw = rng.random(ants) * cumulative[:, -1]
            current = np.minimum((cumulative <= draw[:, None]).sum(axis=1), n - 1)
            orders[:, step] = current
            unvisited[rows, current] = False
        costs = np.where(stuck, np.inf, d[orders[:, :-1], orders[:, 1:]].sum(axis=1))
        k = int(np.argmin(costs))
        if costs[k] < best_cost:
            best_cost, best_order = float(costs[k]), orders[k].copy()
        pheromone *= 1.0 - p.evaporation
        ok = np.isfinite(costs)
        if ok.any():
            amount = np.repeat(p.deposit / np.maximum(costs[ok], floor), n - 1)
            a, b = orders[ok, :-1].ravel(), orders[ok, 1:].ravel()
            np.add.at(pheromone, (a, b), amount)
            np.add.at(pheromone, (b, a), amount)
    if best_order is None:
        raise ValueError(
            "ant_colony_order: no ant found an order that avoids the unknown (NaN/inf) distances"
        )
    return _result(d, best_order, "ant_colony", False)


def best_order(matrix, exact_limit: int = EXACT_LIMIT, seed: int = 0) -> SequencingResult:
    """The exact order when there are at most `exact_limit` particles, else the heuristic's."""
    d = validated_distances(matrix)
    if not (1 <= exact_limit <= EXACT_MAX):
        raise ValueError(f"best_order: exact_limit={exact_limit} must be in [1, {EXACT_MAX}]")
    if d.shape[0] <= exact_limit:
        return exact_order(d)
    return heuristic_order(d, seed=seed)
