"""A rosbag2 recording given as its folder (what `ros2 bag record -s mcap -o NAME` writes): read
through its one MCAP file, or refused with what to do."""

import subprocess
import sys

import pytest
import yaml
from test_recording_files import write_session

from afm_core.recording import RecordingError, RecordingReader


def bag_folder(tmp_path, files=("session_0.mcap",), written=None, **information):
    """A folder as rosbag2 (Jazzy) lays it out; `written`: which listed files exist."""
    folder = tmp_path / "session"
    folder.mkdir()
    for name in files if written is None else written:
        write_session(folder / name, n=2)
    info = {
        "version": 9,
        "storage_identifier": "mcap",
        "duration": {"nanoseconds": 2_000_000_000},
        "starting_time": {"nanoseconds_since_epoch": 1_000_000_001},
        "message_count": 6,
        "topics_with_message_count": [],
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": list(files),
        "files": [{"path": name, "message_count": 6} for name in files],
        "custom_data": None,
        "ros_distro": "jazzy",
        **information,
    }
    (folder / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": info}))
    return folder


def test_a_rosbag2_folder_reads_as_its_mcap_file(tmp_path):
    folder = bag_folder(tmp_path)
    with RecordingReader(folder) as reader:
        assert reader.path == folder / "session_0.mcap"
        assert reader.message_count == 6
        assert set(reader.topics()) == {"/afm/scan", "/afm/force_trace", "/afm/landmarks"}


def test_a_folder_listing_its_own_name_before_the_file_is_read(tmp_path):
    folder = bag_folder(tmp_path, files=("session/session_0.mcap",), written=("session_0.mcap",))
    with RecordingReader(folder) as reader:
        assert reader.message_count == 6


def test_a_folder_without_metadata_but_one_mcap_file_reads_as_it(tmp_path):
    folder = tmp_path / "copied"
    folder.mkdir()
    write_session(folder / "only.mcap", n=1)
    with RecordingReader(folder) as reader:
        assert reader.message_count == 3


@pytest.mark.parametrize(
    "files, written, information, complaint",
    [
        (("a_0.mcap", "a_1.mcap"), None, {}, r"split into 2 files \(a_0.mcap, a_1.mcap\)"),
        (("a_0.db3",), (), {"storage_identifier": "sqlite3"}, "in sqlite3 storage, not MCAP"),
        (("a_0.mcap.zstd",), (), {"compression_mode": "FILE"}, "compression_mode FILE"),
        (("a_0.mcap",), (), {"compression_mode": "MESSAGE"}, "compression_mode MESSAGE"),
        (("a_0.mcap",), (), {}, "lists 'a_0.mcap', which is not in the folder"),
        ((), (), {}, "lists no file"),
    ],
)
def test_what_cannot_be_read_is_refused_with_what_to_do(
    tmp_path, files, written, information, complaint
):
    folder = bag_folder(tmp_path, files=files, written=written, **information)
    with pytest.raises(RecordingError, match=complaint) as refused:
        RecordingReader(folder)
    assert str(folder) in str(refused.value)
    if "which is not" not in complaint and "no file" not in complaint:
        assert "ros2 bag convert" in str(refused.value)


def test_a_folder_that_is_no_bag_is_refused_as_a_folder(tmp_path):
    with pytest.raises(RecordingError, match="a folder with no metadata.yaml and no .mcap file;"):
        RecordingReader(tmp_path)
    write_session(tmp_path / "monday.mcap", n=1)
    write_session(tmp_path / "tuesday.mcap", n=1)
    with pytest.raises(RecordingError, match=r"2 .mcap files \(monday.mcap, tuesday.mcap\)"):
        RecordingReader(tmp_path)
    (tmp_path / "metadata.yaml").write_text("- not: rosbag2\n")
    with pytest.raises(RecordingError, match="metadata.yaml is not rosbag2 metadata"):
        RecordingReader(tmp_path)


def test_afm_info_takes_the_folder(tmp_path):
    folder = bag_folder(tmp_path)
    shown = subprocess.run(
        [sys.executable, "-m", "afm_bringup.cli", "info", str(folder)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert shown.returncode == 0, shown.stderr
    assert "/afm/force_trace" in shown.stdout and "session_0.mcap" in shown.stdout


def test_sim2real_refuses_an_unreadable_bag_as_a_session_error(tmp_path):
    from afm_core.sim2real.diagnose import run_sim2real
    from afm_core.sim2real.session import SessionError

    folder = bag_folder(tmp_path, files=("a_0.mcap", "a_1.mcap"))
    with pytest.raises(SessionError, match="split into 2 files"):
        run_sim2real(folder, None, tmp_path / "report")
    assert not (tmp_path / "report").exists()
