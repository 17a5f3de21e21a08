"""Recording fixes: rosbag2 folders that list files outside themselves, nothing to replay, a
rate that overflows the schedule, recovering what holds nothing, unfinished files named as
such, `afm info` into a closed pipe, and a .part that may be a live recording. Every file here
is written by the project's own RecordingWriter."""

import os
import shutil
import struct
import subprocess
import sys

import pytest
import yaml
from sample_messages import cdr, force_trace
from test_recording_files import STREAM, write_session

from afm_bringup.cli import main as afm
from afm_core.recording import RecordingError, RecordingReader, RecordingWriter, recover


def bag_folder(tmp_path, listed, **information):
    folder = tmp_path / "bag"
    folder.mkdir()
    info = {
        "version": 9,
        "storage_identifier": "mcap",
        "compression_mode": "",
        "relative_file_paths": listed,
        **information,
    }
    (folder / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": info}))
    return folder


def outside_recording(tmp_path):
    """A readable recording outside the bag folder: what an escaping entry would have opened."""
    path = tmp_path / "elsewhere" / "secret.mcap"
    path.parent.mkdir()
    write_session(path, n=1)
    return path


# -- 1. a rosbag2 folder reads only its own files --------------------------------------------
@pytest.mark.parametrize("how", ["absolute", "dotdot"])
def test_a_listed_file_outside_the_folder_is_refused(tmp_path, how):
    target = outside_recording(tmp_path)
    entry = str(target) if how == "absolute" else "../elsewhere/secret.mcap"
    folder = bag_folder(tmp_path, [entry])
    with pytest.raises(RecordingError, match="outside the folder") as refused:
        RecordingReader(folder)
    assert str(folder) in str(refused.value) and repr(entry) in str(refused.value)


def test_a_listed_non_mcap_file_outside_is_refused_without_its_bytes(tmp_path):
    secret = tmp_path / "passwords.txt"
    secret.write_text("root:hunter2\n")
    folder = bag_folder(tmp_path, ["../passwords.txt"])
    with pytest.raises(RecordingError, match="outside the folder") as refused:
        RecordingReader(folder)
    assert "root:hun" not in str(refused.value)


def test_a_symlink_out_of_the_folder_is_refused(tmp_path):
    target = outside_recording(tmp_path)
    folder = bag_folder(tmp_path, ["bag_0.mcap"])
    (folder / "bag_0.mcap").symlink_to(target)
    with pytest.raises(RecordingError, match="outside the folder"):
        RecordingReader(folder)


def test_a_listed_file_inside_the_folder_still_reads(tmp_path):
    folder = bag_folder(tmp_path, ["sub/../bag_0.mcap"])
    write_session(folder / "bag_0.mcap", n=1)
    with RecordingReader(folder) as reader:
        assert reader.message_count == 3


def test_relative_file_paths_as_a_string_is_not_rosbag2_metadata(tmp_path):
    folder = bag_folder(tmp_path, "my_bag_0.mcap")
    write_session(folder / "my_bag_0.mcap", n=1)
    with pytest.raises(RecordingError, match="not rosbag2 metadata") as refused:
        RecordingReader(folder)
    assert "split into" not in str(refused.value)


def test_a_folder_without_metadata_or_mcap_says_so(tmp_path):
    folder = tmp_path / "nothing"
    folder.mkdir()
    with pytest.raises(RecordingError, match=r"no metadata.yaml and no \.mcap file;"):
        RecordingReader(folder)


# -- 2, 3. nothing to replay, an overflowing rate --------------------------------------------
def silent_and_one_trace(path):
    """/afm/scan recorded with 0 messages beside 3 force traces 1 s apart."""
    with RecordingWriter(path) as rec:
        rec.add_channel("/afm/scan", "afm_msgs/msg/RasterScan", [STREAM])
        trace = rec.add_channel("/afm/force_trace", "afm_msgs/msg/ForceTrace", [STREAM])
        for i in range(3):
            rec.write(trace, (i + 1) * 10**9, cdr(force_trace(i)))
    return path


def test_check_playable_refuses_nothing_to_replay_and_huge_stretches(tmp_path):
    from afm_bringup.replay_node import MAX_PLAYBACK_S, check_playable

    path = silent_and_one_trace(tmp_path / "s.mcap")
    with RecordingReader(path) as reader:
        check_playable(reader, ["/afm/scan", "/afm/force_trace"], 1.0)
        check_playable(reader, ["/afm/force_trace"], 2.0 / MAX_PLAYBACK_S)
        with pytest.raises(RecordingError, match=r"nothing to replay.*/afm/scan \(0 messages\)"):
            check_playable(reader, ["/afm/scan"], 1.0)
        for rate in (1e-300, 5e-324, 1.0 / MAX_PLAYBACK_S):
            with pytest.raises(RecordingError, match=r"parameter rate=.*limit is 1e\+09 s"):
                check_playable(reader, ["/afm/force_trace"], rate)


def replay(tmp_path, nodes, **overrides):
    return nodes("replay", start_delay=0.0, publish_clock="false", **overrides).wait(30)


@pytest.mark.ros
@pytest.mark.parametrize("loop", ["true", "false"])
def test_replay_of_no_messages_is_refused(tmp_path, nodes, loop):
    empty = tmp_path / "empty.mcap"
    with RecordingWriter(empty) as rec:
        rec.add_channel("/afm/force_trace", "afm_msgs/msg/ForceTrace", [STREAM])
    code, output = replay(tmp_path, nodes, input=empty, loop=loop)
    assert code == 2 and "nothing to replay" in output, output
    assert "/afm/force_trace (0 messages)" in output and "replayed 0" not in output


@pytest.mark.ros
def test_replay_of_topics_without_messages_is_refused(tmp_path, nodes):
    path = silent_and_one_trace(tmp_path / "s.mcap")
    code, output = replay(tmp_path, nodes, input=path, loop="true", topics="['/afm/scan']")
    assert code == 2 and "nothing to replay" in output and "/afm/scan (0 messages)" in output


@pytest.mark.ros
def test_replay_at_a_rate_that_overflows_is_refused_at_start(tmp_path, nodes):
    path = silent_and_one_trace(tmp_path / "s.mcap")
    code, output = replay(tmp_path, nodes, input=path, rate="1e-300")
    assert code == 2 and "parameter rate=1e-300" in output and "limit" in output, output
    assert "OverflowError" not in output


# -- 4. recover: nothing to recover, no file left behind --------------------------------------
def test_recover_of_a_file_cut_to_20_bytes_says_so_and_writes_nothing(tmp_path, capsys):
    write_session(tmp_path / "s.mcap", n=2)
    cut = tmp_path / "x.mcap"
    cut.write_bytes((tmp_path / "s.mcap").read_bytes()[:20])
    for _ in range(2):  # a second run says the same, not that the output exists
        assert afm(["recover", str(cut)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "Errno" not in err, err
        assert f"{str(cut)!r} holds nothing to recover" in err and "already exists" not in err
        assert sorted(p.name for p in tmp_path.iterdir()) == ["s.mcap", "x.mcap"]


def test_recover_of_a_recording_without_messages_writes_nothing(tmp_path, capsys):
    empty = tmp_path / "e.mcap"
    with RecordingWriter(empty) as rec:
        rec.add_channel("/afm/force_trace", "afm_msgs/msg/ForceTrace", [STREAM])
    with pytest.raises(RecordingError, match="holds nothing to recover.*no file written"):
        recover(empty)
    assert afm(["recover", str(empty), "-o", str(tmp_path / "out.mcap")]) == 2
    assert "nothing to recover" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["e.mcap"]


def test_recover_still_saves_a_cut_file(tmp_path):
    write_session(tmp_path / "s.mcap", n=20)
    data = (tmp_path / "s.mcap").read_bytes()
    (tmp_path / "c.mcap").write_bytes(data[: len(data) * 2 // 3])
    recovery = recover(tmp_path / "c.mcap")
    assert 0 < recovery.messages < 60 and recovery.path.exists()


# -- 5. unfinished files are named as such --------------------------------------------------
@pytest.mark.parametrize("cut", [1, 8, 29, 40, 300])
def test_a_file_cut_before_its_end_is_unfinished_with_how_to_recover(tmp_path, cut):
    write_session(tmp_path / "s.mcap", n=3)
    path = tmp_path / "c.mcap"
    path.write_bytes((tmp_path / "s.mcap").read_bytes()[:-cut])
    with pytest.raises(RecordingError) as refused:
        RecordingReader(path)
    text = str(refused.value)
    assert "is unfinished" in text and f"`afm recover {path}`" in text, text
    assert f"it ends at byte {path.stat().st_size}" in text
    assert "()" not in text and "non-negative" not in text and "exceeds limit" not in text


def test_a_killed_recorders_part_is_unfinished_in_every_reader(tmp_path, capsys):
    now = [0.0]
    rec = RecordingWriter(tmp_path / "k.mcap", flush_interval=1.0, clock=lambda: now[0])
    channel = rec.add_channel("/afm/force_trace", "afm_msgs/msg/ForceTrace", [STREAM])
    for i in range(5):
        rec.write(channel, (i + 1) * 10**9, cdr(force_trace(i)))
    now[0] = 2.0
    assert rec.flush_if_due()
    part = tmp_path / "killed.mcap.part"  # what a SIGKILL leaves: the bytes so far, no footer
    shutil.copyfile(rec.part, part)
    with pytest.raises(RecordingError, match=r"unfinished.*afm recover .*killed\.mcap\.part"):
        RecordingReader(part)
    assert afm(["info", str(part)]) == 2
    err = capsys.readouterr().err
    assert "unfinished" in err and "has length" not in err, err
    assert recover(part, tmp_path / "r.mcap").messages == 5


def test_an_empty_reason_is_replaced_by_where_the_file_ends(tmp_path):
    path = tmp_path / "s.mcap"
    write_session(path, n=2)
    data = bytearray(path.read_bytes())
    footer = len(data) - 8 - 29
    data[footer + 9 : footer + 17] = struct.pack("<Q", len(data))  # summary at the very end
    path.write_bytes(data)
    with pytest.raises(RecordingError, match="truncated or corrupt") as refused:
        RecordingReader(path)
    assert "()" not in str(refused.value) and f"ends at byte {len(data)}" in str(refused.value)


# -- 6. `afm info` into a closed pipe ---------------------------------------------------------
def test_afm_info_into_a_closed_pipe_ends_quietly(tmp_path):
    path = tmp_path / "s.mcap"
    write_session(path, n=1)
    reader_end, writer_end = os.pipe()
    os.close(reader_end)  # the reader has gone before the first line, as `| head -0` would
    done = subprocess.run(
        [sys.executable, "-c", "import sys; from afm_bringup.cli import main; sys.exit(main())"]
        + ["info", str(path)],
        stdout=writer_end,
        stderr=subprocess.PIPE,
        text=True,
        timeout=120,
    )
    os.close(writer_end)
    assert done.returncode == 141 and done.stderr == "", done.stderr


# -- 7. a .part in the way may be a live recording ------------------------------------------
def test_a_part_in_the_way_is_never_to_be_removed(tmp_path):
    live = RecordingWriter(tmp_path / "x.mcap")
    try:
        with pytest.raises(RecordingError) as refused:
            RecordingWriter(tmp_path / "x.mcap")
    finally:
        live.close()
    text = str(refused.value)
    assert "recording in progress" in text and "afm recover" in text, text
    assert "remove" not in text
