"""Push outcomes of a recorded session: each push goal (/afm/push_goal, geometry_msgs/PointStamped,
one per accepted goal) against where the simulator's truth (/afm/ground_truth) says the pushed
object ended.

A goal's push lasts from its log time to the next goal's (the last one: to the recording's
end); its outcome is read from the last ground truth before that end. The pushed object is
the particle (pits excluded) that moved most over the push: only a push moves an object in the
simulator (drift moves the scanner, not the sample); if none moved more than MOVED, the push
moved nothing and the particle nearest the goal is judged (the push failed unless a particle
already sat at the goal).

Frames: a goal is in the maps' frame (commanded scanner coordinates, where the images and the
localizer's estimates are); the truth is metric. A true position p is brought into the maps'
frame as the tip's is (afm_core.evaluation.truth_frame: the first landmark map's own frame,
fitted to the true particle centres at its time; without a map, anchored where the session
started at rest). Anchoring at the start alone left out the drift up to the map, which the map's
frame holds: a push the nano-hand's rescan put 4 nm from its goal was judged 24 nm off.
"""

from __future__ import annotations

import math

import numpy as np

from afm_core.evaluation import PIT, in_frame

GOAL = "/afm/push_goal"
TOLERANCE = 20e-9  # m: the project's push success radius (SPEC section 5, book 7.3)
# m: a displacement below this is no push's (1 nm is below what an AFM image resolves and far
# above the round-off of positions of ~1e-4 m)
MOVED = 1e-9


def _particles(truth: dict, index: int) -> dict[int, np.ndarray]:
    return {
        int(o["id"]): np.array([o["position.x"], o["position.y"]])
        for o in truth["objects"][index]
        if int(o["kind"]) != PIT
    }


def goal_outcomes(goals: dict, truth: dict, frame: np.ndarray, tolerance: float) -> list:
    """Per goal (recording order): (goal xy, pushed object id or None, its final xy in the
    maps' frame, error m, success, moved); final, error NaN when no truth follows the goal."""
    times = np.asarray(goals["log_time"], float)
    order = np.argsort(times, kind="stable")
    truth_times = np.asarray(truth["log_time"], float)
    out = []
    for rank, k in enumerate(order):
        goal = np.array([goals["point.x"][k], goals["point.y"][k]])
        end_time = times[order[rank + 1]] if rank + 1 < len(order) else math.inf
        # the truth when the goal came (the last before it, else the first) and when it ended
        start = max(0, int(np.searchsorted(truth_times, times[k], side="right")) - 1)
        end = int(np.searchsorted(truth_times, end_time, side="left")) - 1
        if end < 0 or truth_times[end] < times[k]:
            out.append((goal, None, np.full(2, np.nan), math.nan, False, False))
            continue
        before, after = _particles(truth, start), _particles(truth, end)
        if not after:
            out.append((goal, None, np.full(2, np.nan), math.nan, False, False))
            continue
        shift = {i: float(np.hypot(*(after[i] - before[i]))) for i in before.keys() & after}
        moved = max(shift, key=shift.get, default=None)
        ids = list(after)
        finals = in_frame([after[i] for i in ids], frame)
        if moved is not None and shift[moved] > MOVED:
            pushed = moved
        else:
            pushed, moved = ids[int(np.argmin(np.hypot(*(finals - goal).T)))], None
        final = finals[ids.index(pushed)]
        error = float(np.hypot(*(final - goal)))
        out.append((goal, pushed, final, error, bool(error <= tolerance), moved is not None))
    return out


def push_columns(goals: dict, truth: dict | None, frame, tolerance: float) -> dict:
    """The row's push-goal columns (evaluate.COLUMNS); without truth only the goals' count.
    frame: (2, 3) the truth into the maps' frame (evaluation.truth_frame)."""
    row = {"push_goals": len(goals["log_time"]), "push_tolerance_m": tolerance}
    if truth is None or not len(truth["log_time"]) or not row["push_goals"]:
        return row
    outcomes = goal_outcomes(goals, truth, frame, tolerance)
    judged = [o for o in outcomes if o[1] is not None]
    errors = [o[3] for o in judged]
    row.update(
        push_goals_judged=len(judged),
        push_succeeded=sum(o[4] for o in judged),
        push_error_median_m=float(np.median(errors)) if errors else math.nan,
        push_error_max_m=max(errors, default=math.nan),
        # per goal: object id, its final x,y (maps' frame, m), error (m); "-" not judged
        push_outcomes=";".join(
            f"{o[1]}:{float(o[2][0])!r},{float(o[2][1])!r}:{o[3]!r}" if o[1] is not None else "-"
            for o in outcomes
        ),
    )
    return row


def outcome_errors(cell: str) -> list[float]:
    """The judged goals' errors (m) of a row's push_outcomes cell."""
    return [float(p.rsplit(":", 1)[1]) for p in (cell or "").split(";") if p and p != "-"]


def describe(cell: str) -> list[str]:
    """Markdown table rows (goal number, object, error in nm) of a row's push_outcomes cell."""
    rows = []
    for number, part in enumerate(p for p in (cell or "").split(";") if p):
        if part == "-":
            rows.append(f"| {number + 1} | - | not judged (no truth after it) |")
            continue
        obj, _final, error = part.split(":")
        rows.append(f"| {number + 1} | {obj} | {float(error) * 1e9:.1f} nm |")
    return rows
