"""The closed loop's observations in the maps' frame (issue 32): with the calibration the
graph ships (`sim_calibration.yaml`, measured in the images' own frame, its scanner matrix the
gain of a short move after a reversal, 1.4 % above the images' in y), what the loop's local
scan lines say the particle moved is compared with the simulator's truth brought into the maps'
frame (`image_frame_matrix`, as the benches do). The chain of lines reaches the particle through
reversals, on the images' hysteresis branch: measured with the short move's gain instead, a
500 nm push's displacement came out ~8 nm long, beyond the observation's own 2 sigma. And the
strokes meet the particle where the maps' frame has the contact: the radii (metres) divided by
the images' scale (`Calibration.lateral_scale`), else every centre stroke stopped ~8.5 nm short
and pushes asked for 10 nm ended 10-14 nm off. The open-loop hands place their strokes in the
same frame and plan the same contact distance (`push_steps.in_maps_frame`)."""

import math
from pathlib import Path

import numpy as np
import pytest
from test_push_procedure import MAP_SCAN, SPHERES, Session

from afm_core.evaluation import image_frame_matrix, images_frame_matrix
from afm_core.localization.calibration.model import load_calibration
from afm_core.manipulation import PushFailed
from afm_core.manipulation.execute import OBSERVED
from afm_core.manipulation.verdict import (
    CANNOT_TELL,
    OUTSIDE,
    WITHIN,
    judge,
    within_probability,
)
from afm_core.sim.config import load_config

NM = 1e-9
ROOT = Path(__file__).resolve().parents[1]


def run(calibration, seed: int, push: float = 500 * NM, tolerance: float = 10 * NM):
    """One closed-loop push along -y; per observation (estimated displacement, its covariance,
    true displacement in the maps' frame)."""
    session = Session(calibration, seed=seed)
    procedure, true_sphere = session.procedure, session.true_sphere
    mark = session.row[1]
    start = np.array([mark.x, mark.y])
    frame = np.linalg.inv(image_frame_matrix())
    before = true_sphere(start)
    seen = []

    def progress(p):
        if p.phase == "observing" and p.belief == OBSERVED:
            truth = frame @ (true_sphere(before) - before)
            seen.append((np.array(p.particle_estimate) - start, p.belief_covariance, truth))

    result = procedure.push(
        mark.id,
        start + [0.0, -push],
        strategy="closed_loop",
        tolerance=tolerance,
        progress=progress,
    )
    moved = frame @ (true_sphere(before) - before)
    return seen, float(np.hypot(*(moved - [0.0, -push]))), result


SIM_CALIBRATION = ROOT / "afm_localization" / "config" / "sim_calibration.yaml"
# a plan's contact distance may differ from the truth's in the maps' frame by the calibration's
# own scale error (1.047 measured on a grating against the creep-free 1.0596: 1.2 %); metric
# radii in the maps' frame were 6 % off (8.3 nm of a sphere's 150 nm, 3.1 nm of a tube's 60 nm)
SCALE_ERROR = 0.02


def first_plan(procedure, landmark_id, goal, strategy, **fields):
    """The first plan (a closed loop's first leg) of a push, which is then cancelled before
    its first stroke."""
    plans = []

    def progress(p):
        if p.plan is not None:
            plans.append(p.plan)

    with pytest.raises(PushFailed, match="cancelled"):
        procedure.push(
            landmark_id,
            goal,
            strategy=strategy,
            progress=progress,
            should_stop=lambda: bool(plans),
            **fields,
        )
    return plans[0]


def true_contact_in_maps(plan, radius: float) -> float:
    """The contact distance of the map's particle of `radius` (m, from its height, which the
    lateral scale does not touch) and the simulator's tip in the maps' frame along the plan's
    first contact stroke, through the images' true-per-commanded matrix."""
    true_contact = radius + load_config().contact.tip_radius
    stroke = next(st for st in plan.strokes if st.contact)
    d = np.asarray(stroke.end, float) - np.asarray(stroke.start, float)
    return true_contact / float(np.hypot(*(image_frame_matrix() @ (d / np.hypot(*d)))))


@pytest.mark.parametrize("strategy", ["nano_hand", "center", "closed_loop"])
def test_every_hand_plans_the_maps_frames_contact_distance(strategy):
    """The contact distance a plan stops the tip at (the particle's radius + the tip's, which
    the strokes' ends and the pushing model both use) is the map's radius and the simulator's
    tip brought into the maps' frame, for the open-loop hands as for the closed loop."""
    session = Session(load_calibration(SIM_CALIBRATION), seed=1)
    mark = session.row[1]
    goal = np.array([mark.x, mark.y - 500 * NM])
    plan = first_plan(session.procedure, mark.id, goal, strategy)
    assert_contact_in_maps_frame(plan, mark.radius, strategy)


def assert_contact_in_maps_frame(plan, radius: float, strategy: str) -> None:
    """The plan's contact distance (particle + tip radius) is the truth's in the maps' frame,
    within the calibration's scale error."""
    truth = true_contact_in_maps(plan, radius)
    planned = plan.particle_radius + plan.tip_radius
    assert abs(planned - truth) <= SCALE_ERROR * truth, (
        f"{strategy}: planned contact {planned / NM:.1f} nm, the truth's in the maps' frame "
        f"{truth / NM:.1f} nm"
    )


@pytest.mark.parametrize("seed", [1])
def test_observed_displacement_is_the_maps_frames_truth(seed):
    calibration = load_calibration(ROOT / "afm_localization" / "config" / "sim_calibration.yaml")
    # the premise: the shipped matrix differs from the images' gain by more than the test's
    # margin over the push (else the test could not tell the two apart)
    assert abs(calibration.scanner_matrix[1][1] - 1.0) * 500 * NM > 5 * NM
    seen, _, _ = run(calibration, seed)
    assert seen, "no observation of the particle"
    for estimated, covariance, truth in seen:
        sigma = math.sqrt(covariance[1, 1])
        along = estimated[1] - truth[1]
        assert abs(along) <= 2 * sigma, (
            f"observed {estimated[1] / NM:.1f} nm along, true {truth[1] / NM:.1f} nm in the "
            f"maps' frame: {along / NM:.1f} nm off, the observation's sigma {sigma / NM:.1f} nm"
        )


@pytest.mark.parametrize("seed", [2, 4])
def test_a_push_asked_for_10_nm_ends_within_it_by_the_truth(seed):
    """Issue 32's figure on two seeds: the loop's own stop rule claims the tolerance with 2
    sigma, so the truth (maps' frame) must be within it."""
    calibration = load_calibration(ROOT / "afm_localization" / "config" / "sim_calibration.yaml")
    tolerance = 10 * NM
    _, error, _ = run(calibration, seed, tolerance=tolerance)
    assert error <= tolerance, f"true error {error / NM:.1f} nm in the maps' frame"


@pytest.fixture(scope="module")
def images_frame():
    """True per image displacement of the maps' own scan with the scanner's creep (the
    verification's images have it; the benches' `image_frame_matrix` is creep-free, 0.7 % off
    in y)."""
    return images_frame_matrix(load_config(), MAP_SCAN, SPHERES[1])


@pytest.mark.parametrize("seed", [1, 3])
def test_verified_displacement_is_the_images_truth_within_its_sigma(seed, images_frame):
    """The rescan's verified displacement, in the maps' frame, against the truth in the maps'
    own (images') frame, per axis within 2 of the verdict's sigmas. Through the short-move
    scanner matrix it came out 7 nm long over 500 nm, and the drift during the before
    image's pass (0.13 nm/s over its 15.6 s between start and goal rows) added 2 nm more."""
    calibration = load_calibration(ROOT / "afm_localization" / "config" / "sim_calibration.yaml")
    session = Session(calibration, seed=seed)
    mark = session.row[1]
    start = np.array([mark.x, mark.y])
    before = session.true_sphere(start)
    result = session.procedure.push(
        mark.id, start + [0.0, -500 * NM], strategy="closed_loop", tolerance=10 * NM
    )
    truth = np.linalg.solve(images_frame, session.true_sphere(before) - before)
    miss = (result.achieved - start) - truth
    sigma = np.sqrt(np.diag(result.verdict.covariance))
    assert np.all(np.abs(miss) <= 2 * sigma), (
        f"verified minus true {miss / NM} nm, sigma {sigma / NM} nm ({result.message})"
    )


@pytest.mark.parametrize("seed", [2, 3])
def test_the_verdict_at_10_nm_agrees_with_the_truth(seed, images_frame):
    """Pushes that landed 4 nm from the goal by the truth were reported 10.4 and 10.8 nm off
    (failed at 10 nm) by the scanner-matrix conversion; the verdict now says within, or at
    worst that it cannot tell, never outside, and success only when the truth is within."""
    calibration = load_calibration(ROOT / "afm_localization" / "config" / "sim_calibration.yaml")
    session = Session(calibration, seed=seed)
    mark = session.row[1]
    start = np.array([mark.x, mark.y])
    goal = start + [0.0, -500 * NM]
    before = session.true_sphere(start)
    result = session.procedure.push(mark.id, goal, strategy="closed_loop", tolerance=10 * NM)
    truth = np.linalg.solve(images_frame, session.true_sphere(before) - before)
    true_error = float(np.hypot(*(truth - (goal - start))))
    assert true_error <= 10 * NM, f"the premise: true error {true_error / NM:.1f} nm"
    assert result.verdict.verdict != OUTSIDE, result.message
    assert result.success == (result.verdict.verdict == WITHIN)


def test_within_probability_is_the_closed_form():
    """A measured error of 0: the true error is Rayleigh, P = 1 - exp(-t^2 / (2 sigma^2));
    and the verdict's thresholds."""
    sigma, tolerance = 3 * NM, 5 * NM
    p = within_probability([0.0, 0.0], np.eye(2) * sigma**2, tolerance)
    assert p == pytest.approx(1 - math.exp(-(tolerance**2) / (2 * sigma**2)), rel=1e-9)
    # far beyond the tolerance, a one-dimensional Gaussian tail along the error
    far = within_probability([0.0, 20 * NM], np.eye(2) * sigma**2, 10 * NM)
    assert far == pytest.approx(0.0, abs=1e-3)
    assert judge(0.96) == WITHIN and judge(0.04) == OUTSIDE and judge(0.5) == CANNOT_TELL
