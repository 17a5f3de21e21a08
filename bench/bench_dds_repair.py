"""How late a reliable command stream arrives beside big messages on a loaded machine, with
Fast DDS's own repair period (3 s) and with the project's (afm_ros.exposure.REPAIR_PERIOD_S).

What is measured
----------------
Two processes on the localhost profile (afm_ros.exposure): one publishes a Twist at 20 Hz
(reliable, depth 10: what the teleop node hears) and, on another topic, a 2 MB message at
10 Hz (a scan's images are that size); the other subscribes to both in one executor. `--busy`
shell loops keep the two CPUs busy, as the other nodes of a graph and other jobs do. Every
Twist carries its sequence number and its wall time of publication; the subscriber counts:
- lost: never delivered (a depth-10 writer had replaced it before it was repaired);
- late: delivered more than the teleop dead-man timeout (0.5 s) after it was published.

A reliable reader hands nothing on after a lost sample until that sample is repaired, and the
writer offers the repair only at its next heartbeat: every 3 s by default. Each round runs
both variants back to back, differing only in the writer's heartbeat period.

Run: `scripts/with_env.sh python bench/bench_dds_repair.py [--rounds 3] [--seconds 20]`
(~1 min per round). Results: bench/results/dds_repair.md and dds_repair.json.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

from afm_ros.exposure import isolate_run  # noqa: E402

isolate_run()  # a domain no other run uses

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import busy_loops, command_line, machine_record  # noqa: E402

from afm_ros import exposure  # noqa: E402

RESULTS_DIR = Path(__file__).resolve().parent / "results"
DEAD_MAN = 0.5  # s, the teleop node's default timeout
RATE = 20.0  # Hz of the commands
# afm launch's graph but the viewer, whose fixed WebSocket port another run may hold
GRAPH_NAMES = ("driver", "imaging", "localizer", "planner", "nano_hand", "teleop", "sim2real")
VARIANTS = {
    "Fast DDS's period (3 s)": exposure.LOCALHOST_PROFILE.replace(exposure.WRITER_TIMES, ""),
    f"the project's period ({exposure.REPAIR_PERIOD_S:g} s)": exposure.LOCALHOST_PROFILE,
}


def publish(seconds: float, big_hz: float, big_bytes: int) -> dict:
    import rclpy
    from geometry_msgs.msg import Twist
    from sensor_msgs.msg import Image

    rclpy.init()
    node = rclpy.create_node("afm_dds_repair_pub")
    commands = node.create_publisher(Twist, "/afm_bench/cmd", 10)
    big = node.create_publisher(Image, "/afm_bench/big", 10)
    while commands.get_subscription_count() == 0 or big.get_subscription_count() == 0:
        time.sleep(0.1)
    time.sleep(2.0)  # both ends matched both ways
    image = Image(height=1, width=big_bytes, encoding="mono8", step=big_bytes)
    image.data = bytes(big_bytes)
    start = time.monotonic()
    sent = bigs = 0
    next_big = start
    while time.monotonic() - start < seconds:
        msg = Twist()
        msg.linear.z, msg.angular.z = float(sent), time.time()
        commands.publish(msg)
        sent += 1
        while time.monotonic() >= next_big:
            big.publish(image)
            bigs += 1
            next_big += 1.0 / big_hz
        time.sleep(1.0 / RATE)
    time.sleep(4.0)  # one default repair period, so nothing is lost by leaving early
    return {"sent": sent, "big_sent": bigs}


def subscribe(seconds: float) -> dict:
    import rclpy
    from geometry_msgs.msg import Twist
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import Image

    rclpy.init()
    node = rclpy.create_node("afm_dds_repair_sub")
    latency: dict[int, float] = {}
    bigs = [0]

    def on_command(msg):
        latency.setdefault(int(msg.linear.z), time.time() - msg.angular.z)

    def on_big(_msg):
        bigs[0] += 1

    node.create_subscription(Twist, "/afm_bench/cmd", on_command, 10)
    node.create_subscription(Image, "/afm_bench/big", on_big, 10)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.1)
    return {"latency": latency, "big_received": bigs[0]}


def run_variant(profile: str, seconds: float, busy: int, big_hz: float, big_bytes: int) -> dict:
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / exposure.PROFILE_NAME  # ours by name: no discovery range added
        path.write_text(profile)
        env = dict(os.environ)
        for name in exposure.PROFILE_VARIABLES:
            env[name] = str(path)
        env.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)
        me = [sys.executable, __file__, "--role"]
        with busy_loops(busy):
            sub = subprocess.Popen(
                [*me, "sub", "--seconds", str(seconds + 30)], env=env, stdout=subprocess.PIPE
            )
            pub = subprocess.run(
                [*me, "pub", "--seconds", str(seconds), "--big-hz", str(big_hz)]
                + ["--big-bytes", str(big_bytes)],
                env=env,
                stdout=subprocess.PIPE,
                check=True,
            )
            received = json.loads(sub.communicate(timeout=seconds + 120)[0].splitlines()[-1])
    sent = json.loads(pub.stdout.splitlines()[-1])
    load = os.getloadavg()[0]  # over the last minute, i.e. this run
    latency = sorted(received["latency"].values())
    return {
        "sent": sent["sent"],
        "lost": sent["sent"] - len(latency),
        "late": sum(t > DEAD_MAN for t in latency),
        "max_latency_s": max(latency) if latency else None,
        "median_latency_s": latency[len(latency) // 2] if latency else None,
        "big_sent": sent["big_sent"],
        "big_received": received["big_received"],
        "load_average": load,
    }


def idle_graph_cpu(profile: str, seconds: float) -> float:
    """CPU seconds the whole graph (afm launch's nodes, idle) spends over `seconds`, after a
    start-up of 40 s: what the shorter heartbeat period costs where nothing happens."""
    import psutil

    from afm_bringup.launcher import Graph

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / exposure.PROFILE_NAME
        path.write_text(profile)
        env = dict(os.environ)
        for name in exposure.PROFILE_VARIABLES:
            env[name] = str(path)
        env.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)
        graph = Graph(Path(folder) / "logs", environment=env)
        try:
            nodes = [psutil.Process(graph.start(name).pid) for name in GRAPH_NAMES]
            time.sleep(40.0)

            def cpu() -> float:
                return sum(sum(p.cpu_times()[:2]) for p in nodes)

            before = cpu()
            time.sleep(seconds)
            return cpu() - before
        finally:
            graph.stop_all()


def report(rounds: list[dict], args, started: str, load) -> str:
    lines = [
        "# A reliable command stream beside big messages: Fast DDS's repair period and ours",
        "",
        f"Measured {started} on {load['cpu_count']} CPUs ({load['cpu_model']}), load average "
        f"{load['load_average_at_start'][0]:.1f} at the start, {args.busy} busy loops beside; "
        f"{args.rounds} rounds of {args.seconds:g} s per variant, a 20 Hz Twist beside "
        f"{args.big_bytes / 1e6:g} MB at {args.big_hz:g} Hz. On this machine's loopback only.",
        "",
        f"Command: `{command_line()}`",
        "",
        "| variant | Twists sent | lost | late (> 0.5 s) | latency: median of the rounds' "
        "medians / max | per round (lost, late; load average) |",
        "|---|---|---|---|---|---|",
    ]
    for name in VARIANTS:
        runs = [r[name] for r in rounds]
        worst = max(r["max_latency_s"] or 0.0 for r in runs)
        median = sorted(r["median_latency_s"] or 0.0 for r in runs)[len(runs) // 2]
        lines.append(
            f"| {name} | {sum(r['sent'] for r in runs)} | {sum(r['lost'] for r in runs)} | "
            f"{sum(r['late'] for r in runs)} | {median * 1e3:.0f} ms / {worst:.2f} s | "
            + ", ".join(f"({r['lost']}, {r['late']}; {r['load_average']:.1f})" for r in runs)
            + " |"
        )
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    lines += [
        "",
        "A command late with none lost waited for CPU (the subscriber's one executor thread "
        "behind 2 MB messages); late ones behind a lost one waited for its repair.",
        "",
    ]
    if rounds and "idle_graph_cpu_s" in rounds[0]:
        lines += [
            f"The cost: CPU seconds of the whole graph ({len(GRAPH_NAMES)} nodes, idle, "
            f"{args.idle_seconds:g} s after a 40 s start), per round in order: "
            + "; ".join(
                f"{name}: " + ", ".join(f"{r['idle_graph_cpu_s'][name]:.1f}" for r in rounds)
                for name in VARIANTS
            )
            + ".",
            "",
        ]
    lines += [
        f"Peak memory of a child process: {peak:.0f} MiB.",
        "",
    ]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--role", choices=("pub", "sub"), help=argparse.SUPPRESS)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=20.0, help="s of commands per run")
    parser.add_argument("--busy", type=int, default=2, help="busy loops beside the two")
    parser.add_argument("--big-hz", type=float, default=10.0)
    parser.add_argument("--big-bytes", type=int, default=2_000_000)
    parser.add_argument(
        "--idle-seconds", type=float, default=30.0, help="s of the idle graph's CPU (0: none)"
    )
    args = parser.parse_args()
    if args.role == "pub":
        print(json.dumps(publish(args.seconds, args.big_hz, args.big_bytes)))
        return
    if args.role == "sub":
        print(json.dumps(subscribe(args.seconds)))
        return
    started = datetime.now(timezone.utc).isoformat(timespec="seconds")
    load = machine_record(os.getloadavg())
    rounds = []
    for k in range(args.rounds):
        rounds.append({})
        for name, profile in VARIANTS.items():
            rounds[-1][name] = run_variant(
                profile, args.seconds, args.busy, args.big_hz, args.big_bytes
            )
            print(f"round {k + 1} {name}: {json.dumps(rounds[-1][name])}", flush=True)
        if args.idle_seconds > 0:
            rounds[-1]["idle_graph_cpu_s"] = {
                name: idle_graph_cpu(profile, args.idle_seconds)
                for name, profile in VARIANTS.items()
            }
            print(f"round {k + 1} idle graph: {rounds[-1]['idle_graph_cpu_s']}", flush=True)
    text = report(rounds, args, started, load)
    print(text)
    RESULTS_DIR.mkdir(exist_ok=True)
    (RESULTS_DIR / "dds_repair.md").write_text(text)
    record = {"started": started, "machine": load, "command": command_line(), "rounds": rounds}
    (RESULTS_DIR / "dds_repair.json").write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
