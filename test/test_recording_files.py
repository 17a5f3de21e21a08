"""The MCAP writer and reader without DDS: values, schemas, rosbag2 metadata, safety."""

import errno
import os

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.reader import read_ros2_messages
from sample_messages import cdr, force_trace, landmarks, raster_scan

from afm_core.recording import (
    QosDescription,
    RecordingError,
    RecordingReader,
    RecordingWriter,
    full_message_definition,
    recover_recording,
)
from afm_core.recording import writer as writer_module

LATCHED = QosDescription(depth=1, durability="transient_local")
STREAM = QosDescription(depth=5, reliability="best_effort")


def write_session(path, n=6):
    originals = {"/afm/scan": [], "/afm/force_trace": [], "/afm/landmarks": []}
    with RecordingWriter(path, chunk_size=64 * 1024) as rec:
        channels = {
            "/afm/scan": rec.add_channel("/afm/scan", "afm_msgs/msg/RasterScan", [LATCHED]),
            "/afm/force_trace": rec.add_channel(
                "/afm/force_trace", "afm_msgs/msg/ForceTrace", [STREAM]
            ),
            "/afm/landmarks": rec.add_channel(
                "/afm/landmarks", "afm_msgs/msg/LandmarkArray", [LATCHED]
            ),
        }
        for i in range(n):
            for topic, make in (
                ("/afm/scan", raster_scan),
                ("/afm/force_trace", force_trace),
                ("/afm/landmarks", landmarks),
            ):
                msg = make(i)
                originals[topic].append(msg)
                rec.write(
                    channels[topic], 1_000_000_000 * (i + 1) + len(originals[topic]), cdr(msg)
                )
    return originals


def test_independent_mcap_ros2_reader_decodes_every_value(tmp_path):
    path = tmp_path / "s.mcap"
    originals = write_session(path)
    decoded = {topic: [] for topic in originals}
    for item in read_ros2_messages(str(path)):
        decoded[item.channel.topic].append(item.ros_msg)
    for got, want in zip(decoded["/afm/scan"], originals["/afm/scan"]):
        assert bytes(got.height.data) == bytes(want.height.data)
        assert got.pixel_size_x == want.pixel_size_x and got.pair_id == want.pair_id
        assert list(got.line_start_times) == list(want.line_start_times)
        assert got.header.stamp.sec == want.header.stamp.sec
    for got, want in zip(decoded["/afm/force_trace"], originals["/afm/force_trace"]):
        np.testing.assert_array_equal(got.vertical_deflection, want.vertical_deflection)
        assert got.sample_rate == want.sample_rate and got.object_id == want.object_id
    for got, want in zip(decoded["/afm/landmarks"], originals["/afm/landmarks"]):
        assert [lm.id for lm in got.landmarks] == [lm.id for lm in want.landmarks]
        np.testing.assert_array_equal(got.landmarks[1].covariance, want.landmarks[1].covariance)
    assert {t: len(v) for t, v in decoded.items()} == {t: len(v) for t, v in originals.items()}


def test_offline_reader_returns_numpy_arrays(tmp_path):
    path = tmp_path / "s.mcap"
    originals = write_session(path, n=4)
    with RecordingReader(path) as reader:
        scans = reader.arrays("/afm/scan")
        traces = reader.arrays("/afm/force_trace")
        marks = reader.arrays("/afm/landmarks")
    from afm_ros.conversions import image_msg_to_array

    expected = np.stack([image_msg_to_array(m.height) for m in originals["/afm/scan"]])
    np.testing.assert_array_equal(scans["height"], expected)
    assert scans["height"].dtype == np.float32 and scans["height"].shape == (4, 24, 32)
    # ragged per-line times (0 and 90 deg scans alternate) stay a list
    assert [len(t) for t in scans["line_start_times"]] == [24, 32, 24, 32]
    np.testing.assert_allclose(
        traces["vertical_deflection"][2], originals["/afm/force_trace"][2].vertical_deflection
    )
    np.testing.assert_allclose(
        scans["log_time"], [1.000000001 * 0 + 1 + 1e-9 * 1, 2 + 2e-9, 3 + 3e-9, 4 + 4e-9]
    )
    assert marks["landmarks"][0][2]["position.x"] == pytest.approx(2e-6)


def test_the_viewers_colour_images_and_an_empty_image_read_as_arrays(tmp_path):
    """What the graph records by default: the rgb8 scan image (rows x columns x 3), and a
    message whose image is empty (a tip shape without its certainty map: encoding '')."""
    from sensor_msgs.msg import Image
    from std_msgs.msg import Header

    from afm_core.recording import QosDescription
    from afm_ros.height_image import height_image_msg

    height = np.random.default_rng(3).normal(size=(5, 7)) * 1e-9
    coloured, _scale = height_image_msg(height, Header(frame_id="afm_scanner"))
    path = tmp_path / "images.mcap"
    with RecordingWriter(path) as rec:
        channel = rec.add_channel("/afm/scan/image", "sensor_msgs/msg/Image", [QosDescription()])
        rec.write(channel, 1, cdr(coloured))
        rec.write(channel, 2, cdr(Image()))
    with RecordingReader(path) as reader:
        images = reader.arrays("/afm/scan/image")["image"]
    from afm_core.imaging.colour_map import height_to_rgb

    np.testing.assert_array_equal(images[0], height_to_rgb(height)[0])
    assert images[1].shape == (0, 0)


def test_summary_holds_what_rosbag2_needs(tmp_path):
    path = tmp_path / "s.mcap"
    write_session(path, n=3)
    with open(path, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        summary = reader.get_summary()
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert header.profile == "ros2"
    assert summary.statistics.message_count == 9
    assert set(summary.statistics.channel_message_counts.values()) == {3}
    assert summary.chunk_indexes and all(
        ci.message_index_length > 0 for ci in summary.chunk_indexes
    )
    assert all(ci.compression == "zstd" for ci in summary.chunk_indexes)
    assert metadata["rosbag2"]["serialized_metadata"] == ""  # rosbag2 then reads QoS as version 8
    for channel in summary.channels.values():
        assert channel.message_encoding == "cdr"
        profiles = yaml.safe_load(channel.metadata["offered_qos_profiles"])
        assert set(profiles[0]) == {
            "history",
            "depth",
            "reliability",
            "durability",
            "deadline",
            "lifespan",
            "liveliness",
            "liveliness_lease_duration",
            "avoid_ros_namespace_conventions",
        }
        assert all(
            isinstance(profiles[0][k], int)
            for k in ("history", "reliability", "durability", "liveliness")
        )
    scan_channel = next(c for c in summary.channels.values() if c.topic == "/afm/scan")
    assert (
        yaml.safe_load(scan_channel.metadata["offered_qos_profiles"])[0]["durability"] == 1
    )  # transient local
    for schema in summary.schemas.values():
        assert schema.encoding == "ros2msg"


def test_schema_holds_every_dependency_once_depth_first():
    text = full_message_definition("afm_msgs/msg/LandmarkArray")
    names = [line[5:] for line in text.splitlines() if line.startswith("MSG: ")]
    assert names == [
        "afm_msgs/Landmark",
        "geometry_msgs/Point",
        "std_msgs/Header",
        "builtin_interfaces/Time",
    ]
    assert text.count("=" * 80) == len(names)
    assert "Landmark[] landmarks" in text.split("=" * 80)[0]


def test_qos_description_round_trips():
    from afm_core.recording.qos import dump_profiles, load_profiles

    profiles = [LATCHED, STREAM, QosDescription(history="unknown", deadline_ns=2**63 - 1)]
    assert load_profiles(dump_profiles(profiles)) == profiles


@pytest.mark.parametrize(
    "name, complaint",
    [
        ("exists.mcap", "already exists"),
        ("no_suffix.bag", "must end in .mcap"),
        ("missing_dir/x.mcap", "does not exist"),
    ],
)
def test_bad_output_paths_are_refused_by_name(tmp_path, name, complaint):
    (tmp_path / "exists.mcap").write_bytes(b"precious")
    with pytest.raises(RecordingError, match=complaint):
        RecordingWriter(tmp_path / name)
    assert (tmp_path / "exists.mcap").read_bytes() == b"precious"


def test_unfinished_part_file_blocks_the_name(tmp_path):
    (tmp_path / "x.mcap.part").write_bytes(b"unfinished")
    with pytest.raises(RecordingError, match="afm recover"):
        RecordingWriter(tmp_path / "x.mcap")
    # the command it suggests can be pasted into a shell in a folder whose name has a space
    folder = tmp_path / "run 3"
    folder.mkdir()
    (folder / "x.mcap.part").write_bytes(b"unfinished")
    with pytest.raises(RecordingError, match=r"`afm recover '.*/run 3/x.mcap.part'`"):
        RecordingWriter(folder / "x.mcap")


def test_unwritable_location_is_refused(tmp_path):
    with pytest.raises(RecordingError, match="x.mcap"):
        RecordingWriter("/proc/x.mcap")
    assert not os.path.exists("/proc/x.mcap.part")


def test_low_disk_refuses_to_start(tmp_path):
    with pytest.raises(RecordingError, match="min_free_bytes"):
        RecordingWriter(tmp_path / "x.mcap", min_free_bytes=2**62)
    assert list(tmp_path.iterdir()) == []


def test_disk_filling_up_closes_a_readable_recording(tmp_path, monkeypatch):
    rec = RecordingWriter(tmp_path / "x.mcap", free_space_check_bytes=1)
    channel = rec.add_channel("/afm/force_trace", "afm_msgs/msg/ForceTrace", [STREAM])
    rec.write(channel, 1, cdr(force_trace(0)))
    real = writer_module.shutil.disk_usage
    monkeypatch.setattr(
        writer_module.shutil, "disk_usage", lambda p: real(p)._replace(free=rec.min_free_bytes - 1)
    )
    with pytest.raises(RecordingError, match="recording stopped and closed with 2 messages"):
        rec.write(channel, 2, cdr(force_trace(1)))
    with RecordingReader(tmp_path / "x.mcap") as reader:
        assert reader.message_count == 2


class FailingStream:
    """A file that reports ENOSPC once `budget` bytes were written."""

    def __init__(self, real, budget):
        self.real, self.budget = real, budget

    def write(self, data):
        if self.real.tell() + len(data) > self.budget:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return self.real.write(data)

    def __getattr__(self, name):
        return getattr(self.real, name)


def test_write_failure_leaves_no_broken_recording_and_recover_saves_the_rest(
    tmp_path, monkeypatch
):
    path = tmp_path / "x.mcap"
    monkeypatch.setattr(
        writer_module, "open", lambda *a: FailingStream(open(*a), budget=200_000), raising=False
    )
    rec = RecordingWriter(path, chunk_size=4096)
    channel = rec.add_channel("/afm/force_trace", "afm_msgs/msg/ForceTrace", [STREAM])
    with pytest.raises(RecordingError, match="No space left on device.*afm recover"):
        for i in range(100):
            rec.write(channel, i + 1, cdr(force_trace(i)))
    assert not path.exists() and (tmp_path / "x.mcap.part").exists()
    with pytest.raises(RecordingError, match="truncated|no summary"):
        RecordingReader(tmp_path / "x.mcap.part")
    recovered, count = recover_recording(tmp_path / "x.mcap.part")
    assert recovered == tmp_path / "x.recovered.mcap" and 0 < count < 100
    with RecordingReader(recovered) as reader:
        values = reader.arrays("/afm/force_trace")["object_id"]
    np.testing.assert_array_equal(values, np.arange(count))


def test_truncated_recording_is_reported_and_recoverable(tmp_path):
    path = tmp_path / "s.mcap"
    write_session(path, n=20)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(RecordingError, match="afm recover"):
        RecordingReader(cut)
    recovered, count = recover_recording(cut)
    assert 0 < count < 60
    with RecordingReader(recovered) as reader:
        assert reader.message_count == count


def test_reader_names_missing_topics(tmp_path):
    path = tmp_path / "s.mcap"
    write_session(path, n=1)
    with (
        RecordingReader(path) as reader,
        pytest.raises(RecordingError, match="/afm/nothing.*not recorded"),
    ):
        reader.arrays("/afm/nothing")
