"""`make demo`: the graph on the simulated instrument, end to end, with a report.

Every node runs as its own process with a recorder: the driver acquires a 0/90 deg scan
pair (and a frame-down scan), the imaging node corrects the drift and maps the particles,
the planner plans the tip's way to the push, and the nano-hand pushes a particle to a goal
through its PushParticle action (localize on the particle, scan, plan the zigzag, push
stroke by stroke through the driver, rescan, verify). Everything is recorded to MCAP; the
recording is replayed into a second recording (checked byte for byte), and the replayed copy
is evaluated offline against the simulator's ground truth into report.html: before/after
maps, the tip path with its covariance ellipses, the particle path, the achieved error and
the timings.

The localizer, planner and nano-hand use the calibration the calibration experiments
produced on this simulated instrument (afm_localization/config/sim_calibration.yaml,
regenerated with `afm calibrate --backend sim`).
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from rclpy.qos import QoSProfile
from std_msgs.msg import Header

from afm_bringup.commander import AfmCommander
from afm_bringup.launcher import GRAPH, Graph
from afm_bringup.units import nm
from afm_core.evaluation import (
    compare_payloads,
    find_particles,
    image_frame_matrix,
    match_to_truth,
)
from afm_core.manipulation import path_blocker
from afm_core.recording import RecordingReader
from afm_core.report import save_height_maps, save_push_figure, table, write_html
from afm_msgs.msg import LandmarkArray, RasterScan
from afm_msgs.srv import PlanPath
from afm_ros import topics
from afm_ros.conversions import FRAME_TASK, mean_cov_to_pose, msg_to_landmarks
from afm_ros.qos_profiles import LATCHED

SCAN_ORIGIN = (54.3e-6, 54.3e-6)  # m: the simulated sample's particles lie around (55 um, 55 um)
SCAN_SIZE = (1.8e-6, 1.8e-6)
SCAN_PIXELS = (256, 256)
MEMORY_LIMIT = 2 * 2**30  # bytes, the whole graph's peak resident memory
# m: images are in commanded scanner coordinates, which hysteresis residue, creep, coupling,
# line deflection and drift put tens of nm off the truth; a particle this close is the same one
MATCH_DISTANCE = 300e-9
PUSH_DISTANCE = 300e-9  # m, from the particle's mapped centre to the goal
PUSH_TOLERANCE = 20e-9  # m
CALIBRATED_NODES = ("localizer", "planner", "nano_hand")
# true displacement per commanded (= map) displacement of the simulated instrument, for the
# evaluation against truth only (afm_core.evaluation.image_frame_matrix)
IMAGE_FRAME = image_frame_matrix()


def calibration_file() -> str:
    from ament_index_python.packages import get_package_share_directory

    return str(
        Path(get_package_share_directory("afm_localization")) / "config" / "sim_calibration.yaml"
    )


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


def choose_push(landmarks) -> tuple[object, np.ndarray]:
    """The mapped particle nearest the map's centre and a goal PUSH_DISTANCE away in the first
    of eight directions whose way is clear of the other particles."""
    centre = np.mean([[m.x, m.y] for m in landmarks], axis=0)
    particle = min(landmarks, key=lambda m: np.hypot(m.x - centre[0], m.y - centre[1]))
    others = [m for m in landmarks if m.id != particle.id]
    start = np.array([particle.x, particle.y])
    for angle in np.radians([270, 0, 90, 180, 315, 45, 135, 225]):
        goal = start + PUSH_DISTANCE * np.array([np.cos(angle), np.sin(angle)])
        if path_blocker(start, goal, particle.radius, 50e-9, others) is None:
            return particle, goal
    raise RuntimeError(f"no clear direction to push particle {particle.id}")


def push_stage(afm: AfmCommander, log, timings: dict) -> dict:
    """Plan and push one particle with the virtual nano-hand; returns what the report needs."""
    marks: list = []
    afm.node.create_subscription(
        LandmarkArray, topics.LANDMARKS, lambda m: marks.append(m), LATCHED
    )
    deadline = time.monotonic() + 30.0
    while not marks and time.monotonic() < deadline:
        time.sleep(0.1)
    if not marks:
        raise RuntimeError("no landmarks from the imaging node")
    landmarks = msg_to_landmarks(marks[-1])
    particle, goal = choose_push(landmarks)
    log(
        f"push particle {particle.id} at ({nm(particle.x)}, {nm(particle.y)}) to ({nm(goal[0])}, {nm(goal[1])})"
    )
    started = time.monotonic()
    client = afm.node.create_client(PlanPath, topics.SERVICE_PLAN_PATH)
    request = PlanPath.Request(
        start=mean_cov_to_pose(
            (particle.x - 500e-9, particle.y), np.diag([50e-9**2] * 2), Header(frame_id=FRAME_TASK)
        )
    )
    request.target.x, request.target.y = float(goal[0]), float(goal[1])
    plan_message = "planner not answering"
    if client.wait_for_service(timeout_sec=30.0):
        future = client.call_async(request)
        end = time.monotonic() + 30.0
        while not future.done() and time.monotonic() < end:
            time.sleep(0.05)
        if future.done():
            plan_message = future.result().message
    timings["plan the way to the goal (planner)"] = time.monotonic() - started
    log(f"planner: {plan_message}")
    phases: dict[str, float] = {}
    last = {"phase": None, "t": time.monotonic()}

    def on_feedback(feedback):
        now = time.monotonic()
        if feedback.phase != last["phase"]:
            if last["phase"]:
                phases[last["phase"]] = phases.get(last["phase"], 0.0) + now - last["t"]
            last.update(phase=feedback.phase, t=now)
            log(f"nano-hand: {feedback.phase}")

    started = time.monotonic()
    result = afm.push(
        goal,
        particle_id=particle.id,
        strategy="nano_hand",
        tolerance=PUSH_TOLERANCE,
        feedback=on_feedback,
        timeout=900,
    )
    if last["phase"]:
        phases[last["phase"]] = phases.get(last["phase"], 0.0) + time.monotonic() - last["t"]
    timings.update({f"nano-hand: {phase}": seconds for phase, seconds in phases.items()})
    timings["push, whole action"] = time.monotonic() - started
    log(f"push result: {result.message}")
    return {
        "particle_id": int(particle.id),
        "start": [particle.x, particle.y],
        "goal": goal.tolist(),
        "achieved": [result.achieved.x, result.achieved.y],
        "error": float(result.error),
        "steps": int(result.steps),
        "success": bool(result.success),
        "message": result.message,
        "plan_message": plan_message,
        "ran": bool(result.steps > 0),
    }


def acquire(run_dir: Path, log) -> tuple[dict, dict, dict, dict]:
    """Start the graph with a recorder, map, push, stop everything. Returns (exit codes, peak
    memory per process, the push's outcome, timings)."""
    graph = Graph(run_dir / "logs")
    graph.start("recorder", {"output": str(run_dir / "session.mcap")})
    calibration = calibration_file()
    for name in GRAPH:
        graph.start(name, {"calibration_file": calibration} if name in CALIBRATED_NODES else None)
    log(f"graph started: {', '.join(graph.processes)} (logs in {run_dir / 'logs'})")
    memory, push, timings = {}, {}, {}
    try:
        with AfmCommander(server_timeout=60.0) as afm:
            started = time.monotonic()
            afm.clients["scan_image"].wait_for_server(timeout_sec=60.0)
            afm.wait_until_subscribed(
                [topics.SCAN, topics.TIP_COMMAND, topics.GROUND_TRUTH]
            )  # the recorder
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
            push = push_stage(afm, log, timings)
        time.sleep(1.0)  # the recorder drains its queues
        dead = graph.dead()
        if dead:
            raise RuntimeError(f"nodes died during the demo: {dead}")
        memory = {name: peak_rss_bytes(p.pid) for name, p in graph.processes.items()}
    finally:
        codes = graph.stop_all()
    return codes, memory, push, timings


def replay_into_new_recording(run_dir: Path, log) -> dict:
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
            "rate": "4.0",
            "wait_for_subscribers": "1",
            "start_delay": "0.2",
            "publish_clock": "false",
        },
    )
    replay.wait(timeout=300)
    time.sleep(1.0)
    codes = graph.stop_all()
    log(f"replayed session.mcap at 4x into replayed.mcap (exit codes {codes})")
    return codes


def evaluate(run_dir: Path) -> dict:
    """Offline, from the replayed copy of the session: scans against ground truth, the tip
    estimate against the true tip, the push; and the replayed copy against the original."""
    recording = run_dir / "replayed.mcap"
    with RecordingReader(run_dir / "session.mcap") as reader:
        topics = {t: i.message_count for t, i in reader.topics().items()}
        duration = reader.duration_s
    with RecordingReader(recording) as reader:
        scans = reader.arrays("/afm/scan")
        truth = reader.arrays("/afm/ground_truth")
        poses = reader.arrays("/afm/tip_pose") if "/afm/tip_pose" in reader.topics() else {}
        paths = (
            reader.arrays("/afm/planned_path") if "/afm/planned_path" in reader.topics() else {}
        )
        marks = (
            reader.arrays("/afm/landmarks")["landmarks"]
            if "/afm/landmarks" in reader.topics()
            else []
        )

    def truth_at(t: float) -> int:
        """Index of the last ground truth published before t (the one the scan saw)."""
        return max(0, int(np.searchsorted(truth["log_time"], t, side="right")) - 1)

    def truth_xy(index: int) -> np.ndarray:
        return np.array([[o["position.x"], o["position.y"]] for o in truth["objects"][index]])

    views = []
    for i in range(len(scans["scan_id"])):
        found = find_particles(
            scans["height"][i],
            scans["pixel_size_x"][i],
            scans["pixel_size_y"][i],
            scans["origin.x"][i],
            scans["origin.y"][i],
        )
        pairs = match_to_truth(
            found, truth_xy(truth_at(scans["log_time"][i])), max_distance=MATCH_DISTANCE
        )
        views.append(
            {
                "scan_id": int(scans["scan_id"][i]),
                "angle": float(scans["scan_angle_deg"][i]),
                "frame_up": bool(scans["slow_scan_up"][i]),
                "pair_id": str(scans["pair_id"][i]),
                "found": len(found),
                "matched": len(pairs),
                "centre_error_rms": float(np.sqrt(np.mean([d**2 for _, _, d in pairs])))
                if pairs
                else float("nan"),
                "peak_height_mean": float(np.mean([v.height for _, v, _ in pairs]))
                if pairs
                else float("nan"),
                "apparent_radius_mean": float(np.mean([v.apparent_radius for _, v, _ in pairs]))
                if pairs
                else float("nan"),
            }
        )
    with RecordingReader(run_dir / "session.mcap") as a, RecordingReader(recording) as b:
        replay = compare_payloads(
            ((c.topic, m.data) for _, c, m in a.raw_messages()),
            (
                (c.topic, m.data)
                for _, c, m in b.raw_messages([t for t in b.topics() if t in topics])
            ),
        )
    final_truth = truth_xy(len(truth["log_time"]) - 1)
    landmarks = []
    for mark in marks[-1] if len(marks) else []:
        distance = float(
            np.min(
                np.hypot(
                    final_truth[:, 0] - mark["position.x"], final_truth[:, 1] - mark["position.y"]
                )
            )
        )
        landmarks.append(
            {
                "id": int(mark["id"]),
                "x": float(mark["position.x"]),
                "y": float(mark["position.y"]),
                "sigma_x": float(np.sqrt(mark["covariance"][0])),
                "sigma_y": float(np.sqrt(mark["covariance"][3])),
                "height": float(mark["height"]),
                "nearest_truth": distance,
            }
        )
    tip = {}
    if poses:
        means = np.stack([poses["pose.pose.position.x"], poses["pose.pose.position.y"]], axis=1)
        cov = np.asarray(poses["pose.covariance"])[:, [0, 1, 6, 7]].reshape(-1, 2, 2)
        # the estimate is in the maps' (commanded) frame, the truth metric: bring the truth into
        # the maps' frame about where the session started (at rest, commanded = true)
        metric = np.stack([truth["tip_position.x"], truth["tip_position.y"]], axis=1)
        start_commanded = np.array(
            [truth["commanded_position.x"][0], truth["commanded_position.y"][0]]
        )
        true_tip = start_commanded + (metric - metric[0]) @ np.linalg.inv(IMAGE_FRAME).T
        # the localizer publishes its estimate as each command ends, the driver its truth: compare
        # the pairs with the same stamp (error and NEES). A command DDS delivers late (a reliable
        # sample repaired after a loss) is predicted after hold poses already went out with its end
        # stamp, so stamps are not in order: take the last pose published with each stamp.
        # (a stamp summed from a start and a duration in float seconds since 1970 is good to ~0.3 us)
        origin = int(truth["header.stamp.sec"][0])
        stamps = (poses["header.stamp.sec"] - origin) + poses["header.stamp.nanosec"] * 1e-9
        truth_stamps = (truth["header.stamp.sec"] - origin) + truth["header.stamp.nanosec"] * 1e-9
        same = np.abs(stamps[None, :] - truth_stamps[:, None]) < 5e-6
        ok = same.any(axis=1)
        k = (
            len(stamps) - 1 - np.argmax(same[:, ::-1], axis=1)
        )  # the last published with that stamp
        errors = true_tip[ok] - means[k[ok]]
        nees = [float(e @ np.linalg.solve(c, e)) for e, c in zip(errors, cov[k[ok]])]
        tip = {
            "means": means,
            "covariances": cov,
            "true_tip": true_tip,
            "error_rms": float(np.sqrt(np.mean(np.sum(errors**2, axis=1))))
            if len(errors)
            else float("nan"),
            "mean_nees": float(np.mean(nees)) if nees else float("nan"),
            "compared": int(len(errors)),
            "final_sigma": np.sqrt(np.diag(cov[-1])).tolist(),
        }
    strokes = []
    pushes = [k for k, roles in enumerate(paths.get("waypoint_role", [])) if "push" in list(roles)]
    if pushes:  # the nano-hand's strokes (the planner's paths have no pushes)
        roles, poses_k = list(paths["waypoint_role"][pushes[-1]]), paths["path.poses"][pushes[-1]]
        points = [(p["pose.position.x"], p["pose.position.y"]) for p in poses_k]
        strokes = [
            (points[i], points[i + 1], roles[i + 1] == "push")
            for i in range(0, len(points) - 1, 2)
        ]
    return {
        "topics": topics,
        "duration_s": duration,
        "scans": views,
        "replay": replay,
        "landmarks": landmarks,
        "truth_xy": truth_xy(0).tolist(),
        "final_truth_xy": final_truth.tolist(),
        "truth_radius": [o["radius"] for o in truth["objects"][-1]],
        "scan_arrays": scans,
        "tip": tip,
        "strokes": strokes,
        "truth_objects": [truth_xy(i) for i in range(len(truth["log_time"]))],
    }


def push_truth(result: dict, push: dict) -> dict:
    """The push against ground truth: the pushed object is the true particle nearest the
    mapped start at the first truth; its true displacement, brought into the maps' frame,
    against the planned one (absolute positions differ by the instrument's positioning
    errors; displacements do not)."""
    if not push.get("ran"):
        return {}
    first = np.asarray(result["truth_objects"][0])
    index = int(np.argmin(np.hypot(*(first - np.asarray(push["start"])).T)))
    track = np.array([objects[index] for objects in result["truth_objects"]])
    moved = np.linalg.solve(IMAGE_FRAME, track[-1] - track[0])  # in the maps' frame
    wanted = np.asarray(push["goal"]) - np.asarray(push["start"])
    axis = wanted / np.linalg.norm(wanted)
    return {
        "track": track,
        "true_displacement": moved.tolist(),
        "true_error": float(np.linalg.norm(moved - wanted)),
        "along": float(moved @ axis),
        "sideways": float(moved @ np.array([-axis[1], axis[0]])),
        "verified_displacement": (
            np.asarray(push["achieved"]) - np.asarray(push["start"])
        ).tolist(),
    }


def write_report(
    run_dir: Path,
    result: dict,
    memory: dict,
    codes: dict,
    elapsed: float,
    push: dict,
    timings: dict,
) -> Path:
    scans = result.pop("scan_arrays")
    images, local = [], []
    for i in range(len(scans["scan_id"])):
        x0, y0 = scans["origin.x"][i], scans["origin.y"][i]
        h = scans["height"][i]
        extent = (
            x0,
            x0 + h.shape[1] * scans["pixel_size_x"][i],
            y0,
            y0 + h.shape[0] * scans["pixel_size_y"][i],
        )
        title = (
            f"scan {scans['scan_id'][i]}: {scans['scan_angle_deg'][i]:.0f} deg, "
            f"frame-{'up' if scans['slow_scan_up'][i] else 'down'}"
        )
        (local if str(scans["pair_id"][i]).startswith("local") else images).append(
            (title, h, extent)
        )
    save_height_maps(run_dir / "scans.png", images, markers=result["truth_xy"])
    truth = push_truth(result, push)
    tip = result.get("tip") or {}
    if push.get("ran"):
        before = (f"before the push ({local[0][0]})", *local[0][1:]) if local else None
        after = (f"after the push ({local[-1][0]})", *local[-1][1:]) if len(local) > 1 else None
        save_push_figure(
            run_dir / "push.png",
            before,
            after,
            tip.get("means", []),
            tip.get("covariances", []),
            tip.get("true_tip", []),
            truth.get("track", []),
            push["goal"],
            push["achieved"],
            result.get("strokes", []),
        )
    total_memory = sum(memory.values())
    replay_ok = all(v["identical"] for v in result["replay"].values())
    sections = [
        (
            "Summary",
            table(
                ["check", "value"],
                [
                    [
                        "nodes started and stopped cleanly",
                        "yes" if all(c == 0 for c in codes.values()) else f"no: {codes}",
                    ],
                    [
                        "recording",
                        f"session.mcap, {sum(result['topics'].values())} messages, {result['duration_s']:.1f} s",
                    ],
                    [
                        "replay reproduced every payload (evaluation reads the replayed copy)",
                        "yes" if replay_ok else "NO",
                    ],
                    ["push", push.get("message", "not run")],
                    [
                        "graph peak memory (sum of node peaks)",
                        f"{total_memory / 2**20:.0f} MiB (limit {MEMORY_LIMIT / 2**30:.0f} GiB)",
                    ],
                    ["demo wall time", f"{elapsed:.1f} s"],
                ],
            ),
        ),
    ]
    if push.get("ran"):
        sections.append(
            (
                "The push (virtual nano-hand, PushParticle action)",
                table(
                    ["", "value"],
                    [
                        ["particle (landmark id)", push["particle_id"]],
                        ["mapped start", f"({nm(push['start'][0])}, {nm(push['start'][1])})"],
                        ["goal", f"({nm(push['goal'][0])}, {nm(push['goal'][1])})"],
                        [
                            "verified position (rescan, control points)",
                            f"({nm(push['achieved'][0])}, {nm(push['achieved'][1])})",
                        ],
                        [
                            "verified error to the goal",
                            f"{nm(push['error'])} (tolerance {nm(PUSH_TOLERANCE)}): "
                            f"{'within' if push['success'] else 'outside'}",
                        ],
                        [
                            "true displacement along / sideways",
                            f"{nm(truth['along'])} / {nm(truth['sideways'])} "
                            f"(planned {nm(PUSH_DISTANCE)} / 0)",
                        ],
                        [
                            "true error (displacement against the planned one)",
                            nm(truth["true_error"]),
                        ],
                        [
                            "verification error (verified against true displacement)",
                            nm(
                                float(
                                    np.linalg.norm(
                                        np.subtract(
                                            truth["verified_displacement"],
                                            truth["true_displacement"],
                                        )
                                    )
                                )
                            ),
                        ],
                        ["push strokes", push["steps"]],
                        ["planner", push["plan_message"]],
                    ],
                )
                + "<img src='push.png' alt='push'><p>Left and middle: the nano-hand's own before and after "
                "rescans (scanner coordinates) with the goal (*) and the verified position (x). Right: the "
                "localizer's tip estimate over the session with 3-sigma ellipses, the true tip, the planned "
                "strokes (red: in contact) and the true particle track.</p>",
            )
        )
    if tip:
        sections.append(
            (
                "Tip localization against ground truth",
                table(
                    ["", "value"],
                    [
                        [
                            "estimates compared with the truth (one per driver command)",
                            tip["compared"],
                        ],
                        ["RMS error of the estimate", nm(tip["error_rms"])],
                        [
                            "mean NEES (2 dof; consistent filter: about 2)",
                            f"{tip['mean_nees']:.2f}",
                        ],
                        [
                            "final 1-sigma x / y",
                            f"{nm(tip['final_sigma'][0])} / {nm(tip['final_sigma'][1])}",
                        ],
                    ],
                ),
            )
        )
    sections += [
        (
            "Timings",
            table(["stage", "wall time"], [[k, f"{v:.1f} s"] for k, v in timings.items()]),
        ),
        (
            "Scans (true particle centres at the start marked +)",
            "<img src='scans.png' alt='height maps'>",
        ),
        (
            "Particles in each scan against ground truth",
            table(
                [
                    "scan",
                    "angle",
                    "slow axis",
                    "pair id",
                    "found",
                    "matched",
                    "centre error RMS",
                    "peak height",
                    "apparent radius",
                ],
                [
                    [
                        v["scan_id"],
                        f"{v['angle']:.0f} deg",
                        "up" if v["frame_up"] else "down",
                        v["pair_id"],
                        v["found"],
                        v["matched"],
                        nm(v["centre_error_rms"]),
                        nm(v["peak_height_mean"]),
                        nm(v["apparent_radius_mean"]),
                    ]
                    for v in result["scans"]
                ],
            )
            + f"<p>True radii: {', '.join(nm(r) for r in result['truth_radius'])}. The apparent radius at half "
            "height exceeds the true one by the tip's broadening. Images are in commanded scanner coordinates: "
            "the centre errors are the simulated instrument's positioning errors (hysteresis residue after the "
            "controller's feed-forward, creep, x/y coupling, scan-line rotation, thermal drift), which drift "
            "compensation and landmark localization are there to remove.</p>",
        ),
        (
            "Landmarks at the end (imaging node's map, the pushed particle updated by the nano-hand)",
            table(
                [
                    "id",
                    "x",
                    "y",
                    "sigma x",
                    "sigma y",
                    "height",
                    "distance to the nearest true centre",
                ],
                [
                    [
                        m["id"],
                        nm(m["x"]),
                        nm(m["y"]),
                        nm(m["sigma_x"]),
                        nm(m["sigma_y"]),
                        nm(m["height"]),
                        nm(m["nearest_truth"]),
                    ]
                    for m in result["landmarks"]
                ],
            ),
        ),
        (
            "Recorded topics",
            table(["topic", "messages"], [[t, n] for t, n in result["topics"].items()]),
        ),
        (
            "Replay check (original vs replayed recording)",
            table(
                ["topic", "original", "replayed", "identical payloads"],
                [
                    [t, v["count_a"], v["count_b"], "yes" if v["identical"] else "NO"]
                    for t, v in result["replay"].items()
                ],
            ),
        ),
        (
            "Peak resident memory per process",
            table(
                ["process", "peak RSS"], [[n, f"{m / 2**20:.0f} MiB"] for n, m in memory.items()]
            ),
        ),
    ]
    summary = {key: value for key, value in result.items() if key not in ("tip", "truth_objects")}
    summary.update(
        memory_bytes=memory,
        exit_codes=codes,
        elapsed_s=elapsed,
        timings=timings,
        push=push,
        push_truth={k: v for k, v in truth.items() if k != "track"},
        tip={k: v for k, v in tip.items() if k not in ("means", "covariances", "true_tip")},
    )
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=float))
    return write_html(run_dir / "report.html", "AFM nano-manipulation demo", sections)


def run_demo(output_root: Path) -> int:
    started = time.monotonic()
    run_dir = new_run_dir(output_root)

    def log(text):
        print(f"[demo {time.monotonic() - started:6.1f} s] {text}", flush=True)

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    codes, memory, push, timings = acquire(run_dir, log)
    replay_started = time.monotonic()
    codes.update(replay_into_new_recording(run_dir, log))
    timings["replay into a second recording"] = time.monotonic() - replay_started
    evaluation_started = time.monotonic()
    result = evaluate(run_dir)
    timings["offline evaluation and report"] = time.monotonic() - evaluation_started
    report = write_report(
        run_dir, result, memory, codes, time.monotonic() - started, push, timings
    )
    truth = json.loads((run_dir / "summary.json").read_text())["push_truth"]
    failures = []
    if any(code != 0 for code in codes.values()):
        failures.append(f"processes exited with errors: {codes}")
    differing = {
        t: f"{v['count_a']} recorded, {v['count_b']} replayed"
        for t, v in result["replay"].items()
        if not v["identical"]
    }
    if differing:
        failures.append(f"the replayed recording differs from the original: {differing}")
    if sum(memory.values()) > MEMORY_LIMIT:
        failures.append(f"graph peak memory {sum(memory.values()) / 2**20:.0f} MiB exceeds 2 GiB")
    if any(v["matched"] == 0 for v in result["scans"]):
        failures.append("a scan shows none of the true particles")
    if len(result["landmarks"]) != len(result["truth_xy"]):
        failures.append(
            f"the imaging node found {len(result['landmarks'])} landmarks, the sample has "
            f"{len(result['truth_xy'])} particles"
        )
    if not push.get("ran"):
        failures.append(f"the push did not run: {push.get('message', 'no result')}")
    elif truth["true_error"] > 3 * PUSH_TOLERANCE:
        failures.append(
            f"the particle ended {truth['true_error'] * 1e9:.0f} nm from where it should have "
            f"(more than 3x the {PUSH_TOLERANCE * 1e9:.0f} nm tolerance)"
        )
    log(f"report: {report}")
    for failure in failures:
        print(f"demo FAILED: {failure}", file=sys.stderr)
    return 1 if failures else 0
