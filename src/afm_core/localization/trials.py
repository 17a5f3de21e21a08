"""The book's tip-localization trials (7.2.3-7.2.4) on the simulated AFM, one seed at a time:
the sweeps behind bench/bench_localization.py (its docstring says what each measures and why)
and `afm batch localize` (afm_core.batch.sweeps).

- table_71_72_trial(seed, calibration, mode): Tables 7.1 / 7.2, the tip from x0 to x8 directly
  or via a particle landmark (MODES_71_72); at x8 the true error, the estimate's error, the
  filter's sigma and the NEES.
- table_73_trial(seed, calibration, line_ends_at_pit): Table 7.3, a pit punched 130 nm below a
  nanotube after two lines across it; the pit's distance from the tube's axis.
- sim_oracle_calibration(): what a perfect calibration of the default simulator finds (the
  scanner matrix measured on a noise-free copy, the rest from its configuration).
- nees_band(trials, dof): the two-sided 95 % band of a consistent filter's mean NEES.

Each trial builds a fresh simulator of its seed and draws its own randomness from a generator
seeded from it: a trial is the same wherever and in whatever order it runs. SI units.
"""

from __future__ import annotations

import math
from datetime import datetime, timezone

import numpy as np
from scipy.stats import chi2

from afm_core.localization.calibration.model import Calibration
from afm_core.localization.calibration.simulator_comparison import simulator_calibration
from afm_core.localization.landmark_observation import MapLandmark
from afm_core.localization.localizer import Localizer
from afm_core.sim.config import load_config, merge
from afm_core.sim.instrument import SimulatedAfm

UM = 1e-6
NM = 1e-9
CENTRE = np.array([55e-6, 55e-6])  # scanner centre = image centre of the book's geometry
BOOK = {
    k: np.array(v) * UM
    for k, v in {
        "x0": (-1.245, 1.316),
        "xd_1": (-1.245, -1.381),
        "x1": (-1.245, -0.645),
        "x8": (1.101, -1.471),
        "landmark": (0.801, -0.684),
    }.items()
}
PARTICLE_RADIUS = 100e-9
P0_TABLE_71 = np.diag([(13e-9) ** 2, (16e-9) ** 2])  # Table 7.1 x0 (experiment sigma 14 / 18 nm)
SETTLE_TIME = 250.0  # s at x0 before the localizer starts
TUBE_RADIUS = 10e-9
TUBE_LENGTH = 3e-6
HIRES_MAP_SIGMA = 0.8e-9
PIT_BELOW = 130e-9
P0_TABLE_74 = np.diag([(10e-9) ** 2, (10e-9) ** 2])  # Table 7.4 x0 sigma 10 nm
LINE_SAMPLE_SPACING = 2e-9  # m, spheres (the sim's dilation cost grows as 1/spacing^3)
TUBE_SAMPLE_SPACING = 1e-9


# -- configurations and calibrations ------------------------------------------------------------
def sim_config(seed: int, spheres=(), rods=(), **overrides):
    config = merge(
        load_config(),
        {
            "seed": int(seed),
            "sample": {
                "spheres": [
                    {"x": float(x), "y": float(y), "radius": float(r)} for x, y, r in spheres
                ],
                "rods": [dict(r) for r in rods],
                "random_spheres": 0,
            },
        },
    )
    return merge(config, overrides) if overrides else config


def quiet(config_overrides: dict) -> dict:
    quiet = {
        "drift": {"enabled": False},
        "scanner": {"creep_enabled": False, "positioning_noise_enabled": False},
    }
    for key, value in config_overrides.items():
        quiet.setdefault(key, {}).update(value)
    return quiet


def measure_scanner_matrix(step: float = 1e-6) -> np.ndarray:
    """True displacement per commanded displacement about the centre, on a noise-, drift- and
    creep-free simulator (compensated hysteresis residual, coupling, rotation)."""
    columns = []
    for d in (np.array([step, 0.0]), np.array([0.0, step])):
        sim = SimulatedAfm(sim_config(0, **quiet({})))
        before = np.array(sim.truth()["tip_position"])
        x, y = np.array(sim.commanded_position()) + d
        sim.move_tip(x, y, 1e-5)
        columns.append((np.array(sim.truth()["tip_position"]) - before) / step)
    return np.array(columns).T


def measure_scan_region_sigma(
    matrix: np.ndarray, kind: str, lines: int = 24, seed: int = 7
) -> float:
    """Spread of the centre found by lines across a known sphere / tube at random offsets,
    on the noise-free-positioning simulator (sensor noise on): the true tip position at the
    crossing time is known exactly from the command (linear scanner, no creep, no drift)."""
    from afm_core.instrument import LineRequest
    from afm_core.localization.landmark_observation import observe_line

    rng = np.random.default_rng(seed)
    centre = CENTRE + np.array([0.3e-6, 0.2e-6])
    if kind == "sphere":
        landmark = MapLandmark(*centre, np.zeros((2, 2)), PARTICLE_RADIUS)
        config = sim_config(seed, spheres=[(*centre, PARTICLE_RADIUS)], **quiet({}))
        spacing, half, offset_range, vertical = (
            LINE_SAMPLE_SPACING,
            250e-9,
            0.8 * PARTICLE_RADIUS,
            False,
        )
    else:
        landmark = MapLandmark(*centre, np.zeros((2, 2)), TUBE_RADIUS, kind="tube")
        config = sim_config(
            seed,
            rods=[
                {
                    "x": float(centre[0]),
                    "y": float(centre[1]),
                    "angle": 0.0,
                    "length": TUBE_LENGTH,
                    "radius": TUBE_RADIUS,
                    "kind": "tube",
                }
            ],
            **quiet({}),
        )
        spacing, half, offset_range, vertical = TUBE_SAMPLE_SPACING, 120e-9, 500e-9, True
    sim = SimulatedAfm(config)
    inverse = np.linalg.inv(matrix)
    c0 = np.array(sim.commanded_position())
    p0 = np.array(sim.truth()["tip_position"])
    errors = []
    calibration = Calibration(scan_region_sigma=0.0, line_deflection_sigma_deg=0.0)
    for _ in range(lines):
        offset = rng.uniform(-offset_range, offset_range)
        if vertical:
            d = np.array([0.0, 1.0])
            start_true = centre + np.array([offset, -half])
        else:
            d = np.array([1.0, 0.0])
            start_true = centre + np.array([-half, offset])
        start = c0 + inverse @ (start_true - p0)
        end = start + inverse @ (2 * half * d)
        request = LineRequest(*start, *end, int(2 * half / spacing) + 1, 1e-6)
        data = sim.local_scan(request)
        direction = matrix @ (end - start)
        obs = observe_line(data, landmark, calibration, direction)
        if not obs.ok:
            continue
        tip = p0 + matrix @ (np.array(obs.command) - c0)
        errors.append(float(obs.direction @ (centre - tip)))
    return float(np.std(errors, ddof=1)) if len(errors) > 2 else math.nan


def sim_oracle_calibration() -> Calibration:
    """See the module docstring: what a perfect calibration of the default simulator finds."""
    config = load_config()
    matrix = measure_scanner_matrix()
    return simulator_calibration(
        config,
        matrix,
        f"sim-derived oracle (bench_localization.py, {datetime.now(timezone.utc).date()}): "
        "matrix measured on a noise-free simulator, other parameters from the simulator's default "
        "config; not a calibration experiment",
        map_sigma=[5.0e-9, 4.5e-9],
        scan_region_sigma=measure_scan_region_sigma(matrix, "sphere"),
        line_deflection_mean_deg=config.scanner.deflection_deg,
        line_deflection_sigma_deg=0.0,
    )


# -- experiment 1: Tables 7.1 / 7.2 --------------------------------------------------------------
def start_at(
    sim: SimulatedAfm,
    point: np.ndarray,
    calibration: Calibration,
    p0: np.ndarray,
    rng: np.random.Generator,
) -> Localizer:
    """Tip moved to the command of `point` (open loop), settled; localizer started there."""
    command = np.array(sim.commanded_position()) + np.linalg.solve(
        np.array(calibration.scanner_matrix), point - np.array(sim.truth()["tip_position"])
    )
    sim.move_tip(*command, 2e-6)
    sim.hold(SETTLE_TIME)
    truth = np.array(sim.truth()["tip_position"])
    return Localizer(
        sim,
        calibration,
        rng.multivariate_normal(truth, p0),
        p0,
        sample_spacing=LINE_SAMPLE_SPACING,
    )


MODES_71_72 = ("direct", "via_landmark", "via_landmark_straight", "via_landmark_toward_x8")


def table_71_72_trial(seed: int, calibration: Calibration, mode: str) -> dict:
    """mode: "direct" (x0 -> xd_1 -> x8), "via_landmark" (book path: horizontal and vertical
    line through the particle, each ending clear of it, then free moves x6 -> x7 -> x8) or
    "via_landmark_straight" (the same lines, then one straight move x6 -> x8) or
    "via_landmark_toward_x8" (observe_landmark toward x8, as the Localize action's `toward`:
    the vertical line is continued down to x7 = (particle x, x8 y), so x6 -> x7 is scan-line
    motion, not a free move; then x7 -> x8)."""
    rng = np.random.default_rng(10_000 + seed)
    particle = CENTRE + BOOK["landmark"]
    sim = SimulatedAfm(sim_config(seed, spheres=[(*particle, PARTICLE_RADIUS)]))
    loc = start_at(sim, CENTRE + BOOK["x0"], calibration, P0_TABLE_71, rng)
    target = CENTRE + BOOK["x8"]
    lines = []
    if mode not in MODES_71_72:
        raise ValueError(f"mode={mode!r}: must be one of {MODES_71_72}")
    if mode != "direct":
        map_cov = np.diag(np.square(calibration.map_sigma))
        landmark = MapLandmark(
            *rng.multivariate_normal(particle, map_cov), map_cov, PARTICLE_RADIUS
        )
        loc.move_to(*(CENTRE + BOOK["x1"]))
        result = loc.observe_landmark(
            landmark, toward=target if mode == "via_landmark_toward_x8" else None
        ).lines
        lines = [(line.axis, line.status, line.mahalanobis) for line in result]
        if mode == "via_landmark":
            loc.move_to(loc.mean[0], target[1])
    else:
        loc.move_to(*(CENTRE + BOOK["xd_1"]))
        loc.move_to(target[0], loc.mean[1])
    loc.move_to(*target)
    truth = np.array(sim.truth()["tip_position"])
    error = loc.mean - truth
    return {
        "seed": seed,
        "true_error": truth - target,  # m: where the tip truly is, off x8
        "estimate_error": error,  # m: the estimate minus the truth
        "reported_sigma": np.sqrt(np.diag(loc.covariance)),  # m: the filter's own
        "nees": float(error @ np.linalg.solve(loc.covariance, error)),
        "lines": lines,
        "sim_time_s": sim.time,
    }


def nees_band(trials: int, dof: int = 2, confidence: float = 0.95) -> tuple[float, float]:
    a = (1 - confidence) / 2
    return float(chi2.ppf(a, dof * trials) / trials), float(chi2.ppf(1 - a, dof * trials) / trials)


def table_73_trial(seed: int, calibration: Calibration, line_ends_at_pit: bool) -> dict:
    """`calibration` already holds the high-resolution map's sigma (see run_73)."""
    rng = np.random.default_rng(20_000 + seed)
    tube = CENTRE + np.array([0.0, 0.25e-6])
    rod = {
        "x": float(tube[0]),
        "y": float(tube[1]),
        "angle": 0.0,
        "length": TUBE_LENGTH,
        "radius": TUBE_RADIUS,
        "kind": "tube",
    }
    sim = SimulatedAfm(sim_config(seed, rods=[rod]))
    loc = start_at(sim, CENTRE.copy(), calibration, P0_TABLE_74, rng)
    loc.sample_spacing = TUBE_SAMPLE_SPACING
    map_cov = np.diag([HIRES_MAP_SIGMA**2] * 2)
    landmark = MapLandmark(
        *rng.multivariate_normal(tube, map_cov), map_cov, TUBE_RADIUS, kind="tube", orientation=0.0
    )
    up = loc.observe_line(landmark, "y", +1.0)  # x0 -> x1 across the tube
    if line_ends_at_pit:
        down = loc.observe_line(landmark, "y", -1.0, after=PIT_BELOW)  # x1 -> pit, across the tube
        # the line's end was planned before its update: correct by the (~1 nm) difference
        loc.move_to(loc.mean[0], landmark.y - PIT_BELOW)
    else:
        down = loc.observe_line(landmark, "y", -1.0)  # x1 -> x2 (clear of the tube)
        loc.move_to(loc.mean[0], landmark.y - PIT_BELOW)  # x2 -> x3
    sigma_y = math.sqrt(loc.covariance[1, 1])
    estimate_error = loc.mean[1] - sim.truth()["tip_position"][1]
    loc.indent_here(0.5e-6, 0.1)
    pit = sim.sample.pits[-1]
    return {
        "seed": seed,
        "distance": tube[1] - pit.y,  # m: the pit from the tube's true axis
        "lines": [up.status, down.status],
        "reported_sigma": sigma_y,  # m
        "nees": estimate_error**2 / sigma_y**2,
    }
