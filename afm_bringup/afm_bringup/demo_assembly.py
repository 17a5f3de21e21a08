"""The demo's main job: assemble a small pattern through the nano-hand's Assemble action.

The simulated sample (DEMO_SAMPLE: spheres scattered around the scanner's centre and a rod,
which is mapped but never pushed) is mapped by the demo; the core places the pattern
(afm_core.planning.plan_pattern: goals inside the map, clear of every other object, every way
clear whatever the order) and the nano-hand pushes the particles in the planner's order with
its default strategy (the closed loop). Offline, from the replayed recording: the pattern
planned (the goals), predicted (the push model's last prediction of each particle, on
/afm/objects/believed), achieved (the action's rescans) and true (the simulator's truth in
the maps' frame), the figure and table of the report, and what the run is judged by.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import yaml
from geometry_msgs.msg import Point

from afm_bringup.units import nm
from afm_core.evaluation import PIT, pattern_against_truth
from afm_core.planning.pattern import DEFAULT_PITCH, pattern_offsets, plan_pattern
from afm_core.report import table
from afm_core.report_figures import save_pattern_figure
from afm_msgs.action import Assemble

NM = 1e-9
# The sample: eight spheres (r = 100 nm) and a rod (r = 40 nm, 400 nm long: taller than a
# tube, so the imaging node maps it as a rod) around the scanner's centre, where the tip rests
# at power-on; none nearer another than 800 nm, so the map separates them and the pattern has
# room between them.
DEMO_SAMPLE = {
    "spheres": [
        {"x": x * 1e-6, "y": y * 1e-6, "radius": 100e-9}
        for x, y in (
            (54.40, 54.50),
            (55.30, 54.35),
            (56.20, 54.50),
            (54.35, 55.50),
            (56.25, 55.45),
            (54.50, 56.30),
            (55.40, 56.25),
            (55.30, 55.40),
        )
    ],
    "rods": [{"x": 56.15e-6, "y": 56.25e-6, "angle": 0.5, "length": 400e-9, "radius": 40e-9}],
}
SCAN_ORIGIN = (53.95e-6, 53.95e-6)  # m: the map holds the whole sample with 150 nm to spare
SCAN_SIZE = (2.8e-6, 2.8e-6)
SCAN_PIXELS = (256, 256)  # 11 nm pixels: the map's centres to ~5 nm (book Fig. 7.10)
PATTERN_SHAPE, PATTERN_COUNT = "L", 6  # a letter of six particles
PATTERN_PITCH = DEFAULT_PITCH
TOLERANCE = 20e-9  # m, asked of each push (the nano-hand's default)
# The nano-hand places its before/after rescans in the map's (commanded) coordinates, and the
# sample drifts against them as the session goes on (measured in the first assembly runs:
# 140 nm at the first push, ~200 nm by the second, 1000-1500 s of instrument time after the
# map): the default 300 nm margin then leaves a particle at the edge of its after image, where
# the landmark extraction drops it and the verification fails. 500 nm held a 100 nm particle
# (apparent radius ~130 nm) with 200 nm of drift to spare, until the sixth push of the demo
# came 411 nm off (2026-11-27, the closed loop's frame fix changing the session's timing): 700
# nm. (Placing the rescans by the localizer's current offset would remove the cause; that is
# the push procedure's, not built.)
RESCAN_MARGIN = 700e-9  # m
NANO_HAND_OVERRIDES = {"rescan_margin": str(RESCAN_MARGIN)}


def write_sample(run_dir: Path) -> Path:
    """The simulator configuration of the demo's sample (merged into the defaults)."""
    path = run_dir / "sample.yaml"
    path.write_text(yaml.safe_dump({"sample": DEMO_SAMPLE}))
    return path


def map_area() -> tuple[float, float, float, float]:
    return (
        SCAN_ORIGIN[0],
        SCAN_ORIGIN[1],
        SCAN_ORIGIN[0] + SCAN_SIZE[0],
        SCAN_ORIGIN[1] + SCAN_SIZE[1],
    )


def assembly_stage(afm, landmarks, log, timings: dict) -> dict:
    """Plan the pattern on the map's landmarks and assemble it through Assemble; what the
    report needs."""
    started = time.monotonic()
    plan = plan_pattern(
        landmarks,
        pattern_offsets(PATTERN_SHAPE, PATTERN_COUNT, PATTERN_PITCH),
        area=map_area(),
    )
    timings["plan the pattern (core)"] = time.monotonic() - started
    log(
        f"pattern: {PATTERN_COUNT} particles as an {PATTERN_SHAPE!r}, {nm(PATTERN_PITCH)} apart, "
        f"centred at ({nm(plan.centre[0])}, {nm(plan.centre[1])}); particles "
        f"{list(plan.particle_ids)}, {nm(plan.total_distance)} of pushing in all"
    )
    request = Assemble.Goal(particle_ids=list(plan.particle_ids), tolerance=TOLERANCE)
    request.goals = [Point(x=float(g[0]), y=float(g[1])) for g in plan.goals]
    steps: dict[int, int] = {}
    last = {"particle": None}

    def on_feedback(feedback):
        pid = int(feedback.particle_id)
        steps[pid] = max(
            steps.get(pid, 0), int(feedback.step) if feedback.phase == "pushing" else 0
        )
        if pid != last["particle"]:
            last["particle"] = pid
            log(f"nano-hand: particle {feedback.index + 1} of {PATTERN_COUNT} (landmark {pid})")

    started = time.monotonic()
    result = afm.send("assemble", request, feedback=on_feedback, timeout=1800)
    seconds = time.monotonic() - started
    timings["assemble the pattern, whole action"] = seconds
    log(f"assembly: {result.message}")
    errors = [float(e) for e in result.errors]
    return {
        "shape": PATTERN_SHAPE,
        "pitch": PATTERN_PITCH,
        "tolerance": TOLERANCE,
        "particle_ids": list(plan.particle_ids),
        "starts": plan.starts.tolist(),
        "goals": plan.goals.tolist(),
        "order": [int(i) for i in result.order],
        "achieved": [[p.x, p.y] for p in result.achieved],
        "errors": errors,
        "steps": [steps.get(pid, 0) for pid in plan.particle_ids],
        "success": bool(result.success),
        "message": result.message,
        "seconds": seconds,
        "instrument_seconds": float(result.duration),
        "ran": bool(errors) and all(math.isfinite(e) for e in errors),
        "others": [[m.x, m.y] for m in landmarks if int(m.id) not in set(plan.particle_ids)],
    }


def first_push(assembly: dict) -> dict:
    """The first particle pushed, as the demo's single-push sections have a push."""
    if not assembly.get("order"):
        return {"ran": False, "message": assembly.get("message", "not run")}
    pid = assembly["order"][0]
    k = assembly["particle_ids"].index(pid)
    error = assembly["errors"][k]
    return {
        "particle_id": pid,
        "start": assembly["starts"][k],
        "goal": assembly["goals"][k],
        "achieved": assembly["achieved"][k],
        "error": error,
        "steps": assembly["steps"][k],
        "success": bool(error <= assembly["tolerance"]),
        "message": f"the first of the assembly's pushes: particle {pid}, {nm(error)} from its "
        "goal by the rescan",
        "plan_message": "the pattern's plan (afm_core.planning.plan_pattern)",
        "ran": math.isfinite(error),
    }


def predicted_ends(believed: dict, particle_ids) -> list:
    """Per particle: where the push model last predicted it (/afm/objects/believed, source
    PREDICTED, from the nano-hand), NaN when it never did."""
    last: dict[int, list] = {}
    for source, origin, objects in zip(
        believed.get("source", []), believed.get("origin", []), believed.get("objects", [])
    ):
        if int(source) != 0 or str(origin) != "nano_hand":
            continue
        for state in objects:
            last[int(state["id"])] = [state["position.x"], state["position.y"]]
    return [last.get(int(pid), [math.nan, math.nan]) for pid in particle_ids]


def true_particles(truth: dict, index: int) -> dict:
    """{object id: (x, y)} of the index-th ground truth, pits left out."""
    return {
        int(o["id"]): (o["position.x"], o["position.y"])
        for o in truth["objects"][index]
        if int(o["kind"]) != PIT
    }


def assembly_truth(result: dict, assembly: dict, to_maps) -> dict:
    """The pattern against the truth (afm_core.evaluation.pattern_against_truth), the true
    centres brought into the maps' frame by `to_maps`."""
    if not assembly.get("ran") and not assembly.get("order"):
        return {}
    first, last = result["truth_by_id"][0], result["truth_by_id"][-1]
    ids = sorted(set(first) & set(last))
    before = to_maps([first[i] for i in ids])
    after = to_maps([last[i] for i in ids])
    return pattern_against_truth(assembly["starts"], assembly["goals"], before, after)


def assembly_section(path: Path, result: dict, assembly: dict, truth: dict):
    """The figure and the table: per particle its goal, the predicted, verified and true ends,
    its errors; the pattern's RMS error and time."""
    predicted = np.asarray(assembly.get("predicted", []), float).reshape(-1, 2)
    order = [assembly["particle_ids"].index(pid) for pid in assembly["order"]]
    save_pattern_figure(
        path,
        result.get("map_image"),
        assembly["starts"],
        assembly["goals"],
        order,
        predicted=predicted if len(predicted) else None,
        achieved=assembly["achieved"],
        true_ends=truth.get("true_end"),
        obstacles=assembly["others"],
    )
    rank = {pid: k + 1 for k, pid in enumerate(assembly["order"])}
    rows = []
    for k, pid in enumerate(assembly["particle_ids"]):
        goal = np.asarray(assembly["goals"][k])

        def at(points, k=k):
            p = np.asarray(points[k], float) if len(points) > k else np.full(2, np.nan)
            return f"({nm(p[0])}, {nm(p[1])})" if np.isfinite(p).all() else "-"

        rows.append(
            [
                rank.get(pid, "-"),
                pid,
                at(assembly["goals"]),
                nm(float(np.hypot(*(goal - assembly["starts"][k])))),
                at(predicted),
                at(assembly["achieved"]),
                nm(assembly["errors"][k]),
                nm(truth["errors"][k]) if truth else "-",
            ]
        )
    header = [
        "order",
        "landmark",
        "goal (planned)",
        "push",
        "predicted end",
        "achieved (rescan)",
        "error, rescan",
        "error, simulator truth",
    ]
    summary = [
        ["pattern", f"{assembly['shape']!r} of {len(rows)}, {nm(assembly['pitch'])} apart"],
        ["Assemble result", assembly["message"]],
        ["pattern RMS error (truth)", nm(truth["rms"]) if truth else "-"],
        ["its shape alone (common offset removed)", nm(truth["shape_rms"]) if truth else "-"],
        [
            "within 20 / 10 nm (truth)",
            f"{truth['within_20nm']:.0%} / {truth['within_10nm']:.0%}" if truth else "-",
        ],
        [
            "time",
            f"{assembly['seconds']:.1f} s wall, {assembly['instrument_seconds']:.0f} s of "
            "instrument time",
        ],
    ]
    caption = (
        "<img src='pattern.png' alt='pattern'><p>Left: the map with each particle's mapped "
        "start (o), its way to its goal (*) numbered in the order the planner gave, and the "
        "objects left in place (squares; the rod among them). Right: each particle's end minus "
        "its goal: predicted by the push model as the push was verified (triangle; the closed "
        "loop's last leg is planned to end on the goal), verified by the nano-hand's rescan "
        "(x), and true (+, the simulator's truth brought into the maps' frame: the particle's "
        "true displacement from its mapped start).</p>"
    )
    return "The assembly (Assemble action, planner's order)", (
        table(["", "value"], summary) + caption + table(header, rows)
    )


def judge_assembly(assembly: dict, truth: dict) -> list[str]:
    """What went wrong in the assembly: it did not run every push, or a particle ended more
    than 3x the tolerance from its goal by the truth."""
    if not assembly.get("ran"):
        return [f"the assembly did not push every particle: {assembly.get('message', '')}"]
    far = [
        (pid, e)
        for pid, e in zip(assembly["particle_ids"], truth.get("errors", []))
        if e > 3 * assembly["tolerance"]
    ]
    return [
        f"particle {pid} ended {e / NM:.0f} nm from its goal (more than 3x the "
        f"{assembly['tolerance'] / NM:.0f} nm tolerance)"
        for pid, e in far
    ]
