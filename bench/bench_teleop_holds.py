"""How often the teleop node holds the operator's commands, with and without the spinning
thread's yield of the GIL before each executor pass (afm_ros.executor, issue 33).

What is measured
----------------
The teleop dead-man test (test/test_teleop_ros.py: driver and teleop node at real time, 1 s of
Twists at 20 Hz) is run `--runs` times per variant, the variants in turn. From the teleop
node's own status after each run: how many commands waited more than 50 ms after they arrived
before their callback ran, and the longest such wait. A run "held the commands" when at least
`--held` commands were late (a held run had 7-22 of about 21; a good one 0-3). The test's own
outcome is counted too (passed, xfailed as the known defect, failed).

`--busy N` runs N shell loops that only spin on the CPU beside the tests, for the same count under
CPU contention (on 2 CPUs, 2 of them bring the load to about 4).

Run: `scripts/with_env.sh python bench/bench_teleop_holds.py [--runs 30] [--held 5] [--busy 0]
[--name teleop_holds]` (about 7 s per run). Results: bench/results/<name>.md and .json.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import re
import resource
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import busy_loops, command_line, machine_record  # noqa: E402

from afm_ros.executor import YIELD_ENVIRONMENT  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RESULTS_DIR = ROOT / "bench" / "results"
TEST = "test/test_teleop_ros.py"
SELECT = "dead_man"
TIMING = re.compile(r"teleop's timing (\{[^}]*\})")
# name: the executor's yield variable for the nodes ("" = unset, the default)
VARIANTS = {"yield before each pass (now)": "", "no yield (before 2026-11-28)": "0"}


def run_once(setting: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("ROS_DOMAIN_ID", YIELD_ENVIRONMENT)}
    if setting:
        env[YIELD_ENVIRONMENT] = setting
    done = subprocess.run(
        [sys.executable, "-m", "pytest", TEST, "-q", "-s", "-rxs", "-p", "no:cacheprovider"]
        + ["-k", SELECT],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    lines = done.stdout.strip().splitlines()
    found = TIMING.search(done.stdout)
    timing = ast.literal_eval(found.group(1)) if found else {}
    summary = lines[-1] if lines else done.stderr[-200:]
    outcome = "failed" if "failed" in summary else "xfailed" if "xfailed" in summary else "passed"
    return {
        "outcome": outcome if found or outcome != "passed" else "no timing",
        "late_commands": timing.get("late_commands"),
        "longest_wait_s": timing.get("longest_command_wait"),
        "longest_segment_s": timing.get("longest_segment"),
        "load_average": round(os.getloadavg()[0], 2),
    }


def summarise(runs: list[dict], held: int) -> dict:
    timed = [r for r in runs if r["late_commands"] is not None]
    waits = sorted(r["longest_wait_s"] for r in timed)
    return {
        "runs": len(runs),
        "held": sum(r["late_commands"] >= held for r in timed),
        "late_commands_total": sum(r["late_commands"] for r in timed),
        "longest_wait_median_s": waits[len(waits) // 2] if waits else None,
        "longest_wait_max_s": waits[-1] if waits else None,
        "passed": sum(r["outcome"] == "passed" for r in runs),
        "xfailed": sum(r["outcome"] == "xfailed" for r in runs),
        "failed": sum(r["outcome"] == "failed" for r in runs),
        "no_timing": sum(r["outcome"] == "no timing" for r in runs),
    }


def report(results: dict, args, started: str, machine: dict) -> str:
    loads = [r["load_average"] for runs in results.values() for r in runs]
    lines = [
        "# Teleop commands held by the node, with and without the executor's yield",
        "",
        f"Measured {started} on {machine['cpu_count']} CPUs ({machine['cpu_model']}), load "
        f"average {machine['load_average_at_start'][0]:.1f} at the start, "
        f"{min(loads):.1f}-{max(loads):.1f} after the runs; {args.runs} runs of the teleop "
        f"dead-man test per variant, in turn, beside {args.busy} busy-looping processes. On "
        "this machine and our simulated driver only.",
        "",
        f"Command: `{command_line()}`",
        "",
        f"| variant | runs | runs with >= {args.held} late commands | late commands in all | "
        "longest wait, median / max | test passed / xfailed / failed |",
        "|---|---|---|---|---|---|",
    ]
    for name, runs in results.items():
        s = summarise(runs, args.held)
        lines.append(
            f"| {name} | {s['runs']} | {s['held']} | {s['late_commands_total']} | "
            f"{s['longest_wait_median_s']} / {s['longest_wait_max_s']} s | "
            f"{s['passed']} / {s['xfailed']} / {s['failed']} |"
        )
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    lines += [
        "",
        "Late: the command's callback ran more than 50 ms after the middleware had it (the "
        "teleop status's `late_commands`).",
        "",
        f"Peak memory of a child process (a pytest run): {peak:.0f} MiB.",
        "",
    ]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=30)
    parser.add_argument("--held", type=int, default=5, help="late commands that make a run held")
    parser.add_argument("--busy", type=int, default=0, help="busy-looping processes beside")
    parser.add_argument("--name", default="teleop_holds", help="results file name (no suffix)")
    args = parser.parse_args()
    if args.runs < 1 or args.held < 1:
        parser.error(f"--runs {args.runs} and --held {args.held}: each must be at least 1")
    if not 0 <= args.busy <= 16:
        parser.error(f"--busy {args.busy}: must be 0-16")
    started = datetime.now(timezone.utc).isoformat(timespec="seconds")
    machine = machine_record(os.getloadavg())
    results: dict[str, list[dict]] = {name: [] for name in VARIANTS}
    with busy_loops(args.busy):
        for k in range(args.runs):
            for name, setting in VARIANTS.items():
                results[name].append(run_once(setting))
                print(f"run {k + 1} {name}: {json.dumps(results[name][-1])}", flush=True)
    text = report(results, args, started, machine)
    print(text)
    RESULTS_DIR.mkdir(exist_ok=True)
    (RESULTS_DIR / f"{args.name}.md").write_text(text)
    record = {
        "started": started,
        "machine": machine,
        "command": command_line(),
        "busy": args.busy,
        "runs": results,
    }
    (RESULTS_DIR / f"{args.name}.json").write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
