"""How the localizer's prediction error grows with the length of a move (issue 36), ROS-free on
the simulated AFM with its default physics and the shipped calibration.

What is measured
----------------
From the range centre the tip moves L (1-45 um, along +-x and +-y) to a region with one sphere
(r = 100 nm), images it as a 0/90 pair (256 x 256 px over 2.4 um, 4 Hz; the pair drift-corrected,
the landmark extracted) and the localizer predicts every command as the graph's localizer does
(the driver's TipCommands). The figure is the line-planning error: where the map puts the
particle relative to the estimated tip, minus where it truly is relative to the true tip
(brought into the maps' frame by the scanner's local gain), per axis; and how far it lies in
the estimate's own sigmas. Two set-ups in the same run:

- "before": the motion model as it was (the scanner matrix extrapolated over every move, an
  image predicted as a free move), no wait for creep;
- "now": the matrix's residual bounded by the span it was measured over, an image resetting it,
  and the wait for creep before each image (afm_core.localization.creep_settle).

Run: `scripts/with_env.sh python bench/bench_long_moves.py` (~5 min).
Results: bench/results/long_moves.json and long_moves.md.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import command_line, machine_record  # noqa: E402

from afm_core.evaluation import image_frame_matrix  # noqa: E402
from afm_core.imaging.drift_compensation import compensate_pair  # noqa: E402
from afm_core.imaging.landmarks import extract_landmarks  # noqa: E402
from afm_core.imaging.raster_approach import (  # noqa: E402
    RASTER_APPROACH_OVERSHOOT,
    approach_point,
)
from afm_core.instrument import ScanRequest  # noqa: E402
from afm_core.localization import Localizer  # noqa: E402
from afm_core.localization.calibration.model import load_calibration  # noqa: E402
from afm_core.localization.creep_settle import CreepSettler, settle_before  # noqa: E402
from afm_core.sim.config import load_config, merge  # noqa: E402
from afm_core.sim.instrument import SimulatedAfm  # noqa: E402

RESULTS_DIR = Path(__file__).resolve().parent / "results"
CALIBRATION = (
    Path(__file__).resolve().parents[1] / "afm_localization" / "config" / "sim_calibration.yaml"
)
NM, UM = 1e-9, 1e-6
CENTRE = np.array([55 * UM, 55 * UM])
LENGTHS = (1 * UM, 5 * UM, 10 * UM, 20 * UM, 45 * UM)
DIRECTIONS = ((1, 0), (-1, 0), (0, 1), (0, -1))
AREA, PIXELS = 2.4 * UM, 256  # the graph's pair (bench_push_range)
RASTER_SIGMA = 30e-9  # the localizer node's default raster_sigma
TOLERANCE, MAX_WAIT = 5e-9, 600.0  # the driver's defaults


def one_case(region, now: bool, seed: int) -> dict:
    config = merge(
        load_config(),
        {
            "seed": seed,
            "sample": {
                "spheres": [{"x": region[0], "y": region[1], "radius": 100 * NM}],
                "random_spheres": 0,
            },
        },
    )
    calibration = load_calibration(CALIBRATION)
    if not now:
        calibration = replace(calibration, scanner_matrix_span=1.0)  # extrapolated everywhere
    sim = SimulatedAfm(config)
    loc = Localizer(sim, calibration, CENTRE, np.diag([50 * NM] * 2) ** 2)
    settler = CreepSettler(calibration, sim.commanded_position(), sim.time)
    waited = 0.0
    scans = []
    for angle in (0.0, 90.0):
        request = ScanRequest(
            *(region - AREA / 2), AREA, AREA, PIXELS, PIXELS, scan_angle_deg=angle, line_rate=4.0
        )
        if now:
            t0, c0 = sim.time, sim.commanded_position()
            sim.move_tip(*approach_point(request, RASTER_APPROACH_OVERSHOOT.default), 1e-5)
            loc.predict_command("move", c0, sim.commanded_position(), t0, sim.time)
            settler.observe(c0, sim.commanded_position(), t0, sim.time)
            t0, c0 = sim.time, sim.commanded_position()
            settling = settle_before(
                sim, settler, *request.first_point(), 1e-5, TOLERANCE, MAX_WAIT
            )
            waited += settling.seconds
            loc.predict_command("move", c0, request.first_point(), t0, t0 + 1e-9)
        t0, c0 = sim.time, sim.commanded_position()
        scans.append(sim.raster_scan(request))
        settler.observe(c0, sim.commanded_position(), t0, sim.time)
        loc.predict_command(
            "raster" if now else "move",
            c0,
            sim.commanded_position(),
            t0,
            sim.time,
            RASTER_SIGMA**2,
        )
    s = scans[0]
    try:
        corrected = compensate_pair(scans[0], scans[1]).corrected
        marks = extract_landmarks(
            np.asarray(corrected, float), s.pixel_size_x, s.pixel_size_y, s.origin_x, s.origin_y
        )
    except ValueError as exc:  # the particle left the image (creep moved it out): no map
        return {"error_nm": None, "sigmas": None, "wait_s": waited, "failed": str(exc)}
    if not marks:
        return {"error_nm": None, "sigmas": None, "wait_s": waited, "failed": "no landmark"}
    mark = min(marks, key=lambda m: np.hypot(m.x - region[0], m.y - region[1]))
    truth = sim.truth()
    sphere = np.array([truth["objects"][0].x, truth["objects"][0].y])
    to_particle = np.linalg.solve(
        image_frame_matrix(config, at=region), sphere - truth["tip_position"]
    )
    error = (np.array([mark.x, mark.y]) - loc.mean) - to_particle
    sigma = np.sqrt(np.diag(loc.covariance + mark.covariance))
    return {
        "error_nm": (error / NM).tolist(),
        "sigmas": (error / sigma).tolist(),
        "wait_s": waited,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    started, load = time.monotonic(), os.getloadavg()
    rows = []
    for length in LENGTHS:
        for direction in DIRECTIONS:
            region = CENTRE + length * np.array(direction, float)
            for now in (False, True):
                row = {"length_um": length / UM, "direction": direction, "now": now}
                row.update(one_case(region, now, args.seed))
                rows.append(row)
                setup = "now   " if now else "before"
                outcome = (
                    f"no map: {row['failed'][:60]}"
                    if row["error_nm"] is None
                    else f"error ({row['error_nm'][0]:7.1f}, {row['error_nm'][1]:7.1f}) nm = "
                    f"({row['sigmas'][0]:5.1f}, {row['sigmas'][1]:5.1f}) sigma"
                )
                print(
                    f"L {length / UM:4.0f} um {str(direction):8s} {setup}: {outcome}, waited "
                    f"{row['wait_s']:.0f} s",
                    flush=True,
                )
    summary = []
    for length in LENGTHS:
        for now in (False, True):
            every = [r for r in rows if r["length_um"] == length / UM and r["now"] == now]
            mine = [r for r in every if r["error_nm"] is not None]
            if not mine:
                summary.append({"length_um": length / UM, "now": now, "mapped": 0})
                continue
            worst = max(max(abs(e) for e in r["error_nm"]) for r in mine)
            summary.append(
                {
                    "length_um": length / UM,
                    "now": now,
                    "mapped": len(mine),
                    "of": len(every),
                    "rms_nm": float(np.sqrt(np.mean([np.square(r["error_nm"]) for r in mine]))),
                    "worst_nm": float(worst),
                    "worst_sigmas": float(max(max(abs(s) for s in r["sigmas"]) for r in mine)),
                    "wait_s": float(np.mean([r["wait_s"] for r in mine])),
                }
            )
    slopes = {}
    for now in (False, True):
        mapped = [s for s in summary if s["now"] == now and s["mapped"]]
        lengths = np.array([s["length_um"] for s in mapped])
        rms = np.array([s["rms_nm"] for s in mapped])
        slopes["now" if now else "before"] = float(np.polyfit(lengths, rms, 1)[0])
    result = {
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": machine_record(load),
        "seed": args.seed,
        "summary": summary,
        "nm_per_um": slopes,
        "runs": rows,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "wall_seconds": time.monotonic() - started,
    }
    RESULTS_DIR.mkdir(exist_ok=True)
    (RESULTS_DIR / "long_moves.json").write_text(json.dumps(result, indent=2))
    command = command_line()
    lines = [
        "# The localizer's prediction error against the length of a move",
        "",
        f"Measured {result['date']} on {result['machine']['cpu_count']} CPUs "
        f"({result['machine']['cpu_model']}), Python {result['machine']['python']}, load "
        f"{load[0]:.2f} at start; "
        f"{result['wall_seconds']:.0f} s wall, peak memory {result['peak_rss_mib']:.0f} MiB.",
        "",
        f"Command: `{command}`",
        "",
        "Protocol: bench/bench_long_moves.py's docstring (simulated AFM, default physics, the "
        "shipped calibration; one sphere imaged as a 0/90 pair after a move of L from the range "
        "centre along +-x and +-y). Error: map minus estimate, minus truth, per axis; sigmas: "
        "the same in the estimate's (and landmark's) standard deviations. 'before' extrapolates "
        "the scanner matrix over every move and takes no wait; 'now' bounds its residual and "
        "waits for creep before each image. Mapped: the pair gave a map with the particle (a "
        "pair that creep moved it out of gives none).",
        "",
        "| move | set-up | mapped | RMS error | worst axis | worst in sigmas "
        "| wait before the images |",
        "|---|---|---|---|---|---|---|",
    ]
    for s in summary:
        name = "now" if s["now"] else "before"
        if not s["mapped"]:
            lines.append(f"| {s['length_um']:.0f} um | {name} | 0 | - | - | - | - |")
            continue
        lines.append(
            f"| {s['length_um']:.0f} um | {name} | {s['mapped']} of {s['of']} | "
            f"{s['rms_nm']:.0f} nm | {s['worst_nm']:.0f} nm | {s['worst_sigmas']:.1f} | "
            f"{s['wait_s']:.0f} s |"
        )
    if any(s["mapped"] < s.get("of", 0) or not s["mapped"] for s in summary):
        lines += [
            "",
            "Where a pair gave no map, the particle lay outside the 2.4 um images: far from the "
            "range centre the tip is up to ~1 um from its command (the command frame is not the "
            "sample's; docs/localization.md), in both set-ups.",
        ]
    lines += [
        "",
        f"Growth of the RMS error with the move (least squares over the lengths): before "
        f"{slopes['before']:.1f} nm per um moved, now {slopes['now']:.1f} nm per um.",
    ]
    (RESULTS_DIR / "long_moves.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines[-(len(summary) + 4) :]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
