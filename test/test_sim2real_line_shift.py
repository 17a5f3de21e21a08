"""A random per-line lateral offset against white height noise: the lines' own shifts
(`raster.line_shift`) on synthetic images of known shifts (closed form), the simulator's generic
`line_jitter` term measured back by that statistic, and its config errors."""

import math

import numpy as np
import pytest

from afm_core.instrument import ScanRequest
from afm_core.sim.config import load_config, merge
from afm_core.sim.instrument import SimulatedAfm
from afm_core.sim2real.line_shift import (
    MAD_VARIANCE,
    line_shift_noise,
    line_shifts,
    statistic_variance,
)

N, PIXEL = 192, 23e-9  # the protocol's cluster images: 192 lines of 23 nm pixels


def _image(rng, offsets, noise, bumps=20, height=100e-9, width=45e-9):
    """Gaussian bumps; line i read at s + offsets[i] along the fast axis (rows), exactly;
    white noise of sd `noise` on every pixel."""
    s = (np.arange(N) + 0.5) * PIXEL
    centres = np.random.default_rng(3).uniform(0.1, 0.9, (bumps, 2)) * N * PIXEL
    yy, xx = s[:, None], s[None, :] + np.asarray(offsets)[:, None]
    h = np.zeros((N, N))
    for cx, cy in centres:
        h += height * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * width**2))
    return h + rng.normal(0.0, noise, h.shape)


@pytest.mark.parametrize("sd", [3e-9, 6e-9])
def test_the_statistic_reads_the_sd_of_independent_line_offsets(sd):
    """Offsets normal with sd `sd`, independent line to line: the statistic estimates sd,
    within 3 of its own sampling sigma (sqrt(MAD_VARIANCE / k) sd over k lines) and the
    linearization's few per cent."""
    rng = np.random.default_rng(11)
    value, k = line_shift_noise(_image(rng, rng.normal(0.0, sd, N), 0.3e-9), PIXEL)
    assert k >= 60
    sigma = math.sqrt(statistic_variance(sd, k))
    assert sigma == pytest.approx(sd * math.sqrt(MAD_VARIANCE / k))
    assert abs(value - sd) < 3 * sigma + 0.1 * sd, (value, sd, sigma)


def test_white_noise_does_not_pass_for_line_offsets_and_a_z_gain_changes_nothing():
    """White noise is independent of the slope: at 0.3 nm and 1 nm per pixel it reads a
    fraction of the shifts a 3 nm jitter reads (what it adds is estimation noise, not a shift);
    a z gain scales the heights and the slopes alike, so the statistic does not move."""
    rng = np.random.default_rng(5)
    jitter, _ = line_shift_noise(_image(rng, rng.normal(0.0, 3e-9, N), 0.3e-9), PIXEL)
    for noise in (0.3e-9, 1e-9):
        white, _ = line_shift_noise(_image(rng, np.zeros(N), noise), PIXEL)
        assert white < 0.25 * jitter, (noise, white, jitter)
    image = _image(np.random.default_rng(7), np.random.default_rng(8).normal(0, 4e-9, N), 0.3e-9)
    d0, d1 = line_shifts(image, PIXEL), line_shifts(1.2 * image, PIXEL)
    both = np.isfinite(d0) & np.isfinite(d1)  # (the crossing threshold is in m)
    assert both.sum() > 60
    assert np.allclose(d1[both], d0[both], rtol=1e-9, atol=0.0)


def test_an_image_crossing_no_particle_gives_no_statistic_and_bad_pixels_are_refused():
    flat = np.random.default_rng(0).normal(0.0, 0.3e-9, (N, N))
    value, k = line_shift_noise(flat, PIXEL)
    assert math.isnan(value) and k == 0
    with pytest.raises(ValueError, match="pixel"):
        line_shifts(flat, -1.0)


def _cluster(config):
    sim = SimulatedAfm(config)
    req = ScanRequest(54.4e-6, 54.4e-6, 2.2e-6, 2.2e-6, 96, 96, line_rate=8.0)
    return np.asarray(sim.raster_scan(req).height, float), req.size_x / req.pixels_x


def test_the_simulators_line_jitter_is_read_back_and_leaves_the_noise_draws_alone():
    """The generic term `line_jitter` of sd s, re-simulated: the lines' own shifts read s back
    (within the statistic's sampling and the tip's few-per-cent linearization); at sd 0 the
    image is the one without the term, bit for bit (its offsets are drawn from a generator of
    their own, so the sensor noise draws are the same)."""
    base = merge(load_config(), {"seed": 4})
    plain, pixel = _cluster(base)
    zero, _ = _cluster(merge(base, {"generic_terms": [_jitter(0.0)]}))
    assert np.array_equal(plain, zero)
    shifted, _ = _cluster(merge(base, {"generic_terms": [_jitter(5e-9)]}))
    value, k = line_shift_noise(shifted, pixel)
    assert k >= 8, k
    sigma = math.sqrt(statistic_variance(5e-9, k))
    assert abs(value - 5e-9) < 3 * sigma + 0.5e-9, (value, sigma, k)
    assert line_shift_noise(plain, pixel)[0] < 0.3 * value


def _jitter(sd):
    return {"signal": "lateral", "form": "line_jitter", "amplitude": sd}


@pytest.mark.parametrize(
    "entry, words",
    [
        (_jitter(-1e-9), "generic_terms[0].amplitude=-1e-09: an sd in m"),
        ({"signal": "lateral", "form": "constant"}, "line_jitter, and only it"),
        ({"signal": "height", "form": "line_jitter"}, "line_jitter, and only it"),
    ],
)
def test_a_bad_line_jitter_is_an_error_naming_its_field(entry, words):
    with pytest.raises(ValueError) as err:
        merge(load_config(), {"generic_terms": [entry]})
    assert words in str(err.value), str(err.value)
