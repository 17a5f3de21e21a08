"""The images' lateral scale measured on a reference lattice of known pitch (a calibration
grating), against the simulator's truth of the images' frame (`image_frame_matrix`).

`image_frame_matrix` is the gain of a creep-free step on the images' hysteresis branch; it is
the images' frame where creep is off. With creep on (the default simulator) a raster line is
too fast for the scanner's creep to follow, so the images' fast axis is shorter than that step
by the creep fractions (about 2 %): the measurement sees it and the creep-free truth does not,
which the last simulator test states."""

import numpy as np
import pytest

from afm_core.evaluation import image_frame_matrix
from afm_core.localization.calibration.lateral_scale import fit_lattice, measure_lateral_scale
from afm_core.sim.config import load_config, merge
from afm_core.sim.instrument import SimulatedAfm

PITCH = 300e-9
CENTRE = 55e-6
NO_CREEP = {"scanner": {"creep_enabled": False}}


def lattice(pitch=PITCH, radius=50e-9, n=6):
    return [
        {"x": CENTRE + i * pitch, "y": CENTRE + j * pitch, "radius": radius}
        for i in range(-n, n + 1)
        for j in range(-n, n + 1)
    ]


def simulator(seed: int, extra: dict, spheres=None) -> SimulatedAfm:
    spheres = lattice() if spheres is None else spheres
    return SimulatedAfm(
        merge(load_config(), {"seed": seed, "sample": {"spheres": spheres}, **extra})
    )


def truth(extra: dict) -> np.ndarray:
    return image_frame_matrix(merge(load_config(), extra))


@pytest.mark.parametrize("seed", [0, 1])
def test_scale_is_the_images_frame_truth(seed):
    true = truth(NO_CREEP)
    result = measure_lateral_scale(simulator(seed, NO_CREEP), PITCH)
    true_scale = float(np.sqrt(np.linalg.det(true)))
    assert abs(result.scale - true_scale) <= 2 * result.scale_sigma
    assert abs(result.scale / true_scale - 1) < 0.005
    assert np.all(np.abs(result.matrix - true) <= 3 * result.matrix_sigma + 1e-4)
    assert result.particles >= 2 * 49  # both passes, most of the 8 x 8 sites in the image


def test_scale_follows_the_feed_forward_error():
    # a feed-forward with a worse model of the loop width leaves more residual hysteresis:
    # another gain of the images' branch
    other = {**NO_CREEP, "controller": {"model_error": 0.3}}
    true = float(np.sqrt(np.linalg.det(truth(other))))
    default = float(np.sqrt(np.linalg.det(truth(NO_CREEP))))
    result = measure_lateral_scale(simulator(0, other), PITCH)
    assert abs(true - default) > 5 * result.scale_sigma  # the test tells the two apart
    assert abs(result.scale - true) <= 2 * result.scale_sigma
    assert abs(result.scale / true - 1) < 0.005


def test_default_simulator_fast_axis_loses_the_creep():
    config = load_config()
    true = truth({})
    creep = sum(config.scanner.creep_fractions)
    result = measure_lateral_scale(simulator(0, {}), PITCH)
    # a 2.4 um line at 4 Hz is traced in 0.125 s, faster than the creep (0.5-50 s) follows
    assert result.matrix[0, 0] == pytest.approx(true[0, 0] / (1 + creep), rel=0.003)
    assert result.scale < float(np.sqrt(np.linalg.det(true))) - 3 * result.scale_sigma


def test_fit_lattice_recovers_a_known_affine_lattice():
    rng = np.random.default_rng(3)
    vectors = np.array([[0.95, 0.01], [-0.02, 1.04]]) * PITCH
    ij = np.array([(i, j) for i in range(-3, 5) for j in range(-4, 3)], float)
    points = [1e-6, 2e-6] + ij @ vectors.T + rng.normal(0, 1e-9, (len(ij), 2))
    fit = fit_lattice(points, PITCH)
    sigma = np.sqrt(np.diag(fit.covariance)).reshape(2, 2)
    assert np.all(np.abs(fit.vectors - vectors) <= 4 * sigma)
    assert fit.particles == len(ij)
    assert fit.residual_rms == pytest.approx(1e-9, rel=0.3)


def test_bad_input_names_the_field_and_the_limit():
    sim = simulator(0, NO_CREEP)
    with pytest.raises(ValueError, match="pitch"):
        measure_lateral_scale(sim, 0.0)
    with pytest.raises(ValueError, match="pitch=.*size/3"):
        measure_lateral_scale(sim, 1e-6)
    with pytest.raises(ValueError, match="particles found=4: need at least 9"):
        fit_lattice([[0, 0], [PITCH, 0], [0, PITCH], [PITCH, PITCH]], PITCH)
    points = [(i * PITCH, j * PITCH) for i in range(4) for j in range(4)]
    with pytest.raises(ValueError, match="20 %"):
        fit_lattice(points, 1.3 * PITCH)  # the reference's pitch is not the one given
    with pytest.raises(ValueError, match="particles found=0"):  # no reference in the image
        measure_lateral_scale(simulator(0, NO_CREEP, spheres=[]), PITCH)
