"""How often a node of the graph stands still as a whole, and why, with the DDS transport, the
publication mode and the executor: what the project had (shared memory, synchronous writes,
rclpy's MultiThreadedExecutor), asynchronous writes (measured, not taken: they lost bursts of
publishes), and what it has now (UDP on the loopback, synchronous writes, afm_ros.exposure;
the queue-aware executor, afm_ros.executor).

What is measured
----------------
The workload is the teleop graph tests (test/test_teleop_ros.py: driver, teleop node, and the
graphs of the hand-back and nano-hand tests), run once per variant per round, the variants in
turn, every node with the stall watch on (afm_ros.stall_watch, threshold 0.15 s). A stall is
written up with every thread's stack and each thread's CPU and run-queue time over it:
- held: the threads together ran and queued for less than half its length, so they waited
  on something (a lock, the GIL held by a thread that waits);
- starved: the rest, threads queued for a CPU (the machine is loaded).
A held stall whose stacks show rclpy's publish is a write that waited with the GIL held.

Beside the stalls, the teleop node's own figures from the first test (a 1 s drive at real
time): commands whose callback ran more than 50 ms after they arrived, the longest such wait,
the longest segment (one MoveTip round trip to the driver), the command-to-motion latency, and
how many tests reported the node standing still (their known-defect guard).

Run: `scripts/with_env.sh python bench/bench_node_stalls.py [--rounds 3] [--busy 0]
[--variants TEXT] [--no-watch] [--name node_stalls]` (~1-4 min per variant and round, with the
load). Results: bench/results/<name>.md and .json.
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
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import busy_loops, command_line, machine_record  # noqa: E402

from afm_ros import exposure  # noqa: E402
from afm_ros.executor import ENVIRONMENT as EXECUTOR  # noqa: E402
from afm_ros.executor import STOCK  # noqa: E402
from afm_ros.stall_watch import ENVIRONMENT  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RESULTS_DIR = ROOT / "bench" / "results"
WORKLOAD = "test/test_teleop_ros.py"
SHARED_MEMORY = """      <transport_descriptor>
        <transport_id>afm_shared_memory</transport_id>
        <type>SHM</type>
      </transport_descriptor>
    </transport_descriptors>"""
WITH_SHARED_MEMORY = exposure.LOCALHOST_PROFILE.replace(
    "    </transport_descriptors>", SHARED_MEMORY, 1
).replace(
    "          <transport_id>afm_loopback_udp</transport_id>",
    "          <transport_id>afm_shared_memory</transport_id>\n"
    "          <transport_id>afm_loopback_udp</transport_id>",
    1,
)
assert WITH_SHARED_MEMORY.count("afm_shared_memory") == 2, "the profile's layout changed"
# name: (profile text, publication mode, executor: "" ours, STOCK rclpy's MultiThreadedExecutor)
VARIANTS = {
    "shared memory + UDP, synchronous writes, rclpy's executor (until 2026-11-28)": (
        WITH_SHARED_MEMORY,
        "SYNCHRONOUS",
        STOCK,
    ),
    "UDP, synchronous writes, rclpy's executor": (
        exposure.LOCALHOST_PROFILE,
        "SYNCHRONOUS",
        STOCK,
    ),
    # measured, not taken: asynchronous writes lost bursts of publishes (afm_ros.exposure)
    "UDP, asynchronous writes, rclpy's executor": (
        exposure.LOCALHOST_PROFILE,
        "ASYNCHRONOUS",
        STOCK,
    ),
    "UDP, synchronous writes, queue-aware executor (now)": (
        exposure.LOCALHOST_PROFILE,
        "SYNCHRONOUS",
        "",
    ),
}
# the first teleop test prints what the teleop node measured of its commands and segments
TIMING = re.compile(r"command-to-motion latency (\d+) ms;.*?teleop's timing (\{[^}]*\})")
STALL = re.compile(r"STALL ([\d.]+) s, ended \S+ \(monotonic [\d.]+\): (.*)")


def classify(report: str) -> list[dict]:
    """Each stall of one node's report: its length, held or starved, and whether the stacks
    written during it show a publish."""
    stalls = []
    for block in re.split(r"(?=Timeout \()", report):
        found = STALL.search(block)
        if not found:
            continue
        seconds = float(found.group(1))
        busy_ms = sum(int(v) for v in re.findall(r"(?:ran|queued) (\d+) ms", found.group(2)))
        stalls.append(
            {
                "seconds": seconds,
                "held": busy_ms < 0.5 * seconds * 1e3,
                "in_publish": "rclpy/publisher.py" in block and "in publish" in block,
                "where": own_frames(block),
            }
        )
    return stalls


def own_frames(block: str, count: int = 3) -> list[str]:
    """The innermost frames of the project's code (and rclpy's publish) in a stall's stacks,
    beyond the threads that only wait for work."""
    frames = re.findall(r'File "([^"]+)", line (\d+) in (\S+)', block)
    idle = ("threading.py", "thread.py", "stall_watch.py", "node_main.py", "<frozen runpy>")
    own = [
        f"{Path(path).name}:{line} {name}"
        for path, line, name in frames
        if not path.endswith(idle) and ("site-packages" not in path or name == "publish")
    ]
    return own[:count]


def run_variant(profile_text: str, mode: str, executor: str, watch_on: bool = True) -> dict:
    with tempfile.TemporaryDirectory(prefix="afm_stalls_") as folder:
        # named as the project's own profile, so the nodes take it as theirs (is_ours)
        profile = Path(folder) / exposure.PROFILE_NAME
        profile.write_text(profile_text)
        watch = Path(folder) / "stalls"
        env = {k: v for k, v in os.environ.items() if k not in exposure.PROFILE_VARIABLES}
        env.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)
        env.pop("ROS_DOMAIN_ID", None)  # the test run claims its own
        for name in exposure.PROFILE_VARIABLES:
            env[name] = str(profile)
        env[exposure.PUBLICATION_MODE] = mode
        if watch_on:
            env[ENVIRONMENT] = str(watch)
        else:
            env.pop(ENVIRONMENT, None)
        env.pop(EXECUTOR, None)
        if executor:
            env[EXECUTOR] = executor
        started = time.monotonic()
        done = subprocess.run(
            [sys.executable, "-m", "pytest", WORKLOAD, "-q", "-p", "no:cacheprovider", "-rxsP"],
            cwd=ROOT,
            env=env,
            capture_output=True,
            text=True,
            timeout=1800,
        )
        lines = done.stdout.strip().splitlines()
        summary = lines[-1] if lines else done.stderr[-300:]
        outcomes = [line[:300] for line in lines if line.startswith(("FAILED", "XFAIL", "ERROR"))]
        timing = TIMING.search(done.stdout)
        stalls = {}
        for file in sorted(watch.glob("*.stalls.txt")) if watch.is_dir() else []:
            node = file.name.split(".")[0]
            stalls.setdefault(node, []).extend(classify(file.read_text()))
    return {
        "tests": summary,
        "outcomes": outcomes,
        "wall_s": round(time.monotonic() - started, 1),
        "load_average": os.getloadavg()[0],
        "stalls": stalls,
        "latency_ms": int(timing.group(1)) if timing else None,
        "teleop_timing": ast.literal_eval(timing.group(2)) if timing else None,
    }


def figures(runs: list[dict]) -> dict:
    every = [s for run in runs for node in run["stalls"].values() for s in node]
    held = [s for s in every if s["held"]]
    return {
        "held": len(held),
        "held_in_publish": sum(s["in_publish"] for s in held),
        "held_max_s": max((s["seconds"] for s in held), default=0.0),
        "starved": len(every) - len(held),
        "held_nodes": sorted(
            {
                node
                for run in runs
                for node, ss in run["stalls"].items()
                if any(s["held"] for s in ss)
            }
        ),
    }


def report(rounds: list[dict], chosen: list[str], args, started: str, load) -> str:
    lines = [
        "# Whole-node stalls in the teleop graph tests, by DDS transport, publication mode and "
        "executor",
        "",
        f"Measured {started} on {load['cpu_count']} CPUs ({load['cpu_model']}), load average "
        f"{load['load_average_at_start'][0]:.1f} at the start, {args.busy} busy loops beside; "
        f"{args.rounds} rounds, each running `{WORKLOAD}` once per variant, every node's stall "
        f"watch {'off' if args.no_watch else 'on (0.15 s)'}. On this machine's loopback and our "
        "simulated driver only.",
        "",
        f"Command: `{command_line()}`",
        "",
        "| variant | held stalls (in publish) | longest held | starved stalls | nodes held "
        "| teleop held the commands (tests) | late commands | longest command wait "
        "| longest segment "
        "| command-to-motion latency, median | tests per round (load average) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name in chosen:
        runs = [r[name] for r in rounds]
        f = figures(runs)
        timings = [r["teleop_timing"] for r in runs if r.get("teleop_timing")]
        latencies = sorted(r["latency_ms"] for r in runs if r.get("latency_ms") is not None)
        stood = sum("held the commands" in o for r in runs for o in r["outcomes"])
        lines.append(
            f"| {name} | {f['held']} ({f['held_in_publish']}) | {f['held_max_s']:.2f} s | "
            f"{f['starved']} | {', '.join(f['held_nodes']) or '-'} | {stood} | "
            f"{sum(t.get('late_commands', 0) for t in timings)} | "
            f"{max((t.get('longest_command_wait', 0) for t in timings), default=0):.3f} s | "
            f"{max((t.get('longest_segment', 0) for t in timings), default=0):.3f} s | "
            f"{latencies[len(latencies) // 2] if latencies else '-'} ms | "
            + "; ".join(f"{r['tests']} ({r['load_average']:.1f})" for r in runs)
            + " |"
        )
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    lines += [
        "",
        "Held: the node's threads together ran and queued for less than half the stall, so they "
        "waited (rclpy's publish holds the GIL through Fast DDS's write: a write that waits stops "
        "the whole node). Starved: they queued for a CPU; that is the machine's load, the same "
        "for every variant.",
        "",
        f"Peak memory of a child process (the pytest run): {peak:.0f} MiB.",
        "",
    ]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--busy", type=int, default=0, help="busy loops beside the runs")
    parser.add_argument(
        "--variants", default="", help="only the variants whose name contains this text"
    )
    parser.add_argument(
        "--no-watch",
        action="store_true",
        help="the nodes' stall watch off (their own figures only)",
    )
    parser.add_argument("--name", default="node_stalls", help="results file name (no suffix)")
    args = parser.parse_args()
    chosen = [name for name in VARIANTS if args.variants in name]
    if not chosen:
        parser.error(f"--variants {args.variants!r} matches none of {list(VARIANTS)}")
    started = datetime.now(timezone.utc).isoformat(timespec="seconds")
    load = machine_record(os.getloadavg())
    rounds = []
    with busy_loops(args.busy):
        for k in range(args.rounds):
            rounds.append({})
            for name in chosen:
                rounds[-1][name] = run_variant(*VARIANTS[name], watch_on=not args.no_watch)
                print(f"round {k + 1} {name}: {json.dumps(rounds[-1][name])}", flush=True)
    text = report(rounds, chosen, args, started, load)
    print(text)
    RESULTS_DIR.mkdir(exist_ok=True)
    (RESULTS_DIR / f"{args.name}.md").write_text(text)
    record = {"started": started, "machine": load, "command": command_line(), "rounds": rounds}
    (RESULTS_DIR / f"{args.name}.json").write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
