"""`make demo`: the graph on the simulated instrument, end to end, with a report.

What the graph can do so far: start every node as its own process, acquire a 0/90 deg scan
pair and a frame-down scan through the driver's action, record all of it to MCAP, evaluate
the recording offline against the simulator's ground truth, replay it into a second
recording and check that every payload came back byte for byte. Later work (imaging,
localization, planning, pushing) extends this script.
"""
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from rclpy.qos import QoSProfile

from afm_bringup import topics
from afm_bringup.commander import AfmCommander
from afm_bringup.launcher import GRAPH, Graph
from afm_bringup.qos_profiles import LATCHED
from afm_bringup.units import nm
from afm_core.evaluation import compare_payloads, find_particles, match_to_truth
from afm_core.recording import RecordingReader
from afm_core.report import save_height_maps, table, write_html
from afm_msgs.msg import RasterScan

SCAN_ORIGIN = (54.3e-6, 54.3e-6)   # m: the simulated sample's particles lie around (55 um, 55 um)
SCAN_SIZE = (1.8e-6, 1.8e-6)
SCAN_PIXELS = (256, 256)
MEMORY_LIMIT = 2 * 2**30           # bytes, the whole graph's peak resident memory
# m: images are in commanded scanner coordinates, which hysteresis residue, creep, coupling,
# line deflection and drift put tens of nm off the truth; a particle this close is the same one
MATCH_DISTANCE = 300e-9


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


def acquire(run_dir: Path, log) -> tuple[dict, dict]:
    """Start the graph with a recorder, take the scans, stop everything. Returns
    (exit codes, peak memory per process)."""
    graph = Graph(run_dir / "logs")
    graph.start("recorder", {"output": str(run_dir / "session.mcap")})
    for name in GRAPH:
        graph.start(name)
    log(f"graph started: {', '.join(graph.processes)} (logs in {run_dir / 'logs'})")
    memory = {}
    try:
        with AfmCommander(server_timeout=60.0) as afm:
            afm.clients["scan_image"].wait_for_server(timeout_sec=60.0)
            afm.wait_until_recorded([topics.SCAN, topics.TIP_COMMAND, topics.GROUND_TRUTH])
            maps_seen = []
            afm.node.create_subscription(RasterScan, topics.CORRECTED_MAP, lambda m: maps_seen.append(m.pair_id),
                                         QoSProfile(depth=10, reliability=LATCHED.reliability,
                                                    durability=LATCHED.durability))
            for angle, frame_up, pair in ((0.0, True, "pair-0-90"), (90.0, True, "pair-0-90"),
                                          (0.0, False, "pair-up-down")):
                scan = afm.scan(SCAN_ORIGIN, SCAN_SIZE, SCAN_PIXELS, angle_deg=angle, frame_up=frame_up,
                                line_rate=2.0, pair_id=pair)
                log(f"scan {scan.scan_id}: {angle:.0f} deg, frame-{'up' if frame_up else 'down'}, "
                    f"{SCAN_PIXELS[0]}x{SCAN_PIXELS[1]} px over {nm(SCAN_SIZE[0])}")
            deadline = time.monotonic() + 120.0
            while "pair-0-90" not in maps_seen and time.monotonic() < deadline:
                time.sleep(0.2)       # the imaging node corrects the 0/90 pair
            log("imaging node published the drift-corrected map" if "pair-0-90" in maps_seen
                else "imaging node published no corrected map within 120 s")
        time.sleep(1.0)   # the recorder drains its queues
        dead = graph.dead()
        if dead:
            raise RuntimeError(f"nodes died during the demo: {dead}")
        memory = {name: peak_rss_bytes(p.pid) for name, p in graph.processes.items()}
    finally:
        codes = graph.stop_all()
    return codes, memory


def replay_into_new_recording(run_dir: Path, log) -> dict:
    graph = Graph(run_dir / "logs")
    graph.start("recorder", {"output": str(run_dir / "replayed.mcap"), "all_topics": "true",
                             "discovery_period": "0.1"}, alias="replay_recorder")
    replay = graph.start("replay", {"input": str(run_dir / "session.mcap"), "rate": "4.0",
                                    "wait_for_subscribers": "1", "start_delay": "0.2",
                                    "publish_clock": "false"})
    replay.wait(timeout=300)
    time.sleep(1.0)
    codes = graph.stop_all()
    log(f"replayed session.mcap at 4x into replayed.mcap (exit codes {codes})")
    return codes


def evaluate(run_dir: Path) -> dict:
    """Offline: scans against ground truth, and replay against the original."""
    with RecordingReader(run_dir / "session.mcap") as reader:
        topics = {t: i.message_count for t, i in reader.topics().items()}
        scans = reader.arrays("/afm/scan")
        truth = reader.arrays("/afm/ground_truth")
        duration = reader.duration_s
    objects = truth["objects"][-1]
    truth_xy = np.array([[o["position.x"], o["position.y"]] for o in objects])
    truth_r = np.array([o["radius"] for o in objects])
    views = []
    for i in range(len(scans["scan_id"])):
        found = find_particles(scans["height"][i], scans["pixel_size_x"][i], scans["pixel_size_y"][i],
                               scans["origin.x"][i], scans["origin.y"][i])
        pairs = match_to_truth(found, truth_xy, max_distance=MATCH_DISTANCE)
        views.append({
            "scan_id": int(scans["scan_id"][i]), "angle": float(scans["scan_angle_deg"][i]),
            "frame_up": bool(scans["slow_scan_up"][i]), "found": len(found), "matched": len(pairs),
            "centre_error_rms": float(np.sqrt(np.mean([d**2 for _, _, d in pairs]))) if pairs else float("nan"),
            "peak_height_mean": float(np.mean([v.height for _, v, _ in pairs])) if pairs else float("nan"),
            "apparent_radius_mean": float(np.mean([v.apparent_radius for _, v, _ in pairs])) if pairs else float("nan"),
        })
    with RecordingReader(run_dir / "session.mcap") as a, RecordingReader(run_dir / "replayed.mcap") as b:
        replay = compare_payloads(((c.topic, m.data) for _, c, m in a.raw_messages()),
                                  ((c.topic, m.data) for _, c, m in b.raw_messages(
                                      [t for t in b.topics() if t in topics])))
    landmarks = []
    if "/afm/landmarks" in topics:
        with RecordingReader(run_dir / "session.mcap") as reader:
            latest = reader.arrays("/afm/landmarks")["landmarks"][-1]
        for mark in latest:
            distance = float(np.min(np.hypot(truth_xy[:, 0] - mark["position.x"], truth_xy[:, 1] - mark["position.y"])))
            landmarks.append({"id": int(mark["id"]), "x": float(mark["position.x"]), "y": float(mark["position.y"]),
                              "sigma_x": float(np.sqrt(mark["covariance"][0])),
                              "sigma_y": float(np.sqrt(mark["covariance"][3])),
                              "height": float(mark["height"]), "nearest_truth": distance})
    return {"topics": topics, "duration_s": duration, "scans": views, "replay": replay, "landmarks": landmarks,
            "truth_xy": truth_xy.tolist(), "truth_radius": truth_r.tolist(), "scan_arrays": scans}


def write_report(run_dir: Path, result: dict, memory: dict, codes: dict, elapsed: float) -> Path:
    scans = result.pop("scan_arrays")
    images = []
    for i in range(len(scans["scan_id"])):
        x0, y0 = scans["origin.x"][i], scans["origin.y"][i]
        h = scans["height"][i]
        extent = (x0, x0 + h.shape[1] * scans["pixel_size_x"][i], y0, y0 + h.shape[0] * scans["pixel_size_y"][i])
        title = (f"scan {scans['scan_id'][i]}: {scans['scan_angle_deg'][i]:.0f} deg, "
                 f"frame-{'up' if scans['slow_scan_up'][i] else 'down'}")
        images.append((title, h, extent))
    save_height_maps(run_dir / "scans.png", images, markers=result["truth_xy"])
    total_memory = sum(memory.values())
    replay_ok = all(v["identical"] for v in result["replay"].values())
    sections = [
        ("Summary", table(["check", "value"], [
            ["nodes started and stopped cleanly", "yes" if all(c == 0 for c in codes.values()) else f"no: {codes}"],
            ["recording", f"session.mcap, {sum(result['topics'].values())} messages, {result['duration_s']:.1f} s"],
            ["replay reproduced every payload", "yes" if replay_ok else "NO"],
            ["graph peak memory (sum of node peaks)", f"{total_memory / 2**20:.0f} MiB "
             f"(limit {MEMORY_LIMIT / 2**30:.0f} GiB)"],
            ["demo wall time", f"{elapsed:.1f} s"],
        ])),
        ("Scans (true particle centres marked +)", "<img src='scans.png' alt='height maps'>"),
        ("Particles in each scan against ground truth", table(
            ["scan", "angle", "slow axis", "found", "matched", "centre error RMS", "peak height", "apparent radius"],
            [[v["scan_id"], f"{v['angle']:.0f} deg", "up" if v["frame_up"] else "down", v["found"], v["matched"],
              nm(v["centre_error_rms"]), nm(v["peak_height_mean"]), nm(v["apparent_radius_mean"])]
             for v in result["scans"]]) +
         f"<p>True radii: {', '.join(nm(r) for r in result['truth_radius'])}. The apparent radius at half "
         "height exceeds the true one by the tip's broadening. Images are in commanded scanner coordinates: "
         "the centre errors are the simulated instrument's positioning errors (hysteresis residue after the "
         "controller's feed-forward, creep, x/y coupling, scan-line rotation, thermal drift), which drift "
         "compensation and landmark localization are there to remove.</p>"),
        ("Landmarks of the imaging node's last map (drift-corrected 0/90 pair)", table(
            ["id", "x", "y", "sigma x", "sigma y", "height", "distance to the nearest true centre"],
            [[m["id"], nm(m["x"]), nm(m["y"]), nm(m["sigma_x"]), nm(m["sigma_y"]), nm(m["height"]),
              nm(m["nearest_truth"])] for m in result["landmarks"]]) +
         "<p>The distances include the scanner's positioning errors, which drift compensation does not remove "
         "(calibration and localization do).</p>"),
        ("Recorded topics", table(["topic", "messages"], [[t, n] for t, n in result["topics"].items()])),
        ("Replay check (original vs replayed recording)", table(
            ["topic", "original", "replayed", "identical payloads"],
            [[t, v["count_a"], v["count_b"], "yes" if v["identical"] else "NO"] for t, v in result["replay"].items()])),
        ("Peak resident memory per process", table(
            ["process", "peak RSS"], [[n, f"{m / 2**20:.0f} MiB"] for n, m in memory.items()])),
    ]
    summary = {**result, "memory_bytes": memory, "exit_codes": codes, "elapsed_s": elapsed}
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=float))
    return write_html(run_dir / "report.html", "AFM nano-manipulation demo", sections)


def run_demo(output_root: Path) -> int:
    started = time.monotonic()
    run_dir = new_run_dir(output_root)

    def log(text):
        print(f"[demo {time.monotonic() - started:6.1f} s] {text}", flush=True)

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    codes, memory = acquire(run_dir, log)
    codes.update(replay_into_new_recording(run_dir, log))
    result = evaluate(run_dir)
    report = write_report(run_dir, result, memory, codes, time.monotonic() - started)
    failures = []
    if any(code != 0 for code in codes.values()):
        failures.append(f"processes exited with errors: {codes}")
    if not all(v["identical"] for v in result["replay"].values()):
        failures.append("the replayed recording differs from the original")
    if sum(memory.values()) > MEMORY_LIMIT:
        failures.append(f"graph peak memory {sum(memory.values()) / 2**20:.0f} MiB exceeds 2 GiB")
    if any(v["matched"] == 0 for v in result["scans"]):
        failures.append("a scan shows none of the true particles")
    if len(result["landmarks"]) != len(result["truth_xy"]):
        failures.append(f"the imaging node found {len(result['landmarks'])} landmarks, the sample has "
                        f"{len(result['truth_xy'])} particles")
    log(f"report: {report}")
    for failure in failures:
        print(f"demo FAILED: {failure}", file=sys.stderr)
    return 1 if failures else 0
