"""The demo report's estimated tip (afm_bringup.demo_tip, afm_core.imaging.tip_apex,
report_figures.save_tip_figure): from a small run's map, made by imaging particles with a
known tip, the figure is drawn at the page's width, its caption's numbers are the estimate's,
the width bound holds for the true tip, and the apex radius is called measured only when the
features are sharp enough to show it (then the stated range holds the true radius)."""

import re

import matplotlib.image
import numpy as np
import pytest

from afm_bringup.demo_tip import estimate_run_tip, tip_shape_caption, tip_shape_section
from afm_core.physics.tip_morphology import dilate
from afm_core.report import DPI, FIGURE_WIDTH_IN
from afm_core.sim.tip import TipParams, paraboloid_cone_tip

PIXEL, PIXELS, TIP_SIZE = 7e-9, 96, 15
TRUE = TipParams(apex_radius=20e-9, half_angle_deg=20.0, asymmetry=0.2)


def small_run_map(surface, seed=3):
    """(title, height, extent) as the demo's evaluation has its last map: `surface` imaged by
    the true tip, with 0.3 nm of noise (the simulator's map noise)."""
    tip = paraboloid_cone_tip(
        TRUE.apex_radius, TRUE.half_angle_deg, PIXEL, 400e-9, TRUE.asymmetry, 20
    )
    image = dilate(surface, tip) + np.random.default_rng(seed).normal(0, 0.3e-9, surface.shape)
    return "map", image, (0.0, PIXELS * PIXEL, 0.0, PIXELS * PIXEL)


def _grid():
    return (np.mgrid[0:PIXELS, 0:PIXELS] + 0.5) * PIXEL


def spheres(radius, centres_px):
    yy, xx = _grid()
    s = np.zeros((PIXELS, PIXELS))
    for cx, cy in centres_px:
        r2 = (xx - cx * PIXEL) ** 2 + (yy - cy * PIXEL) ** 2
        cap = radius + np.sqrt(np.clip(radius**2 - r2, 0, None))
        s = np.maximum(s, np.where(r2 < radius**2, cap, 0.0))
    return s


def _numbers(text):
    return [float(v) for v in re.findall(r"-?\d+(?:\.\d+)?", text)]


def test_blunt_particles_bound_the_width_and_leave_the_apex_unmeasured(tmp_path):
    """Three 100 nm spheres (the demo's particles; five times the tip's apex radius)."""
    shape = estimate_run_tip(
        small_run_map(spheres(100e-9, [(25, 30), (70, 40), (45, 75)])),
        TRUE.apex_radius,
        TRUE,
        TIP_SIZE,
        "auto",
    )
    r = shape["reading"]
    assert not r.apex_measured and r.drop < r.resolution
    # the estimate is an upper bound: the true tip is no wider at the constrained depth
    assert shape["true_width"] <= r.max_width
    caption = tip_shape_caption(shape)
    assert "apex radius not measurable from these images" in caption
    numbers = _numbers(caption.split("as the imaging node makes it:")[1])
    # (value m, decimals shown in nm) in the caption's order
    expected = [
        (r.depth, 1), (r.radius, 0), (r.max_width, 0), (r.drop, 1), (r.fit_ring, 0),
        (r.resolution, 1), (r.threshold, 1), (3e-9, 0), (r.noise, 2),
        (TRUE.apex_radius, 0), (shape["true_width"], 0), (r.depth, 1),
    ]  # fmt: skip
    assert numbers == pytest.approx([round(v * 1e9, d) for v, d in expected], abs=1e-9), caption
    heading, body = tip_shape_section(tmp_path / "tip.png", shape)
    assert "tip" in heading and "tip.png" in body
    height, width = matplotlib.image.imread(tmp_path / "tip.png").shape[:2]
    assert width == FIGURE_WIDTH_IN * DPI and height < width / 2


def test_sharp_features_measure_the_apex_within_the_stated_range():
    """Spikes of 5 nm radius, 60 nm high, on a grid: far sharper than the tip."""
    yy, xx = _grid()
    s = np.zeros((PIXELS, PIXELS))
    for cx in range(12, PIXELS, 24):
        for cy in range(12, PIXELS, 24):
            r2 = (xx - cx * PIXEL) ** 2 + (yy - cy * PIXEL) ** 2
            s = np.maximum(s, np.where(r2 < (5e-9) ** 2, 60e-9, 0.0))
    shape = estimate_run_tip(small_run_map(s), TRUE.apex_radius, TRUE, TIP_SIZE, "auto")
    r = shape["reading"]
    assert r.apex_measured
    assert r.apex_low <= TRUE.apex_radius <= r.fit_radius
    assert shape["true_width"] <= r.max_width
    # on the constrained pixels the true tip lies below the estimate (an upper bound), to
    # within its resolution band
    ok = np.isfinite(shape["uncertainty"])
    below = shape["true_tip"][ok] - shape["tip"][ok]
    assert below.max() <= r.resolution
    assert "apex radius" in tip_shape_caption(shape) and "not measurable" not in tip_shape_caption(
        shape
    )


def test_a_threshold_below_the_noise_bounds_nothing(tmp_path):
    """A threshold set by hand below 3 sigma of the noise: noise sharpens the estimate beyond
    the tip, so the report claims neither the width bound nor an apex radius."""
    shape = estimate_run_tip(
        small_run_map(spheres(100e-9, [(25, 30), (70, 40), (45, 75)])),
        TRUE.apex_radius,
        TRUE,
        TIP_SIZE,
        0.2e-9,
    )
    r = shape["reading"]
    assert r.below_noise and not r.apex_measured
    caption = tip_shape_caption(shape)
    assert "nothing measured" in caption and "at most" not in caption
    tip_shape_section(tmp_path / "tip.png", shape)
    assert (tmp_path / "tip.png").stat().st_size > 10_000
