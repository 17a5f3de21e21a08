"""The live viewer's latency and cost: from a driver event to the Foxglove client, and the
viewer process's CPU and memory while a push runs (issue 33).

What is measured
----------------
The graph runs as separate processes on the simulated instrument (driver with the default
physics in real time (real_time_factor 1, what an operator watches live; --real-time-factor 0:
as fast as it can), imaging, localizer, planner, nano_hand, the
simulator's calibration) with the viewer on a free port; a headless Foxglove WebSocket client
(afm_viewer.probe, in this process) subscribes to every channel, as the Foxglove app with the
afm_live layout does.

Latency: this process publishes ForceTrace messages on /afm/force_trace, the driver's topic and
QoS, of SAMPLES samples, at RATE Hz, each stamped with a unique time far
from the instrument's (so none is mistaken for the driver's own); the latency of one is the
wall time its first sample reaches the client minus the wall time just before publish(). Both
ends are in this process, on one clock, so the figure is the whole path a driver event takes:
DDS to the viewer, conversion, the SDK's server, the WebSocket, the client's decoding of the
frame. Measured after a warm-up (events sent until one arrives: DDS discovery) with the graph idle
(mapped, nothing moving) and while the push runs, when the
real driver's traces, tip poses, plans and predicted objects go the same way (during the push
the synthetic traces are sent until it ends).

Cost: the viewer's CPU time (utime + stime from /proc) over the push's wall time, synthetic
traces included (RATE x SAMPLES messages/s, small beside the push's), and its peak resident
memory (VmHWM) at the end.

Run: `scripts/with_env.sh python bench/bench_viewer.py [--events 200]` (~4 min).
Results: bench/results/viewer.json and viewer.md.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import threading
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import command_line, machine_record  # noqa: E402

from afm_bringup.commander import AfmCommander  # noqa: E402
from afm_bringup.demo import peak_rss_bytes  # noqa: E402
from afm_bringup.launcher import Graph, read_port, sim_calibration_file  # noqa: E402
from afm_msgs.msg import ForceTrace, LandmarkArray  # noqa: E402
from afm_ros.qos_profiles import LATCHED, STREAM  # noqa: E402
from afm_viewer.probe import Probe  # noqa: E402
from afm_viewer.server import CHANNELS  # noqa: E402

RESULTS_DIR = Path(__file__).resolve().parent / "results"
# samples per synthetic trace: few, so the probe itself adds little load (each sample is one
# WebSocket message); the first sample's latency does not depend on how many follow
SAMPLES = 20
RATE = 10.0  # Hz of synthetic traces
BENCH_EPOCH = 1_000_000  # s: synthetic stamps start here, ~50 years before any instrument's
ORIGIN, SIZE, PIXELS = (54.3e-6, 54.3e-6), (1.8e-6, 1.8e-6), (128, 128)


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class Events:
    """Synthetic driver events: publish, and the wall time each left, by its stamp (ns)."""

    def __init__(self, node):
        self.pub = node.create_publisher(ForceTrace, "/afm/force_trace", STREAM)
        self.sent: dict[int, float] = {}
        self.count = 0

    def publish(self) -> None:
        self.count += 1
        msg = ForceTrace(task="bench", object_id=-1, sample_rate=1e4)
        msg.header.stamp.sec, msg.header.stamp.nanosec = BENCH_EPOCH + self.count, 0
        msg.header.frame_id = "afm_scanner"
        msg.times = list(np.arange(SAMPLES) / 1e4)
        msg.lateral_torsion = [1e-4] * SAMPLES
        msg.vertical_deflection = [1e-9] * SAMPLES
        msg.normal_spring_constant, msg.lateral_spring_constant = 0.2, 1e-9
        stamp = (BENCH_EPOCH + self.count) * 1_000_000_000
        self.sent[stamp] = time.time()
        self.pub.publish(msg)


def latencies(client: Probe, events: Events, stamps: list[int]) -> list[float]:
    arrived = {m.log_time: m.wall for m in client.messages("/afm/viewer/force")}
    return [arrived[s] - events.sent[s] for s in stamps if s in arrived]


def send_events(events: Events, count: int, stop: threading.Event | None = None) -> list[int]:
    """`count` events at RATE, or, given `stop`, events at RATE until it is set."""
    stamps = []
    while (len(stamps) < count) if stop is None else not stop.is_set():
        events.publish()
        stamps.append((BENCH_EPOCH + events.count) * 1_000_000_000)
        time.sleep(1.0 / RATE)
    return stamps


def summary(values: list[float], sent: int) -> dict:
    ms = np.asarray(values) * 1e3
    return {
        "sent": sent,
        "received": len(values),
        "median_ms": float(np.median(ms)) if len(ms) else None,
        "p95_ms": float(np.percentile(ms, 95)) if len(ms) else None,
        "max_ms": float(ms.max()) if len(ms) else None,
    }


def warm_up(client: Probe, events: Events, timeout: float = 60.0) -> None:
    """Send events until one reaches the client: discovery and matching are done."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        events.publish()
        time.sleep(1.0 / RATE)
        if latencies(client, events, list(events.sent)):
            return
    raise RuntimeError(f"no synthetic force trace reached the client in {timeout:.0f} s")


def run(events_count: int, factor: float, workdir: Path, log) -> dict:
    graph = Graph(workdir / "logs")
    calibrated = {"calibration_file": sim_calibration_file()}
    graph.start("driver", {"seed": "4", "real_time_factor": str(factor), **calibrated})
    graph.start("imaging")
    for name in ("localizer", "planner", "nano_hand"):
        graph.start(name, calibrated)
    port_file = workdir / "viewer.port"
    viewer = graph.start("viewer", {"port": "0", "port_file": str(port_file)})
    try:
        port = read_port(port_file, timeout=60.0)
        if port is None:
            raise RuntimeError(f"the viewer wrote no port (logs in {graph.log_dir})")
        with (
            Probe(f"ws://127.0.0.1:{port}", timeout=30.0) as client,
            AfmCommander(server_timeout=60.0) as afm,
        ):
            client.wait(lambda: len(client.channels) == len(CHANNELS), what="every channel")
            client.subscribe(sorted(CHANNELS))
            events = Events(afm.node)
            maps = []
            afm.node.create_subscription(LandmarkArray, "/afm/landmarks", maps.append, LATCHED)
            afm.wait_until_subscribed(["/afm/scan"], "afm_imaging", timeout=60.0)
            afm.wait_until_subscribed(["/afm/force_trace"], "afm_viewer", timeout=60.0)
            for angle in (0.0, 90.0):
                afm.scan(ORIGIN, SIZE, PIXELS, angle_deg=angle, line_rate=4.0, pair_id="bench")
            deadline = time.monotonic() + 120
            while not (maps and len(maps[-1].landmarks) >= 3) and time.monotonic() < deadline:
                time.sleep(0.1)
            if not maps:
                raise RuntimeError(f"no landmark map (logs in {graph.log_dir})")
            warm_up(client, events)
            idle = send_events(events, events_count)
            time.sleep(1.0)
            idle_latency = latencies(client, events, idle)
            log(f"idle: {summary(idle_latency, len(idle))}")
            particle = min(
                maps[-1].landmarks,
                key=lambda lm: np.hypot(lm.position.x - 55e-6, lm.position.y - 55e-6),
            )
            goal = (particle.position.x, particle.position.y - 300e-9)
            stop = threading.Event()
            busy: list[int] = []
            sender = threading.Thread(
                target=lambda: busy.extend(send_events(events, events_count, stop))
            )
            cpu0, wall0 = cpu_seconds(viewer.pid), time.monotonic()
            received0 = len(client.received)
            sender.start()
            result = afm.push(goal, particle_id=particle.id, tolerance=40e-9, timeout=900)
            push_wall = time.monotonic() - wall0
            cpu = cpu_seconds(viewer.pid) - cpu0
            stop.set()
            sender.join()
            time.sleep(1.0)
            busy_latency = latencies(client, events, busy)
            log(f"during the push: {summary(busy_latency, len(busy))}; {result.message}")
            return {
                "idle": summary(idle_latency, len(idle)),
                "during_push": summary(busy_latency, len(busy)),
                "push": {
                    "real_time_factor": factor,
                    "message": result.message,
                    "steps": int(result.steps),
                    "wall_seconds": push_wall,
                    "viewer_cpu_seconds": cpu,
                    "viewer_cpu_share": cpu / push_wall,
                    "messages_to_client": len(client.received) - received0,
                },
                "viewer_peak_rss_mib": peak_rss_bytes(viewer.pid) / 2**20,
            }
    finally:
        graph.stop_all()


def markdown(out: dict) -> str:
    r = out["results"]
    rows = [
        f"| {name} | {s['sent']} | {s['received']} | {s['median_ms']:.1f} | {s['p95_ms']:.1f} "
        f"| {s['max_ms']:.1f} |"
        for name, s in (("graph idle", r["idle"]), ("during a push", r["during_push"]))
    ]
    p = r["push"]
    return "\n".join(
        [
            "# The live viewer: latency and cost (issue 33)",
            "",
            f"Date: {out['date']}. Machine: {out['machine']['cpu_count']} x "
            f"{out['machine']['cpu_model']}, load {out['machine']['load_average_at_start']} at "
            f"start. Command: `{out['command']}`.",
            "",
            "End to end, a ForceTrace published on /afm/force_trace (the driver's topic and QoS, "
            f"{SAMPLES} samples, {RATE:g} Hz) to its first sample at a headless Foxglove "
            "client subscribed to every channel (bench/bench_viewer.py says how):",
            "",
            "| when | sent | received | median ms | 95th percentile ms | max ms |",
            "| --- | ---: | ---: | ---: | ---: | ---: |",
            *rows,
            "",
            f"While the push ran ({p['steps']} strokes in contact, "
            f"{p['wall_seconds']:.1f} s wall, simulator at real_time_factor "
            f"{p['real_time_factor']:g}): the viewer used {p['viewer_cpu_seconds']:.2f} CPU s "
            f"({100 * p['viewer_cpu_share']:.0f} % of one core) and sent "
            f"{p['messages_to_client']} messages to the client; its peak resident memory was "
            f"{r['viewer_peak_rss_mib']:.0f} MiB.",
            "",
        ]
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--events", type=int, default=200, help="synthetic traces when idle")
    parser.add_argument(
        "--real-time-factor", type=float, default=1.0, help="the simulator's (0: fastest)"
    )
    args = parser.parse_args()
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="bench_viewer-") as tmp:
        results = run(
            args.events, args.real_time_factor, Path(tmp), lambda m: print(m, flush=True)
        )
    out = {
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": machine_record(round(load, 2)),
        "command": command_line(),
        "results": results,
    }
    RESULTS_DIR.mkdir(exist_ok=True)
    (RESULTS_DIR / "viewer.json").write_text(json.dumps(out, indent=1) + "\n")
    (RESULTS_DIR / "viewer.md").write_text(markdown(out))
    print(markdown(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
