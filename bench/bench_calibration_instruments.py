"""Calibration experiments (book 7.2.2) on simulated instruments away from the default:
recovered against configured values per instrument (issue 37).

What is run
-----------
`run_calibration` on `SimulatedAfm` with each of INSTRUMENTS (overrides of the default
configuration spanning the ranges a lab's instrument may have: hysteresis loops 0.05-0.25 of
the range, asymmetry up to 0.1, creep 0.3-3x in size and time, coupling up to 0.05,
positioning noise 0.5-4x, drift means up to 1 nm/s, other seeds). The drift statistics use
--pairs frame pairs (default 6: the drift rows are then sample statistics of a few pairs, with
a sampling error of about sigma / sqrt(pairs), shown in the note); the other experiments run at
their default sizes (--quick: the smaller hysteresis cycle of the tests).

How to read it
--------------
One table per instrument: recovered, configured and relative error of the hysteresis, creep
and motion-noise parameters and the drift means (`compare_with_simulator`), and the checks the
calibration itself raised (`calibration_checks`: a parameter it flags is one it says it could
not recover). The target: within 10 %, or flagged.

Run: `scripts/with_env.sh python bench/bench_calibration_instruments.py [--pairs N] [--quick]
[--only NAME ...]`. Writes bench/results/calibration_instruments.json and .md (with -quick
for --quick). Wall time with perf_counter; peak memory is this process's VmHWM.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from datetime import datetime, timezone

from bench_calibration import RESULTS, jsonable, machine_info, peak_rss_mib, table
from machine import command_line

from afm_core.localization.calibration.procedure import run_calibration
from afm_core.localization.calibration.simulator_comparison import compare_with_simulator
from afm_core.sim.config import load_config, merge


def _creep(scale_size: float, scale_time: float) -> dict:
    base = load_config().scanner
    return {
        "creep_time_constants": [scale_time * t for t in base.creep_time_constants],
        "creep_fractions": [scale_size * f for f in base.creep_fractions],
    }


def _noise(scale: float) -> dict:
    base = load_config().scanner
    return {
        "positioning_noise_slope": scale * base.positioning_noise_slope,
        "positioning_noise_offset": scale * base.positioning_noise_offset,
    }


INSTRUMENTS = {
    # issue 37's first instrument: a narrow asymmetric loop, more creep, more coupling, noise 2x
    "narrow_loop": {
        "seed": 1,
        "scanner": {
            "hysteresis_fraction": 0.07,
            "hysteresis_asymmetry": 0.05,
            "coupling_x_to_y": 0.02,
            "coupling_y_to_x": 0.02,
            **_creep(1.5, 1.5),
            **_noise(2.0),
        },
        "drift": {"mean_velocity_x": 3e-10, "mean_velocity_y": -2e-10},
    },
    # issue 37's second: a wide loop, less creep, faster
    "wide_loop": {
        "seed": 2,
        "scanner": {"hysteresis_fraction": 0.18, "hysteresis_asymmetry": 0.08, **_creep(0.6, 0.6)},
    },
    # the ends of the ranges: the narrowest loop, the most asymmetric, the largest creep
    "narrowest_most_creep": {
        "seed": 3,
        "scanner": {
            "hysteresis_fraction": 0.05,
            "hysteresis_asymmetry": 0.1,
            **_creep(3.0, 3.0),
            **_noise(0.5),
        },
        "drift": {"mean_velocity_x": 1e-9, "mean_velocity_y": 1e-9},
    },
    "widest_most_coupled": {
        "seed": 4,
        "scanner": {
            "hysteresis_fraction": 0.25,
            "hysteresis_asymmetry": 0.1,
            "coupling_x_to_y": 0.05,
            "coupling_y_to_x": 0.05,
            **_creep(0.3, 0.3),
            **_noise(4.0),
        },
    },
    # the default instrument on the seed where motion noise measured 0 trials (issue 37)
    "default_seed_23": {"seed": 23},
}


def _check_text(check: dict) -> str:
    return f"{check['level']} {check['experiment']}: {check['message']}"


# Off by more than this (relative) is a miss unless flagged (issue 37's target).
TARGET = 0.10


def _flagging_checks(name: str) -> list[tuple[str, str | None]]:
    """(experiment, parameter) of the checks that speak for the row `name` (None: any)."""
    head, _, rest = name.partition(".")
    if head.startswith("hysteresis_"):
        parameter = None if rest in ("branch_error", "gain") else rest
        return [(head, parameter), ("hysteresis_x vs hysteresis_y", rest)]
    if head == "creep":
        if rest.startswith("step_response_"):
            axis = rest[-1]
            return [("creep", f"step_response_25s_{axis}"), ("creep_x vs creep_y", None)]
        term = int(rest.split("[")[1].rstrip("]")) + 1
        own = [("creep", f"term_{term}")]
        return own + ([("creep", "time_constants")] if rest.startswith("time_constant") else [])
    if head == "motion_noise":
        return [("motion_noise", "pooled_slope"), (f"motion_noise.{rest} vs pooled_slope", None)]
    return [(head, None)]


def _verdict(row: dict, checks: list[dict], report: dict) -> str:
    """within / flagged / SILENT for one row: off by more than TARGET (drift: the configured
    value outside the run's own 95 % interval), and whether a check that speaks for it is not
    "ok"."""
    name, error = row["name"], row["relative_error"]
    if row["recovered"] is None:
        return "flagged (not measured)"
    if name == "motion_noise.offset":
        return "not a target (the intercept holds the pits' position noise)"
    drift = ((report.get("drift") or {}).get("parameters")) or {}
    if name.startswith("drift.mean_velocity_"):
        interval = drift.get("mean_velocity_interval95", [math.nan] * 2)["xy".index(name[-1])]
        off = abs(row["recovered"] - row["true"]) > interval
    elif name.startswith("drift.sigma_velocity_"):
        low, high = drift.get("sigma_velocity_interval95", [[math.nan] * 2] * 2)[
            "xy".index(name[-1])
        ]
        off = not low <= row["true"] <= high
    elif error is None or not math.isfinite(error):
        return "-"
    else:
        off = abs(error) > TARGET
    keys = _flagging_checks(name)
    flagged = any(
        c["level"] != "ok"
        and any(
            c["experiment"].replace("motion_noise.pooled_slope", "pooled_slope") == e
            and (p is None or c["parameter"] == p)
            for e, p in keys
        )
        for c in checks
    )
    if not off:
        return "within (flagged)" if flagged else "within"
    return "flagged" if flagged else "SILENT"


def _verdict_table(rows: list[dict]) -> list[str]:
    lines = table(rows)
    lines[0] = lines[0].rstrip() + " verdict |"
    lines[1] += "---|"
    return lines[:2] + [line + f" {row['verdict']} |" for line, row in zip(lines[2:], rows)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=6, help="drift frame pairs per instrument")
    parser.add_argument("--quick", action="store_true", help="the tests' smaller hysteresis cycle")
    parser.add_argument("--only", nargs="+", choices=sorted(INSTRUMENTS), help="instruments")
    args = parser.parse_args()
    options = {"drift": {"pairs": args.pairs, "interval": 1800.0}}
    if args.quick:
        options["hysteresis"] = {"steps_per_sweep": 96, "pixel": 35e-9}
    started = datetime.now(timezone.utc)
    results, lines = {}, []
    for name in args.only or INSTRUMENTS:
        overrides = INSTRUMENTS[name]
        config = merge(load_config(), overrides)
        # imported here so a bench of one instrument does not pay for the others' set-up
        from afm_core.sim.instrument import SimulatedAfm

        afm = SimulatedAfm(config)
        started_at = {}

        def progress(text, afm=afm, started_at=started_at):
            # where the motion-noise lanes' pits start in the simulator's list, so their true
            # separations give the images' scale there (simulator_comparison.lane_image_scales)
            if text.endswith(": motion_noise ..."):
                started_at["motion_noise"] = len(afm.sample.pits)

        clock = time.perf_counter()
        calibration, report = run_calibration(
            afm, source=f"bench_calibration_instruments {name}", progress=progress, **options
        )
        wall = time.perf_counter() - clock
        first = started_at.get("motion_noise")
        pits = None if first is None else afm.sample.pits[first:]
        rows = [
            row
            for row in compare_with_simulator(calibration, report, config, pits)
            if row["name"].split(".")[0] in ("hysteresis_x", "hysteresis_y", "creep", "drift")
            or row["name"].startswith("motion_noise")
        ]
        checks = report.get("checks", [])
        for row in rows:
            row["verdict"] = _verdict(row, checks, report)
        results[name] = {
            "overrides": overrides,
            "wall_seconds": wall,
            "instrument_seconds": report["instrument_seconds"],
            "defaults": calibration.defaults,
            "failed": {
                k: v["failed"] for k, v in report.items() if isinstance(v, dict) and "failed" in v
            },
            "checks": checks,
            "rows": rows,
        }
        lines += [
            f"## {name}",
            "",
            f"Overrides: `{json.dumps(overrides)}`; {wall:.0f} s wall, "
            f"{report['instrument_seconds'] / 3600:.1f} h of instrument time.",
            "",
            *_verdict_table(rows),
            "",
            "Checks: " + ("; ".join(_check_text(c) for c in checks) or "-"),
            "",
        ]
        print("\n".join(lines[-len(rows) - 8 :]), flush=True)
    RESULTS.mkdir(exist_ok=True)
    stem = "calibration_instruments" + ("-quick" if args.quick else "")
    result = {
        "date": started.isoformat(timespec="seconds"),
        "machine": machine_info(),
        "command": command_line(),
        "options": options,
        "peak_rss_mib": peak_rss_mib(),
        "instruments": results,
    }
    (RESULTS / f"{stem}.json").write_text(json.dumps(jsonable(result), indent=1))
    head = [
        f"# Calibration on instruments away from the default{' (quick)' if args.quick else ''}",
        "",
        f"Measured {result['date']} on {result['machine']['cpus_usable']} CPUs "
        f"({result['machine']['cpu_model']}), Python {result['machine']['python']}; peak "
        f"resident memory {result['peak_rss_mib']:.0f} MiB; {args.pairs} drift pairs.",
        "",
        f"Command: `{result['command']}`",
        "",
    ]
    summary = [
        "Verdicts (a row off by more than 10 %, or a drift value outside the run's own 95 % "
        "interval, is flagged when a check that speaks for it is not ok; SILENT otherwise):",
        "",
        "| instrument | within | within (flagged) | flagged | SILENT |",
        "|---|---|---|---|---|",
    ]
    for name, result_of in results.items():
        verdicts = [row["verdict"] for row in result_of["rows"]]
        silent = [row["name"] for row in result_of["rows"] if row["verdict"] == "SILENT"]
        summary.append(
            f"| {name} | {verdicts.count('within')} | {verdicts.count('within (flagged)')} | "
            f"{sum(v.startswith('flagged') for v in verdicts)} | "
            f"{len(silent)}{': ' + ', '.join(silent) if silent else ''} |"
        )
    (RESULTS / f"{stem}.md").write_text("\n".join(head + summary + [""] + lines) + "\n")


if __name__ == "__main__":
    main()
