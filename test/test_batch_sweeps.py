"""`afm batch push|localize` (the benchmark sweeps over seeds), push goals' outcomes in
`afm batch evaluate`, and a batch killed the hard way (SIGKILL, SIGINT) and run again."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys

import numpy as np
import pytest

from afm_core.batch import read_rows, run_batch

NM = 1e-9


@pytest.fixture(scope="module")
def client():
    """One single-worker embedded cluster for the in-process batches (its start is seconds)."""
    from afm_core.batch import dask_client

    with dask_client(workers=1) as client:
        yield client


def _sigint_ignored() -> bool:
    return signal.getsignal(signal.SIGINT) is signal.SIG_IGN


def test_the_embedded_cluster_workers_leave_ctrl_c_to_the_batch_process(client):
    """Ctrl-C signals the terminal's whole process group: each worker raised its own
    KeyboardInterrupt mid-task and printed two tracebacks while the batch closed them anyway."""
    # (this process's own handling is left as it was: a pytest worker may itself ignore SIGINT)
    assert set(client.run(_sigint_ignored).values()) == {True}


# the cheapest trial (one stroke, ~0.2 s on one core): the tests are about the batch
STRATEGY = "centre_single"


def test_a_push_sweep_is_one_row_per_seed_equal_to_the_trial_and_resumes_by_seed(tmp_path, client):
    from afm_core.batch.sweeps import summarise_push
    from afm_core.manipulation.push_trials import push_trial

    tolerance = 40 * NM
    first = run_batch(
        "push", "0-1", tmp_path, client=client, strategy=STRATEGY, tolerance=tolerance
    )
    assert (first.total, first.computed, first.ok) == (2, 2, 2)
    # more seeds, given as a list: the two done are skipped by seed and configuration
    again = run_batch(
        "push", [0, "1,2"], tmp_path, client=client, strategy=STRATEGY, tolerance=tolerance
    )
    assert (again.total, again.computed, again.skipped) == (3, 1, 2)
    rows = {int(r["seed"]): r for r in read_rows(again.table)}
    assert sorted(rows) == [0, 1, 2]
    for seed, row in rows.items():
        trial = push_trial(seed, STRATEGY, tolerance=tolerance)  # the same simulator, in here
        assert float(row["error_m"]) == trial["error"]
        assert row["success"] == str(trial["error"] <= tolerance)
        assert (float(row["final_x_m"]), float(row["final_y_m"])) == tuple(trial["final"])
    # another configuration is another row per seed, not a skip
    other = run_batch("push", "0", tmp_path, client=client, strategy=STRATEGY)
    assert other.computed == 1 and len(read_rows(other.table)) == 4
    text = other.summary.read_text()
    errors = sorted(float(r["error_m"]) for r in rows.values())
    successes = sum(e <= tolerance for e in errors)
    assert f"| {STRATEGY} | 4 | 20.0, 40.0 |" in text  # both tolerances' rows, said so
    assert (tmp_path / "push_errors.png").stat().st_size > 0
    summary = summarise_push(list(rows.values()))
    assert summary["strategies"][STRATEGY]["success_rate"] == successes / 3
    assert summary["strategies"][STRATEGY]["error_median_m"] == errors[1]


def test_a_monte_carlo_sweep_row_is_the_models_share_within_the_tolerance(tmp_path, client):
    from afm_core.manipulation import monte_carlo_push
    from afm_core.manipulation.push_trials import monte_carlo_plans

    result = run_batch(
        "montecarlo", "4", tmp_path, client=client, plan="nano_hand", samples=60, tolerance=15 * NM
    )
    (row,) = read_rows(result.table)
    plan = monte_carlo_plans()["nano_hand"]
    model = monte_carlo_push(plan, samples=60, sigma=10 * NM, seed=4, tolerance=15 * NM)
    within = np.hypot(*(model.final - plan.goal).T) <= 15 * NM
    assert float(row["success_probability"]) == np.mean(within)
    assert float(row["sigma_lateral_m"]) == model.sigma_lateral
    assert f"| nano_hand | 1 | 60 | 15.0 | {np.mean(within):.3f} +- nan |" in (
        result.summary.read_text()
    )


def test_a_localization_sweep_reports_the_trials_nees_against_its_band(tmp_path, client):
    from afm_core.localization import trials
    from afm_core.localization.calibration.model import Calibration, save_calibration

    save_calibration(Calibration(), tmp_path / "book.yaml")  # the book's defaults: no oracle
    result = run_batch(
        "localize", "3-5", tmp_path / "out", client=client, mode="direct",
        calibration=str(tmp_path / "book.yaml"),
    )  # fmt: skip
    rows = read_rows(result.table)
    assert result.ok == 3 and sorted(int(r["seed"]) for r in rows) == [3, 4, 5]
    nees = []
    for row in rows:
        trial = trials.table_71_72_trial(int(row["seed"]), Calibration(), "direct")
        assert float(row["nees"]) == trial["nees"]
        assert float(row["true_error_y_m"]) == trial["true_error"][1]
        nees.append(trial["nees"])
    lo, hi = trials.nees_band(3)
    text = result.summary.read_text()
    assert f"{np.mean(nees):.2f} (2 dof) [{lo:.2f}, {hi:.2f}]" in text


def test_a_table_7_3_sweep_uses_the_high_resolution_maps_sigma(tmp_path, client):
    import dataclasses

    from afm_core.localization import trials
    from afm_core.localization.calibration.model import Calibration, save_calibration

    save_calibration(Calibration(), tmp_path / "book.yaml")
    mode = "table_7_3_line_ends_at_pit"
    result = run_batch(
        "localize", "2", tmp_path / "out", client=client, mode=mode,
        calibration=str(tmp_path / "book.yaml"),
    )  # fmt: skip
    (row,) = read_rows(result.table)
    hires = dataclasses.replace(Calibration(), map_sigma=[trials.HIRES_MAP_SIGMA] * 2)
    trial = trials.table_73_trial(2, hires, True)
    assert float(row["pit_distance_m"]) == trial["distance"] and row["nees_dof"] == "1"
    assert f"{trial['distance'] * 1e9:.1f} +- nan" in result.summary.read_text()


def test_the_table_keeps_older_rows_and_drops_garbled_ones(tmp_path):
    from afm_core.batch import ResultsTable
    from afm_core.batch.table import COMMON_COLUMNS

    old = [c for c in COMMON_COLUMNS if c != "finished_utc"] + ["seed"]
    lines = [",".join(old), "1,,c1,ok,,0.5,w,1", "2,,c1,ok,,0.5,w,2,surplus", "3,,c1,ok"]
    (tmp_path / "results.csv").write_text("\n".join(lines) + "\n")
    with ResultsTable(tmp_path / "results.csv", COMMON_COLUMNS + ["seed"]) as table:
        assert table.done == {("1", "c1")}  # a row of the older header; not the garbled two
    (row,) = read_rows(tmp_path / "results.csv")
    assert row["item"] == "1" and row["seed"] == "1" and row["finished_utc"] == ""
    with pytest.raises(ValueError, match="another kind of batch"):
        ResultsTable(tmp_path / "results.csv", ["item", "other"])
    # the message names the columns that differ (the common ones said nothing)
    with pytest.raises(ValueError, match=r"it has \['seed'\], this one writes \['particles'\]"):
        ResultsTable(tmp_path / "results.csv", COMMON_COLUMNS + ["particles"])


def test_sweep_input_is_refused_naming_the_field(tmp_path):
    with pytest.raises(ValueError, match="seeds '5-2'"):
        run_batch("push", "5-2", tmp_path, workers=1)
    with pytest.raises(ValueError, match="'x'"):
        run_batch("push", "1,x", tmp_path, workers=1)
    with pytest.raises(ValueError, match="strategy 'zigzag'"):
        run_batch("push", "1", tmp_path, workers=1, strategy="zigzag")
    with pytest.raises(ValueError, match="mode 'diagonal'"):
        run_batch("localize", "1", tmp_path, workers=1, mode="diagonal")
    with pytest.raises(ValueError, match=r"no setting \['mode'\]"):
        run_batch("push", "1", tmp_path, workers=1, mode="direct")


def test_the_command_asks_for_seeds_or_paths_by_kind(tmp_path, capsys):
    from afm_bringup.cli import main

    assert main(["batch", "push", "--output", str(tmp_path)]) == 2
    assert "give --seeds" in capsys.readouterr().err
    assert main(["batch", "evaluate", "--seeds", "0-3", "--output", str(tmp_path)]) == 2
    assert "give PATHs" in capsys.readouterr().err
    assert main(["batch", "localize", "--seeds", "3-1", "--output", str(tmp_path)]) == 2
    assert "seeds '3-1'" in capsys.readouterr().err


# -- push goals in `evaluate` -----------------------------------------------------------------
def _channels(writer, types: dict) -> tuple[dict, dict]:
    """(channel id, CDR encoder) per topic of `types` (topic -> message type) on `writer`."""
    from afm_core.recording.cdr import encoder
    from afm_core.recording.definitions import full_message_definition

    channels, encode = {}, {}
    for topic, type_name in types.items():
        definition = full_message_definition(type_name)
        channels[topic] = writer.add_channel(topic, type_name, [], definition=definition)
        encode[topic] = encoder(type_name, definition)
    return channels, encode


def _write_push_session(path, tip, moves, goals, pit=(1e-5, 1e-5)):
    """Ground truth of two particles and a pit, and push goals: moves = [(time s, id, xy)]
    (a truth message after each move), goals = [(time s, xy)]."""
    from afm_core.recording import RecordingWriter

    types = {
        "/afm/ground_truth": "afm_msgs/msg/GroundTruth",
        "/afm/push_goal": "geometry_msgs/msg/PointStamped",
    }
    positions = {1: (50.2e-6, 50.0e-6), 2: (51.0e-6, 52.0e-6)}

    def point(xy):
        return {"x": float(xy[0]), "y": float(xy[1]), "z": 0.0}

    def header(seconds):
        return {"stamp": {"sec": int(seconds), "nanosec": 0}, "frame_id": "afm_task"}

    with RecordingWriter(path) as writer:
        channels, encode = _channels(writer, types)
        events = [(t, "truth", i, xy) for t, i, xy in [(1.0, None, None), *moves]]
        events += [(t, "goal", None, xy) for t, xy in goals]
        for seconds, what, ident, xy in sorted(events, key=lambda e: e[0]):
            if what == "goal":
                message = {"header": header(seconds), "point": point(xy)}
                data = encode["/afm/push_goal"](message)
                writer.write(channels["/afm/push_goal"], int(seconds * 1e9), data)
                continue
            if ident is not None:
                positions[ident] = xy
            objects = [
                {"id": i, "kind": 0, "position": point(p), "orientation": 0.0, "radius": 50e-9,
                 "length": 0.0}
                for i, p in positions.items()
            ] + [{"id": 9, "kind": 3, "position": point(pit), "orientation": 0.0,
                  "radius": 20e-9, "length": 0.0}]  # fmt: skip
            zero = point((0.0, 0.0))
            truth = {
                "header": header(seconds),
                "tip_position": point(tip),
                "commanded_position": point(tip),
                "drift_offset": zero,
                "drift_velocity": zero,
                "tip_apex_radius": 10e-9,
                "objects": objects,
            }
            data = encode["/afm/ground_truth"](truth)
            writer.write(channels["/afm/ground_truth"], int(seconds * 1e9), data)


def test_push_goals_are_judged_by_the_pushed_objects_final_true_position(tmp_path):
    """Two goals, each followed by one particle's push (its truth in two steps); the goals lie
    off the particles' final positions, in the maps' frame, by 3-4-5 and 30-40-50 nm: the
    errors are 5 and 50 nm, so 1 of 2 within 20 nm and 2 of 2 within 60 nm."""
    from afm_core.batch import evaluate_recording
    from afm_core.evaluation import image_frame_matrix

    tip = np.array([50.0e-6, 50.0e-6])
    inverse = np.linalg.inv(image_frame_matrix())

    def maps(p):  # where an image shows a true position (commanded = true tip at the start)
        return tip + inverse @ (np.asarray(p) - tip)

    final_1, final_2 = np.array([50.2e-6, 50.5e-6]), np.array([51.3e-6, 52.4e-6])
    goals = [(10.0, maps(final_1) + [3 * NM, 4 * NM]), (20.0, maps(final_2) - [30 * NM, 40 * NM])]
    moves = [
        (12.0, 1, (50.2e-6, 50.3e-6)),
        (14.0, 1, tuple(final_1)),
        (22.0, 2, (51.2e-6, 52.2e-6)),
        (25.0, 2, tuple(final_2)),
    ]
    path = tmp_path / "pushes.mcap"
    _write_push_session(path, tip, moves, goals)

    row = evaluate_recording(path)
    assert (row["push_goals"], row["push_goals_judged"], row["push_succeeded"]) == (2, 2, 1)
    assert row["push_tolerance_m"] == 20 * NM
    assert row["push_error_max_m"] == pytest.approx(50 * NM, rel=1e-6)
    assert row["push_error_median_m"] == pytest.approx(27.5 * NM, rel=1e-6)
    outcomes = row["push_outcomes"].split(";")
    assert [o.split(":")[0] for o in outcomes] == ["1", "2"]
    final = [float(v) for v in outcomes[1].split(":")[1].split(",")]
    assert final == pytest.approx(maps(final_2), abs=1e-15)
    assert evaluate_recording(path, push_tolerance=60 * NM)["push_succeeded"] == 2
    from afm_core.batch.evaluate import session_report

    report = session_report(row, "pushes.mcap")  # each goal's object and error, for a person
    assert "| 1 | 1 | 5.0 nm |" in report and "| 2 | 2 | 50.0 nm |" in report

    # a goal whose push moved nothing: judged by the particle nearest it, and failed
    still = tmp_path / "still.mcap"
    _write_push_session(
        still, tip, [(12.0, 1, (50.2e-6, 50.0e-6))], [(10.0, maps((50.2e-6, 50.3e-6)))]
    )
    row = evaluate_recording(still)
    assert row["push_outcomes"].startswith("1:") and row["push_succeeded"] == 0
    assert row["push_error_max_m"] == pytest.approx(
        math.hypot(*(maps((50.2e-6, 50.3e-6)) - maps((50.2e-6, 50.0e-6)))), rel=1e-9
    )


def test_push_goals_reach_the_batch_table_and_summary(tmp_path, client):
    tip = np.array([50.0e-6, 50.0e-6])
    (tmp_path / "in").mkdir()
    _write_push_session(
        tmp_path / "in" / "a.mcap", tip, [(12.0, 1, (50.2e-6, 50.5e-6))],
        [(10.0, (50.2e-6, 50.5e-6))],
    )  # fmt: skip
    result = run_batch("evaluate", [tmp_path / "in"], tmp_path / "out", client=client)
    (row,) = read_rows(result.table)
    assert row["push_goals"] == "1" and row["push_goals_judged"] == "1"
    text = result.summary.read_text()
    assert "| push goals (total; judged against truth) | 1 (1) |" in text
    assert f"{float(row['push_error_median_m']) * 1e9:.1f} nm" in text


# -- interrupted the hard way -----------------------------------------------------------------
SEEDS = 8


def _start(output) -> subprocess.Popen:
    command = [
        sys.executable, "-m", "afm_bringup.cli", "batch", "push", "--seeds", f"0-{SEEDS - 1}",
        "--strategy", STRATEGY, "--workers", "1", "--output", str(output),
    ]  # fmt: skip
    # its own session: whatever it leaves behind (its cluster's workers) is ended with it; and
    # Ctrl-C's default handling, as a terminal starts it: a child inherits an ignored SIGINT, and
    # a pytest worker may ignore it (in CI the batch then ran to its end, status 0)
    return subprocess.Popen(
        command,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


def _data_lines(table) -> int:
    try:
        return max(0, table.read_bytes().count(b"\n") - 1)
    except FileNotFoundError:
        return 0


def _interrupt(output, how: int) -> int:
    from conftest import wait_for

    process = _start(output)
    try:
        wait_for(lambda: _data_lines(output / "results.csv") >= 1, timeout=120.0,
                 interval=0.01, what="the first row")  # fmt: skip
        process.send_signal(how)
        return process.wait(timeout=60)
    finally:
        try:
            os.killpg(process.pid, signal.SIGKILL)  # the group this test started
        except ProcessLookupError:
            pass
        process.wait()


@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGINT], ids=["SIGKILL", "SIGINT"])
def test_a_batch_killed_midway_resumes_without_redoing_or_duplicating_rows(tmp_path, how):
    for attempt in range(3):
        output = tmp_path / f"attempt-{attempt}"
        status = _interrupt(output, how)
        # a batch that finished before the signal was handled was not interrupted: again
        if not (status == 0 and _data_lines(output / "results.csv") == SEEDS):
            break
    tmp_path = output
    assert status == (-signal.SIGKILL if how == signal.SIGKILL else 130)
    table = tmp_path / "results.csv"
    written = read_rows(table)
    assert 1 <= len(written) < SEEDS  # stopped after a row, before the end
    if how == signal.SIGKILL:
        # the write a kill cuts: a row without its end (and its newline)
        text = table.read_text()
        table.write_text(text + text.splitlines()[-1][: len(text.splitlines()[-1]) // 2])

    from afm_bringup.cli import main

    assert main(["batch", "push", "--seeds", f"0-{SEEDS - 1}", "--strategy", STRATEGY,
                 "--workers", "1", "--output", str(tmp_path)]) == 0  # fmt: skip
    rows = read_rows(table)
    assert sorted(int(r["seed"]) for r in rows) == list(range(SEEDS))  # each once, all done
    assert all(r["status"] == "ok" and r["finished_utc"] for r in rows)
    # the rows finished before the interrupt are kept as they were (time written, worker)
    assert [r for r in rows if r["item"] in {w["item"] for w in written}] == written
    later = [r["finished_utc"] for r in rows if r["item"] not in {w["item"] for w in written}]
    assert min(later) > max(w["finished_utc"] for w in written)


def test_push_goals_are_judged_in_the_landmark_map_s_frame_as_the_tip_is(tmp_path):
    """The map was made after the scanner drifted 20 nm: its landmarks sit 20 nm from where the
    session's start puts the true particles. A goal is in the map's frame, so a particle pushed
    to exactly the map-frame goal is 0 nm off (judged from the start's anchor, as before, it was
    20 nm off, and the nano-hand's verified 4 nm push of the README's session read 24 nm)."""
    from afm_core.batch import evaluate_recording
    from afm_core.evaluation import image_frame_matrix
    from afm_core.recording import RecordingWriter

    tip = np.array([50.0e-6, 50.0e-6])
    inverse = np.linalg.inv(image_frame_matrix())
    drift = np.array([20 * NM, 0.0])

    def mapped(p):  # where the drifted map shows a true position
        return tip + inverse @ (np.asarray(p) - tip) + drift

    particles = {1: (50.2e-6, 50.0e-6), 2: (51.0e-6, 52.0e-6), 3: (52.5e-6, 50.5e-6)}
    final = np.array([50.2e-6, 50.4e-6])
    types = {
        "/afm/ground_truth": "afm_msgs/msg/GroundTruth",
        "/afm/landmarks": "afm_msgs/msg/LandmarkArray",
        "/afm/push_goal": "geometry_msgs/msg/PointStamped",
    }

    def point(xy):
        return {"x": float(xy[0]), "y": float(xy[1]), "z": 0.0}

    def header(seconds, frame="afm_task"):
        return {"stamp": {"sec": int(seconds), "nanosec": 0}, "frame_id": frame}

    def truth(seconds, where):
        objects = [
            {"id": i, "kind": 0, "position": point(p), "orientation": 0.0, "radius": 50e-9,
             "length": 0.0}
            for i, p in where.items()
        ]  # fmt: skip
        return {
            "header": header(seconds),
            "tip_position": point(tip),
            "commanded_position": point(tip),
            "drift_offset": point((0.0, 0.0)),
            "drift_velocity": point((0.0, 0.0)),
            "tip_apex_radius": 10e-9,
            "objects": objects,
        }

    marks = {
        "header": header(5.0),
        "landmarks": [
            {"id": i, "kind": 0, "position": point(mapped(p)), "covariance": [1e-18, 0, 0, 1e-18],
             "radius": 50e-9, "height": 100e-9, "length": 0.0, "orientation": 0.0}
            for i, p in particles.items()
        ],
    }  # fmt: skip
    path = tmp_path / "drifted.mcap"
    with RecordingWriter(path) as writer:
        channels, encode = _channels(writer, types)
        events = [
            (1.0, "/afm/ground_truth", truth(1.0, particles)),
            (5.0, "/afm/landmarks", marks),
            (10.0, "/afm/push_goal", {"header": header(10.0), "point": point(mapped(final))}),
            (14.0, "/afm/ground_truth", truth(14.0, {**particles, 1: tuple(final)})),
        ]
        for seconds, topic, message in events:
            writer.write(channels[topic], int(seconds * 1e9), encode[topic](message))

    row = evaluate_recording(path)
    assert (row["push_goals_judged"], row["push_succeeded"]) == (1, 1)
    assert row["push_error_max_m"] == pytest.approx(0.0, abs=1e-12)
