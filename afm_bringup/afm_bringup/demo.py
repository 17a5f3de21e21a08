"""`make demo`: the graph on the simulated instrument, end to end, with a report.

Every node runs as its own process with a recorder, the driver on the demo's sample (eight
spheres and a rod, demo_assembly.DEMO_SAMPLE): the driver acquires a 0/90 deg scan pair (and
a frame-down scan), the imaging node corrects the drift and maps the particles, the core
places a small pattern (an "L" of six particles, afm_core.planning.plan_pattern) on the map,
and the nano-hand assembles it through its Assemble action in the planner's order, each push
with its default strategy, the closed loop (scan, localize on the particle, push in legs of
zigzag strokes through the driver with local scan lines across the particle between them,
re-planned until it is within tolerance, rescan, verify). Everything is recorded to MCAP; the
recording is replayed into a second recording (checked byte for byte), and the replayed copy
is evaluated offline against the simulator's ground truth into report.html: the pattern
planned, predicted, verified and true, the first push zoomed in, the maps, the tip path with
its covariance ellipses, the errors and the timings.

The driver, localizer, planner and nano-hand use the calibration the calibration experiments
produced on this simulated instrument (afm_localization/config/sim_calibration.yaml,
regenerated with `afm calibrate --backend sim`); the driver's use of it is the wait for creep
before each image.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

from rclpy.qos import QoSProfile

from afm_bringup.commander import AfmCommander
from afm_bringup.demo_assembly import (
    NANO_HAND_OVERRIDES,
    SCAN_ORIGIN,
    SCAN_PIXELS,
    SCAN_SIZE,
    assembly_stage,
    judge_assembly,
    write_sample,
)
from afm_bringup.demo_evaluation import evaluate, judge_run
from afm_bringup.demo_report import write_report
from afm_bringup.launcher import (
    CALIBRATED_NODES,
    GRAPH,
    Graph,
    read_port,
    sim_calibration_file,
    viewer_overrides,
)
from afm_bringup.units import nm
from afm_core.recording import RecordingReader
from afm_msgs.msg import LandmarkArray, RasterScan
from afm_ros import topics
from afm_ros.conversions import msg_to_landmarks
from afm_ros.qos_profiles import LATCHED


def peak_rss_bytes(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def new_run_dir(root: Path) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    for suffix in [""] + [f"-{i}" for i in range(1, 100)]:
        run_dir = root / (stamp + suffix)
        try:
            run_dir.mkdir()
        except FileExistsError:
            continue
        latest = root / "latest"
        if latest.is_symlink() or not latest.exists():
            latest.unlink(missing_ok=True)
            latest.symlink_to(run_dir.name)
        return run_dir
    raise RuntimeError(f"{root}: could not make a new run folder")


def mapped_landmarks(afm: AfmCommander):
    """The imaging node's latest landmark map (core Landmarks)."""
    marks: list = []
    afm.node.create_subscription(
        LandmarkArray, topics.LANDMARKS, lambda m: marks.append(m), LATCHED
    )
    deadline = time.monotonic() + 30.0
    while not marks and time.monotonic() < deadline:
        time.sleep(0.1)
    if not marks:
        raise RuntimeError("no landmarks from the imaging node")
    return msg_to_landmarks(marks[-1])


def acquire(run_dir: Path, log) -> tuple[dict, dict, dict, dict]:
    """Start the graph with a recorder on the demo's sample, map, assemble, stop everything.
    Returns (exit codes, peak memory per process, the assembly's outcome, timings)."""
    graph = Graph(run_dir / "logs")
    graph.start("recorder", {"output": str(run_dir / "session.mcap")})
    calibration = sim_calibration_file()
    port_file = run_dir / "logs" / "viewer.port"
    for name in GRAPH:
        overrides = {"calibration_file": calibration} if name in CALIBRATED_NODES else {}
        if name == "driver":
            overrides["sim_config"] = str(write_sample(run_dir))
        if name == "nano_hand":
            overrides.update(NANO_HAND_OVERRIDES)
        graph.start(name, viewer_overrides(port_file) if name == "viewer" else overrides)
    log(f"graph started: {', '.join(graph.processes)} (logs in {run_dir / 'logs'})")
    port = read_port(port_file)
    if port is not None:
        log(
            f"watch it live: Foxglove, Open connection > Foxglove WebSocket, ws://127.0.0.1:{port}"
        )
    memory, assembly, timings = {}, {}, {}
    try:
        with AfmCommander(server_timeout=60.0) as afm:
            started = time.monotonic()
            afm.clients["scan_image"].wait_for_server(timeout_sec=60.0)
            # the recorder, on the driver's topics (the volatile streams are lost if it is late)
            afm.wait_until_subscribed(
                [
                    topics.SCAN,
                    topics.TIP_COMMAND,
                    topics.GROUND_TRUTH,
                    topics.SCAN_LINE,
                    topics.FORCE_TRACE,
                ]
            )
            for node_name, inputs in (
                ("afm_imaging", [topics.SCAN]),
                ("afm_localizer", [topics.TIP_COMMAND]),
            ):
                afm.wait_until_subscribed(inputs, node_name, timeout=60.0)
            maps_seen = []
            afm.node.create_subscription(
                RasterScan,
                topics.CORRECTED_MAP,
                lambda m: maps_seen.append(m.pair_id),
                QoSProfile(
                    depth=10, reliability=LATCHED.reliability, durability=LATCHED.durability
                ),
            )
            for angle, frame_up, pair in (
                (0.0, True, "pair-0-90"),
                (90.0, True, "pair-0-90"),
                (0.0, False, "pair-up-down"),
            ):
                scan = afm.scan(
                    SCAN_ORIGIN,
                    SCAN_SIZE,
                    SCAN_PIXELS,
                    angle_deg=angle,
                    frame_up=frame_up,
                    line_rate=2.0,
                    pair_id=pair,
                )
                log(
                    f"scan {scan.scan_id}: {angle:.0f} deg, frame-{'up' if frame_up else 'down'}, "
                    f"{SCAN_PIXELS[0]}x{SCAN_PIXELS[1]} px over {nm(SCAN_SIZE[0])}"
                )
            deadline = time.monotonic() + 120.0
            while "pair-0-90" not in maps_seen and time.monotonic() < deadline:
                time.sleep(0.2)  # the imaging node corrects the 0/90 pair
            log(
                "imaging node published the drift-corrected map"
                if "pair-0-90" in maps_seen
                else "imaging node published no corrected map within 120 s"
            )
            timings["scans and drift-corrected map"] = time.monotonic() - started
            assembly = assembly_stage(afm, mapped_landmarks(afm), log, timings)
        time.sleep(1.0)  # the recorder drains its queues
        dead = graph.dead()
        if dead:
            raise RuntimeError(f"nodes died during the demo: {dead}")
        memory = {name: peak_rss_bytes(p.pid) for name, p in graph.processes.items()}
    finally:
        codes = graph.stop_all()
    return codes, memory, assembly, timings


REPLAY_SPEED_UP = 4.0  # the replay takes a quarter of the wall time the session took


def replay_rate(recording: Path) -> float:
    """The replay rate that plays the recording in REPLAY_SPEED_UP times less wall time than
    it was recorded in. Its log times are the instrument's (header stamps), which the
    simulator runs far ahead of wall time (447 s of instrument time in 8.5 s of wall time in
    one demo); the wall time each message arrived is its publish time."""
    with RecordingReader(recording) as reader:
        publish = [m.publish_time for _, _, m in reader.raw_messages()]
        log_span_ns = reader.end_time_ns - reader.start_time_ns
    wall_span_ns = max(publish) - min(publish) if publish else 0
    return REPLAY_SPEED_UP * max(1.0, log_span_ns / wall_span_ns if wall_span_ns else 1.0)


def replay_into_new_recording(run_dir: Path, log) -> dict:
    rate = replay_rate(run_dir / "session.mcap")
    graph = Graph(run_dir / "logs")
    graph.start(
        "recorder",
        {
            "output": str(run_dir / "replayed.mcap"),
            "all_topics": "true",
            "discovery_period": "0.1",
        },
        alias="replay_recorder",
    )
    replay = graph.start(
        "replay",
        {
            "input": str(run_dir / "session.mcap"),
            "rate": str(rate),
            "wait_for_subscribers": "1",
            "start_delay": "0.2",
            "publish_clock": "false",
        },
    )
    replay.wait(timeout=300)
    time.sleep(1.0)
    codes = graph.stop_all()
    log(f"replayed session.mcap at {rate:.0f}x into replayed.mcap (exit codes {codes})")
    return codes


def run_demo(output_root: Path) -> int:
    started = time.monotonic()
    run_dir = new_run_dir(output_root)

    def log(text):
        print(f"[demo {time.monotonic() - started:6.1f} s] {text}", flush=True)

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    codes, memory, assembly, timings = acquire(run_dir, log)
    replay_started = time.monotonic()
    codes.update(replay_into_new_recording(run_dir, log))
    timings["replay into a second recording"] = time.monotonic() - replay_started
    evaluation_started = time.monotonic()
    result = evaluate(run_dir)
    timings["offline evaluation and report"] = time.monotonic() - evaluation_started
    report = write_report(
        run_dir, result, memory, codes, time.monotonic() - started, assembly, timings
    )
    summary = json.loads((run_dir / "summary.json").read_text())
    failures = judge_run(codes, memory, result, summary["push"], summary["push_truth"])
    failures += judge_assembly(assembly, summary["assembly_truth"])
    log(f"report: {report}")
    for failure in failures:
        print(f"demo FAILED: {failure}", file=sys.stderr)
    return 1 if failures else 0
