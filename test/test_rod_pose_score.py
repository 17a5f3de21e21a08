"""The rods' pose score of the graph benchmark (afm_core.evaluation.rod_pose_against_truth)
against a closed form: a true end pose built from a known error in the maps' frame, through a
sheared, anisotropic images' frame, must score exactly that error."""

import math

import numpy as np
import pytest

from afm_core.evaluation import rod_pose_against_truth

NM = 1e-9
DEG = math.pi / 180
FRAME = np.array([[1.06, 0.02], [-0.01, 0.94]])  # true per maps' displacement


def true_end(before, move, turn, offset, angle_offset):
    """The true pose whose maps'-frame displacement is move + offset and whose maps'-frame
    axis is turned by turn + angle_offset from the start's."""
    x0, y0, a0 = before
    d0 = np.linalg.solve(FRAME, [math.cos(a0), math.sin(a0)])
    a_maps = math.atan2(d0[1], d0[0]) + turn + angle_offset
    d1 = FRAME @ [math.cos(a_maps), math.sin(a_maps)]
    xy = np.array([x0, y0]) + FRAME @ (np.asarray(move) + np.asarray(offset))
    return np.array([xy[0], xy[1], math.atan2(d1[1], d1[0])])


@pytest.mark.parametrize(
    "offset, angle_offset",
    [((12 * NM, -5 * NM), 2.0 * DEG), ((0.0, 0.0), 0.0), ((-30 * NM, 4 * NM), -7.5 * DEG)],
)
def test_known_pose_error_is_scored(offset, angle_offset):
    before = np.array([55e-6, 55.85e-6, 0.2])
    move, turn = (180 * NM, -120 * NM), 21 * DEG
    after = true_end(before, move, turn, offset, angle_offset)
    score = rod_pose_against_truth(before, after, move, turn, FRAME)
    assert score["error"] == pytest.approx(math.hypot(*offset), abs=1e-13)
    assert score["angle_error"] == pytest.approx(abs(angle_offset), abs=1e-9)
    assert np.allclose(score["moved"], np.add(move, offset), atol=1e-13)
    assert score["turned"] == pytest.approx(turn + angle_offset, abs=1e-9)


def test_axis_has_no_head():
    """The same axis reported a half turn apart scores the same angle error."""
    before = np.array([55e-6, 55e-6, -0.4])
    move, turn = (0.0, -200 * NM), -10 * DEG
    after = true_end(before, move, turn, (0.0, 0.0), 1.5 * DEG)
    flipped = after + [0.0, 0.0, math.pi]
    a = rod_pose_against_truth(before, after, move, turn, FRAME)
    b = rod_pose_against_truth(before, flipped, move, turn, FRAME)
    assert a["angle_error"] == pytest.approx(1.5 * DEG, abs=1e-9)
    assert b["angle_error"] == pytest.approx(a["angle_error"], abs=1e-9)


def test_the_frame_matters():
    """A pose exact in the simulator's metres is off in the maps' frame by the frame's scale."""
    before = np.array([55e-6, 55e-6, 0.0])
    move = np.array([300 * NM, 0.0])
    after = before + [*move, 0.0]
    score = rod_pose_against_truth(before, after, move, 0.0, FRAME)
    expected = np.hypot(*(np.linalg.solve(FRAME, move) - move))
    assert score["error"] == pytest.approx(expected, rel=1e-9)
    assert score["error"] > 10 * NM


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="true_before"):
        rod_pose_against_truth([0.0, 0.0], [0.0, 0.0, 0.0], (0.0, 0.0), 0.0, FRAME)
    with pytest.raises(ValueError, match="frame"):
        rod_pose_against_truth([0.0] * 3, [0.0] * 3, (0.0, 0.0), 0.0, np.eye(3))
