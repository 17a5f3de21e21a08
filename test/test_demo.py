"""`make demo` end to end (the graph, recording, replay, offline evaluation, report)."""
import json

from afm_bringup.demo import run_demo


def test_demo_runs_end_to_end_and_reports(tmp_path):
    assert run_demo(tmp_path) == 0
    run = tmp_path / "latest"
    assert (run / "report.html").read_text().count("<img") == 1 and (run / "scans.png").stat().st_size > 10_000
    summary = json.loads((run / "summary.json").read_text())
    assert summary["topics"]["/afm/scan"] == 3
    assert all(v["identical"] and v["count_a"] == v["count_b"] for v in summary["replay"].values())
    # every true particle is seen, near where the simulator put it but not exactly there:
    # the simulated instrument misplaces the tip as a real one does
    for view in summary["scans"]:
        assert view["matched"] == len(summary["truth_xy"])
        assert 2e-9 < view["centre_error_rms"] < 300e-9
    # the imaging node turned the 0/90 pair into landmarks, one per particle
    assert len(summary["landmarks"]) == len(summary["truth_xy"])
    assert all(m["nearest_truth"] < 300e-9 and m["sigma_x"] >= 5e-9 for m in summary["landmarks"])
