"""What a node's executor costs and how late it runs callbacks while its threads are busy:
rclpy 7.1's MultiThreadedExecutor against the queue-aware one every node now spins
(afm_ros.executor), on one workload, in one run.

Workloads (a node shaped like the teleop node): 4 pool threads, some of them running callbacks
that each wait without the GIL (an action round trip to another server), one after the other:
3 of the 4 in 50 ms waits, and all 4 in 200 ms waits (the pool saturated, as when every thread
waits on a slow driver); meanwhile another process publishes a command at COMMAND_HZ (the
operator's Twist) and a TIMER_HZ timer ticks (the lease renewal). Per executor, over SECONDS:
- commands' callback delay after the middleware received them (message info), median, p95, max;
- passes of the executor's wait loop per second (each a Python loop over the node's entities
  and the executor's task list with the GIL held; the wait itself releases it), and the
  spinning thread's CPU per second (the wait's own CPU in rcl included);
- the most copies of one callback queued in the thread pool at once (rclpy 7.1 queues a
  waiting callback again at every wake-up);
- the process's peak memory.

Run: `scripts/with_env.sh python bench/bench_executor.py [--seconds 10] [--repeats 3]`
(~2 min). Results: bench/results/executor.md and executor.json. On this machine only; compare
the two executors within one run.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import textwrap
from datetime import datetime, timezone
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import command_line, machine_record  # noqa: E402

from afm_ros.executor import ENVIRONMENT, STOCK  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RESULTS_DIR = ROOT / "bench" / "results"
# name: (pool threads, threads in waits, one wait in s)
WORKLOADS = {"3 of 4 threads in 50 ms waits": (4, 3, 0.05), "4 of 4 in 200 ms waits": (4, 4, 0.2)}
COMMAND_HZ, TIMER_HZ = 50.0, 20.0
TOPIC = "/afm_bench_executor/command"

NODE = """
    import collections, json, os, statistics, sys, threading, time
    import resource
    import rclpy
    from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
    from std_msgs.msg import Empty
    from afm_ros.executor import multi_threaded

    THREADS, WAITERS, WAIT_S = {threads}, {waiters}, {wait_s}
    TIMER_HZ, SECONDS = {timer_hz}, {seconds}
    rclpy.init()
    node = rclpy.create_node("afm_bench_executor")
    executor = multi_threaded(THREADS)
    executor.add_node(node)
    delays, stop = [], threading.Event()

    def on_command(msg, info):
        received = info["received_timestamp"] * 1e-9
        delays.append(time.time() - received)

    def wait_like_a_round_trip():
        time.sleep(WAIT_S)
        if not stop.is_set():
            executor.create_task(wait_like_a_round_trip)

    node.create_subscription(
        Empty, "{topic}", on_command, 10, callback_group=MutuallyExclusiveCallbackGroup()
    )
    node.create_timer(1.0 / TIMER_HZ, lambda: None, callback_group=ReentrantCallbackGroup())
    queued, most = collections.Counter(), [0]
    submit = executor._executor.submit

    def counting(fn, *args):
        key = id(args[0] if args else fn)
        queued[key] += 1
        most[0] = max(most[0], queued[key])

        def start():
            queued[key] -= 1
            return fn(*args)

        return submit(start)

    executor._executor.submit = counting
    for _ in range(WAITERS):
        executor.create_task(wait_like_a_round_trip)
    passes, wait = [0], executor.wait_for_ready_callbacks

    def counted_wait(*args, **kwargs):
        passes[0] += 1
        return wait(*args, **kwargs)

    executor.wait_for_ready_callbacks = counted_wait
    print("ready", flush=True)
    started, cpu = time.monotonic(), time.thread_time()
    while time.monotonic() - started < SECONDS:
        executor.spin_once(timeout_sec=0.1)
    elapsed, cpu = time.monotonic() - started, time.thread_time() - cpu
    stop.set()
    delays = sorted(delays) or [float("nan")]
    q = lambda p: delays[min(len(delays) - 1, int(p * len(delays)))] * 1e3
    print(json.dumps({{
        "commands": len(delays),
        "delay_ms_median": round(q(0.5), 2),
        "delay_ms_p95": round(q(0.95), 2),
        "delay_ms_max": round(delays[-1] * 1e3, 2),
        "passes_per_s": round(passes[0] / elapsed),
        "spin_cpu_per_s": round(cpu / elapsed, 3),
        "most_copies_queued": most[0],
        "peak_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
    }}), flush=True)
    executor.shutdown(timeout_sec=1.0)
    rclpy.shutdown()
"""

PUBLISHER = """
    import time
    import rclpy
    from std_msgs.msg import Empty
    rclpy.init()
    node = rclpy.create_node("afm_bench_executor_operator")
    pub = node.create_publisher(Empty, "{topic}", 10)
    period = 1.0 / {hz}
    next_at = time.monotonic()
    while True:
        next_at += period
        time.sleep(max(0.0, next_at - time.monotonic()))
        pub.publish(Empty())
"""


def run_once(choice: str, seconds: float, workload: tuple[int, int, float]) -> dict:
    threads, waiters, wait_s = workload
    env = {k: v for k, v in os.environ.items() if k != ENVIRONMENT}
    if choice:
        env[ENVIRONMENT] = choice
    source = NODE.format(
        threads=threads,
        waiters=waiters,
        wait_s=wait_s,
        timer_hz=TIMER_HZ,
        seconds=seconds,
        topic=TOPIC,
    )
    operator = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(PUBLISHER.format(topic=TOPIC, hz=COMMAND_HZ))],
        env=env,
    )
    try:
        done = subprocess.run(
            [sys.executable, "-c", textwrap.dedent(source)],
            capture_output=True,
            text=True,
            timeout=seconds + 120,
            env=env,
        )
    finally:
        operator.kill()
        operator.wait()
    lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
    if not lines:
        raise RuntimeError(f"exit {done.returncode}: {done.stdout[-1500:]} {done.stderr[-1500:]}")
    return {**json.loads(lines[-1]), "load_average": round(os.getloadavg()[0], 2)}


def report(runs: dict, args, started: str, machine: dict) -> str:
    lines = [
        "# A node's executor while its threads are busy: rclpy 7.1's and the queue-aware one",
        "",
        f"Measured {started} on {machine['cpu_count']} CPUs ({machine['cpu_model']}), "
        f"Python {machine['python']}, load average {machine['load_average_at_start'][0]:.1f} "
        f"at the start; {args.repeats} runs of {args.seconds:.0f} s per executor, alternating.",
        "",
        f"Command: `{command_line()}`",
        "",
        "Workloads: pool threads held by callbacks that wait without the GIL, one after "
        f"another; commands from another process at {COMMAND_HZ:.0f} Hz; a {TIMER_HZ:.0f} Hz "
        "timer.",
        "",
        "| workload | executor | run | commands | delay median / p95 / max "
        "| wait-loop passes per s | spinning thread's CPU per s "
        "| most copies of one callback queued | peak memory | load |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for key, results in runs.items():
        workload, name = key.split(" | ")
        for k, r in enumerate(results):
            lines.append(
                f"| {workload} | {name} | {k + 1} | {r['commands']} | {r['delay_ms_median']} / "
                f"{r['delay_ms_p95']} / {r['delay_ms_max']} ms | {r['passes_per_s']} | "
                f"{r['spin_cpu_per_s']:.3f} s | {r['most_copies_queued']} | {r['peak_mib']} MiB "
                f"| {r['load_average']} |"
            )
    lines += [
        "",
        "Delay: from the middleware's reception of a command to its callback's start. The "
        "spinning thread holds the GIL while it loops, so its passes are time the callbacks "
        "waiting for the GIL do not run.",
        "",
    ]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    started = datetime.now(timezone.utc).isoformat(timespec="seconds")
    machine = machine_record(os.getloadavg())
    executors = {"rclpy 7.1 MultiThreadedExecutor": STOCK, "queue-aware (now)": ""}
    runs = {f"{w} | {name}": [] for w in WORKLOADS for name in executors}
    for k in range(args.repeats):
        for workload, shape in WORKLOADS.items():
            for name, choice in executors.items():
                key = f"{workload} | {name}"
                runs[key].append(run_once(choice, args.seconds, shape))
                print(f"run {k + 1} {key}: {json.dumps(runs[key][-1])}", flush=True)
    text = report(runs, args, started, machine)
    print(text)
    RESULTS_DIR.mkdir(exist_ok=True)
    (RESULTS_DIR / "executor.md").write_text(text)
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    record = {
        "started": started,
        "machine": machine,
        "command": command_line(),
        "runs": runs,
        "peak_child_mib": round(peak),
    }
    (RESULTS_DIR / "executor.json").write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
