"""`make demo` end to end: the graph maps, localizes, plans and pushes a particle with the
virtual nano-hand, records everything, replays it, evaluates the replayed copy, reports."""

import html
import json
import re
from pathlib import Path

import pytest

from afm_bringup.demo import run_demo
from afm_bringup.demo_evaluation import PUSH_DISTANCE
from afm_core.batch.evaluate import evaluate_recording

pytestmark = pytest.mark.ros


def test_demo_runs_end_to_end_and_reports(tmp_path):
    assert run_demo(tmp_path) == 0
    run = tmp_path / "latest"
    report = (run / "report.html").read_text()
    figures = ("push.png", "map.png", "tip.png", "forces.png", "localizer.png", "scans.png")
    assert report.count("<img") == len(figures)
    for name in figures:
        assert f"src='{name}'" in report and (run / name).stat().st_size > 10_000, name
    for block in ("Reproducibility", "simulator seed", "commit", "Open the recording in Foxglove"):
        assert block in report, block
    layout = re.search(r"Import from file</b>: <code>([^<]+)</code>", report).group(1)
    assert Path(html.unescape(layout)).is_file()  # the layout the report points to is there
    # the rescans were placed in the task frame by the push's own particle and control points
    assert "could not be placed" not in report and "after by (" in report
    summary = json.loads((run / "summary.json").read_text())
    # the 0/90 pair and the frame-down map, then the nano-hand's before and after rescans
    map_scans = [v for v in summary["scans"] if not v["pair_id"].startswith("local")]
    local_scans = [v for v in summary["scans"] if v["pair_id"].startswith("local")]
    assert len(map_scans) == 3 and len(local_scans) == 2
    assert all(v["identical"] and v["count_a"] == v["count_b"] for v in summary["replay"].values())
    # every true particle is seen, near where the simulator put it but not exactly there:
    # the simulated instrument misplaces the tip as a real one does
    for view in map_scans:
        assert view["matched"] == len(summary["truth_xy"])
        assert 2e-9 < view["centre_error_rms"] < 300e-9
    assert all(view["matched"] >= 1 for view in local_scans)
    assert len(summary["landmarks"]) == len(summary["truth_xy"])
    # the push ran through the action and moved the particle (truth) about as planned
    push, truth = summary["push"], summary["push_truth"]
    assert push["ran"] and push["steps"] >= 3
    assert abs(truth["along"] - PUSH_DISTANCE) < 60e-9 and abs(truth["sideways"]) < 40e-9
    # the action's verdict agrees with the truth, and the localizer was consistent
    verified = [a - s for a, s in zip(push["achieved"], push["start"])]
    assert sum((v - t) ** 2 for v, t in zip(verified, truth["true_displacement"])) ** 0.5 < 20e-9
    assert summary["tip"]["compared"] >= 5 and 0.2 < summary["tip"]["mean_nees"] < 10
    # the tip shape estimated from the map is an upper bound: the true tip is no wider
    shape = summary["tip_shape"]
    assert 0 < shape["true_width"] <= shape["max_width"] and shape["depth"] > 0
    # the nano-hand published its goal, so an offline batch evaluation judges the push
    row = evaluate_recording(run / "session.mcap")
    assert (row["push_goals"], row["push_goals_judged"]) == (1, 1)
    assert 0 <= row["push_error_max_m"] < 100e-9
