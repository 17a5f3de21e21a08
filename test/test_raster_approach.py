"""Approaching an image from beyond its start (imaging.raster_approach, issue 36): the point,
and that it puts every image on the hysteresis branch of the range centre, against the
simulator's truth."""

from __future__ import annotations

import numpy as np
import pytest

from afm_core.imaging.landmarks import extract_landmarks
from afm_core.imaging.raster_approach import RASTER_APPROACH_OVERSHOOT, approach_point
from afm_core.instrument import ScannerLimits, ScanRequest
from afm_core.sim.config import load_config, merge
from afm_core.sim.instrument import SimulatedAfm

NM, UM = 1e-9, 1e-6
SIZE, PIXELS = 1.6 * UM, 128
SPACING = 0.8 * UM


def request_at(x, y, angle=0.0, up=True, size=SIZE):
    return ScanRequest(x, y, size, size, PIXELS, PIXELS, angle, up, line_rate=4.0)


@pytest.mark.parametrize(
    ("angle", "up", "sign"),
    [(0.0, True, (1, 1)), (0.0, False, (1, -1)), (90.0, True, (1, 1)), (90.0, False, (-1, 1))],
)
def test_the_approach_comes_from_beyond_the_start_along_both_axes(angle, up, sign):
    request = request_at(50 * UM, 50 * UM, angle, up)
    first = np.array(request.first_point())
    point = np.array(approach_point(request, 1.0))
    assert np.allclose(point - first, np.array(sign) * SIZE)
    assert approach_point(request, 0.0) == pytest.approx(tuple(first))


def test_the_approach_stays_inside_the_range_and_a_bad_overshoot_is_refused():
    limits = ScannerLimits()
    request = request_at(limits.range_x - SIZE, limits.range_y - SIZE)
    x, y = approach_point(request, 2.0, limits)
    assert (x, y) == (limits.range_x, limits.range_y)
    for bad in (-0.1, RASTER_APPROACH_OVERSHOOT.maximum + 1):
        with pytest.raises(ValueError, match="raster_approach_overshoot"):
            approach_point(request, bad)


def image_gains(place, overshoot: float) -> np.ndarray:
    """(gain along x, gain along y) of a 0 deg and a 90 deg image (rows) at `place` (m,
    commanded), reached by a move from the range centre: the separation of spheres placed
    SPACING apart (truth) as the image shows it, per true metre."""
    config = load_config()
    quiet = {
        "drift": {"enabled": False},
        "scanner": {"creep_enabled": False, "positioning_noise_enabled": False},
    }
    probe = SimulatedAfm(merge(config, {**quiet, "sample": {"spheres": [], "random_spheres": 0}}))
    probe.move_tip(*place, 1e-5)
    true = np.array(probe.truth()["tip_position"][:2])  # where the scanner really is there
    spheres = [
        {"x": float(true[0] + dx), "y": float(true[1] + dy), "radius": 40 * NM}
        for dx, dy in (
            (-SPACING / 2, -SPACING / 2),
            (SPACING / 2, -SPACING / 2),
            (-SPACING / 2, SPACING / 2),
        )
    ]
    gains = []
    for angle in (0.0, 90.0):
        sim = SimulatedAfm(
            merge(config, {**quiet, "sample": {"spheres": spheres, "random_spheres": 0}})
        )
        request = request_at(place[0] - SIZE / 2, place[1] - SIZE / 2, angle)
        sim.move_tip(*approach_point(request, overshoot), 1e-5)
        scan = sim.raster_scan(request)
        marks = extract_landmarks(
            scan.height,
            scan.pixel_size_x,
            scan.pixel_size_y,
            scan.origin_x,
            scan.origin_y,
            min_height=20 * NM,
        )
        assert len(marks) == 3
        p = np.array([[m.x, m.y] for m in marks])
        corner = p[np.argmin(p.sum(axis=1))]
        right, top = p[np.argmax(p[:, 0] - p[:, 1])], p[np.argmax(p[:, 1] - p[:, 0])]
        gains.append([(right[0] - corner[0]) / SPACING, (top[1] - corner[1]) / SPACING])
    return np.array(gains)


def test_images_away_from_the_centre_are_on_the_centre_branch_only_when_approached_from_beyond():
    """30-45 um from the centre an image whose slow axis continues the long move's direction
    images that axis several % differently from the fast axis (the hysteresis branch); from
    one image size beyond, both images of a pair image both axes as at the centre."""
    centre = image_gains((55 * UM, 55 * UM), 1.0)
    assert np.ptp(centre) < 0.005  # the centre: one gain for both axes and both images
    away = (85 * UM, 88 * UM)
    direct = image_gains(away, 0.0)
    assert np.ptp(direct) > 0.03, direct
    beyond = image_gains(away, 1.0)
    assert np.max(np.abs(beyond - centre.mean())) < 0.005, (beyond, centre)
