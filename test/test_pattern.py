"""Assembly patterns (afm_core.planning.pattern): the shapes, the placement's checks against
the geometry itself (goals clear of every other object, inside the mapped area and the range,
every way clear of the other starts and goals), and bad input refused naming the field."""

import math

import numpy as np
import pytest

from afm_core.evaluation import pattern_against_truth
from afm_core.instrument import ScannerLimits
from afm_core.manipulation.plans import path_blocker
from afm_core.planning.pattern import (
    DEFAULT_CLEARANCE,
    PatternObject,
    pattern_offsets,
    plan_pattern,
)

R = 100e-9
AREA = (53.9e-6, 53.9e-6, 56.9e-6, 56.9e-6)
ROUNDING = 1e-15  # m: a grid point on the area's edge, in float64 at ~55 um


def scattered_sample(seed: int, n: int = 9):
    """n spheres at random, at least 400 nm apart, and a rod, inside AREA."""
    rng = np.random.default_rng(seed)
    points = []
    while len(points) < n:
        p = rng.uniform(AREA[:2], AREA[2:])
        if all(np.hypot(*(p - q)) > 400e-9 for q in points):
            points.append(p)
    objects = [PatternObject(i, "sphere", p[0], p[1], R) for i, p in enumerate(points)]
    objects.append(PatternObject(n, "rod", 56.2e-6, 56.4e-6, 40e-9, length=500e-9))
    return objects


@pytest.mark.parametrize("shape,count", [("line", 6), ("L", 6), ("ring", 6), ("L", 5)])
def test_pattern_offsets_have_the_pitch_between_neighbours(shape, count):
    pitch = 350e-9
    points = pattern_offsets(shape, count, pitch, angle=0.3)
    assert points.shape == (count, 2)
    assert np.allclose(points.mean(axis=0), 0.0, atol=1e-15)
    gaps = np.hypot(*(points[:, None] - points[None]).transpose(2, 0, 1))
    np.fill_diagonal(gaps, np.inf)
    # every point has a neighbour at the pitch and none nearer
    assert np.allclose(gaps.min(axis=1), pitch, rtol=1e-9)
    if shape == "line":
        assert math.isclose(gaps[np.isfinite(gaps)].max(), (count - 1) * pitch, rel_tol=1e-9)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("shape", ["line", "L"])
def test_placed_pattern_is_clear_inside_and_order_independent(seed, shape):
    objects = scattered_sample(seed)
    offsets = pattern_offsets(shape, 6, 350e-9)
    plan = plan_pattern(objects, offsets, area=AREA)
    by_id = {o.id: o for o in objects}
    assert len(set(plan.particle_ids)) == 6
    assert all(by_id[i].kind == "sphere" for i in plan.particle_ids)

    # the goals are the pattern, moved and turned: the same distances between them
    def distances(points):
        return np.sort(np.hypot(*(points[:, None] - points[None]).transpose(2, 0, 1)).ravel())

    assert np.allclose(distances(plan.goals), distances(offsets), atol=1e-12)
    assert np.allclose(plan.goals.mean(axis=0), plan.centre)
    for pid, start, goal in zip(plan.particle_ids, plan.starts, plan.goals):
        assert np.allclose(start, (by_id[pid].x, by_id[pid].y))
        # inside the mapped area, with the particle and the clearance inside too
        inset = R + DEFAULT_CLEARANCE - ROUNDING
        assert AREA[0] + inset <= goal[0] <= AREA[2] - inset
        assert AREA[1] + inset <= goal[1] <= AREA[3] - inset
        # clear of every other object (a rod by its bounding circle)
        for other in objects:
            if other.id == pid:
                continue
            reach = other.radius + (0 if other.kind == "sphere" else other.length / 2)
            assert np.hypot(*(goal - (other.x, other.y))) >= R + reach + DEFAULT_CLEARANCE
            # and no nearer than the pattern's own neighbours
            assert np.hypot(*(goal - (other.x, other.y))) >= 350e-9 + reach - other.radius
    # any order: every other particle is at its start or at its goal, neither in the way
    for k, (start, goal) in enumerate(zip(plan.starts, plan.goals)):
        for j, (qid, s, g) in enumerate(zip(plan.particle_ids, plan.starts, plan.goals)):
            if j == k:
                continue
            for where in (s, g):
                other = PatternObject(qid, "sphere", where[0], where[1], R)
                assert path_blocker(start, goal, R, 50e-9, [other]) is None
    # no other assignment to the same goals is shorter (the Hungarian method's optimum)
    assert plan.total_distance == pytest.approx(plan.distances.sum())


def test_a_pattern_never_lands_on_an_obstacle_in_the_only_free_spot():
    """A field full of spheres but for one clear corner: the pattern goes there or nowhere."""
    grid = [
        PatternObject(i, "sphere", 54.2e-6 + 0.5e-6 * (i % 6), 54.2e-6 + 0.5e-6 * (i // 6), R)
        for i in range(36)
    ]
    with pytest.raises(ValueError, match="no placement") as refused:
        plan_pattern(grid, pattern_offsets("line", 6, 300e-9), area=AREA)
    assert "too near another object" in str(refused.value)


def test_goals_stay_inside_the_range_where_the_area_reaches_past_it():
    corner = [(0.5e-6, 0.5e-6), (2.5e-6, 0.5e-6), (0.5e-6, 2.5e-6)]
    objects = [PatternObject(i, "sphere", x, y, R) for i, (x, y) in enumerate(corner)]
    # a mapped area that reaches past the range's corner at (0, 0): it is cut to the range
    plan = plan_pattern(
        objects, pattern_offsets("line", 2, 400e-9), area=(-2e-6, -2e-6, 4e-6, 3e-6), max_push=3e-6
    )
    assert (plan.goals >= R + DEFAULT_CLEARANCE - ROUNDING).all()
    limits = ScannerLimits()
    with pytest.raises(ValueError, match="does not fit in the area"):
        plan_pattern(
            objects,
            pattern_offsets("line", 3, 300e-9),
            area=(limits.range_x + 1e-6, 0, limits.range_x + 3e-6, 2e-6),
        )


@pytest.mark.parametrize(
    "call,field",
    [
        (lambda: pattern_offsets("star", 6, 300e-9), "shape='star'"),
        (lambda: pattern_offsets("line", 1, 300e-9), "count=1"),
        (lambda: pattern_offsets("line", 6, -1.0), "pitch=-1.0"),
        (lambda: pattern_offsets("line", 6, math.nan), "pitch=nan"),
        (
            lambda: plan_pattern(scattered_sample(0), [[0, 0]], area=AREA, clearance=-1),
            "clearance",
        ),
        (lambda: plan_pattern(scattered_sample(0), [[0, 0, 0]], area=AREA), "offsets"),
        (lambda: plan_pattern(scattered_sample(0), [[0, math.inf]], area=AREA), "offsets"),
        (
            lambda: plan_pattern(
                scattered_sample(0), pattern_offsets("line", 6, 250e-9), area=AREA
            ),
            "offsets: points 250 nm apart",
        ),
        (
            lambda: plan_pattern(
                scattered_sample(0, 4), pattern_offsets("line", 6, 300e-9), area=AREA
            ),
            "the map has 4 spheres",
        ),
        (
            lambda: plan_pattern(
                scattered_sample(0), pattern_offsets("line", 6, 300e-9), area=(0, 0, 1e-6, 1e-6)
            ),
            "does not fit in the area",
        ),
        (lambda: plan_pattern(scattered_sample(0), [[0, 0]], area=(1, 1, 0, 0)), "area="),
        (
            lambda: plan_pattern(
                [PatternObject(0, "sphere", 55e-6, 55e-6, -R)], [[0, 0]], area=AREA
            ),
            "objects[0].radius",
        ),
    ],
)
def test_bad_input_is_refused_naming_the_field(call, field):
    with pytest.raises(ValueError, match=None) as refused:
        call()
    assert field in str(refused.value), str(refused.value)


def test_pattern_against_truth_scores_the_true_displacement_from_the_mapped_start():
    """The true particles in another frame than the map (shifted by 1 um: only displacements
    count), listed in another order, one of them not in the pattern."""
    starts = np.array([[0.0, 0.0], [1e-6, 0.0], [0.0, 1e-6]])
    goals = starts + [[300e-9, 0.0], [0.0, 300e-9], [-300e-9, 0.0]]
    ends_off = np.array([[3e-9, 4e-9], [3e-9, 4e-9], [3e-9, 4e-9]])  # a common 5 nm offset
    shift = np.array([1e-6, 1e-6])
    before = np.vstack([starts[::-1] + shift, [[5e-6, 5e-6]]])
    after = np.vstack([(goals + ends_off)[::-1] + shift, [[5e-6, 5e-6]]])
    scored = pattern_against_truth(starts + shift, goals + shift, before, after)
    assert scored["true_index"] == [2, 1, 0]
    assert np.allclose(scored["errors"], 5e-9)
    assert scored["rms"] == pytest.approx(5e-9)
    assert scored["shape_rms"] == pytest.approx(0.0, abs=1e-18)  # the shape itself is exact
    assert scored["within_10nm"] == 1.0
    after[0] += [0.0, 30e-9]  # the last of the pattern (row 0 here) 30 nm further
    scored = pattern_against_truth(starts + shift, goals + shift, before, after)
    assert scored["errors"][2] == pytest.approx(np.hypot(3e-9, 34e-9))
    assert scored["within_20nm"] == pytest.approx(2 / 3)
    with pytest.raises(ValueError, match="true_before"):
        pattern_against_truth(starts, goals, before[:2], after[:2])
