"""The images' lateral scale measured on a reference lattice (a calibration grating), against
the simulator's truth, over seeds.

Per seed: the simulator with that seed and a square lattice of spheres (r = 50 nm, pitch
300 nm, 13 x 13 about the range centre) as the reference; `measure_lateral_scale` images it
like the maps (2.4 um, 256 px, 4 Hz, approached from beyond, slow axis up and down). Two
simulators: the default one, and the same with creep off, the conditions the truth
(`image_frame_matrix`, the gain of a creep-free step on the images' hysteresis branch) is
defined in. With creep on a raster line is faster than the creep follows, so the maps' fast
axis is about 2 % shorter than that step: the measurement, which is of the maps as imaged,
then lies below the creep-free truth. Figures hold on our simulator only.

Run: `scripts/with_env.sh python bench/bench_lateral_scale.py --seeds 8`
Results: bench/results/lateral_scale.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import command_line, machine_record  # noqa: E402

from afm_core.evaluation import image_frame_matrix  # noqa: E402
from afm_core.localization.calibration.lateral_scale import measure_lateral_scale  # noqa: E402
from afm_core.sim.config import load_config, merge  # noqa: E402
from afm_core.sim.instrument import SimulatedAfm  # noqa: E402

PITCH = 300e-9
RADIUS = 50e-9
SITES = 6  # each side of the centre
CONDITIONS = {"default": {}, "creep off": {"scanner": {"creep_enabled": False}}}
RESULTS = Path(__file__).resolve().parents[1] / "bench" / "results"


def reference(centre) -> list[dict]:
    return [
        {"x": centre[0] + i * PITCH, "y": centre[1] + j * PITCH, "radius": RADIUS}
        for i in range(-SITES, SITES + 1)
        for j in range(-SITES, SITES + 1)
    ]


def measure(seed: int, extra: dict, truth: np.ndarray) -> dict:
    config = load_config()
    centre = (config.limits.range_x / 2, config.limits.range_y / 2)
    sim = SimulatedAfm(
        merge(config, {"seed": seed, "sample": {"spheres": reference(centre)}, **extra})
    )
    clock, began = sim.time, time.perf_counter()
    result = measure_lateral_scale(sim, PITCH)
    wall = time.perf_counter() - began
    true_scale = float(np.sqrt(np.linalg.det(truth)))
    return {
        "seed": seed,
        "scale": result.scale,
        "scale_sigma": result.scale_sigma,
        "fit_sigma": result.fit_sigma,
        "pass_scales": list(result.pass_scales),
        "matrix": result.matrix.tolist(),
        "matrix_sigma": result.matrix_sigma.tolist(),
        "particles": result.particles,
        "residual_rms_nm": result.residual_rms * 1e9,
        "truth_scale": true_scale,
        "deviation_percent": 100 * (result.scale / true_scale - 1),
        "deviation_sigmas": (result.scale - true_scale) / result.scale_sigma,
        "wall_seconds": wall,
        "instrument_seconds": float(sim.time - clock),
    }


def summarise(rows: list[dict]) -> dict:
    scales = np.array([r["scale"] for r in rows])
    return {
        "seeds": len(rows),
        "truth_scale": rows[0]["truth_scale"],
        "scale_mean": float(scales.mean()),
        "scale_sd": float(scales.std(ddof=1)) if len(rows) > 1 else 0.0,
        "scale_sigma_median": float(np.median([r["scale_sigma"] for r in rows])),
        "fit_sigma_median": float(np.median([r["fit_sigma"] for r in rows])),
        "deviation_percent_max": float(max(abs(r["deviation_percent"]) for r in rows)),
        "within_2_sigma": float(np.mean([abs(r["deviation_sigmas"]) <= 2 for r in rows])),
        "x_gain_mean": float(np.mean([r["matrix"][0][0] for r in rows])),
        "y_gain_mean": float(np.mean([r["matrix"][1][1] for r in rows])),
        "wall_seconds_median": float(np.median([r["wall_seconds"] for r in rows])),
        "instrument_seconds": float(np.median([r["instrument_seconds"] for r in rows])),
    }


def markdown(result: dict) -> str:
    m = result["machine"]
    lines = [
        "# The images' lateral scale on a reference lattice (simulator only)",
        "",
        f"Measured {result['date']} on {m['cpu_count']} CPUs ({m['cpu_model']}), Python "
        f"{m['python']}, load {m['load_average_at_start'][0]:.2f} at start; "
        f"{result['wall_seconds']:.0f} s wall, peak memory {result['peak_rss_mib']:.0f} MiB.",
        "",
        f"Command: `{result['command']}`",
        "",
        f"Reference: spheres r = {RADIUS * 1e9:.0f} nm on a square lattice of pitch "
        f"{PITCH * 1e9:.0f} nm; imaged like the maps (2.4 um, 256 px, 4 Hz, approached from "
        "beyond, slow axis up and down). Truth: sqrt(det(image_frame_matrix)) of the "
        "simulator's configuration (creep-free by construction). sigma: the stated 1-sigma "
        "(fits and the passes' spread); fit sigma: the fits' residuals alone.",
        "",
        "| simulator | seeds | measured (mean +- sd) | truth | max deviation | within 2 sigma "
        "| sigma (median) | fit sigma | x gain | y gain | wall per measurement | "
        "instrument time |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, s in result["summary"].items():
        lines.append(
            f"| {name} | {s['seeds']} | {s['scale_mean']:.5f} +- {s['scale_sd']:.5f} | "
            f"{s['truth_scale']:.5f} | {s['deviation_percent_max']:.2f} % | "
            f"{s['within_2_sigma']:.0%} | {s['scale_sigma_median']:.5f} | "
            f"{s['fit_sigma_median']:.6f} | {s['x_gain_mean']:.4f} | {s['y_gain_mean']:.4f} | "
            f"{s['wall_seconds_median']:.1f} s | {s['instrument_seconds']:.0f} s |"
        )
    lines += [
        "",
        "| simulator | seed | measured | sigma | up, down passes | deviation |",
        "|---|---|---|---|---|---|",
    ]
    for name, rows in result["rows"].items():
        for r in rows:
            lines.append(
                f"| {name} | {r['seed']} | {r['scale']:.5f} | {r['scale_sigma']:.5f} | "
                f"{r['pass_scales'][0]:.5f}, {r['pass_scales'][1]:.5f} | "
                f"{r['deviation_percent']:+.3f} % ({r['deviation_sigmas']:+.1f} sigma) |"
            )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--first-seed", type=int, default=1)
    parser.add_argument("--out", default=str(RESULTS / "lateral_scale"))
    args = parser.parse_args()
    load = os.getloadavg()
    began = time.monotonic()
    rows, summary = {}, {}
    for name, extra in CONDITIONS.items():
        truth = image_frame_matrix(merge(load_config(), extra))
        rows[name] = []
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            r = measure(seed, extra, truth)
            rows[name].append(r)
            print(
                f"{name:9s} seed {seed}: {r['scale']:.5f} +- {r['scale_sigma']:.5f} "
                f"(truth {r['truth_scale']:.5f}, {r['deviation_percent']:+.3f} %), "
                f"{r['wall_seconds']:.1f} s",
                flush=True,
            )
        summary[name] = summarise(rows[name])
    result = {
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": machine_record(list(load)),
        "command": command_line(),
        "seeds": args.seeds,
        "pitch_m": PITCH,
        "radius_m": RADIUS,
        "wall_seconds": time.monotonic() - began,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "summary": summary,
        "rows": rows,
    }
    Path(args.out + ".json").write_text(json.dumps(result, indent=1))
    Path(args.out + ".md").write_text(markdown(result))
    print(markdown(result))


if __name__ == "__main__":
    main()
