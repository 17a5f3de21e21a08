"""`afm batch` (afm_core.batch): many recordings on Dask, one row each, on an embedded cluster
or on a scheduler and workers started as separate processes; a corrupt recording is a failed
row; a re-run after an interrupt does only what is not done."""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from afm_core.batch import read_rows, run_batch

# one xdist worker runs the tests that share the module's sessions and its LocalCluster batch
pytestmark = pytest.mark.xdist_group("batch_sessions")
# the columns that depend on where and when a row was computed, not on what it says
RUN_COLUMNS = ("seconds", "worker", "finished_utc")
SEEDS = (1, 2, 3)


def _tiny_session(path: Path, seed: int) -> dict:
    """A raster of one particle, a push stroke through it, the raster again: the simulator's
    truth of the pushed particle before and after (m)."""
    from afm_core.instrument import ScanRequest
    from afm_core.sim.config import merge
    from afm_core.sim.instrument import SimulatedAfm
    from afm_core.sim2real.session_writer import RecordingInstrument
    from afm_core.sim2real.work_session import WORK_SPHERES, work_config

    x, y = WORK_SPHERES[0]
    scan = ScanRequest(x - 0.5e-6, y - 0.5e-6, 1e-6, 1e-6, 32, 32, line_rate=8.0)
    with RecordingInstrument(SimulatedAfm(merge(work_config(), {"seed": seed})), path) as rec:
        # the truth's objects are the simulator's own (moved in place): keep their numbers
        before = (rec.truth()["objects"][0].x, rec.truth()["objects"][0].y)
        rec.raster_scan(scan)
        rec.move_tip(x - 0.3e-6, y + 20e-9 * (seed - 2), 1e-6)
        rec.move_tip(x + 0.3e-6, y + 20e-9 * (seed - 2), 1e-7, contact=True)
        after = (rec.truth()["objects"][0].x, rec.truth()["objects"][0].y)
        rec.raster_scan(scan)
    return {"moved": math.hypot(after[0] - before[0], after[1] - before[1])}


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    """Three tiny recordings, a corrupt one (the second half of a good one overwritten), and
    the truth of each good one."""
    folder = tmp_path_factory.mktemp("sessions")
    truth = {}
    for seed in SEEDS:
        path = folder / f"session_{seed}.mcap"
        truth[str(path)] = _tiny_session(path, seed)
    corrupt = folder / "session_corrupt.mcap"
    data = bytearray((folder / "session_1.mcap").read_bytes())
    data[len(data) // 2 :] = b"\x5a" * (len(data) - len(data) // 2)
    corrupt.write_bytes(bytes(data))
    return folder, truth, corrupt


@pytest.fixture(scope="module")
def local_batch(sessions, tmp_path_factory):
    folder, _truth, _corrupt = sessions
    output = tmp_path_factory.mktemp("local")
    lines = []
    result = run_batch(
        "evaluate", [folder], output, workers=2, progress=lambda s: lines.append(s.line())
    )
    return result, read_rows(output / "results.csv"), lines


def _by_item(rows):
    return {r["item"]: {k: v for k, v in r.items() if k not in RUN_COLUMNS} for r in rows}


def test_a_local_cluster_batch_gives_one_row_per_recording_against_truth(sessions, local_batch):
    folder, truth, corrupt = sessions
    result, rows, lines = local_batch

    assert sorted(r["item"] for r in rows) == sorted([*truth, str(corrupt)])
    assert (result.total, result.computed, result.skipped) == (4, 4, 0)
    for row in (r for r in rows if r["item"] in truth):
        assert row["status"] == "ok" and row["error"] == ""
        assert row["ground_truth"] == "True" and row["scans"] == "2"
        # the one particle in view is found and matched in both scans
        assert row["particles_matched"] == "2"
        assert float(row["centre_error_rms_m"]) < 300e-9
        # the push: one stroke moved one object, by what the simulator's truth says
        assert row["push_strokes"] == "1" and row["objects_moved"] == "1"
        assert float(row["push_displacement_max_m"]) == pytest.approx(
            truth[row["item"]]["moved"], rel=1e-12
        )
        # and a report of the session a person reads, beside the table
        report = (result.summary.parent / row["report"]).read_text()
        assert report.startswith(f"# Session {row['item']}")
        assert "| particles found / matched to truth |" in report and "/ 2 |" in report
        moved = float(row["push_displacement_max_m"]) * 1e9
        assert f"| objects moved / largest displacement | 1 / {moved:.1f} nm |" in report
    # progress: every item counted, with a rate
    assert lines[-1].startswith("4/4 (3 ok, 1 failed, 0 done before)")
    assert "recordings/min" in lines[-1]
    assert "3 sessions evaluated" in result.summary.read_text()
    assert "![errors_by_session.png]" in result.summary.read_text()
    assert (result.summary.parent / "errors_by_session.png").stat().st_size > 0


def test_a_corrupt_recording_is_a_failed_row_and_the_rest_finish(sessions, local_batch):
    _folder, _truth, corrupt = sessions
    result, rows, _lines = local_batch

    failed = [r for r in rows if r["status"] == "failed"]
    assert [r["item"] for r in failed] == [str(corrupt)]
    assert "corrupt" in failed[0]["error"] and "\n" not in failed[0]["error"]
    assert failed[0]["sha256"]  # the file was read and hashed; the evaluation refused it
    assert result.ok == 3 and result.failed == 1


def _dask_process(*args) -> subprocess.Popen:
    command = [sys.executable, "-m", "distributed.cli.dask_" + args[0], *args[1:]]
    return subprocess.Popen(
        command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
    )


def test_a_scheduler_and_two_worker_processes_give_the_same_rows(sessions, local_batch, tmp_path):
    from conftest import wait_for

    folder, _truth, _corrupt = sessions
    address_file = tmp_path / "scheduler.json"
    scheduler = _dask_process(
        "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
        "--scheduler-file", str(address_file),
    )  # fmt: skip
    workers = []
    try:
        wait_for(address_file.is_file, timeout=30.0, what="the scheduler's address file")
        import json

        address = wait_for(
            lambda: json.loads(address_file.read_text() or "{}").get("address"), timeout=10.0
        )
        workers = [
            _dask_process(
                "worker", address, "--nthreads", "1", "--no-dashboard", "--nworkers", "1"
            )
            for _ in range(2)
        ]
        result = run_batch("evaluate", [folder], tmp_path / "out", scheduler=address, workers=2)
        # a sweep over seeds on the same workers: each row is its seed's trial, as in here
        sweep = run_batch(
            "push", "0-1", tmp_path / "push", scheduler=address, strategy="centre_single"
        )
    finally:
        for process in [*workers, scheduler]:
            process.terminate()
        for process in [*workers, scheduler]:
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()

    rows = read_rows(result.table)
    assert _by_item(rows) == _by_item(local_batch[1])
    # computed by the worker processes, not in this one
    assert all(str(os.getpid()) not in r["worker"] and r["worker"] for r in rows)
    from afm_core.manipulation.push_trials import push_trial

    for row in read_rows(sweep.table):
        assert str(os.getpid()) not in row["worker"] and row["status"] == "ok"
        assert float(row["error_m"]) == push_trial(int(row["seed"]), "centre_single")["error"]


def test_an_interrupted_batch_is_resumed_without_redoing_finished_items(
    sessions, local_batch, tmp_path
):
    folder, _truth, corrupt = sessions
    _result, rows, _lines = local_batch
    # the table an interrupt leaves after two finished rows, in the middle of the third
    finished = [r for r in rows if r["status"] == "ok"][:2]
    shutil.copytree(local_batch[0].table.parent, tmp_path / "out")
    table = tmp_path / "out" / "results.csv"
    header = table.read_text().splitlines()[0]
    kept = [line for line in table.read_text().splitlines()[1:] if line.startswith(
        tuple(r["item"] + "," for r in finished)
    )]  # fmt: skip
    table.write_text("\n".join([header, *kept]) + "\n" + rows[-1]["item"][:10])

    resumed = run_batch("evaluate", [folder], tmp_path / "out", workers=1)

    # only the two items without a finished row ran: the third good one and the corrupt one
    assert (resumed.computed, resumed.skipped) == (2, 2)
    after = read_rows(table)
    assert sorted(r["item"] for r in after) == sorted(r["item"] for r in rows)
    assert _by_item(after) == _by_item(rows)
    # the finished rows were kept as written (the worker that computed them and its time)
    assert [r for r in after if r["item"] in {f["item"] for f in finished}] == finished
    # and again: everything good is done; the failed one is tried again (it may have been a
    # lost worker), and fails again
    again = run_batch("evaluate", [folder], tmp_path / "out", workers=1)
    assert (again.computed, again.skipped, again.failed) == (1, 3, 1)
    assert len(read_rows(table)) == 4


def test_bad_input_is_refused_naming_it(tmp_path):
    with pytest.raises(ValueError, match="nothing_here"):
        run_batch("evaluate", [tmp_path / "nothing_here"], tmp_path / "out", workers=1)
    with pytest.raises(ValueError, match="kind 'evaluat'"):
        run_batch("evaluat", [tmp_path], tmp_path / "out", workers=1)
    with pytest.raises(ValueError, match="tip_raduis"):
        run_batch("sim2real", [tmp_path], tmp_path / "out", effects=["tip_raduis"])


def test_the_sim2real_summary_counts_effects_by_date():
    from afm_core.batch.sim2real import summarise, summary_markdown

    def row(date, named, parameters, status="ok"):
        return {
            "status": status,
            "recording_date": date,
            "verdict": "named" if named else "no missing physics",
            "named": named,
            "parameters": parameters,
        }

    rows = [
        row("2026-01-01", "tip_radius", "tip.radius=1e-08+-1e-09"),
        row("2026-01-01", "", ""),
        row("2026-01-02", "tip_radius;height_gain", "tip.radius=3e-08+-1e-09;noise.g=1.02+-0.01"),
        row("2026-01-02", "", "", status="failed"),
    ]
    summary = summarise(rows)
    assert summary["sessions"] == 3 and summary["failed"] == 1
    assert summary["effects"] == {"tip_radius": 2, "height_gain": 1}
    assert summary["by_date"]["2026-01-01"]["sessions"] == 2
    assert summary["parameter_medians"][("2026-01-02", "tip.radius")] == 3e-08
    text = summary_markdown(summary)
    assert "| tip_radius | 2 | 67% |" in text and "2026-01-02" in text


def test_a_sim2real_batch_reports_each_diagnosis_or_why_not(sessions, tmp_path):
    """Through the batch, the diagnosis of a session too small to diagnose is a failed row
    naming why (the diagnosis itself is tested in test_sim2real_*)."""
    folder, _truth, _corrupt = sessions
    result = run_batch(
        "sim2real", [folder / "session_2.mcap"], tmp_path, workers=1, effects=["height_gain"]
    )
    (row,) = read_rows(result.table)
    assert row["status"] == "failed" and "too little to diagnose" in row["error"]
    assert np.isfinite(float(row["seconds"]))


def test_localization_error_and_nees_against_truth_are_the_closed_form(tmp_path):
    """A recording of the truth (tip at rest) and four localizer estimates off it by known
    errors, with known covariances: the row's error RMS and mean NEES are the closed form."""
    from sample_messages import dict_message_writer

    from afm_core.batch import evaluate_recording
    from afm_core.recording import RecordingWriter

    tip = {"x": 50e-6, "y": 51e-6, "z": 0.0}
    errors = np.array([[10e-9, 0.0], [0.0, -20e-9], [30e-9, 40e-9], [-10e-9, -10e-9]])
    sigma = np.array([10e-9, 20e-9])
    types = {
        "/afm/ground_truth": "afm_msgs/msg/GroundTruth",
        "/afm/tip_pose": "geometry_msgs/msg/PoseWithCovarianceStamped",
    }
    path = tmp_path / "poses.mcap"
    with RecordingWriter(path) as writer:
        write = dict_message_writer(writer, types)
        zero = {"x": 0.0, "y": 0.0, "z": 0.0}
        for k, (ex, ey) in enumerate(errors):
            header = {"stamp": {"sec": 1000 + k, "nanosec": 0}, "frame_id": "afm_task"}
            truth = {
                "header": header,
                "tip_position": tip,
                "commanded_position": tip,
                "drift_offset": zero,
                "drift_velocity": zero,
                "tip_apex_radius": 10e-9,
                "objects": [],
            }
            covariance = np.zeros(36)
            covariance[[0, 7]] = sigma**2
            pose = {
                "header": header,
                "pose": {
                    "pose": {
                        "position": {"x": tip["x"] + ex, "y": tip["y"] + ey, "z": 0.0},
                        "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                    },
                    "covariance": covariance.tolist(),
                },
            }
            log_ns = (1000 + k) * 10**9
            write("/afm/ground_truth", log_ns, truth)
            write("/afm/tip_pose", log_ns + 1, pose)

    row = evaluate_recording(path)

    assert row["localization_compared"] == 4
    # the estimate minus the truth, squared over its variance, summed over x and y
    assert row["localization_mean_nees"] == pytest.approx(
        np.mean(np.sum((errors / sigma) ** 2, axis=1)), rel=1e-9
    )
    assert row["localization_error_rms_m"] == pytest.approx(
        np.sqrt(np.mean(np.sum(errors**2, axis=1))), rel=1e-9
    )
    assert "scans" not in row and "push_strokes" not in row  # neither was recorded


def test_recordings_behind_a_url_are_listed_hashed_and_read_where_they_lie(sessions):
    """fsspec's in-memory filesystem stands for a lab's object store: a folder URL lists its
    recordings, each is hashed by streaming and read through a temporary local copy."""
    import hashlib

    import fsspec

    from afm_core.batch import evaluate_recording, expand_items, file_sha256
    from afm_core.batch.items import local_file

    folder, _truth, _corrupt = sessions
    memory = fsspec.filesystem("memory")
    for name in ("session_1.mcap", "session_2.mcap"):
        memory.pipe(f"/lab/day1/{name}", (folder / name).read_bytes())
    memory.pipe("/lab/notes.txt", b"not a recording")

    items = expand_items(["memory://lab"])
    assert [i.rsplit("/", 1)[-1] for i in items] == ["session_1.mcap", "session_2.mcap"]
    data = (folder / "session_1.mcap").read_bytes()
    assert file_sha256(items[0]) == hashlib.sha256(data).hexdigest()
    with local_file(items[0]) as path:
        assert path.read_bytes() == data
        row = evaluate_recording(path)
    assert not path.exists()  # the copy is gone
    assert row == evaluate_recording(folder / "session_1.mcap")
    with pytest.raises(ValueError, match="memory://lab/none"):
        expand_items(["memory://lab/none"])


def test_a_sim2real_batch_names_a_changed_z_gain_with_its_value(tmp_path):
    """One work session whose z gain is 3 % off the model, diagnosed through the batch with
    the one library term that is the test's subject (small: the search is tested elsewhere):
    the row names it, its value within 3 sigma of the truth, and the summary counts it."""
    from afm_core.sim.config import dump_config, merge
    from afm_core.sim2real.work_session import record_work_session, work_config

    truth = 1.03
    model = work_config()
    (tmp_path / "model.yaml").write_text(dump_config(model))
    changed = merge(model, {"seed": 11, "noise": {"height_gain": truth}})
    (tmp_path / "sessions").mkdir()
    record_work_session(tmp_path / "sessions" / "work.mcap", changed, seed=11, pushes=1)

    result = run_batch(
        "sim2real",
        [tmp_path / "sessions"],
        tmp_path / "out",
        workers=1,
        model=str(tmp_path / "model.yaml"),
        effects=["height_gain"],
    )

    (row,) = read_rows(result.table)
    assert row["status"] == "ok" and row["verdict"] == "named"
    assert row["named"] == "height_gain"
    key, value = row["parameters"].split("=")
    fitted, sigma = (float(v) for v in value.split("+-"))
    assert key == "noise.height_gain" and abs(fitted - truth) <= 3 * sigma
    assert (Path(row["report"]) / "report.md").is_file()
    assert "| height_gain | 1 | 100% |" in result.summary.read_text()
    assert (tmp_path / "out" / "effects_by_date.png").stat().st_size > 0


def test_the_command_shows_progress_and_says_by_its_status_whether_an_item_failed(
    sessions, tmp_path, capsys
):
    from afm_bringup.cli import main

    folder, _truth, corrupt = sessions
    status = main(["batch", "evaluate", str(folder), "--output", str(tmp_path), "--workers", "1"])
    out, err = capsys.readouterr()
    assert status == 1  # the corrupt recording
    assert "afm batch: 4/4 (3 ok, 1 failed, 0 done before)" in out
    assert f"{corrupt} failed: RecordingError" in err
    # nothing to run: refused with the input named, status 2, no cluster started
    assert main(["batch", "evaluate", str(tmp_path / "none"), "--output", str(tmp_path)]) == 2
    assert "none" in capsys.readouterr().err


def test_a_re_run_with_other_settings_keeps_each_row_s_own_report(sessions, tmp_path):
    """Two tolerances over one recording: both rows pointed at one report file, which held the
    second run's numbers only."""
    from afm_core.batch.items import file_sha256
    from afm_core.batch.runner import run_item

    folder, truth, _ = sessions
    item = sorted(truth)[0]
    sha = file_sha256(item)
    rows = [
        run_item("evaluate", item, sha, config, {"push_tolerance": tolerance}, str(tmp_path))
        for config, tolerance in (("0123456789ab", 20e-9), ("fedcba987654", 50e-9))
    ]
    assert [r["status"] for r in rows] == ["ok", "ok"], rows
    assert rows[0]["report"] != rows[1]["report"]
    for row in rows:
        assert row["config"][:8] in row["report"] and (tmp_path / row["report"]).is_file()


@pytest.mark.parametrize(
    "workers, memory_limit, complaint",
    [
        (0, "auto", r"workers=0: must be at least 1"),
        (1, "1KiB", r"memory_limit: 0 MiB per worker \(1 workers\) is below the 512 MiB"),
        (1, "-5GiB", r"memory_limit: -5120 MiB per worker"),
        (1, "lots", r"memory_limit='lots': not a size"),
        (100_000, "auto", r"\(100000 workers sharing .* GiB\) is below the 512 MiB"),
    ],
)
def test_a_cluster_that_would_not_run_is_refused_before_anything_is_written(
    sessions, tmp_path, workers, memory_limit, complaint
):
    """1 KiB per worker (or 1000 workers sharing the memory) had Dask restart its workers
    without end: the batch hung with no row; a negative limit gave 14 tracebacks."""
    folder, _, _ = sessions
    with pytest.raises(ValueError, match=complaint):
        run_batch(
            "evaluate", [str(folder)], tmp_path / "out", workers=workers, memory_limit=memory_limit
        )
    assert not (tmp_path / "out").exists()
