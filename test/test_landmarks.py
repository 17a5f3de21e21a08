"""Landmark extraction (afm_core.imaging.landmarks) against the simulator's ground truth."""

import math

import numpy as np
import pytest

from afm_core.imaging.landmarks import Landmark, MapErrorModel, extract_landmarks, substrate_plane
from afm_core.instrument import ScanRequest
from afm_core.sim.config import load_config, merge
from afm_core.sim.instrument import SimulatedAfm

ORIGIN = 10e-6  # m, scan area corner (x and y)
SIZE = 0.8e-6  # m
PIXELS = 400  # 2 nm pixels: a fine map


def exact_config(spheres, rods=()):
    """Scanner imperfections and drift off: the image sits exactly where the sample is.
    Sensor noise, substrate roughness and the tip (20 nm apex, 20 deg cone) stay on."""
    return merge(
        load_config(),
        {
            "scanner": {
                "hysteresis_enabled": False,
                "creep_enabled": False,
                "coupling_enabled": False,
                "deflection_enabled": False,
                "positioning_noise_enabled": False,
            },
            "drift": {"enabled": False},
            "sample": {"spheres": list(spheres), "rods": list(rods)},
        },
    )


def scan(config, pixels=PIXELS):
    afm = SimulatedAfm(config)
    data = afm.raster_scan(ScanRequest(ORIGIN, ORIGIN, SIZE, SIZE, pixels, pixels, line_rate=5.0))
    return data


SPHERES = [
    {"x": ORIGIN + 200e-9, "y": ORIGIN + 250e-9, "radius": 50e-9},
    {"x": ORIGIN + 455e-9, "y": ORIGIN + 401e-9, "radius": 60e-9},
]
TUBE = {
    "x": ORIGIN + 300e-9,
    "y": ORIGIN + 600e-9,
    "angle": 0.5,
    "length": 300e-9,
    "radius": 10e-9,
    "kind": "tube",
}


@pytest.fixture(scope="module")
def scene():
    data = scan(exact_config(SPHERES, [TUBE]))
    landmarks = extract_landmarks(
        data.height, data.pixel_size_x, data.pixel_size_y, data.origin_x, data.origin_y
    )
    return data, landmarks


def nearest(landmarks, x, y) -> Landmark:
    return min(landmarks, key=lambda lm: math.hypot(lm.x - x, lm.y - y))


def test_spheres_are_found_where_they_are_with_heights_twice_their_radius(scene):
    _, landmarks = scene
    assert len(landmarks) == 3
    for truth in SPHERES:
        lm = nearest(landmarks, truth["x"], truth["y"])
        assert lm.kind == "sphere"
        assert math.hypot(lm.x - truth["x"], lm.y - truth["y"]) < 1.5e-9
        assert lm.height == pytest.approx(2 * truth["radius"], rel=0.02)
        assert lm.radius == pytest.approx(truth["radius"], rel=0.02)
        # the tip broadens laterally: the apparent radius at half height exceeds the true one
        assert lm.half_width > truth["radius"]
        assert lm.length == 0.0 and lm.orientation == 0.0
        assert lm.thresholds_used == 5


def test_a_tube_gets_its_orientation_length_and_width(scene):
    _, landmarks = scene
    lm = nearest(landmarks, TUBE["x"], TUBE["y"])
    assert lm.kind == "tube"
    assert lm.elongation > 3.0
    assert math.hypot(lm.x - TUBE["x"], lm.y - TUBE["y"]) < 2e-9
    assert abs(math.degrees(lm.orientation - TUBE["angle"])) < 1.5
    assert lm.height == pytest.approx(2 * TUBE["radius"], rel=0.08)
    assert lm.radius == pytest.approx(TUBE["radius"], rel=0.08)
    # The image is broadened by the tip (~ the tip's width at that depth) at both ends and sides:
    # end to end at half height it is longer than the tube by 2 * half_width, and wider than it
    # is high.
    assert lm.half_width > TUBE["radius"]
    apparent = lm.length + 2 * lm.half_width
    assert apparent > TUBE["length"] + 2 * TUBE["radius"]
    # `length` is the axis length with the broadening taken out
    assert lm.length == pytest.approx(TUBE["length"], abs=10e-9)


def test_covariance_is_at_least_the_map_error_model_and_positive_definite(scene):
    data, landmarks = scene
    model = MapErrorModel()
    assert (model.sigma_x, model.sigma_y) == (5.0e-9, 4.5e-9)  # book Fig. 7.10
    for lm in landmarks:
        cov = lm.covariance
        assert cov.shape == (2, 2)
        np.testing.assert_allclose(cov, cov.T, rtol=0, atol=0)
        assert np.all(np.linalg.eigvalsh(cov) > 0)
        extra = cov - np.diag([model.sigma_x**2, model.sigma_y**2])
        assert np.all(np.linalg.eigvalsh(extra) >= -1e-30)  # the spread only adds
    custom = MapErrorModel(sigma_x=1e-9, sigma_y=2e-9)
    fewer = extract_landmarks(
        data.height,
        data.pixel_size_x,
        data.pixel_size_y,
        data.origin_x,
        data.origin_y,
        error_model=custom,
    )
    for lm in fewer:
        assert lm.covariance[0, 0] >= 1e-18 and lm.covariance[1, 1] >= 4e-18
        assert lm.covariance[0, 0] < 25e-18


def test_spread_across_thresholds_adds_to_the_covariance():
    """A lopsided bump: the centre of gravity moves with the threshold, and the covariance
    grows by that spread along x (not along y, where the bump is symmetric)."""
    pixel = 2e-9
    rows, cols = np.indices((100, 200))
    x, y = (cols + 0.5) * pixel, (rows + 0.5) * pixel
    dx, dy = x - 80e-9, y - 100e-9
    steep, shallow = 1.0, 0.3  # different flank slopes left and right
    slope = np.where(dx < 0, steep, shallow)
    bump = np.maximum(0.0, 60e-9 - slope * np.abs(dx) - 1.0 * np.abs(dy))
    landmarks = extract_landmarks(bump, pixel, pixel, error_model=MapErrorModel(0.0, 0.0))
    assert len(landmarks) == 1
    cov = landmarks[0].covariance
    assert math.sqrt(cov[0, 0]) > 5e-9  # centroids spread by tens of nm along x
    assert cov[1, 1] < 1e-20


def test_ids_are_sorted_by_position_and_stable(scene):
    data, landmarks = scene
    assert [lm.id for lm in landmarks] == list(range(len(landmarks)))
    rows = [math.floor((lm.y - data.origin_y) / data.pixel_size_y) for lm in landmarks]
    assert rows == sorted(rows)
    again = extract_landmarks(
        data.height, data.pixel_size_x, data.pixel_size_y, data.origin_x, data.origin_y
    )
    assert [(lm.id, lm.kind, lm.x, lm.y) for lm in again] == [
        (lm.id, lm.kind, lm.x, lm.y) for lm in landmarks
    ]


def test_a_tilted_substrate_is_levelled(scene):
    data, landmarks = scene
    rows, cols = np.indices(data.height.shape)
    tilted = data.height + 40e-9 * cols / cols.shape[1] - 25e-9 * rows / rows.shape[0] + 7e-9
    again = extract_landmarks(
        tilted, data.pixel_size_x, data.pixel_size_y, data.origin_x, data.origin_y
    )
    assert len(again) == len(landmarks)
    for a, b in zip(again, landmarks):
        assert a.kind == b.kind
        assert math.hypot(a.x - b.x, a.y - b.y) < 0.5e-9
        assert a.height == pytest.approx(b.height, abs=1e-9)
    plane = substrate_plane(tilted, 10e-9)
    assert (
        np.median(np.abs((tilted - plane) - (data.height - substrate_plane(data.height, 10e-9))))
        < 0.5e-9
    )


@pytest.fixture(scope="module")
def crowded():
    """Two touching 100 nm spheres, a sphere cut by the left border, a tall rod."""
    spheres = [
        {"x": ORIGIN + 250e-9, "y": ORIGIN + 250e-9, "radius": 100e-9},
        {"x": ORIGIN + 450e-9, "y": ORIGIN + 250e-9, "radius": 100e-9},
        {"x": ORIGIN + 5e-9, "y": ORIGIN + 600e-9, "radius": 50e-9},
    ]
    rod = {
        "x": ORIGIN + 500e-9,
        "y": ORIGIN + 600e-9,
        "angle": -1.0,
        "length": 250e-9,
        "radius": 35e-9,
        "kind": "rod",
    }
    data = scan(exact_config(spheres, [rod]), pixels=200)
    landmarks = extract_landmarks(
        data.height, data.pixel_size_x, data.pixel_size_y, data.origin_x, data.origin_y
    )
    return spheres, rod, landmarks


def test_particles_touching_the_border_are_skipped(crowded):
    spheres, rod, landmarks = crowded
    cut = spheres[2]
    assert all(math.hypot(lm.x - cut["x"], lm.y - cut["y"]) > 100e-9 for lm in landmarks)
    assert len(landmarks) == 3


def test_touching_spheres_are_told_apart(crowded):
    spheres, _, landmarks = crowded
    for truth in spheres[:2]:
        lm = nearest(landmarks, truth["x"], truth["y"])
        assert lm.kind == "sphere"
        assert math.hypot(lm.x - truth["x"], lm.y - truth["y"]) < 2e-9
        assert lm.height == pytest.approx(2 * truth["radius"], rel=0.02)


def test_a_tall_elongated_feature_is_a_rod(crowded):
    _, rod, landmarks = crowded
    lm = nearest(landmarks, rod["x"], rod["y"])
    assert lm.kind == "rod"
    assert math.hypot(lm.x - rod["x"], lm.y - rod["y"]) < 3e-9
    assert abs(math.degrees(lm.orientation - rod["angle"])) < 2.0
    assert lm.radius == pytest.approx(rod["radius"], rel=0.05)
    assert lm.length == pytest.approx(rod["length"], abs=15e-9)


def test_coordinates_follow_pixel_centres_with_anisotropic_pixels():
    """Pixel (row, col) is at origin + (col + 0.5) px, origin + (row + 0.5) py: a noiseless
    hemisphere placed off the pixel grid comes back at its place."""
    px, py, ox, oy = 2e-9, 3e-9, -1e-6, 2e-6
    rows, cols = np.indices((150, 200))
    x, y = ox + (cols + 0.5) * px, oy + (rows + 0.5) * py
    cx, cy, r = ox + 201.3e-9, oy + 233.7e-9, 60e-9
    d2 = (x - cx) ** 2 + (y - cy) ** 2
    height = np.where(d2 < r * r, r + np.sqrt(np.clip(r * r - d2, 0, None)), 0.0)
    [lm] = extract_landmarks(height, px, py, ox, oy)
    assert lm.kind == "sphere"
    assert lm.x == pytest.approx(cx, abs=0.3e-9) and lm.y == pytest.approx(cy, abs=0.3e-9)
    assert lm.height == pytest.approx(2 * r, rel=0.01)


def test_nothing_to_find_on_a_flat_or_low_map():
    rng = np.random.default_rng(3)
    flat = rng.normal(0, 0.3e-9, (64, 64))
    assert extract_landmarks(flat, 2e-9, 2e-9) == []
    low = flat.copy()
    low[30:34, 30:34] += 5e-9  # below min_height
    assert extract_landmarks(low, 2e-9, 2e-9) == []


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"height": np.zeros(10)}, "height"),
        ({"height": np.zeros((2, 3, 4))}, "height"),
        ({"height": np.where(np.eye(8) > 0, np.nan, 0.0)}, "height"),
        ({"height": np.full((8, 8), np.inf)}, "height"),
        ({"pixel_size_x": 0.0}, "pixel_size_x"),
        ({"pixel_size_y": -1e-9}, "pixel_size_y"),
        ({"pixel_size_x": float("nan")}, "pixel_size_x"),
        ({"origin_x": float("inf")}, "origin_x"),
        ({"min_height": 0.0}, "min_height"),
        ({"thresholds": (0.5, 1.2)}, "thresholds"),
        ({"thresholds": ()}, "thresholds"),
        ({"tube_elongation": 1.0}, "tube_elongation"),
        ({"error_model": MapErrorModel(sigma_x=-1e-9)}, "error_model.sigma_x"),
    ],
)
def test_bad_input_is_rejected_by_name(kwargs, field):
    args = {"height": np.zeros((8, 8)), "pixel_size_x": 1e-9, "pixel_size_y": 1e-9}
    args.update(kwargs)
    with pytest.raises(ValueError, match=field):
        extract_landmarks(**args)
