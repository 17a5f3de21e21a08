"""The maps' own frame (issue 32, `evaluation.maps_frame_matrix`): the truth a push planned on
a map is judged against. Against closed forms on the simulator: without creep an image is in
the frame of a creep-free step (`image_frame_matrix`); with one creep term too slow to follow
during the image (fraction f), every axis images at the instantaneous gain, (1 - f) times the
step's; with the default creep the fast axis images short by about the creep fractions, which
the creep-free step does not show, and a drift-corrected 0/90 pair takes the fast axis's gain
on both axes (the correction reads the two images' different slow-axis gains as drift)."""

import numpy as np
import pytest

from afm_core.evaluation import image_frame_matrix, maps_frame_matrix
from afm_core.instrument import ScanRequest
from afm_core.sim.config import load_config, merge

AREA = (54.4e-6, 54.4e-6, 1.2e-6, 1.2e-6)
SINGLE = [ScanRequest(*AREA, 96, 96, 0.0, True, 8.0)]
PAIR_AREA = (54.1e-6, 54.1e-6, 1.8e-6, 1.8e-6)
PAIR = [ScanRequest(*PAIR_AREA, 128, 128, angle, True, 4.0) for angle in (0.0, 90.0)]
QUIET = {"drift": {"enabled": False}}
SLOW_CREEP = 0.05  # fraction of a step; its time constant is 1e5 s, the images take 24 s


def _config(extra):
    return merge(merge(load_config(), QUIET), extra)


def test_without_creep_a_map_is_in_the_creep_free_steps_frame():
    config = _config({"scanner": {"creep_enabled": False}})
    relative = np.linalg.solve(image_frame_matrix(config), maps_frame_matrix(config, SINGLE))
    assert np.allclose(relative, np.eye(2), atol=1.5e-3)


def test_creep_too_slow_to_follow_shrinks_every_axis_by_its_fraction():
    creep = {"creep_time_constants": [1e5], "creep_fractions": [SLOW_CREEP]}
    config = _config({"scanner": creep})
    step = image_frame_matrix(config)  # creep-free: the long-term gain
    relative = np.linalg.solve(step, maps_frame_matrix(config, SINGLE))
    assert np.allclose(relative, (1 - SLOW_CREEP) * np.eye(2), atol=1.5e-3)


def test_default_creep_shortens_the_fast_axis_against_the_creep_free_step():
    config = _config({})
    fractions = sum(config.scanner.creep_fractions)
    relative = np.linalg.solve(image_frame_matrix(config), maps_frame_matrix(config, SINGLE))
    # a line (0.06 s) is traced faster than the creep's shortest time constant (0.5 s) follows
    assert 1 - fractions - 2e-3 <= relative[0, 0] <= 1 - 0.6 * fractions
    # the slow axis follows part of the creep in the image's 12 s
    assert relative[0, 0] < relative[1, 1] <= 1 + 1e-3


def test_a_drift_corrected_pair_takes_the_fast_axis_gain_on_both_axes():
    config = _config({})
    step = image_frame_matrix(config)
    single = np.linalg.solve(step, maps_frame_matrix(config, PAIR[:1], approach_overshoot=1.0))
    pair = np.linalg.solve(step, maps_frame_matrix(config, PAIR, approach_overshoot=1.0))
    assert single[1, 1] - single[0, 0] > 5e-3  # the single image's slow axis follows creep
    assert abs(pair[0, 0] - single[0, 0]) < 1e-3
    assert abs(pair[1, 1] - single[0, 0]) < 3e-3


def test_bad_scans_are_refused_by_name():
    config = _config({})
    with pytest.raises(ValueError, match="0/90 pair"):
        maps_frame_matrix(config, SINGLE * 3)
    with pytest.raises(ValueError, match="one 0 deg and one 90 deg"):
        maps_frame_matrix(config, SINGLE * 2)
    small = ScanRequest(55e-6, 55e-6, 0.5e-6, 0.5e-6, 64, 64)
    with pytest.raises(ValueError, match="1 um"):
        maps_frame_matrix(config, [small])


def test_the_demo_judges_a_push_in_the_first_maps_own_frame():
    """The demo's push truth: the true displacement through the first map's affine (its goal's
    frame), the creep-free step's beside it; closed forms of a push along -y."""
    from afm_bringup.demo_evaluation import IMAGE_FRAME, push_truth, truth_in_maps

    gain = 1.02 * np.linalg.inv(IMAGE_FRAME)  # map per true, 2 % above the creep-free step
    frame = np.hstack([gain, [[1e-7], [-2e-7]]])
    anchor = {"commanded": [55e-6, 55e-6], "metric": [55e-6, 55e-6], "frame": frame.tolist()}
    start, shift = np.array([55e-6, 55e-6]), np.array([0.0, -500e-9])
    result = {"truth_objects": [start[None, :], (start + shift)[None, :]], "truth_anchor": anchor}
    goal = start + [0.0, -500e-9]
    push = {"ran": True, "start": start.tolist(), "goal": goal.tolist(), "achieved": goal}
    truth = push_truth(result, push)
    wanted = goal - start
    assert truth["true_error"] == pytest.approx(np.hypot(*(gain @ shift - wanted)), rel=1e-9)
    old = np.linalg.solve(IMAGE_FRAME, shift)
    assert truth["true_error_creep_free"] == pytest.approx(np.hypot(*(old - wanted)), rel=1e-9)
    assert np.allclose(truth_in_maps([start], anchor), gain @ start + frame[:, 2], atol=1e-15)
