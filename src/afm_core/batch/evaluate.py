"""`afm batch evaluate`: the offline evaluation of one recorded session, as one table row.

What a recording holds decides what is evaluated (an empty cell: not recorded):
- always: duration, messages, topics, the recording's date (UTC, from its first log time);
- scans (/afm/scan) against the ground truth at their time (/afm/ground_truth): particles
  found, those within MATCH_DISTANCE of a true centre, the matched centres' RMS error
  (afm_core.evaluation.scan_against_truth; found - matched are false detections);
- the localizer's estimates (/afm/tip_pose) against the true tip: error RMS and mean NEES
  (afm_core.evaluation.tip_against_truth, the demo's evaluation), the truth brought into the
  first landmark map's own frame (/afm/landmarks; without one, the session start's frame:
  afm_core.evaluation.truth_frame);
- pushes: the contact moves commanded (/afm/tip_command kind PUSH) and, with ground truth,
  the objects they moved and how far (first truth to last);
- push goals (/afm/push_goal) with ground truth: each goal's pushed object, its final true
  position and error to the goal, success within the tolerance (afm_core.batch.push_outcomes).

Scans are decoded one at a time from the reader's stream; only the truth and pose topics
(small messages, one per command) are held as arrays.
"""

from __future__ import annotations

import functools
import math
from datetime import datetime, timezone

import numpy as np

from afm_core.batch import push_outcomes
from afm_core.evaluation import (
    image_frame_matrix,
    scan_against_truth,
    tip_against_truth,
    truth_frame,
    truth_index_at,
    truth_xy,
)
from afm_core.recording import RecordingReader
from afm_core.recording.reader import flatten

# bump when a column's meaning changes: the rows computed before are redone (3: the localizer
# judged in its first landmark map's own frame, 2026-11-28)
ROW_FORMAT = 3
SCAN, TRUTH, POSE, COMMAND = "/afm/scan", "/afm/ground_truth", "/afm/tip_pose", "/afm/tip_command"
LANDMARKS = "/afm/landmarks"
PUSH_KIND = 3  # afm_msgs/msg/TipCommand.PUSH
# m: the simulator's truth moves an object only when the tip pushes it (drift moves the
# scanner, not the sample), so any displacement is a push's; 1 nm is below what any AFM
# image resolves and far above float round-off of positions of ~1e-4 m (1e-20 m)
MOVED = 1e-9

COLUMNS = [
    "recording_date",
    "duration_s",
    "messages",
    "topics",
    "ground_truth",
    "scans",
    "particles_found",
    "particles_matched",
    "centre_error_rms_m",
    "localization_compared",
    "localization_error_rms_m",
    "localization_mean_nees",
    "push_strokes",
    "objects_moved",
    "push_displacement_max_m",
    "push_goals",
    "push_goals_judged",
    "push_succeeded",
    "push_tolerance_m",
    "push_error_median_m",
    "push_error_max_m",
    "push_outcomes",
    "report",
]


def options(push_tolerance: float | None = None) -> tuple[dict, dict]:
    """(what each task gets, what the configuration hash is of)."""
    tolerance = push_outcomes.TOLERANCE if push_tolerance is None else float(push_tolerance)
    if not (math.isfinite(tolerance) and tolerance > 0):
        raise ValueError(f"push_tolerance={push_tolerance}: must be finite and > 0 m")
    return {"push_tolerance": tolerance}, {"push_tolerance": tolerance}


@functools.cache
def _image_frame() -> np.ndarray:
    # the default simulated scanner's (the evaluation against truth is of simulated sessions)
    return image_frame_matrix()


def recording_date(start_ns: int) -> str:
    return datetime.fromtimestamp(start_ns * 1e-9, tz=timezone.utc).date().isoformat()


def evaluate_recording(path, push_tolerance: float = push_outcomes.TOLERANCE) -> dict:
    """One recording's row (COLUMNS; SI units). RecordingError when it cannot be read.
    push_tolerance: m, a push goal is reached when its object ends this close to it."""
    with RecordingReader(path) as reader:
        topics = reader.topics()
        row = {
            "recording_date": recording_date(reader.start_time_ns),
            "duration_s": reader.duration_s,
            "messages": reader.message_count,
            "topics": len(topics),
            "ground_truth": TRUTH in topics,
        }
        truth = reader.arrays(TRUTH) if TRUTH in topics else None
        if SCAN in topics:
            row.update(_scans(reader, truth))
        frame = None
        if truth is not None and len(truth["log_time"]):
            marks = reader.arrays(LANDMARKS) if LANDMARKS in topics else {}
            frame, _basis = truth_frame(truth, marks, _image_frame())
        if POSE in topics and frame is not None:
            tip = tip_against_truth(reader.arrays(POSE), truth, frame)
            row.update(
                localization_compared=tip["compared"],
                localization_error_rms_m=tip["error_rms"],
                localization_mean_nees=tip["mean_nees"],
            )
        if COMMAND in topics:
            row.update(_pushes(reader, truth))
        if push_outcomes.GOAL in topics:
            goals = reader.arrays(push_outcomes.GOAL)
            row.update(push_outcomes.push_columns(goals, truth, frame, push_tolerance))
    return row


def _scans(reader: RecordingReader, truth: dict | None) -> dict:
    """Scans streamed one at a time; with truth, each against the truth at its time."""
    count, found, matched, squared = 0, 0, 0, []
    for _topic, log_time, message in reader.messages([SCAN]):
        count += 1
        if truth is None or not len(truth["log_time"]):
            continue
        scan = flatten(message)
        view = scan_against_truth(
            scan["height"],
            (scan["pixel_size_x"], scan["pixel_size_y"]),
            (scan["origin.x"], scan["origin.y"]),
            truth_xy(truth, truth_index_at(truth, log_time * 1e-9)),
        )
        found += view["found"]
        matched += view["matched"]
        if view["matched"]:
            squared.append((view["centre_error_rms"] ** 2, view["matched"]))
    out = {"scans": count}
    if truth is not None:
        weight = sum(n for _, n in squared)
        out.update(
            particles_found=found,
            particles_matched=matched,
            centre_error_rms_m=math.sqrt(sum(s * n for s, n in squared) / weight)
            if weight
            else float("nan"),
        )
    return out


def _pushes(reader: RecordingReader, truth: dict | None) -> dict:
    strokes = sum(1 for _t, _lt, m in reader.messages([COMMAND]) if m.kind == PUSH_KIND)
    out = {"push_strokes": strokes}
    if truth is not None and len(truth["log_time"]) > 1:
        first, last = _by_id(truth, 0), _by_id(truth, len(truth["log_time"]) - 1)
        moved = [float(np.hypot(*(last[i] - first[i]))) for i in first.keys() & last.keys()]
        moved = [d for d in moved if d > MOVED]
        out.update(objects_moved=len(moved), push_displacement_max_m=max(moved, default=0.0))
    return out


def _by_id(truth: dict, index: int) -> dict:
    return {
        int(o["id"]): np.array([o["position.x"], o["position.y"]]) for o in truth["objects"][index]
    }


def _floats(rows: list[dict], column: str) -> list[float]:
    return [float(r[column]) for r in rows if r.get(column) not in (None, "")]


def summarise(rows: list[dict]) -> dict:
    """Across the finished rows: sessions, those with truth, the medians of the localization
    error and NEES and of the scans' centre error, the pushes and the objects they moved."""
    done = [r for r in rows if r.get("status") == "ok"]
    errors = [e for r in done for e in push_outcomes.outcome_errors(r.get("push_outcomes", ""))]

    def median(column):
        values = _floats(done, column)
        return float(np.median(values)) if values else float("nan")

    return {
        "sessions": len(done),
        "failed": sum(1 for r in rows if r.get("status") == "failed"),
        "with_truth": sum(1 for r in done if r.get("ground_truth") == "True"),
        "localization_error_rms_m": median("localization_error_rms_m"),
        "localization_mean_nees": median("localization_mean_nees"),
        "centre_error_rms_m": median("centre_error_rms_m"),
        "push_strokes": int(sum(_floats(done, "push_strokes"))),
        "objects_moved": int(sum(_floats(done, "objects_moved"))),
        "push_goals": int(sum(_floats(done, "push_goals"))),
        "push_goals_judged": int(sum(_floats(done, "push_goals_judged"))),
        "push_succeeded": int(sum(_floats(done, "push_succeeded"))),
        "push_tolerance_m": sorted(set(_floats(done, "push_tolerance_m"))),
        # over every judged goal of every session, not a median of sessions' medians
        "push_error_median_m": float(np.median(errors)) if errors else float("nan"),
    }


def summary_markdown(summary: dict) -> str:
    def nm(value):
        return "not recorded" if math.isnan(value) else f"{value * 1e9:.1f} nm"

    nees = summary["localization_mean_nees"]
    tolerance = ", ".join(nm(t) for t in summary["push_tolerance_m"]) or "the tolerance"
    judged = summary["push_goals_judged"]
    reached = f"{summary['push_succeeded']} of {judged}" + (
        f" ({summary['push_succeeded'] / judged:.0%})" if judged else ""
    )
    return "\n".join(
        [
            "# Offline evaluation across sessions",
            "",
            f"{summary['sessions']} sessions evaluated ({summary['with_truth']} with ground "
            f"truth), {summary['failed']} failed (results.csv has each one's error).",
            "",
            "| measure (median over sessions) | value |",
            "| --- | --- |",
            f"| localization error RMS | {nm(summary['localization_error_rms_m'])} |",
            "| localization mean NEES (2 when consistent) | "
            + ("not recorded" if math.isnan(nees) else f"{nees:.2f}")
            + " |",
            f"| scans' particle centre error RMS | {nm(summary['centre_error_rms_m'])} |",
            f"| push strokes (total) | {summary['push_strokes']} |",
            f"| objects moved (total) | {summary['objects_moved']} |",
            f"| push goals (total; judged against truth) | {summary['push_goals']} "
            f"({summary['push_goals_judged']}) |",
            f"| push goals reached within {tolerance} | {reached} |",
            f"| push error to the goal (median over goals) | "
            f"{nm(summary['push_error_median_m'])} |",
            "",
        ]
    )


def session_report(row: dict, item: str) -> str:
    """One session's evaluation for a person (Markdown): what was recorded and how it compared
    with the ground truth; lengths in nm."""

    def value(column, nm=False):
        v = row.get(column)
        if v is None or (isinstance(v, float) and math.isnan(v)):
            return "not recorded"
        return f"{float(v) * 1e9:.1f} nm" if nm else (f"{v:.3g}" if isinstance(v, float) else v)

    lines = [
        f"# Session {item}",
        "",
        f"Recorded {value('recording_date')}, {value('duration_s')} s, {value('messages')} "
        f"messages on {value('topics')} topics; ground truth "
        + ("recorded." if row.get("ground_truth") else "not recorded: nothing is compared."),
        "",
        "| measure | value |",
        "| --- | --- |",
        f"| scans | {value('scans')} |",
        f"| particles found / matched to truth | {value('particles_found')} / "
        f"{value('particles_matched')} |",
        f"| particle centre error RMS | {value('centre_error_rms_m', nm=True)} |",
        f"| tip poses compared with truth | {value('localization_compared')} |",
        f"| localization error RMS | {value('localization_error_rms_m', nm=True)} |",
        f"| localization mean NEES (2 when consistent) | {value('localization_mean_nees')} |",
        f"| push strokes | {value('push_strokes')} |",
        f"| objects moved / largest displacement | {value('objects_moved')} / "
        f"{value('push_displacement_max_m', nm=True)} |",
        f"| push goals (judged) | {value('push_goals')} ({value('push_goals_judged')}) |",
        f"| push goals within {value('push_tolerance_m', nm=True)} | {value('push_succeeded')} |",
        "",
    ]
    outcomes = push_outcomes.describe(row.get("push_outcomes", ""))
    if outcomes:
        lines += ["| goal | object | error to the goal |", "| --- | --- | --- |", *outcomes, ""]
    return "\n".join(lines)
