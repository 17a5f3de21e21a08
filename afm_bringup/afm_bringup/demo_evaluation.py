"""The demo's evaluation against the simulator's ground truth, offline from the replayed
recording: particles in every scan, the landmark map, the tip estimate (its position; and its
shape, blind-estimated from the last map: demo_tip), the push, the replay check; and the
targets a run is judged by (`judge_run`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from afm_bringup.demo_assembly import true_particles
from afm_bringup.demo_tip import estimate_run_tip
from afm_core.evaluation import (
    compare_payloads,
    image_frame_matrix,
    scan_against_truth,
    tip_against_truth,
    truth_frame,
    truth_index_at,
    truth_xy,
)
from afm_core.manipulation.execute import TIP_HEIGHT
from afm_core.recording import RecordingReader

MEMORY_LIMIT = 2 * 2**30  # bytes, the whole graph's peak resident memory
PUSH_TOLERANCE = 20e-9  # m
# true displacement per commanded (= map) displacement of the simulated instrument, for the
# evaluation against truth only (afm_core.evaluation.image_frame_matrix)
IMAGE_FRAME = image_frame_matrix()


def evaluate(run_dir: Path) -> dict:
    """Offline, from the replayed copy of the session: scans against ground truth, the tip
    estimate against the true tip, the push; and the replayed copy against the original."""
    recording = run_dir / "replayed.mcap"
    with RecordingReader(run_dir / "session.mcap") as reader:
        recorded_topics = {t: i.message_count for t, i in reader.topics().items()}
        duration = reader.duration_s
    scans, truth, poses, paths, marks = _read_replayed(recording)
    frame = _truth_frame(recording, truth)
    replay = _replay_check(run_dir / "session.mcap", recording, recorded_topics)
    final_truth = truth_xy(truth, len(truth["log_time"]) - 1)
    with RecordingReader(recording) as reader:
        topics = reader.topics()
        traces = reader.arrays("/afm/force_trace") if "/afm/force_trace" in topics else {}
        maps = reader.arrays("/afm/map") if "/afm/map" in topics else {}
        believed = (
            reader.arrays("/afm/objects/believed") if "/afm/objects/believed" in topics else {}
        )
        goals = reader.arrays("/afm/push_goal") if "/afm/push_goal" in topics else {}
    # the map and the first push alone (up to the second particle's goal): the part of the
    # session near where it started, which a single push's demo had
    second = goals.get("log_time", [])[1:2]
    first_push = (
        (_until(poses, second[0]), _until(truth, second[0])) if len(second) else (poses, truth)
    )
    return {
        "topics": recorded_topics,
        "duration_s": duration,
        "scans": _scan_views(scans, truth),
        "replay": replay,
        "landmarks": _landmarks_against_truth(marks, final_truth),
        "truth_xy": truth_xy(truth, 0).tolist(),
        "final_truth_xy": final_truth.tolist(),
        "final_particles_xy": truth_xy(truth, len(truth["log_time"]) - 1, particles=True).tolist(),
        "truth_radius": [o["radius"] for o in truth["objects"][-1]],
        "scan_arrays": scans,
        "tip": _tip_against_truth(poses, truth, frame) if poses else {},
        "tip_first_push": _tip_against_truth(*first_push, frame) if poses else {},
        "strokes": _planned_strokes(paths),
        "strokes_by_particle": {pid: _planned_strokes(paths, pid) for pid in _pushed_ids(paths)},
        "truth_by_id": [
            true_particles(truth, 0),
            true_particles(truth, len(truth["log_time"]) - 1),
        ],
        "believed": believed,
        "truth_objects": [truth_xy(truth, i) for i in range(len(truth["log_time"]))],
        "truth_anchor": _truth_anchor(truth, frame[0]),
        "force_strokes": _force_strokes(traces),
        "map_image": _last_map(maps),
        "tip_shape": estimate_run_tip(
            _last_map(maps),
            float(truth["tip_apex_radius"][-1]) if len(truth.get("tip_apex_radius", [])) else None,
        ),
    }


def _until(arrays: dict, t: float) -> dict:
    """The messages of a recording's arrays logged before `t`."""
    keep = np.asarray(arrays["log_time"]) < t
    return {
        k: (
            np.asarray(v)[keep]
            if isinstance(v, np.ndarray)
            else [x for x, kept in zip(v, keep) if kept]
        )
        if len(v) == len(keep)
        else v
        for k, v in arrays.items()
    }


def _truth_anchor(truth: dict, frame=None) -> dict:
    """What ties the simulator's metric truth to the maps' frame (`truth_in_maps`): "frame",
    the first map's own (`_truth_frame`, [A | b], map = A true + b), the frame its goals are
    given in; and where the session started, commanded and true (at rest there, commanded =
    true), which with the creep-free step (IMAGE_FRAME) gives the frame used before
    2026-11-28 ("creep_free", `truth_in_maps(..., creep_free=True)`)."""
    anchor = {
        "commanded": [truth["commanded_position.x"][0], truth["commanded_position.y"][0]],
        "metric": [truth["tip_position.x"][0], truth["tip_position.y"][0]],
    }
    if frame is not None:
        anchor["frame"] = np.asarray(frame, float).tolist()
    return anchor


def truth_in_maps(points, anchor: dict, creep_free: bool = False) -> np.ndarray:
    """True (metric) positions as the maps' frame has them: through the first map's own frame
    (anchor["frame"]); without one, or `creep_free`, about the session's start scaled by the
    creep-free step (IMAGE_FRAME), 2 % off the map's gain on the default simulator."""
    p = np.asarray(points, float).reshape(-1, 2)
    if "frame" in anchor and not creep_free:
        frame = np.asarray(anchor["frame"], float)
        return p @ frame[:, :2].T + frame[:, 2]
    return (
        np.asarray(anchor["commanded"])
        + (p - np.asarray(anchor["metric"])) @ np.linalg.inv(IMAGE_FRAME).T
    )


def _force_strokes(traces: dict) -> list:
    """(label, distance along the stroke m, lateral force N, normal force N) of every push
    stroke's force trace, in order; the lateral force as the nano-hand's own summary has it
    (torsion x spring constant / the tip's lever arm, `execute.force_summary`)."""
    strokes = []
    for i, task in enumerate(traces.get("task", [])):
        if str(task) != "push":
            continue
        x, y = np.asarray(traces["commanded_x"][i]), np.asarray(traces["commanded_y"][i])
        distance = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
        strokes.append(
            (
                f"stroke {len(strokes) + 1}",
                distance,
                np.asarray(traces["lateral_torsion"][i])
                * traces["lateral_spring_constant"][i]
                / TIP_HEIGHT,
                np.asarray(traces["vertical_deflection"][i]) * traces["normal_spring_constant"][i],
            )
        )
    return strokes


def _last_map(maps: dict):
    """(title, height m, extent m) of the last drift-corrected map, or None."""
    if not len(maps.get("height", [])):
        return None
    h = maps["height"][-1]
    x0, y0 = maps["origin.x"][-1], maps["origin.y"][-1]
    extent = (
        x0,
        x0 + h.shape[1] * maps["pixel_size_x"][-1],
        y0,
        y0 + h.shape[0] * maps["pixel_size_y"][-1],
    )
    return (
        f"drift-corrected map ({maps['header.frame_id'][-1]}, {maps['pair_id'][-1]})",
        h,
        extent,
    )


def _read_replayed(recording: Path) -> tuple:
    """(scans, ground truth, tip poses, planned paths, landmark maps) of a recording; the last
    three empty when it has none."""
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
    return scans, truth, poses, paths, marks


def _scan_views(scans: dict, truth: dict) -> list[dict]:
    """Per scan: the particles found in it, matched to the true centres at its time."""
    return [
        {
            "scan_id": int(scans["scan_id"][i]),
            "angle": float(scans["scan_angle_deg"][i]),
            "frame_up": bool(scans["slow_scan_up"][i]),
            "pair_id": str(scans["pair_id"][i]),
            **scan_against_truth(
                scans["height"][i],
                (scans["pixel_size_x"][i], scans["pixel_size_y"][i]),
                (scans["origin.x"][i], scans["origin.y"][i]),
                truth_xy(truth, truth_index_at(truth, scans["log_time"][i])),
            ),
        }
        for i in range(len(scans["scan_id"]))
    ]


def _replay_check(original: Path, replayed: Path, recorded_topics: dict) -> dict:
    """Per topic: the original's and the replayed copy's payloads compared (the copy's topics
    that the original has)."""
    with RecordingReader(original) as a, RecordingReader(replayed) as b:
        return compare_payloads(
            ((c.topic, m.data) for _, c, m in a.raw_messages()),
            (
                (c.topic, m.data)
                for _, c, m in b.raw_messages([t for t in b.topics() if t in recorded_topics])
            ),
        )


def _landmarks_against_truth(marks, final_truth: np.ndarray) -> list[dict]:
    """The last landmark map, each landmark with its distance to the nearest true centre."""
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
                "covariance": [float(c) for c in mark["covariance"]],
                "nearest_truth": distance,
            }
        )
    return landmarks


def _truth_frame(recording: Path, truth: dict) -> tuple:
    """The frame the localizer is judged in: the first landmark map's own (`truth_frame`)."""
    with RecordingReader(recording) as reader:
        marks = reader.arrays("/afm/landmarks") if "/afm/landmarks" in reader.topics() else {}
    return truth_frame(truth, marks, IMAGE_FRAME)


def _tip_against_truth(poses: dict, truth: dict, frame: tuple) -> dict:
    return {**tip_against_truth(poses, truth, frame[0]), "frame_basis": frame[1]}


def _planned_strokes(paths: dict, particle_id: int | None = None) -> list:
    """The nano-hand's strokes of its last push path (of `particle_id`'s pushes when given),
    (start, end, in contact) each; the planner's paths have no pushes."""
    pushes = [
        k
        for k, roles in enumerate(paths.get("waypoint_role", []))
        if "push" in list(roles)
        and (particle_id is None or particle_id in list(paths["landmark_id"][k]))
    ]
    if not pushes:
        return []
    roles, poses_k = list(paths["waypoint_role"][pushes[-1]]), paths["path.poses"][pushes[-1]]
    points = [(p["pose.position.x"], p["pose.position.y"]) for p in poses_k]
    return [
        (points[i], points[i + 1], roles[i + 1] == "push") for i in range(0, len(points) - 1, 2)
    ]


def _pushed_ids(paths: dict) -> list[int]:
    """The particles the nano-hand planned pushes for."""
    ids = set()
    for roles, marks in zip(paths.get("waypoint_role", []), paths.get("landmark_id", [])):
        if "push" in list(roles):
            ids.update(int(m) for m in marks if m >= 0)
    return sorted(ids)


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
    anchor = result["truth_anchor"]
    # the displacement in the maps' frame: the map's own, and the creep-free step's (before)
    moved, creep_free = (
        np.diff(truth_in_maps(track[[0, -1]], anchor, old), axis=0)[0] for old in (False, True)
    )
    wanted = np.asarray(push["goal"]) - np.asarray(push["start"])
    axis = wanted / np.linalg.norm(wanted)
    return {
        "track": track,
        "true_displacement": moved.tolist(),
        "true_error": float(np.linalg.norm(moved - wanted)),
        "true_error_creep_free": float(np.linalg.norm(creep_free - wanted)),
        "along": float(moved @ axis),
        "sideways": float(moved @ np.array([-axis[1], axis[0]])),
        "verified_displacement": (
            np.asarray(push["achieved"]) - np.asarray(push["start"])
        ).tolist(),
    }


def judge_run(codes: dict, memory: dict, result: dict, push: dict, truth: dict) -> list[str]:
    """What went wrong in a run (empty: the demo passed): a process failed, the replay differs,
    the graph used too much memory, a scan or the map misses particles, the push did not run or
    left the particle off its goal by more than 3x the tolerance."""
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
    return failures
