"""The drift compensation checks its timing assumptions against the images (issue 35):
afm_core.imaging.drift_timing, the `timing` of compensate_pair's result, `afm image drift`.

Truth: simulated 0/90 deg pairs (drift only, test_drift_compensation's simulator) whose 90 deg
scan starts a known time after the 0 deg one (the simulator holds in between). The gap truth is
the difference of the scans' first line starts on the simulator's clock; the velocity truth is
the least-squares slope of the simulator's drift over the 0 deg lines. Small images (128 x 128
at 4 lines/s: at 64 x 64 the gap is known to about 15 % only) keep each pair a second or two.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest
from test_drift_compensation import ORIGIN, constant_drift, random_spheres, scan, simulator

from afm_core.imaging.drift_compensation import compensate_pair
from afm_core.imaging.drift_timing import GAP_SIGMAS
from afm_core.imaging.files import HeightMap, save_height_map
from afm_core.imaging.scan_timing import pixel_times

PIXELS, RATE = 128, 4.0  # 32 s per scan
SCAN = PIXELS / RATE
HOLD = 3 * SCAN  # the 90 deg scan starts four scan times after the 0 deg one
AFM = [sys.executable, "-m", "afm_bringup.cli", "image"]


def start(s) -> float:
    return float(s.start_time + np.min(s.line_start_times))


def make(drift: dict, seed: int = 3, hold: float = HOLD):
    spheres = random_spheres(np.random.default_rng(seed), 10)
    afm = simulator(drift, seed, spheres)
    scan0 = scan(afm, 0.0, pixels=PIXELS, rate=RATE)
    afm.hold(hold)
    scan90 = scan(afm, 90.0, pixels=PIXELS, rate=RATE)
    return afm, scan0, scan90, start(scan90) - start(scan0)


@pytest.fixture(scope="module")
def drifting():
    return make(constant_drift(0.2e-9, 0.3e-9))


def assumed(scan0, scan90, gap: float, period_factor: float = 1.0):
    """The pair as a user who gives `gap` (s) and a line period `period_factor` x the true one
    describes it (what `afm image drift` builds from --gap and --line-rate)."""

    def told(s, begin):
        return dataclasses.replace(
            s,
            line_period=s.line_period * period_factor,
            line_start_times=(s.line_start_times - np.min(s.line_start_times)) * period_factor,
            start_time=begin,
        )

    return told(scan0, 0.0), told(scan90, gap)


def velocity_error(afm, scan0, result) -> float:
    ny, nx = scan0.height.shape
    t = pixel_times(scan0, np.arange(ny), np.full(ny, 0.5 * (nx - 1)))
    d = afm.drift.offset(t)
    tc = t - t.mean()
    truth = tc @ (d - d.mean(axis=0)) / (tc @ tc)
    return float(np.linalg.norm(np.array(result.velocity) - truth) / np.linalg.norm(truth))


def test_the_right_gap_passes_and_is_recovered(drifting):
    afm, scan0, scan90, gap = drifting
    timing = compensate_pair(*assumed(scan0, scan90, gap)).timing
    assert timing.checked and timing.warnings == [] and timing.notes == []
    assert timing.gap_assumed == pytest.approx(gap)
    assert abs(timing.gap_implied - gap) <= GAP_SIGMAS * timing.gap_error
    assert timing.gap_error < 0.25 * gap  # the images do fix the gap
    assert timing.dof > 0 and np.isfinite(timing.chi2_assumed)


def test_a_gap_wrong_by_a_factor_four_warns_and_the_implied_gap_fixes_the_velocity(drifting):
    """The CLI's default (the 90 deg scan right after the 0 deg one) when it started three scan
    times later: the drift fitted with that gap is several times off; refitted with the gap the
    images imply (what --gap auto does) it is as good as with the true gap."""
    afm, scan0, scan90, gap = drifting
    wrong = compensate_pair(*assumed(scan0, scan90, SCAN))
    timing = wrong.timing
    assert timing.checked and len(timing.warnings) == 1
    text = timing.warnings[0]
    assert text.startswith(f"gap: {SCAN:.4g} s assumed") and f"{timing.gap_implied:.4g}" in text
    assert abs(timing.gap_implied - gap) <= GAP_SIGMAS * timing.gap_error
    assert timing.chi2_assumed > timing.chi2_implied
    right = compensate_pair(*assumed(scan0, scan90, gap))
    auto = compensate_pair(*assumed(scan0, scan90, timing.gap_implied))
    e_wrong, e_right, e_auto = (velocity_error(afm, scan0, r) for r in (wrong, right, auto))
    assert e_wrong > 1.0 > 0.1 > e_right  # the bias the check exists for
    assert e_auto <= e_right + 0.05
    assert auto.timing.warnings == []


def test_a_wrong_line_rate_is_told_when_the_gap_is_known_in_seconds(drifting):
    """Given a line rate half the true one and the true gap in seconds, the images imply twice
    the gap at the given line period, i.e. a line rate 2x the given one. With the gap tied to
    the line rate (the same count of line periods) no image can tell: every time scales alike."""
    afm, scan0, scan90, gap = drifting
    timing = compensate_pair(*assumed(scan0, scan90, gap, period_factor=2.0)).timing
    assert timing.warnings and "line rate" in timing.warnings[0]
    assert abs(timing.line_rate_ratio - 2.0) <= GAP_SIGMAS * timing.line_rate_ratio_error
    tied = compensate_pair(*assumed(scan0, scan90, 2.0 * gap, period_factor=2.0))
    assert tied.timing.warnings == [] and tied.timing.checked
    right = compensate_pair(*assumed(scan0, scan90, gap))
    np.testing.assert_allclose(tied.velocity, 0.5 * np.array(right.velocity), rtol=0.05)


@pytest.mark.parametrize("gap_factor", [1.0, 0.25])
def test_without_drift_the_gap_cannot_be_checked_and_nothing_warns(gap_factor):
    afm, scan0, scan90, gap = make(constant_drift(0.0, 0.0), seed=4)
    timing = compensate_pair(*assumed(scan0, scan90, gap_factor * gap)).timing
    assert not timing.checked and timing.warnings == [] and timing.gap_implied is None
    assert len(timing.notes) == 1 and timing.notes[0].startswith(
        "cannot check the gap: drift too small"
    )


# Three spheres (x, y in m from the scan corner; radius 80 nm) on which the scans' common
# stretch along their fast axes (~2e-3 in du/dx and dv/dy, 3-10 of the regions' standard
# errors, simulator truth) made the right gap look half as long (32 s against 64 s).
THREE = [(1.589e-6, 1.406e-6), (1.503e-6, 0.956e-6), (0.598e-6, 0.392e-6)]


def three_spheres(v, seed):
    spheres = [{"x": ORIGIN + x, "y": ORIGIN + y, "radius": 80e-9} for x, y in THREE]
    afm = simulator(constant_drift(*v), seed, spheres)
    scan0 = scan(afm, 0.0, pixels=PIXELS, rate=RATE)
    afm.hold(SCAN)
    scan90 = scan(afm, 90.0, pixels=PIXELS, rate=RATE)
    return scan0, scan90, start(scan90) - start(scan0)


@pytest.mark.parametrize("seed", [519, 520])
def test_a_stretch_along_the_fast_axes_is_not_read_as_a_wrong_gap(seed):
    """The stretch is fitted as a nuisance common to the regions, not as drift: at the right
    gap nothing warns; with a drift fast enough for three regions to fix it (0.39 nm/s) a gap
    wrong by 2x still warns and the implied gap holds the true one."""
    scan0, scan90, gap = three_spheres((0.156e-9, 0.085e-9), seed)
    timing = compensate_pair(*assumed(scan0, scan90, gap)).timing
    assert timing.warnings == []
    scan0, scan90, gap = three_spheres((0.3e-9, 0.25e-9), seed)
    right = compensate_pair(*assumed(scan0, scan90, gap)).timing
    assert right.checked and right.warnings == []
    assert abs(right.gap_implied - gap) <= GAP_SIGMAS * right.gap_error
    wrong = compensate_pair(*assumed(scan0, scan90, 2 * gap)).timing
    assert wrong.checked and len(wrong.warnings) == 1
    assert abs(wrong.gap_implied - gap) <= GAP_SIGMAS * wrong.gap_error


def run_cli(*args):
    return subprocess.run(AFM + ["drift"] + [str(a) for a in args], capture_output=True, text=True)


def test_cli_drift_warns_about_the_gap_and_gap_auto_uses_the_images(drifting, tmp_path):
    afm, scan0, scan90, gap = drifting
    files = []
    for name, s in (("s0.npz", scan0), ("s90.npz", scan90)):
        files.append(tmp_path / name)
        save_height_map(
            files[-1],
            HeightMap(s.height, s.pixel_size_x, s.pixel_size_y, s.origin_x, s.origin_y),
        )
    default = run_cli(*files, "--line-rate", RATE, "-o", tmp_path / "a.npz")
    assert default.returncode == 0, default.stderr
    assert (tmp_path / "a.npz").exists()  # written despite the warning
    assert f"warning: --gap: {SCAN:.4g} s assumed" in default.stderr
    assert "the 90 deg scan right after the 0 deg one" in default.stderr
    auto = run_cli(*files, "--line-rate", RATE, "--gap", "auto", "-o", tmp_path / "b.npz")
    assert auto.returncode == 0, auto.stderr
    assert "--gap auto:" in auto.stderr and "warning" not in auto.stderr
    given = run_cli(*files, "--line-rate", RATE, "--gap", gap, "-o", tmp_path / "c.npz")
    assert given.returncode == 0 and given.stderr == "", given.stderr
    bad = run_cli(*files, "--line-rate", RATE, "--gap", "soon", "-o", tmp_path / "d.npz")
    assert bad.returncode == 2 and "--gap" in bad.stderr
    # a 90 deg scan starting before the 0 deg one ends: refused, nothing written
    overlap = run_cli(*files, "--line-rate", RATE, "--gap", SCAN / 2, "-o", tmp_path / "e.npz")
    assert overlap.returncode == 2, overlap.stderr
    assert f">= {SCAN:.4g} s" in overlap.stderr and "--gap auto" in overlap.stderr
    assert not (tmp_path / "e.npz").exists()
