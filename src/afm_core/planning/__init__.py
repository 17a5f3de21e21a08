"""Landmark path planning with probability regions (book chapter 6), ROS-free, numpy/scipy only.

Entry points:
- `plan_observation` (observation_plan.py, eq. 6.1-6.10): the local scan lines L0, L1, ... that
  find a particle anywhere in the tip's 3-sigma ellipse, their probabilities and expected cost.
- `plan_landmark_route` (landmark_paths.py, Guidelines 6.1 / 6.2, Table 6.2): one landmark's
  localization (two lines, four spots, scan modes "hh" "hv" "vh" "vv") with the predicted
  covariance at every waypoint; `observation_distance_matrix` (eq. 6.11-6.12),
  `cheapest_chain` (Dijkstra via scipy) and `plan_landmark_chain` (landmark_chain.py,
  Fig. 6.9: Dijkstra computing only the edges that can matter).
- `best_order`, `exact_order`, `heuristic_order`, `ant_colony_order` (sequencing.py, 6.3.2,
  Table 6.5 / 6.6): the order in which to manipulate many particles.
- `landmark_domain`, `covering_landmarks`, `plan_landmark_configuration` (domain.py, eq.
  6.13-6.15): landmark domains and which particle to push where when none covers the task.
- `pattern_offsets`, `plan_pattern` (pattern.py): an assembly's goals, a small pattern placed
  on the map clear of everything else, particles assigned so that any push order works.

All SI (m, m^2, s), frame afm_task. Motion noise is afm_core.localization.MotionNoise.
Bad input raises ValueError naming the field and its limit.
"""

from .domain import (
    LandmarkConfiguration,
    LandmarkDomain,
    covering_landmarks,
    landmark_domain,
    plan_landmark_configuration,
)
from .landmark_chain import LandmarkChain, plan_landmark_chain
from .landmark_paths import (
    BOOK_OBSERVATION_SIGMA,
    MODES,
    ROLES,
    SPOTS,
    LandmarkRoute,
    Waypoint,
    cheapest_chain,
    nearest_spot,
    observation_distance,
    observation_distance_matrix,
    plan_landmark_route,
)
from .limits import (
    MAX_ACO_POINTS,
    MAX_CHAIN_EDGES,
    MAX_CHAIN_SECONDS,
    MAX_HEURISTIC_POINTS,
    MAX_SEQUENCE_LANDMARKS,
)
from .observation_plan import ObservationPlan, ScanLine, plan_observation
from .pattern import PatternObject, PatternPlan, pattern_offsets, plan_pattern
from .sequencing import (
    EXACT_LIMIT,
    EXACT_MAX,
    AntColonyParameters,
    SequencingResult,
    ant_colony_order,
    best_order,
    exact_order,
    heuristic_order,
    order_cost,
    validated_distances,
)

__all__ = [
    "plan_observation",
    "ObservationPlan",
    "ScanLine",
    "plan_landmark_route",
    "LandmarkRoute",
    "Waypoint",
    "MODES",
    "ROLES",
    "SPOTS",
    "BOOK_OBSERVATION_SIGMA",
    "nearest_spot",
    "observation_distance",
    "observation_distance_matrix",
    "cheapest_chain",
    "plan_landmark_chain",
    "LandmarkChain",
    "MAX_CHAIN_EDGES",
    "MAX_CHAIN_SECONDS",
    "MAX_ACO_POINTS",
    "MAX_HEURISTIC_POINTS",
    "MAX_SEQUENCE_LANDMARKS",
    "best_order",
    "exact_order",
    "heuristic_order",
    "ant_colony_order",
    "order_cost",
    "validated_distances",
    "SequencingResult",
    "AntColonyParameters",
    "EXACT_LIMIT",
    "EXACT_MAX",
    "landmark_domain",
    "covering_landmarks",
    "plan_landmark_configuration",
    "LandmarkDomain",
    "LandmarkConfiguration",
    "pattern_offsets",
    "plan_pattern",
    "PatternPlan",
    "PatternObject",
]
