"""A calibration file for the default simulated instrument, for graph tests whose subject is
the plumbing, not the calibration (which has its own tests)."""

import importlib.util
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "bench" / "bench_localization.py"


def oracle_calibration(path):
    """What a perfect calibration of the default simulator finds: its parameters, with the
    scanner matrix measured on a noise-free copy."""
    from afm_core.localization.calibration.model import Calibration, save_calibration

    spec = importlib.util.spec_from_file_location("bench_localization", BENCH)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    s, d = bench.load_config().scanner, bench.load_config().drift
    save_calibration(
        Calibration(
            source="test oracle",
            scanner_matrix=bench.measure_scanner_matrix().tolist(),
            creep_time_constants=list(s.creep_time_constants),
            creep_fractions_x=list(s.creep_fractions),
            creep_fractions_y=list(s.creep_fractions),
            motion_noise_slope_x=s.positioning_noise_slope,
            motion_noise_slope_y=s.positioning_noise_slope,
            motion_noise_cross_slope=s.positioning_noise_slope,
            motion_noise_offset=s.positioning_noise_offset,
            drift_mean_velocity=[d.mean_velocity_x, d.mean_velocity_y],
            drift_sigma_velocity=[d.sigma_velocity_x, d.sigma_velocity_y],
            scan_region_sigma=0.3e-9,
        ),
        path,
    )
    return path
