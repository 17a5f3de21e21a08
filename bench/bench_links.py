"""What the link reports (afm_ros.links) cost a node, and how long a client waits for a new
subscription to be known and matched by the driver, against when its own graph shows it.

1. One look at a node's link state (link_state: each publisher's matched count and the
   subscriptions its process knows), on a node with TOPICS publishers and two subscriptions
   each, in one process: median and 95th percentile, and the share of one core at the
   reporting period (links.POLL_PERIOD_S).
2. The driver node (sim) in its own process; a client creates a new subscription to
   /afm/scan_line, ROUNDS times: the time until its own graph lists it (what the wait used to
   go by, then slept 0.5 s) and until `wait_until_subscribed` returns (the driver's report
   names it and its matched count covers it).

Run: `scripts/with_env.sh python bench/bench_links.py [--rounds 20]` (~1 min).
Results: bench/results/links.md and links.json. On this machine only.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import command_line, machine_record  # noqa: E402

from afm_ros import links  # noqa: E402
from afm_ros.exposure import isolate_run  # noqa: E402

RESULTS_DIR = Path(__file__).resolve().parent / "results"
TOPICS = 10  # about the driver's publishers
LOOKS = 400


def poll_cost() -> dict:
    import rclpy
    from rclpy.context import Context
    from std_msgs.msg import String

    from afm_ros.qos_profiles import STREAM, STREAM_OFFERED

    context = Context()
    rclpy.init(context=context)
    try:
        publisher = rclpy.create_node("afm_bench_links_publisher", context=context)
        listener = rclpy.create_node("afm_bench_links_listener", context=context)
        for k in range(TOPICS):
            publisher.create_publisher(String, f"/afm_bench_links/t{k}", STREAM_OFFERED)
            for qos in (STREAM, STREAM_OFFERED):
                listener.create_subscription(String, f"/afm_bench_links/t{k}", print, qos)
        time.sleep(1.0)  # discovery within the process
        state = links.link_state(publisher)
        assert all(len(e["known"]) == 2 for e in state.values()), state
        times = []
        for _ in range(LOOKS):
            started = time.perf_counter()
            links.link_state(publisher)
            times.append(time.perf_counter() - started)
    finally:
        rclpy.shutdown(context=context)
    times.sort()
    median, p95 = statistics.median(times), times[int(0.95 * len(times))]
    return {
        "topics": TOPICS,
        "looks": LOOKS,
        "median_ms": round(median * 1e3, 3),
        "p95_ms": round(p95 * 1e3, 3),
        "core_share_percent": round(100 * median / links.POLL_PERIOD_S, 3),
    }


def wait_times(rounds: int) -> dict:
    from rclpy.qos import qos_profile_sensor_data

    from afm_bringup.commander import AfmCommander
    from afm_msgs.msg import ScanLine
    from afm_ros.topics import SCAN_LINE

    driver = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "afm_driver.driver_node",
            "--ros-args",
            "-p",
            "real_time_factor:=0.0",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    graph, waited = [], []
    try:
        with AfmCommander("afm_bench_links", server_timeout=60.0) as afm:
            deadline = time.monotonic() + 60
            while "/afm_driver" not in afm.link_reports():
                if time.monotonic() > deadline:
                    raise RuntimeError("the driver sent no link report in 60 s")
                time.sleep(0.05)
            for _ in range(rounds):
                started = time.monotonic()
                sub = afm.node.create_subscription(
                    ScanLine, SCAN_LINE, lambda _m: None, qos_profile_sensor_data
                )
                while not any(
                    s.node_name == "afm_bench_links"
                    for s in afm.node.get_subscriptions_info_by_topic(SCAN_LINE)
                ):
                    time.sleep(0.002)
                graph.append(time.monotonic() - started)
                afm.wait_until_subscribed([SCAN_LINE], "afm_bench_links", timeout=30.0)
                waited.append(time.monotonic() - started)
                afm.node.destroy_subscription(sub)
                time.sleep(0.3)  # the driver forgets it before the next
    finally:
        driver.terminate()
        driver.wait(timeout=15)

    def summary(values):
        return {
            "median_ms": round(statistics.median(values) * 1e3, 1),
            "max_ms": round(max(values) * 1e3, 1),
        }

    return {"rounds": rounds, "graph_lists_it": summary(graph), "wait_returns": summary(waited)}


def report(result: dict, started: str, machine: dict) -> str:
    cost, wait = result["poll_cost"], result["wait"]
    return "\n".join(
        [
            "# Link reports: their cost to a node, and the wait for a new subscription",
            "",
            f"Measured {started} on {machine['cpu_count']} CPUs ({machine['cpu_model']}), "
            f"Python {machine['python']}, load average {machine['load_average_at_start'][0]:.1f}"
            " at the start.",
            "",
            f"Command: `{command_line()}`",
            "",
            f"One look at the link state of a node with {cost['topics']} publishers, two "
            f"subscriptions each ({cost['looks']} looks): median {cost['median_ms']} ms, 95th "
            f"percentile {cost['p95_ms']} ms; at one look every {links.POLL_PERIOD_S} s, "
            f"{cost['core_share_percent']} % of one core per node.",
            "",
            f"A new subscription to /afm/scan_line beside the driver node, {wait['rounds']} "
            "rounds, from its creation:",
            "",
            "| until | median | max |",
            "|---|---|---|",
            f"| the client's graph lists it | {wait['graph_lists_it']['median_ms']} ms | "
            f"{wait['graph_lists_it']['max_ms']} ms |",
            f"| `wait_until_subscribed` returns (the driver knows and matched it) | "
            f"{wait['wait_returns']['median_ms']} ms | {wait['wait_returns']['max_ms']} ms |",
            "",
            "Before the link reports the wait returned 0.5 s after the graph listed the "
            "subscription, whether or not the driver had discovered it.",
            "",
            f"Peak memory of the benchmark process: {result['peak_mib']} MiB.",
            "",
        ]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=20)
    args = parser.parse_args()
    isolate_run()
    started = datetime.now(timezone.utc).isoformat(timespec="seconds")
    machine = machine_record(os.getloadavg())
    result = {"poll_cost": poll_cost(), "wait": wait_times(args.rounds)}
    result["peak_mib"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    text = report(result, started, machine)
    print(text)
    RESULTS_DIR.mkdir(exist_ok=True)
    (RESULTS_DIR / "links.md").write_text(text)
    record = {"started": started, "machine": machine, "command": command_line(), **result}
    (RESULTS_DIR / "links.json").write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
