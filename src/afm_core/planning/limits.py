"""Size limits of the planning requests, so that no request holds a planner for minutes.

Measured by bench/bench_planner_limits.py (one core, CPython; bench/results/planner_limits.md):
each keeps its request to about 10 s at most (most are far quicker). The sequencing limits are
checked before any work, the chain's while it searches; the refusal names the field and limit.
"""

# plan_landmark_chain: observation edges (two observation plans each, ~0.5 ms) one search may
# work out. The search computes only the edges that can still matter (landmark_chain), so a
# route of a few um over a map of 20000 landmarks needs a few hundred; a route across a dense
# map needs more: 2000 landmarks 300 nm apart and a target 15 um away took 134000 (69 s).
MAX_CHAIN_EDGES = 20_000  # 6.4-10 s
# ... and the search's time, which also goes into each settled landmark's localization routes
# (planned once per radius and sigma): on a map of particles with differing radii the edge
# limit alone took 15 s.
MAX_CHAIN_SECONDS = 10.0

# PlanSequence by landmark_ids: the observation-distance matrix has n (n - 1) edges (~0.35 ms
# each): 80 landmarks 1.3-1.7 s, 100 2.1-2.6 s.
MAX_SEQUENCE_LANDMARKS = 100

# Ant colony (n ants, 200 iterations, vectorised): 100 points 1.5 s, 150 4.4 s, 200 9.4 s.
MAX_ACO_POINTS = 150

# Heuristic (multi-start nearest neighbour + 2-opt + Or-opt; also "best" beyond EXACT_LIMIT):
# 500 points 3.6-3.8 s, 1000 12-17 s.
MAX_HEURISTIC_POINTS = 500
