"""A periodic height signal in time faster than any feature's sampling (height_spectrum.py):
on synthetic residuals sampled as the simulator samples rasters and scan lines, against the
closed form of the injected sine, and the nulls that must stay quiet (topography the
re-simulation does not reproduce, repeating with the line rate)."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from afm_core.sim.generic_terms import GenericTerm
from afm_core.sim2real.height_spectrum import (
    Residual,
    detect,
    fit_sine,
    heldout_chi2,
    stretches,
    tail_threshold,
)

NOISE = 0.3e-9
LINE_PERIOD = 0.25


def _raster(start, pixels=64, angle=0.0):
    return SimpleNamespace(
        height=np.zeros((pixels, pixels)),
        scan_angle_deg=angle,
        line_period=LINE_PERIOD,
        start_time=start,
        line_start_times=np.arange(pixels) * LINE_PERIOD,
        origin_x=0.0,
        origin_y=0.0,
        pixel_size_x=20e-9,
        pixel_size_y=20e-9,
    )


def _scan_line(start, samples=200, dt=5e-3):
    return SimpleNamespace(
        height=np.zeros(samples), start_time=start, times=np.arange(samples) * dt
    )


def _session(seed, signal, topography=2e-9):
    """(recorded, nominal) height samples of 6 rasters (at 0 and 90 degrees) and 40 scan lines,
    one after the other over about 400 s: the nominal a topography that repeats from line to line
    (a bump at the same place along every line, slowly changing across lines), the recorded
    the same bump 3 % higher and shifted (what a re-simulation does not reproduce exactly),
    sensor noise and signal(t)."""
    rng = np.random.default_rng(seed)
    recorded, nominal = {}, {}
    start = 2.0
    for index in range(46):
        if index % 8 == 0:
            data = _raster(start, angle=90.0 * (index % 16 == 0))
        else:
            data = _scan_line(start)
        t, h, period = stretches(data)
        start = float(t.max()) + 1.0 + 10.0 * rng.random()
        s = np.linspace(-1, 1, t.shape[1])[None, :]
        across = np.linspace(0.5, 1.5, t.shape[0])[:, None]
        bump = topography * across * np.exp(-(((s - 0.1) / 0.1) ** 2))
        moved = 1.03 * topography * across * np.exp(-(((s - 0.11) / 0.1) ** 2))
        noisy = moved + rng.normal(0, NOISE, t.shape) + signal(t)
        recorded[index] = (t, noisy, period)
        nominal[index] = (t, bump, period)
    return recorded, nominal


def _sine(amplitude, frequency, phase):
    return lambda t: amplitude * np.sin(2 * math.pi * frequency * t + phase)


def test_tail_threshold_of_exponential_noise_is_bonferronis():
    """For P / floor exponential (Gaussian noise), the level one of m frequencies passes with
    probability alpha is ln(m / alpha)."""
    z = np.random.default_rng(1).exponential(size=400_000)
    m, alpha = 1e6, 1e-3
    assert tail_threshold(z, m, alpha) == pytest.approx(math.log(m / alpha), abs=0.5)
    # a heavier tail (twice the scale above the 99th percentile) raises it
    heavy = np.where(z > math.log(100), math.log(100) + 2 * (z - math.log(100)), z)
    assert tail_threshold(heavy, m, alpha) > math.log(m / alpha) + 5


@pytest.mark.parametrize("frequency", [50.0, 37.3])
def test_a_fast_sine_in_time_is_found_and_fitted_as_its_closed_form(frequency):
    amplitude, phase = 0.4e-9, 1.1
    truth = _sine(amplitude, frequency, phase)
    recorded, nominal = _session(3, truth)
    res = Residual(recorded, nominal)
    found = detect(res, 1e-3)
    assert found is not None  # (its peak may be a sidelobe at the line rate: the fit decides)
    assert found["false_alarm"] < 1e-3
    fit = fit_sine(res, found["candidates"], found["train"], found["resolution"])
    assert fit["frequency"] == pytest.approx(frequency, abs=2e-5)
    assert fit["amplitude"] == pytest.approx(amplitude, rel=0.05)
    # the simulator's time_sine with the fitted period and t0 is the injected sine
    term = GenericTerm(
        "height",
        "time_sine",
        fit["amplitude"],
        (("period", 1 / fit["frequency"]), ("t0", fit["t0"])),
    )
    t = np.concatenate([v[0].ravel() for v in recorded.values()])
    model = term.offset(t, 0 * t, 0 * t)
    assert np.max(np.abs(model - truth(t))) < 0.15 * amplitude
    # held out: the term taken away from the other fold leaves its amplitude at f in the noise
    after = {k: (t_, h - term.offset(t_, 0 * t_, 0 * t_), p) for k, (t_, h, p) in recorded.items()}
    res_after = Residual(after, nominal, res.scales)
    before, left = heldout_chi2(
        res, res_after.unclipped, ~found["train"], fit["frequency"], found["floor_test"], set()
    )
    assert before > 100 and left < 0.05 * before


@pytest.mark.parametrize("seed", [4, 5, 6])
def test_null_residuals_stay_quiet(seed):
    """Noise and a topography mismatch repeating with the line rate: no periodic signal."""
    assert detect(Residual(*_session(seed, lambda t: 0 * t)), 1e-3) is None


def test_line_rate_harmonics_are_not_read_as_a_pickup():
    """A pattern locked to the rasters' lines (the 10th line-rate harmonic, on the rasters'
    own clock: topography, not time) in the rasters only: the lines' neighbours take it out."""
    recorded, nominal = _session(7, lambda t: 0 * t)
    for k, (t, h, period) in recorded.items():
        if period is not None:
            along = t - t[:, :1]
            recorded[k] = (t, h + 0.5e-9 * np.sin(2 * math.pi * 10 / LINE_PERIOD * along), period)
    assert detect(Residual(recorded, nominal), 1e-3) is None
