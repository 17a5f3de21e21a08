"""imaging.levelling against closed forms: a tilted plane, per-row offsets and per-row bows
added to known features and noise are removed, the features kept."""

import numpy as np
import pytest

from afm_core.imaging.levelling import (
    MASK_SIGMAS,
    feature_mask,
    level,
    level_median_rows,
    level_plane,
    level_poly_rows,
)

ROWS, COLS = 64, 80


def _features() -> tuple[np.ndarray, np.ndarray]:
    """Two particles (20 nm, 12 nm) and a 5 nm pit on a flat background; and their footprint."""
    rows, cols = np.indices((ROWS, COLS))
    z = np.zeros((ROWS, COLS))
    for r0, c0, radius, h in ((20, 25, 6, 20e-9), (45, 60, 4, 12e-9), (50, 15, 3, -5e-9)):
        inside = (rows - r0) ** 2 + (cols - c0) ** 2 <= radius**2
        z[inside] = h
    return z, z != 0


def _plane() -> np.ndarray:
    rows, cols = np.indices((ROWS, COLS))
    return 3e-9 + 0.8e-9 * cols - 0.5e-9 * rows  # tens of nm of tilt across the map


def test_plane_with_the_feature_mask_is_exact():
    truth, footprint = _features()
    levelled = level_plane(truth + _plane(), mask=footprint)
    assert np.max(np.abs(levelled - truth)) < 1e-20
    # without the mask the particles pull the plane: the background is left off zero
    biased = level_plane(truth + _plane())
    assert np.max(np.abs(biased[~footprint])) > 1e-10


def test_plane_auto_mask_recovers_features_in_noise():
    rng = np.random.default_rng(3)
    sigma = 0.2e-9
    truth, footprint = _features()
    noise = rng.normal(0.0, sigma, truth.shape)
    levelled, mask = level(truth + noise + _plane(), "plane")
    assert mask[footprint].all()  # every feature pixel left out of the fit
    residual = levelled - truth - noise  # the plane the fit left behind
    # a plane fitted to N pixels of noise sigma is off by ~sigma sqrt(3 / N) (3 coefficients);
    # 5x that is the bound
    assert np.max(np.abs(residual)) < 5 * sigma * np.sqrt(3 / np.count_nonzero(~mask))


def test_median_rows_removes_row_offsets_exactly():
    truth, _ = _features()
    offsets = np.random.default_rng(1).normal(0.0, 5e-9, ROWS)[:, None]
    levelled = level_median_rows(truth + offsets)
    # the features fill less than half of every row: each row's median is its background
    assert np.max(np.abs(levelled - truth)) < 1e-20
    auto, _ = level(truth + offsets, "median")
    assert np.max(np.abs(auto - truth)) < 1e-20


def test_median_rows_needs_the_mask_where_features_fill_a_row():
    truth = np.zeros((8, 10))
    truth[2, :7] = 10e-9  # a tube along row 2, 70 % of it
    offsets = np.arange(8)[:, None] * 1e-9
    assert abs(level_median_rows(truth + offsets)[2, 9]) > 1e-9  # the tube took the median
    mask = truth != 0
    assert np.max(np.abs(level_median_rows(truth + offsets, mask) - truth)) < 1e-20


def test_poly_rows_removes_a_bow_per_row():
    truth, footprint = _features()
    rng = np.random.default_rng(2)
    x = np.linspace(-1, 1, COLS)
    coefficients = rng.normal(0.0, 4e-9, (ROWS, 3))
    bows = coefficients[:, :1] * x**2 + coefficients[:, 1:2] * x + coefficients[:, 2:]
    levelled = level_poly_rows(truth + bows, 2, mask=footprint)
    assert np.max(np.abs(levelled - truth)) < 1e-20


def test_poly_rows_auto_mask_in_noise():
    truth, footprint = _features()
    rng = np.random.default_rng(4)
    sigma = 0.2e-9
    noise = rng.normal(0.0, sigma, truth.shape)
    x = np.linspace(-1, 1, COLS)
    coefficients = rng.normal(0.0, 4e-9, (ROWS, 3))
    bows = coefficients[:, :1] * x**2 + coefficients[:, 1:2] * x + coefficients[:, 2:]
    auto, mask = level(truth + noise + bows, "poly2")
    assert mask[footprint].all()
    residual = auto - truth - noise  # the bow the fits left behind, row by row
    # a quadratic fitted to n pixels is worst at the row ends, std <= sigma sqrt(9 / n)
    n = np.count_nonzero(~mask, axis=1)[:, None]
    assert np.all(np.abs(residual) < 5 * sigma * np.sqrt(9 / n))


def test_feature_mask_false_alarms_follow_the_stated_rate():
    rng = np.random.default_rng(5)
    noise = rng.normal(0.0, 1e-9, (400, 500))
    mask = feature_mask(noise, grow=0)
    expected = 2 * 0.5 * __import__("math").erfc(MASK_SIGMAS / np.sqrt(2)) * noise.size
    assert abs(np.count_nonzero(mask) - expected) < 5 * np.sqrt(expected)


def test_median_plane_median_removes_a_tilt_and_line_offsets():
    rng = np.random.default_rng(6)
    sigma = 0.2e-9
    truth, footprint = _features()
    noise = rng.normal(0.0, sigma, truth.shape)
    offsets = rng.normal(0.0, 3e-9, ROWS)[:, None]
    raw = truth + noise + _plane() + offsets
    # the order matters: the first median takes the line offsets out so they cannot tilt the
    # plane fit through the unevenly masked rows; the last takes out what the plane left
    levelled, mask = level(raw, "median+plane+median")
    assert mask[footprint].all()
    residual = levelled - truth - noise  # constant per row: that row's median of noise
    n = np.count_nonzero(~mask, axis=1)[:, None]
    # the median of n Gaussian samples has standard deviation 1.2533 sigma / sqrt(n)
    assert np.all(np.abs(residual - np.median(residual)) < 5 * 1.2533 * sigma / np.sqrt(n))
    # the plane alone leaves the line offsets
    plane_only, _ = level(raw, "plane")
    assert np.std(plane_only[~footprint] - noise[~footprint]) > 1e-9


def test_bad_input_names_the_problem():
    with pytest.raises(ValueError, match="method="):
        level(np.zeros((4, 4)), "cubic")
    with pytest.raises(ValueError, match=r"method='plane\+'"):
        level(np.zeros((4, 4)), "plane+")
    with pytest.raises(ValueError, match="mask: expected a boolean array"):
        level_plane(np.zeros((4, 4)), mask=np.zeros((3, 4), dtype=bool))
    with pytest.raises(ValueError, match="background pixel"):
        level_plane(np.zeros((4, 4)), mask=np.ones((4, 4), dtype=bool))
    with pytest.raises(ValueError, match="NaN"):
        level(np.full((4, 4), np.nan))
