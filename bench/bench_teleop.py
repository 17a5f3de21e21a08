"""Teleoperation timing on the simulated instrument: command-to-motion latency and the
dead-man stop delay (issue 33).

What is measured
----------------
The driver (default physics, seed 2, the given real_time_factor) and the teleop node (its
defaults: 20 Hz segments, 1 um/s, dead-man 0.5 s) run as separate processes; this script is
the operator. It takes the tip, then for each cycle publishes a Twist of 1 um/s on
/afm/teleop/cmd_vel at 20 Hz for `--hold` s (alternately +x and -x, so the tip stays put on
average), and stops publishing. From the ground truth the driver publishes after every goal
(wall time of arrival here):
- latency: first Twist published -> first ground truth whose commanded position moved. It
  includes waiting for the next segment (<= 50 ms), the goal round trip and, in real time
  (factor 1), the first segment's own duration (the truth is published when a goal ends);
- stop delay: last Twist published -> last ground truth that moved. The closed form is the
  dead-man timeout (0.5 s: no segment runs past it) plus the same delivery.

Run: `scripts/with_env.sh python bench/bench_teleop.py [--cycles 20] [--real-time-factor 1]`
(~2.5 s per cycle). Results: bench/results/teleop.md and teleop.json (appended per run).
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import resource
import sys
import tempfile
import threading
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from afm_ros.exposure import isolate_run  # noqa: E402

isolate_run()  # a domain no other run uses

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import command_line, machine_record  # noqa: E402

from afm_bringup.demo import peak_rss_bytes  # noqa: E402

RESULTS_DIR = Path(__file__).resolve().parent / "results"
SPEED = 1e-6  # m/s, the teleop node's default limit
LATE_STOP = 0.8  # s: the dead-man's 0.5 s plus the graph test's margin for delivery
RATE = 20.0  # Hz of the Twists, what Foxglove's Teleop panel publishes at by default


def measure(cycles: int, hold: float, factor: float) -> dict:
    import rclpy
    from geometry_msgs.msg import Twist
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from std_srvs.srv import SetBool

    from afm_bringup.launcher import Graph
    from afm_msgs.msg import GroundTruth
    from afm_ros import topics
    from afm_ros.qos_profiles import LATCHED

    graph = Graph(tempfile.mkdtemp(prefix="bench-teleop-"))
    driver = graph.start("driver", {"seed": "2", "real_time_factor": str(factor)})
    teleop = graph.start("teleop")
    context = Context()
    rclpy.init(context=context)
    node = rclpy.create_node("bench_teleop", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    threading.Thread(target=executor.spin, daemon=True).start()
    truths: list[tuple[float, tuple[float, float]]] = []
    node.create_subscription(
        GroundTruth,
        topics.GROUND_TRUTH,
        lambda m: truths.append(
            (time.monotonic(), (m.commanded_position.x, m.commanded_position.y))
        ),
        LATCHED,
    )
    twist_pub = node.create_publisher(Twist, topics.TELEOP_CMD_VEL, 10)
    enable = node.create_client(SetBool, topics.SERVICE_TELEOP_ENABLE)
    try:
        if not enable.wait_for_service(timeout_sec=60):
            raise RuntimeError("the teleop node did not come up")
        future = enable.call_async(SetBool.Request(data=True))
        while not future.done():
            time.sleep(0.05)
        if not future.result().success:
            raise RuntimeError(f"could not take the tip: {future.result().message}")
        # Cycle 1 once compared against no position at all (the latched truth had not come),
        # so the start-up's late delivery counted as motion: wait for where the tip stands.
        deadline = time.monotonic() + 30.0
        while not truths and time.monotonic() < deadline:
            time.sleep(0.05)
        if not truths:
            raise RuntimeError("no ground truth from the driver within 30 s")
        while twist_pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        # The nodes freeze their start-up heap (afm_ros.node_main); the operator's process
        # does the same, so a full collection here does not delay the arrival stamps.
        gc.collect()
        gc.freeze()
        time.sleep(0.5)
        latencies, stops = [], []
        for cycle in range(cycles):
            msg = Twist()
            msg.linear.x = SPEED if cycle % 2 == 0 else -SPEED
            before = len(truths)
            start = truths[-1][1]
            first = time.monotonic()
            last = first
            while time.monotonic() - first < hold:
                twist_pub.publish(msg)
                last = time.monotonic()
                time.sleep(1.0 / RATE)
            time.sleep(0.5 + 1.0)  # the dead-man timeout and a margin for the last segment
            moved = [t for t, p in truths[before:] if p != start]
            if moved:
                latencies.append(moved[0] - first)
                stops.append(moved[-1] - last)
        peaks = {
            name: peak_rss_bytes(proc.pid) / 2**20
            for name, proc in (("driver", driver), ("teleop", teleop))
        }
        return {"latency_s": latencies, "stop_delay_s": stops, "peak_rss_mib": peaks}
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        graph.stop_all()


def summary(values) -> str:
    a = np.asarray(values) * 1e3
    return (
        f"median {np.median(a):.0f} ms, 95th percentile {np.percentile(a, 95):.0f} ms, "
        f"max {a.max():.0f} ms (n = {a.size})"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=20)
    parser.add_argument("--hold", type=float, default=0.5, help="s of Twists per cycle")
    parser.add_argument("--real-time-factor", type=float, default=1.0)
    args = parser.parse_args()
    load = os.getloadavg()
    result = measure(args.cycles, args.hold, args.real_time_factor)
    own_peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    record = {
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": command_line(),
        "machine": machine_record(load),
        "real_time_factor": args.real_time_factor,
        **result,
    }
    RESULTS_DIR.mkdir(exist_ok=True)
    with open(RESULTS_DIR / "teleop.json", "a") as out:
        out.write(json.dumps(record) + "\n")
    text = (
        f"## {record['date']}: `{record['command']}`\n\n"
        f"Machine: {record['machine']['cpu_count']} CPUs ({record['machine']['cpu_model']}), "
        f"load at start {load[0]:.1f}; driver real_time_factor {args.real_time_factor:g}.\n\n"
        f"- command-to-motion latency: {summary(result['latency_s'])}\n"
        f"- dead-man stop delay (timeout 0.5 s): {summary(result['stop_delay_s'])}\n"
        f"- first cycle after the take: latency {result['latency_s'][0] * 1e3:.0f} ms, "
        f"stop {result['stop_delay_s'][0] * 1e3:.0f} ms; stops later than "
        f"{LATE_STOP:.1f} s: {sum(s > LATE_STOP for s in result['stop_delay_s'])}\n"
        f"- peak memory: driver {result['peak_rss_mib']['driver']:.0f} MiB, teleop "
        f"{result['peak_rss_mib']['teleop']:.0f} MiB, this script {own_peak:.0f} MiB\n\n"
    )
    with open(RESULTS_DIR / "teleop.md", "a") as out:
        out.write(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
