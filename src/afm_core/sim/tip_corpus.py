"""A corpus of blind-tip-estimation cases made independently of the characterizer.

The automatic threshold of `afm_core.imaging.tip_estimation` must hold on images it was not
tuned on. The characterizer (afm_core.sim.characterizer) images one sample kind (sharp
spikes) with one tip family (afm_core.sim.tip); this module builds other tips and samples from
its own formulas, and images them by its own shift-and-max (not tip_morphology.dilate), so
that a convention slip in either shows as a disagreement:

tips (apex at the centre pixel, height 0, t <= 0):
  hyperboloid      z = -(sqrt(r^2 + b^2) - b) / tan(theta), b = R / tan(theta): apex radius R,
                   asymptotic cone half-angle theta (a smooth apex-to-cone blend);
  pyramid          the same profile of the chebyshev distance max(|x|, |y|): a four-sided
                   pyramid with a rounded apex (silicon nitride tips);
  tilted           the hyperboloid with half-angle theta - tilt on the +x flank and
                   theta + tilt on the -x flank (a tip mounted at an angle);
  double           two hyperboloid apexes `separation` apart, the second `drop` lower;
  chipped          a hyperboloid whose apex has broken off along a tilted plane.
samples (heights >= 0 on a flat substrate at 0, continuous positions sampled at pixel
centres): spheres (colloidal particles), tubes (cylinders lying flat, any orientation),
spikes (a square grating of sharp pyramids, like a TGT1 test grating), steps (a line grating
with vertical edges) and grains (a granular film: the upper envelope of random paraboloid
grains).

`corpus_cases()` lists a fixed design over tips, samples, pixel sizes (1-10 nm) and noise
levels (0.1-1 nm); `make_case()` builds one image with its true tip. `score_depth` and
`best_fixed_threshold` are how a case is scored (bench/bench_tip_corpus.py, the tests).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TIP_KINDS = ("hyperboloid", "pyramid", "tilted", "double", "chipped")
SAMPLE_KINDS = ("spheres", "tubes", "spikes", "steps", "grains")


@dataclass(frozen=True)
class TipModel:
    kind: str
    apex_radius: float  # m
    half_angle_deg: float
    tilt_deg: float = 0.0  # tilted: flank half-angles theta -/+ tilt
    separation: float = 0.0  # double: lateral distance of the second apex (m, along x)
    drop: float = 0.0  # double: how much lower the second apex is; chipped: plane depth (m)

    def name(self) -> str:
        return f"{self.kind} R={self.apex_radius * 1e9:.0f}nm {self.half_angle_deg:.0f}deg"


@dataclass(frozen=True)
class Case:
    tip: TipModel
    sample: str
    pixel: float  # m
    noise: float  # m, white noise sigma
    n: int  # image side, px
    tip_size: int  # px, odd window of the estimate
    seed: int

    def name(self) -> str:
        return (
            f"{self.tip.name()} / {self.sample} / {self.pixel * 1e9:g} nm px / "
            f"{self.noise * 1e9:g} nm noise"
        )


def _profile(r: np.ndarray, radius: float, half_angle_deg) -> np.ndarray:
    tan = np.tan(np.radians(half_angle_deg))
    b = radius / tan  # so that z ~ -r^2 / 2R near the apex
    return -(np.sqrt(r**2 + b**2) - b) / tan


def tip_grid(model: TipModel, pixel: float, half: int) -> np.ndarray:
    """The tip on a (2 half + 1)^2 grid at `pixel` spacing, highest point at the centre."""
    big = 2 * half  # built wider, then cut around its highest point
    ax = np.arange(-big, big + 1) * pixel
    y, x = np.meshgrid(ax, ax, indexing="ij")
    r = np.hypot(x, y)
    if model.kind == "hyperboloid":
        z = _profile(r, model.apex_radius, model.half_angle_deg)
    elif model.kind == "pyramid":
        z = _profile(np.maximum(np.abs(x), np.abs(y)), model.apex_radius, model.half_angle_deg)
    elif model.kind == "tilted":
        plus = _profile(r, model.apex_radius, model.half_angle_deg - model.tilt_deg)
        minus = _profile(r, model.apex_radius, model.half_angle_deg + model.tilt_deg)
        weight = 0.5 * (1 + np.divide(x, r, out=np.zeros_like(r), where=r > 0))
        z = weight * plus + (1 - weight) * minus
    elif model.kind == "double":
        first = _profile(r, model.apex_radius, model.half_angle_deg)
        second = _profile(
            np.hypot(x - model.separation, y), model.apex_radius, model.half_angle_deg
        )
        z = np.maximum(first, second - model.drop)
    elif model.kind == "chipped":
        z = _profile(r, model.apex_radius, model.half_angle_deg)
        # the plane through depth `drop` at the apex, rising 0.3 per unit along +x
        z = np.minimum(z, -model.drop + 0.3 * x + 0.1 * y)
    else:
        raise ValueError(f"tip kind {model.kind!r}: one of {', '.join(TIP_KINDS)}")
    iy, ix = np.unravel_index(int(np.argmax(z)), z.shape)
    iy = int(np.clip(iy, half, z.shape[0] - half - 1))
    ix = int(np.clip(ix, half, z.shape[1] - half - 1))
    cut = z[iy - half : iy + half + 1, ix - half : ix + half + 1]
    return cut - cut[half, half]


def _surface_spheres(n, pixel, rng):
    grid = (np.arange(n) + 0.5) * pixel
    s = np.zeros((n, n))
    area = (n * pixel) ** 2
    count = max(4, int(area / (60 * 60e-18)))
    for _ in range(count):
        radius = rng.uniform(4e-9, 15e-9)
        cy, cx = rng.uniform(0, n * pixel, 2)
        dy = (grid - cy)[:, None]
        dx = (grid - cx)[None, :]
        d2 = dy**2 + dx**2
        cap = np.where(d2 < radius**2, radius + np.sqrt(np.maximum(radius**2 - d2, 0)), 0.0)
        s = np.maximum(s, cap)
    return s


def _surface_tubes(n, pixel, rng):
    grid = (np.arange(n) + 0.5) * pixel
    y, x = np.meshgrid(grid, grid, indexing="ij")
    s = np.zeros((n, n))
    count = max(3, int((n * pixel) ** 2 / (150 * 150e-18)))
    for _ in range(count):
        radius = rng.uniform(1e-9, 6e-9)
        length = rng.uniform(60e-9, 300e-9)
        cy, cx = rng.uniform(0, n * pixel, 2)
        phi = rng.uniform(0, np.pi)
        along = (x - cx) * np.cos(phi) + (y - cy) * np.sin(phi)
        across = -(x - cx) * np.sin(phi) + (y - cy) * np.cos(phi)
        inside = (np.abs(along) < length / 2) & (np.abs(across) < radius)
        tube = np.where(inside, radius + np.sqrt(np.maximum(radius**2 - across**2, 0)), 0.0)
        s = np.maximum(s, tube)
    return s


def _surface_spikes(n, pixel, rng):
    period = rng.uniform(80e-9, 140e-9)
    height = rng.uniform(25e-9, 45e-9)
    slope = 1 / np.tan(np.radians(rng.uniform(8.0, 14.0)))
    grid = (np.arange(n) + 0.5) * pixel
    y, x = np.meshgrid(grid, grid, indexing="ij")
    oy, ox = rng.uniform(0, period, 2)
    dy = np.abs((y - oy + period / 2) % period - period / 2)
    dx = np.abs((x - ox + period / 2) % period - period / 2)
    return np.maximum(height - slope * np.maximum(dx, dy), 0.0)


def _surface_steps(n, pixel, rng):
    period = rng.uniform(120e-9, 220e-9)
    height = rng.uniform(15e-9, 30e-9)
    phi = rng.uniform(0, np.pi)
    grid = (np.arange(n) + 0.5) * pixel
    y, x = np.meshgrid(grid, grid, indexing="ij")
    u = x * np.cos(phi) + y * np.sin(phi) + rng.uniform(0, period)
    return np.where((u % period) < period / 2, height, 0.0)


def _surface_grains(n, pixel, rng):
    grid = (np.arange(n) + 0.5) * pixel
    s = np.full((n, n), -np.inf)
    count = max(20, int((n * pixel) ** 2 / (25 * 25e-18)))
    for _ in range(count):
        curvature = rng.uniform(3e-9, 12e-9)
        top = rng.uniform(0, 8e-9)
        cy, cx = rng.uniform(0, n * pixel, 2)
        d2 = (grid - cy)[:, None] ** 2 + (grid - cx)[None, :] ** 2
        s = np.maximum(s, top - d2 / (2 * curvature))
    return s - s.min()


_SURFACES = {
    "spheres": _surface_spheres,
    "tubes": _surface_tubes,
    "spikes": _surface_spikes,
    "steps": _surface_steps,
    "grains": _surface_grains,
}


def image_surface(surface: np.ndarray, tip: np.ndarray) -> np.ndarray:
    """i(x) = max_u s(x + u) + t(u) by shifts of the edge-padded surface (the project's
    convention, computed without tip_morphology)."""
    half = tip.shape[0] // 2
    padded = np.pad(surface, half, mode="edge")
    n0, n1 = surface.shape
    out = np.full(surface.shape, -np.inf)
    for a in range(tip.shape[0]):
        for b in range(tip.shape[1]):
            np.maximum(out, padded[a : a + n0, b : b + n1] + tip[a, b], out=out)
    return out


def make_case(case: Case) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image, surface, true tip) of `case`; the true tip is imaged with a window wide enough
    for the sample's heights and returned cut to the case's tip_size."""
    if case.sample not in _SURFACES:
        raise ValueError(f"sample {case.sample!r}: one of {', '.join(SAMPLE_KINDS)}")
    rng = np.random.default_rng(case.seed)
    surface = _SURFACES[case.sample](case.n, case.pixel, rng)
    reach = float(surface.max() - surface.min())
    half = max(
        case.tip_size // 2,
        int(np.ceil(np.sqrt(2 * case.tip.apex_radius * reach) / case.pixel)) + 2,
    )
    half = min(half, 4 * (case.tip_size // 2) + 8, case.n // 4)
    full = tip_grid(case.tip, case.pixel, half)
    image = image_surface(surface, full) + rng.normal(0.0, case.noise, surface.shape)
    k = case.tip_size // 2
    return image, surface, full[half - k : half + k + 1, half - k : half + k + 1]


def corpus_cases(n: int = 256, tip_size: int = 21, seeds=(0,)) -> list[Case]:
    """A fixed design: every tip kind meets every sample kind once per seed, with pixel size
    and noise rotating through 1-10 nm and 0.1-1 nm (a Latin square, so no sample is seen at
    one pixel size only)."""
    tips = [
        TipModel("hyperboloid", 8e-9, 20.0),
        TipModel("pyramid", 20e-9, 35.0),
        TipModel("tilted", 12e-9, 22.0, tilt_deg=12.0),
        TipModel("double", 10e-9, 20.0, separation=14e-9, drop=2e-9),
        TipModel("chipped", 15e-9, 25.0, drop=4e-9),
    ]
    pixels = (1e-9, 2e-9, 4e-9, 6e-9, 10e-9)
    noises = (0.1e-9, 0.3e-9, 1.0e-9, 0.2e-9, 0.5e-9)
    out = []
    for seed in seeds:
        for i, tip in enumerate(tips):
            for j, sample in enumerate(SAMPLE_KINDS):
                pixel = pixels[(i + j + seed) % len(pixels)]
                noise = noises[(2 * i + j + seed) % len(noises)]
                out.append(
                    Case(tip, sample, pixel, noise, n, tip_size, seed=100 * seed + 5 * i + j)
                )
    return out


# --------------------------------------------------------------------------------------------
# Scoring


SCORE_DEPTH = 20e-9  # m: the error is the RMS over the top 20 nm of the true tip


def score_depth(true_tip: np.ndarray) -> float:
    """The depth the error is taken over: the top SCORE_DEPTH of the true tip, at least its
    apex's 3x3 neighbours (so that coarse pixels score more than the apex)."""
    h = true_tip.shape[0] // 2
    return max(SCORE_DEPTH, float(-true_tip[h - 1 : h + 2, h - 1 : h + 2].min()))


def best_fixed_threshold(image, true_tip, tip_size: int, noise: float, refine: int = 2):
    """(threshold m, error m) of the fixed threshold a user who knew the true tip would pick:
    a ladder 2^(1/6) apart from 64 to 1/4 `noise` sigmas and 0 (warm-started downwards,
    exact), then the midpoints to the best's neighbours, `refine` times."""
    from afm_core.imaging.tip_estimation import tip_error
    from afm_core.imaging.tip_refinement import TipRefiner, feature_points, work_window
    from afm_core.imaging.tip_thresholds import ThresholdSweep

    depth = score_depth(true_tip)
    est = TipRefiner(image, tip_size)
    features = feature_points(image, tip_size, noise)
    sweep = ThresholdSweep(est, features, work_window(est, features, 0.0), 50)
    errors = {}
    for th in np.append(noise * 64 / 2 ** (np.arange(49) / 6), 0.0):
        errors[float(th)] = tip_error(sweep.run(th), true_tip, depth)
    for _ in range(refine):
        keys = sorted(errors)
        i = keys.index(min(keys, key=errors.get))
        for j in (i - 1, i + 1):
            if 0 <= j < len(keys):
                mid = 0.5 * (keys[i] + keys[j])
                errors[mid] = tip_error(sweep.run(mid), true_tip, depth)
    best = min(errors, key=errors.get)
    return best, errors[best]
