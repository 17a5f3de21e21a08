"""The sim2real node: the /afm/sim2real action on a recorded session with a known missing
effect (the recording's tip is blunter than the model's), on a snapshot of a live (.part)
recording, refusals that name what is missing, and a cancel that stops between steps."""

import math
import shutil
from pathlib import Path

import pytest

from afm_bringup.commander import AfmCommander
from afm_core.sim.config import dump_config, load_config, merge
from afm_core.sim.instrument import SimulatedAfm
from afm_core.sim2real import RecordingInstrument
from afm_core.sim2real.protocol import run_protocol, session_config
from afm_msgs.action import Sim2Real

pytestmark = pytest.mark.ros

TRUE_APEX = 26e-9  # the model says 20 nm
# the terms that change a particle's apparent size (the whole library is the diagnosis tests' job)
SIZE_TERMS = ["tip_radius", "tip_wear", "tip_asymmetry", "height_gain"]


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sim2real")
    model = session_config(load_config())
    (folder / "model.yaml").write_text(dump_config(model))
    truth = merge(model, {"seed": 7, "tip": {"apex_radius": TRUE_APEX}})
    recording = RecordingInstrument(SimulatedAfm(truth), folder / "session.mcap")
    run_protocol(recording, seed=1, blocks=2)
    recording.close()
    # the same session as a recorder writes it live: small chunks, so a file cut short still
    # holds complete chunks of the first operations
    live = RecordingInstrument(
        SimulatedAfm(truth), folder / "live-full.mcap", chunk_size=64 * 1024
    )
    run_protocol(live, seed=1, blocks=2)
    live.close()
    return folder


def test_the_action_names_the_blunter_tip_and_refuses_what_it_cannot_do(session, nodes):
    live = session / "live.mcap"
    # a recorder still writing: only the .part exists, cut mid-file like a file being appended to
    data = (session / "live-full.mcap").read_bytes()
    (session / "live.mcap.part").write_bytes(data[: int(len(data) * 0.8)])
    nodes(
        "sim2real",
        model=str(session / "model.yaml"),
        live_recording=str(live),
        read_roots=f"['{session}']",
        report_root=str(session),
    )
    with AfmCommander("sim2real_test", server_timeout=30.0) as afm:
        phases = []
        result = afm.send(
            "sim2real",
            Sim2Real.Goal(
                recording=str(session / "session.mcap"),
                report_dir=str(session / "report"),
                effects=SIZE_TERMS,
            ),
            feedback=lambda f: phases.append(f.phase),
            timeout=240.0,
        )
        assert result.success, result.message
        assert result.missing_physics and "tip radius" in result.effects[0]
        assert "apex_radius" in result.summary
        assert (session / "report" / "report.md").is_file() and result.report.endswith("report.md")
        assert result.updated_config and load_config(
            result.updated_config
        ).tip.apex_radius == pytest.approx(TRUE_APEX, abs=0.25 * (TRUE_APEX - 20e-9))
        assert result.heldout_reduction > 0.5
        assert phases, "no feedback"

        # no recording named: a snapshot of the live .part file
        result = afm.send("sim2real", Sim2Real.Goal(effects=SIZE_TERMS), timeout=240.0)
        assert result.success, result.message
        assert "snapshot of live.mcap.part" in result.message
        assert (session / "live.mcap.part").read_bytes() == data[
            : int(len(data) * 0.8)
        ]  # left alone

        result = afm.send(
            "sim2real",
            Sim2Real.Goal(
                recording=str(session / "session.mcap"),
                effects=["tip_raduis"],
                report_dir=str(session / "misspelt"),
            ),
            timeout=30.0,
        )
        assert not result.success and "effects: unknown 'tip_raduis'" in result.message
        assert not (session / "misspelt").exists()
        result = afm.send(
            "sim2real", Sim2Real.Goal(recording=str(session / "nope.mcap")), timeout=30.0
        )
        assert (
            not result.success
            and "recording=" in result.message
            and "no such file" in result.message
        )
        # a goal reads only under read_roots and writes only under report_root, symlinks
        # followed (issue 30: any path was read, a report written anywhere)
        (session / "escape.mcap").symlink_to("/etc/hostname")
        for goal, field in (
            (Sim2Real.Goal(recording="/etc/hostname"), "recording='/etc/hostname'"),
            (Sim2Real.Goal(recording=str(session / "escape.mcap")), "recording="),
            (
                Sim2Real.Goal(recording=str(session / "session.mcap"), model="/etc/hostname"),
                "model=",
            ),
            (
                Sim2Real.Goal(recording=str(session / "session.mcap"), report_dir="/tmp/afm-out"),
                "report_dir='/tmp/afm-out'",
            ),
        ):
            result = afm.send("sim2real", goal, timeout=30.0)
            assert not result.success and result.message.startswith(f"refused: {field}")
            assert "outside the allowed folders" in result.message, result.message
        assert not Path("/tmp/afm-out").exists()
        shutil.copy(session / "model.yaml", session / "broken.yaml")
        (session / "broken.yaml").write_text("scanner: {hysteresis_fraction: lots}\n")
        result = afm.send(
            "sim2real",
            Sim2Real.Goal(
                recording=str(session / "session.mcap"), model=str(session / "broken.yaml")
            ),
            timeout=60.0,
        )
        assert not result.success and "hysteresis_fraction" in result.message

        job = afm.send(
            "sim2real",
            Sim2Real.Goal(
                recording=str(session / "session.mcap"), report_dir=str(session / "cancelled")
            ),
            wait=False,
        )
        assert job.cancel()
        result = job.result(120.0)
        assert (
            not result.success
            and "cancelled" in result.message
            and math.isnan(result.heldout_reduction)
        )


def test_cli_refuses_bad_input_with_the_reason(session, tmp_path):
    import subprocess
    import sys

    afm = [sys.executable, "-m", "afm_bringup.cli", "sim2real"]

    def run(*args):
        done = subprocess.run(
            afm + [str(a) for a in args], capture_output=True, text=True, timeout=120
        )
        return done.returncode, done.stderr

    code, err = run(tmp_path / "missing.mcap", "--report", tmp_path / "r1")
    assert code != 0 and "missing.mcap" in err and "does not exist" in err
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("a lab's notes")
    code, err = run(session / "session.mcap", "--report", tmp_path / "full")
    assert (
        code != 0
        and "not empty" in err
        and (tmp_path / "full" / "keep.txt").read_text() == "a lab's notes"
    )
    data = (session / "session.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) // 3])
    code, err = run(
        tmp_path / "cut.mcap", "--model", session / "model.yaml", "--report", tmp_path / "r2"
    )
    assert code != 0 and "cut.mcap" in err
    code, err = run(
        session / "session.mcap", "--effects", "tip_radius,friktion", "--report", tmp_path / "r3"
    )
    assert (
        code != 0
        and "effects: unknown 'friktion'" in err
        and "friction" in err
        and not (tmp_path / "r3").exists()
    )


def test_cli_leaves_out_a_command_without_its_measurement_when_asked(session, tmp_path):
    """A restarted recorder's file begins with the latched commands of the session before it,
    whose measurements are not latched: the error named a Python argument, the CLI had none."""
    import subprocess
    import sys

    from afm_core.recording import RecordingReader, RecordingWriter

    cut = tmp_path / "one_line_lost.mcap"
    dropped = []
    with RecordingReader(session / "session.mcap") as reader, RecordingWriter(cut) as writer:
        channels = {}
        for schema, channel, message in reader.raw_messages():
            if channel.topic == "/afm/scan_line" and not dropped:
                dropped.append(message.log_time)
                continue
            if channel.topic not in channels:
                channels[channel.topic] = writer.add_channel(
                    channel.topic, schema.name, [], definition=schema.data.decode()
                )
            writer.write(channels[channel.topic], message.log_time, message.data)
    assert dropped

    def run(*extra):
        command = [sys.executable, "-m", "afm_bringup.cli", "sim2real", str(cut)]
        command += ["--model", str(session / "model.yaml"), *map(str, extra)]
        return subprocess.run(command, capture_output=True, text=True, timeout=300)

    refused = run("--report", tmp_path / "r1")
    assert refused.returncode == 2, refused.stderr
    assert "has no measurement" in refused.stderr
    assert "afm sim2real --skip-incomplete" in refused.stderr
    done = run("--skip-incomplete", "--effects", "tip_radius", "--report", tmp_path / "r2")
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("verdict: ") and (tmp_path / "r2" / "report.md").is_file()
