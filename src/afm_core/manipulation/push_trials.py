"""One seeded push trial on the simulated AFM: the sweep behind bench/bench_pushing.py (b) and
`afm batch push` (afm_core.batch.sweeps).

Per seed a fresh simulator of the default configuration with that seed; the particle's estimate
is its true centre plus a N(0, estimate_sigma) error per axis (drawn from its own generator,
seeded 1000 + seed: the book's uncertainty, the localization being another module's job); the
goal is `goal_distance` from the estimate along +y; the strategy's plan runs through the
Instrument calls (execute_plan). Success: the particle's true final centre within `tolerance`
of the goal. Everything in SI units.
"""

from __future__ import annotations

import time

import numpy as np

from afm_core.manipulation.centre_push import centre_push_plan
from afm_core.manipulation.execute import execute_plan
from afm_core.manipulation.nano_hand import nano_hand_plan

STRATEGIES = ("nano_hand", "centre", "centre_single", "table_7_6")
# multiples of NM as the bench wrote them (600 * 1e-9 != 600e-9 in floats): the same figures
NM = 1e-9
TOLERANCE = 20 * NM  # m: the project's push success radius (SPEC section 5, book 7.3)
GOAL_DISTANCE = 500 * NM  # m along +y from the estimate (bench_pushing (b))
ESTIMATE_SIGMA = 10 * NM  # m per axis: the book's uncertainty of a particle's centre
PUSH_SPEED = 0.5e-6  # m/s
TABLE_7_6_REACH = 600 * NM  # m: the book's 13-step plan aims this far; its goal is predicted


def push_trial(
    seed: int,
    strategy: str = "nano_hand",
    estimate_sigma: float = ESTIMATE_SIGMA,
    *,
    goal_distance: float = GOAL_DISTANCE,
    tolerance: float = TOLERANCE,
    speed: float = PUSH_SPEED,
) -> dict:
    """One trial (module docstring). strategy: "nano_hand" (aimed zigzag), "centre" (straight
    pushes in the same rhythm), "centre_single" (one push), "table_7_6" (the book's 13 steps,
    the goal being where the model predicts they end). Returns, in m and s: error (final centre
    to goal), success, along / sideways (+ right of the push axis) displacement, the estimate's
    error, strokes, whether the plan completed, simulated and wall seconds."""
    from afm_core.sim.config import load_config, merge
    from afm_core.sim.instrument import SimulatedAfm

    if strategy not in STRATEGIES:
        raise ValueError(f"strategy={strategy!r}: must be one of {list(STRATEGIES)}")
    for name, value in (("estimate_sigma", estimate_sigma), ("goal_distance", goal_distance)):
        if not (np.isfinite(value) and value >= 0):
            raise ValueError(f"{name}={value}: must be finite and >= 0 m")
    if not (np.isfinite(tolerance) and tolerance > 0):
        raise ValueError(f"tolerance={tolerance}: must be finite and > 0 m")
    sim = SimulatedAfm(merge(load_config(), {"seed": seed}))
    sphere = sim.sample.spheres[0]
    truth0 = np.array([sphere.x, sphere.y])
    err = np.random.default_rng(1000 + seed).normal(0.0, estimate_sigma, 2)
    est = truth0 + err
    goal = est + [0.0, goal_distance]
    if strategy == "nano_hand":
        plan = nano_hand_plan(est, goal, limits=sim.limits)
    elif strategy == "centre":
        plan = centre_push_plan(est, goal, limits=sim.limits)
    elif strategy == "centre_single":
        plan = centre_push_plan(est, goal, single=True, limits=sim.limits)
    else:  # table_7_6: the goal is where the model predicts the book's 13 steps end
        plan = nano_hand_plan(
            est, est + [0.0, TABLE_7_6_REACH], steps=13, aim=False, limits=sim.limits
        )
        goal = plan.predicted
    t0 = time.perf_counter()
    result = execute_plan(sim, plan, speed=speed)
    wall = time.perf_counter() - t0
    final = np.array([sphere.x, sphere.y])
    d = final - truth0
    error = float(np.hypot(*(final - goal)))
    return {
        "seed": seed,
        "strategy": strategy,
        "strokes": len(plan),
        "completed": result.completed,
        "goal": goal,
        "final": final,
        "error": error,
        "success": bool(error <= tolerance),
        "along": float(d @ plan.axis),
        "sideways": float(-(d @ plan.normal)),
        "estimate_error": err,
        "sim_seconds": result.duration,
        "wall_seconds": wall,
    }


# -- the Monte Carlo model per seed (bench_pushing (a)) ---------------------------------------
MC_PLANS = ("centre", "nano_hand", "nano_hand_aimed_300nm", "table_7_6_13_steps")
MC_CENTRE = (5e-6, 5e-6)  # m: where the bench's plans start (any point: the model is uniform)


def monte_carlo_plans(centre=MC_CENTRE) -> dict:
    """bench_pushing (a)'s plans from `centre` (6 pushes of the 156 / 120 nm rhythm): "centre"
    (straight pushes through the centre) and "nano_hand" (the Table 7.6 zigzag, not aimed) to
    where that zigzag takes a particle sitting at the estimate; "nano_hand_aimed_300nm" (the
    planner's aimed zigzag to a goal 300 nm away); "table_7_6_13_steps" (the book's 13 steps)."""
    c0 = np.asarray(centre, float)
    plain = nano_hand_plan(c0, c0 + [0.0, 300 * NM], steps=6, aim=False)
    goal = c0 + [0.0, plain.along(plain.predicted)]
    return {
        "centre": centre_push_plan(c0, goal, steps=6),
        "nano_hand": nano_hand_plan(c0, goal, steps=6, aim=False),
        "nano_hand_aimed_300nm": nano_hand_plan(c0, c0 + [0.0, 300 * NM], steps=6),
        "table_7_6_13_steps": nano_hand_plan(c0, c0 + [0.0, 600 * NM], steps=13, aim=False),
    }


def monte_carlo_trial(
    seed: int,
    plan: str = "nano_hand",
    *,
    samples: int = 500,
    sigma: float = ESTIMATE_SIGMA,
    tolerance: float = TOLERANCE,
):
    """monte_carlo_push of one of monte_carlo_plans() with this seed's draws (its
    MonteCarloResult): how one seed's 500-draw estimate of the success probability and the
    spreads scatters from seed to seed is what a sweep over seeds shows."""
    from afm_core.manipulation.monte_carlo import monte_carlo_push

    if plan not in MC_PLANS:
        raise ValueError(f"plan={plan!r}: must be one of {list(MC_PLANS)}")
    return monte_carlo_push(
        monte_carlo_plans()[plan], samples=samples, sigma=sigma, seed=seed, tolerance=tolerance
    )
