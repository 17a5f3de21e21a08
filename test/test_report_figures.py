"""The demo report's frames and figures (afm_core.evaluation.push_image_frames,
afm_core.report_figures): the rescans land in the task frame where the nano-hand's own
verification puts them, and every figure is the page's width."""

import matplotlib.image
import numpy as np
import pytest

from afm_core.evaluation import find_particles, push_image_frames
from afm_core.instrument import RasterScanData
from afm_core.report import DPI, FIGURE_WIDTH_IN, save_height_maps
from afm_core.report_figures import (
    save_force_figure,
    save_localizer_figure,
    save_map_figure,
    save_push_figure,
)

PIXEL = 5e-9
RADIUS = 100e-9


def scan_of(centres, origin, pixels=200) -> RasterScanData:
    """A 0 deg scan of hemispherical particles (radius RADIUS) standing on a flat substrate."""
    xs = origin[0] + (np.arange(pixels) + 0.5) * PIXEL
    ys = origin[1] + (np.arange(pixels) + 0.5) * PIXEL
    gx, gy = np.meshgrid(xs, ys)
    height = np.zeros_like(gx)
    for cx, cy in centres:
        rho2 = (gx - cx) ** 2 + (gy - cy) ** 2
        height = np.maximum(
            height, np.sqrt(np.clip(RADIUS**2 - rho2, 0, None)) + RADIUS * (rho2 < RADIUS**2)
        )
    return RasterScanData(
        height,
        PIXEL,
        PIXEL,
        origin[0],
        origin[1],
        0.0,
        True,
        1.0,
        np.arange(pixels),
        0.0,
        "tapping",
    )


def test_the_rescans_land_in_the_task_frame():
    """A particle pushed 300 nm along -y, another left alone, drift between the map and the
    rescans (d) and between the two rescans (o): shifted by push_image_frames, each image
    shows the particles where the task frame has them."""
    start, goal = np.array([55.0e-6, 55.0e-6]), np.array([55.0e-6, 54.7e-6])
    # beyond the push's reach (the nano-hand leaves nearer ones out of its control points)
    still = np.array([55.7e-6, 55.1e-6])
    d, o = np.array([62e-9, -41e-9]), np.array([-23e-9, 17e-9])
    origin = (54.45e-6, 54.45e-6)
    before = scan_of([start + d, still + d], origin, pixels=300)
    after = scan_of([goal + d + o, still + d + o], origin, pixels=300)
    frames = push_image_frames(before, after, start, goal, RADIUS)
    assert frames.before_shift == pytest.approx(-d, abs=PIXEL)
    assert frames.after_shift == pytest.approx(-(d + o), abs=PIXEL)
    assert frames.control_points == 1
    # where the plotted after image shows the pushed particle, with its extent shifted
    seen = [
        np.array([v.x, v.y]) + frames.after_shift
        for v in find_particles(after.height, PIXEL, PIXEL, *origin)
    ]
    assert min(np.hypot(*(p - goal)) for p in seen) < PIXEL
    assert min(np.hypot(*(p - still)) for p in seen) < PIXEL
    with pytest.raises(ValueError, match="no particle"):
        push_image_frames(scan_of([], origin), None, start, goal)


def width_px(path) -> int:
    return matplotlib.image.imread(path).shape[1]


def test_every_figure_is_the_page_width(tmp_path):
    page = int(FIGURE_WIDTH_IN * DPI)
    start, goal = np.array([55.0e-6, 55.0e-6]), np.array([55.0e-6, 54.7e-6])
    scan = scan_of([start], (54.5e-6, 54.45e-6), pixels=64)
    extent = (54.5e-6, 54.5e-6 + 64 * PIXEL, 54.45e-6, 54.45e-6 + 64 * PIXEL)
    cov = np.diag([(5e-9) ** 2] * 2)
    means = np.array([start, start + [0, -1e-7], goal])
    paths = [
        save_push_figure(
            tmp_path / "push.png",
            ("before", scan.height, extent),
            ("after", scan.height, extent),
            start,
            goal,
            goal + 5e-9,
            true_end=goal,
            strokes=[((55.05e-6, 55.2e-6), (55.05e-6, 54.8e-6), True)],
            tip_means=means,
            tip_covariances=[cov] * 3,
            true_tip=means,
            particle_track=[start, goal],
        ),
        save_map_figure(
            tmp_path / "map.png",
            ("map", scan.height, extent),
            [(0, start, cov)],
            truth=[start],
            tip_mean=goal,
            tip_covariance=cov,
            tip_means=means,
        ),
        save_force_figure(
            tmp_path / "forces.png",
            [("stroke 1", np.linspace(0, 2e-7, 50), np.full(50, 5e-9), np.full(50, 1e-8))],
        ),
        save_localizer_figure(
            tmp_path / "localizer.png", [0.0, 1.0, 2.0], [[1e-9, -2e-9]] * 3, [[3e-9, 3e-9]] * 3
        ),
        save_height_maps(tmp_path / "scans.png", [("a", scan.height, extent)] * 5, [start]),
    ]
    for path in paths:
        assert width_px(path) == page, path.name


def test_an_assembly_s_many_strokes_get_a_colour_bar_not_a_legend_that_buries_the_plot(tmp_path):
    """61 strokes (the demo's assembly) named in a legend filled the figure and matplotlib
    warned; past a few the strokes are coloured by their order with a colour bar."""
    import warnings

    import matplotlib.pyplot as plt

    distance = np.linspace(0, 2e-7, 50)
    many = [
        (f"stroke {i}", distance, np.full(50, i * 1e-10), np.full(50, 1e-8)) for i in range(61)
    ]
    captured = []
    original = plt.Figure.savefig

    def keep(fig, *args, **kwargs):
        captured.append(fig)
        return original(fig, *args, **kwargs)

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the legend's "not enough room" UserWarning fails here
        plt.Figure.savefig = keep
        try:
            save_force_figure(tmp_path / "forces.png", many)
            save_force_figure(tmp_path / "few.png", many[:3])
        finally:
            plt.Figure.savefig = original
    crowded, few = captured
    assert all(ax.get_legend() is None for ax in crowded.axes)
    assert any("stroke, in order (1-61)" in ax.get_ylabel() for ax in crowded.axes)
    assert any(ax.get_legend() is not None for ax in few.axes)
