"""A calibration file for the default simulated instrument, for graph tests whose subject is
the plumbing, not the calibration (which has its own tests)."""

import importlib.util
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "bench" / "bench_localization.py"


def oracle_calibration(path):
    """What a perfect calibration of the default simulator finds: its parameters, with the
    scanner matrix measured on a noise-free copy."""
    from afm_core.localization.calibration.model import save_calibration
    from afm_core.localization.calibration.simulator_comparison import simulator_calibration

    spec = importlib.util.spec_from_file_location("bench_localization", BENCH)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    save_calibration(
        simulator_calibration(
            bench.load_config(),
            bench.measure_scanner_matrix(),
            "test oracle",
            scan_region_sigma=0.3e-9,
        ),
        path,
    )
    return path
