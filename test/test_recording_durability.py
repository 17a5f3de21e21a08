"""What survives damage: a flipped bit in a chunk, a writer killed mid-recording (no ROS)."""

import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from mcap.records import Message
from sample_messages import cdr, force_trace, landmarks, raster_scan

from afm_core.recording import (
    QosDescription,
    RecordingError,
    RecordingReader,
    RecordingWriter,
    recover,
)
from afm_core.recording.reader import read_chunk_at
from afm_core.recording.writer import FLUSH_DUE_SHARE

TOPICS = {
    "/afm/scan": ("afm_msgs/msg/RasterScan", raster_scan),
    "/afm/force_trace": ("afm_msgs/msg/ForceTrace", force_trace),
    "/afm/landmarks": ("afm_msgs/msg/LandmarkArray", landmarks),
}


def write_chunked(path, n=8, chunk_size=16 * 1024):
    """Small chunks, so the file has several; returns every written (topic, log_time)."""
    written = []
    with RecordingWriter(path, chunk_size=chunk_size, flush_interval=None) as rec:
        channels = {t: rec.add_channel(t, ty, [QosDescription()]) for t, (ty, _) in TOPICS.items()}
        for i in range(n):
            for topic, (_, make) in TOPICS.items():
                log_time = 1_000_000_000 * (i + 1) + len(written)
                rec.write(channels[topic], log_time, cdr(make(i)))
                written.append((topic, log_time))
    return written


def chunk_messages(path):
    """[(chunk index record, [log_time, ...])] of a sound file, in file order."""
    with RecordingReader(path) as reader, open(path, "rb") as stream:
        indexes = sorted(reader.summary.chunk_indexes, key=lambda i: i.chunk_start_offset)
        return [
            (i, [r.log_time for r in read_chunk_at(stream, i) if isinstance(r, Message)])
            for i in indexes
        ]


def flip_bit(path, offset):
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x10
    path.write_bytes(bytes(data))


def test_a_flipped_bit_in_a_chunk_is_reported_and_recover_keeps_every_other_message(tmp_path):
    path = tmp_path / "s.mcap"
    written = write_chunked(path)
    chunks = chunk_messages(path)
    assert len(chunks) >= 3
    victim, lost = chunks[1]
    flip_bit(path, victim.chunk_start_offset + victim.chunk_length // 2)

    with RecordingReader(path) as reader:
        damaged = reader.damaged_chunks()
        assert [d.offset for d in damaged] == [victim.chunk_start_offset]
        with pytest.raises(RecordingError, match="corrupt: 1 of .* chunks damaged"):
            list(reader.raw_messages())
        with pytest.raises(RecordingError, match="afm recover"):
            list(reader.messages())

    recovery = recover(path)
    assert [d.offset for d in recovery.damaged] == [victim.chunk_start_offset]
    with RecordingReader(recovery.path) as reader:
        kept = sorted(m.log_time for _, _, m in reader.raw_messages())
        assert reader.damaged_chunks() == []
    assert kept == sorted(t for _, t in written if t not in set(lost))
    assert recovery.messages == len(written) - len(lost)


def test_a_flipped_bit_in_the_summary_is_reported_and_recover_walks_the_chunks(tmp_path):
    path = tmp_path / "s.mcap"
    written = write_chunked(path)
    with RecordingReader(path) as reader:
        channel = next(iter(reader.summary.channels.values()))
    data = path.read_bytes()
    where = data.rindex(channel.topic.encode())  # the topic's name in the summary's channel
    flip_bit(path, where + 5)
    with pytest.raises(RecordingError, match="summary section CRC"):
        RecordingReader(path)
    recovery = recover(path)
    assert recovery.messages == len(written) and not recovery.damaged
    with RecordingReader(recovery.path) as reader:
        assert set(reader.topics()) == set(TOPICS)


def test_a_damaged_unfinished_file_is_recovered_around_the_damage(tmp_path):
    """A .part (no summary, no index): the walk in file order skips the damaged chunk."""
    path = tmp_path / "s.mcap"
    written = write_chunked(path)
    chunks = chunk_messages(path)
    victim, lost = chunks[-2]
    cut = victim.chunk_start_offset + victim.chunk_length + 10_000  # into the chunks after it
    part = tmp_path / "t.mcap.part"
    part.write_bytes(path.read_bytes()[: min(cut, chunks[-1][0].chunk_start_offset + 20)])
    flip_bit(part, victim.chunk_start_offset + victim.chunk_length // 2)
    recovery = recover(part)
    assert len(recovery.damaged) == 1 and recovery.stopped  # and it ends early: cut
    complete = [times for _, times in chunks[:-2]]
    expected = sorted(t for times in complete for t in times)
    with RecordingReader(recovery.path) as reader:
        assert sorted(m.log_time for _, _, m in reader.raw_messages()) == expected
    assert len(expected) < len(written) - len(lost)


class FakeClock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def test_the_open_chunk_is_written_once_its_oldest_message_is_due(tmp_path):
    clock = FakeClock()
    rec = RecordingWriter(tmp_path / "s.mcap", flush_interval=1.0, clock=clock)
    channel = rec.add_channel("/afm/landmarks", "afm_msgs/msg/LandmarkArray", [QosDescription()])
    size_before = rec.part.stat().st_size
    rec.write(channel, 1, cdr(landmarks(0)))
    clock.now = FLUSH_DUE_SHARE * 1.0 - 0.01
    assert not rec.flush_if_due() and rec.part.stat().st_size == size_before
    clock.now = FLUSH_DUE_SHARE * 1.0
    assert rec.flush_if_due() and rec.part.stat().st_size > size_before
    assert not rec.flush_if_due()  # nothing new since
    assert rec.poll_period + FLUSH_DUE_SHARE * 1.0 == pytest.approx(1.0)
    rec.close()


WRITER_SCRIPT = textwrap.dedent(
    """
    import sys, time
    sys.path.insert(0, {test_dir!r})
    from sample_messages import cdr, force_trace
    from afm_core.recording import QosDescription, RecordingWriter
    rec = RecordingWriter({path!r}, flush_interval={interval})
    channel = rec.add_channel("/afm/force_trace", "afm_msgs/msg/ForceTrace", [QosDescription()])
    data = cdr(force_trace(0))
    next_poll = time.monotonic()
    while True:  # what a recorder does: messages as they come, a flush check on a timer
        now = time.time_ns()
        rec.write(channel, now, data)
        print(now, flush=True)
        if time.monotonic() >= next_poll:
            rec.flush_if_due()
            next_poll += rec.poll_period
        time.sleep(0.02)
    """
)


def test_a_killed_writer_loses_at_most_the_flush_interval(tmp_path):
    interval = 1.0
    path = tmp_path / "k.mcap"
    script = WRITER_SCRIPT.format(
        test_dir=str(Path(__file__).parent), path=str(path), interval=interval
    )
    child = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    time.sleep(4.0)
    child.send_signal(signal.SIGKILL)
    out, _ = child.communicate(timeout=10)
    written = [int(line) for line in out.split()]
    assert len(written) > 50  # it did run
    recovery = recover(tmp_path / "k.mcap.part")
    with RecordingReader(recovery.path) as reader:
        kept = [m.log_time for _, _, m in reader.raw_messages()]
    assert kept == written[: len(kept)]  # a prefix, byte-for-byte order
    lost_s = (written[-1] - kept[-1]) * 1e-9
    # bound: the flush interval, plus one message period and scheduling slack on a loaded box
    assert lost_s <= interval + 0.2, f"lost the last {lost_s:.2f} s"
    print(f"killed writer: lost the last {lost_s:.2f} s ({len(written) - len(kept)} messages)")


@pytest.mark.parametrize(
    "content, complaint",
    [
        (b"", "is empty"),
        (b"\x89MCA", "ends within the MCAP magic"),
        (b"# lab notes, not a recording\n", "is not an MCAP recording"),
    ],
)
def test_a_file_that_is_no_recording_is_refused_and_recover_writes_nothing(
    tmp_path, content, complaint
):
    path = tmp_path / "notes.mcap"
    path.write_bytes(content)
    with pytest.raises(RecordingError, match=complaint):
        RecordingReader(path)
    with pytest.raises(RecordingError, match=complaint + ".*no file written"):
        recover(path, tmp_path / "out.mcap")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.mcap"]
    assert path.read_bytes() == content
