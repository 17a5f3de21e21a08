"""Read a recording into numpy arrays without a ROS runtime (mcap + mcap_ros2's decoder).

Streams: messages are decoded one at a time from the chunks they live in; only what a
caller asks for (e.g. one topic's arrays) is ever held in memory.

Integrity: every chunk's CRC (of its uncompressed records, written by every MCAP writer
that enables CRCs, ours included) is checked as the chunk is read, so a damaged chunk is a
RecordingError naming it, never silently changed message contents; `damaged_chunks()`
checks the whole file, and `afm recover` keeps every message of the undamaged chunks.
"""

from __future__ import annotations

import io
import os
import struct
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, ChunkIndex, Message, Schema
from mcap.stream_reader import breakup_chunk
from mcap_ros2.decoder import DecoderFactory
from zstandard import ZstdError

from afm_core.recording.bag_folder import recording_file
from afm_core.recording.errors import RecordingError, recover_command
from afm_core.recording.qos import QosDescription, load_profiles

# What damaged bytes raise inside the mcap library and its decompressors: a CRC mismatch
# (CRCValidationError is a ValueError), a cut record (EOFError, struct.error), a length or id
# that points nowhere (KeyError, IndexError), a corrupt zstd or lz4 frame (ZstdError,
# RuntimeError), garbage where text belongs (UnicodeDecodeError is a ValueError).
DAMAGE_ERRORS = (
    McapError,
    ValueError,
    KeyError,
    IndexError,
    EOFError,
    struct.error,
    ZstdError,
    RuntimeError,
    MemoryError,
)

IMAGE_DTYPES = {
    "32FC1": np.float32,
    "64FC1": np.float64,
    "8UC1": np.uint8,
    "mono8": np.uint8,
    "16UC1": np.uint16,
    "mono16": np.uint16,
    "32SC1": np.int32,
}
# 8-bit colour images (the viewers' /afm/scan/image and /afm/map/image): channels per pixel
COLOUR_CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4}


@dataclass
class TopicInfo:
    topic: str
    type: str
    message_count: int
    schema_encoding: str
    message_encoding: str
    offered_qos: list[QosDescription] = field(default_factory=list)


def image_to_array(image) -> np.ndarray:
    """sensor_msgs/Image (decoded) -> 2-D array (rows x columns x channels for the colour
    encodings), honouring encoding, step and endianness. An empty image (a message that
    carries none, e.g. a tip shape without its certainty map) is a 0 x 0 array whatever its
    encoding says."""
    if image.height == 0 or image.width == 0:
        return np.zeros((image.height, image.width))
    channels = COLOUR_CHANNELS.get(image.encoding, 1)
    name = "uint8" if image.encoding in COLOUR_CHANNELS else IMAGE_DTYPES.get(image.encoding)
    if name is None:
        raise RecordingError(
            f"image encoding {image.encoding!r} not supported; "
            f"expected one of {sorted([*IMAGE_DTYPES, *COLOUR_CHANNELS])}"
        )
    dtype = np.dtype(name).newbyteorder(">" if image.is_bigendian else "<")
    raw = np.frombuffer(bytes(image.data), dtype=np.uint8)
    rows = raw[: image.height * image.step].reshape(image.height, image.step)
    row_bytes = image.width * channels * dtype.itemsize
    shape = (image.height, image.width) + ((channels,) if channels > 1 else ())
    return rows[:, :row_bytes].copy().view(dtype).reshape(shape).astype(dtype.newbyteorder("="))


def _is_image(value) -> bool:
    slots = getattr(value, "__slots__", ())
    return {"height", "width", "encoding", "is_bigendian", "step", "data"} <= set(slots)


def flatten(message, prefix: str = "") -> dict:
    """Decoded message -> {dotted.field: value}; images become arrays, numeric lists arrays.
    A message that is itself an image (sensor_msgs/Image) gives its array as 'image' beside
    its header."""
    out = {}
    if not prefix and _is_image(message):
        return {"image": image_to_array(message), **flatten(message.header, "header.")}
    for name in getattr(message, "__slots__", ()):
        value = getattr(message, name)
        key = f"{prefix}{name}"
        if _is_image(value):
            out[key] = image_to_array(value)
        elif hasattr(value, "__slots__"):
            out.update(flatten(value, key + "."))
        elif isinstance(value, (bytes, bytearray)):
            out[key] = np.frombuffer(bytes(value), dtype=np.uint8)
        elif isinstance(value, (list, tuple)):
            if value and hasattr(value[0], "__slots__"):
                out[key] = [flatten(item) for item in value]
            else:
                out[key] = np.asarray(value)
        else:
            out[key] = value
    return out


def _stack(values: list):
    if not values:
        return np.array([])
    first = values[0]
    if isinstance(first, list):
        return values
    if isinstance(first, np.ndarray):
        if all(isinstance(v, np.ndarray) and v.shape == first.shape for v in values):
            return np.stack(values)
        return values
    return np.asarray(values)


@dataclass(frozen=True)
class DamagedChunk:
    """A chunk whose records cannot be trusted: where it is, the log times it says it holds
    (from its index, which may itself be damaged), and why."""

    offset: int
    start_ns: int
    end_ns: int
    reason: str

    @classmethod
    def of(cls, index, exc: BaseException) -> DamagedChunk:
        """The chunk a summary's chunk index names, damaged as `exc` says."""
        return cls(
            index.chunk_start_offset,
            index.message_start_time,
            index.message_end_time,
            describe_damage(exc),
        )

    def __str__(self) -> str:
        return (
            f"chunk at byte {self.offset} (log times {self.start_ns}..{self.end_ns} ns): "
            f"{self.reason}"
        )


def read_chunk_at(stream, chunk_index: ChunkIndex) -> list:
    """The records of one indexed chunk, its CRC checked; DAMAGE_ERRORS when damaged."""
    stream.seek(chunk_index.chunk_start_offset + 1 + 8, io.SEEK_SET)  # opcode, length
    chunk = Chunk.read(ReadDataStream(stream))
    return breakup_chunk(chunk, validate_crc=True)


FOOTER_BYTES = 1 + 8 + 8 + 8 + 4  # opcode, length, summary_start, summary_offset_start, crc
MAGIC_BYTES = 8
MCAP0_MAGIC = b"\x89MCAP0\r\n"


def check_recording_file(path: Path, refused: str = "") -> None:
    """RecordingError unless `path` is a file that starts as an MCAP recording does (`refused`
    is added to the message). A recording, also a recorder's unfinished .part, starts with the
    MCAP magic, written when it is opened; a file that does not is something else, and no
    chunk of it can be recovered."""
    if path.is_dir():
        raise RecordingError(f"recording {str(path)!r} is a folder; give the recording file")
    if not path.is_file():
        raise RecordingError(f"recording {str(path)!r} does not exist")
    with open(path, "rb") as stream:
        start = stream.read(MAGIC_BYTES)
    if start == MCAP0_MAGIC:
        return
    if not start:
        wrong = "is empty (0 bytes)"
    elif MCAP0_MAGIC.startswith(start):
        wrong = f"ends within the MCAP magic ({len(start)} bytes): it holds no record"
    else:
        wrong = f"is not an MCAP recording (it starts with {start!r}, not the MCAP magic)"
    raise RecordingError(f"{str(path)!r} {wrong}{refused}")


def summary_damage(stream) -> str:
    """'' when the summary section's CRC (in the footer) matches or is not set, else what is
    wrong. The mcap library does not check it; a flipped bit there would change topics,
    types or counts silently. The CRC covers the summary and the footer up to the CRC.
    Leaves the stream at its start."""
    try:
        return _summary_damage(stream)
    finally:
        stream.seek(0)


def _summary_damage(stream) -> str:
    end = stream.seek(0, io.SEEK_END)
    footer_start = end - MAGIC_BYTES - FOOTER_BYTES
    if footer_start < MAGIC_BYTES:
        return ""
    stream.seek(footer_start)
    footer = stream.read(FOOTER_BYTES + MAGIC_BYTES)
    opcode, length, summary_start, _offsets, expected = struct.unpack(
        "<BQQQI", footer[:FOOTER_BYTES]
    )
    if footer[FOOTER_BYTES:] != MCAP0_MAGIC or opcode != Opcode.FOOTER or length != 20:
        return ""  # no footer (an unfinished file): nothing to check here, the reader says why
    if expected == 0 or summary_start == 0:
        return ""
    footer = footer[:FOOTER_BYTES]
    if not MAGIC_BYTES <= summary_start <= footer_start:
        return f"the footer points the summary at byte {summary_start}, outside the file"
    stream.seek(summary_start)
    actual = zlib.crc32(stream.read(footer_start - summary_start) + footer[:-4])
    if actual != expected:
        return f"summary section CRC {actual:#010x} != {expected:#010x} in the footer"
    return ""


RECORD_HEADER_BYTES = 1 + 8  # opcode, length
# a walk over the record headers to say where a file ends gives up after this many records
END_WALK_RECORDS = 1_000_000


def has_footer(stream) -> bool:
    """True when the file ends as a finished MCAP file does: a footer record, then the magic.
    A recorder writes them last, so a killed recorder's .part, or a file cut short, has none.
    Leaves the stream at its start."""
    try:
        end = stream.seek(0, io.SEEK_END)
        if end < 2 * MAGIC_BYTES + FOOTER_BYTES:
            return False
        stream.seek(end - MAGIC_BYTES - FOOTER_BYTES)
        tail = stream.read(FOOTER_BYTES + MAGIC_BYTES)
    finally:
        stream.seek(0)
    opcode, length = struct.unpack("<BQ", tail[:RECORD_HEADER_BYTES])
    return tail[FOOTER_BYTES:] == MCAP0_MAGIC and opcode == Opcode.FOOTER and length == 20


def footer_summary_start(stream) -> int:
    """Where the footer of a finished file says its summary starts (0: no summary)."""
    try:
        end = stream.seek(0, io.SEEK_END)
        stream.seek(end - MAGIC_BYTES - FOOTER_BYTES + RECORD_HEADER_BYTES)
        return struct.unpack("<Q", stream.read(8))[0]
    finally:
        stream.seek(0)


def _record_name(opcode: int) -> str:
    try:
        return f"{Opcode(opcode).name} record"
    except ValueError:
        return f"record of unknown opcode {opcode:#04x}"


def describe_end(stream) -> str:
    """Where the file ends, found by walking the record headers from the magic on (only their
    lengths are read): after a complete record, or how far into which one. Leaves the stream
    at its start."""
    try:
        end = stream.seek(0, io.SEEK_END)
        offset, records = MAGIC_BYTES, 0
        while offset < end and records < END_WALK_RECORDS:
            stream.seek(offset)
            header = stream.read(RECORD_HEADER_BYTES)
            if end - offset == MAGIC_BYTES and header == MCAP0_MAGIC:
                return f"it ends at byte {end}: {records} complete records, then the end magic"
            if len(header) < RECORD_HEADER_BYTES:
                return (
                    f"it ends at byte {end}, {end - offset} bytes into the header of a record "
                    f"at byte {offset}, after {records} complete records"
                )
            opcode, length = struct.unpack("<BQ", header)
            record_end = offset + RECORD_HEADER_BYTES + length
            if record_end > end:
                return (
                    f"it ends at byte {end}, {end - offset} of {record_end - offset} bytes into "
                    f"a {_record_name(opcode)} at byte {offset}, after {records} complete "
                    "records"
                )
            offset, records = record_end, records + 1
        if offset == end:
            return f"it ends at byte {end}, after its last complete record ({records} records)"
        return f"it ends at byte {end}"
    finally:
        stream.seek(0)


def describe_damage(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}"[:200]


class RecordingReader:
    """Open an MCAP recording (ours or rosbag2's, also given as its folder) for offline
    evaluation.

    validate_crcs (default True): each chunk's CRC is checked when it is read, and a
    mismatch is a RecordingError naming the damaged chunks; False reads what is there."""

    def __init__(self, path: str | os.PathLike, validate_crcs: bool = True):
        self.path = recording_file(Path(path))
        check_recording_file(self.path)
        self._stream = open(self.path, "rb")
        try:
            finished = has_footer(self._stream)
            where = "" if finished else describe_end(self._stream)
        except OSError as exc:
            self._stream.close()
            raise RecordingError(f"recording {str(self.path)!r}: cannot read it ({exc})") from exc
        if not finished:
            # a killed recorder's .part, or a file cut short: what the mcap library would make
            # of the bytes at the end (a garbage length, an empty message) says nothing
            self._stream.close()
            raise RecordingError(
                f"recording {str(self.path)!r} is unfinished or truncated: it has no footer "
                "(the writer did not finish, as with a killed recorder's .part, or the file was "
                f"cut short); {where}; "
                f"{recover_command(self.path)} saves its complete chunks into a new recording"
            )
        try:
            self._reader = make_reader(
                self._stream, validate_crcs=validate_crcs, decoder_factories=[DecoderFactory()]
            )
            self.summary = self._reader.get_summary()
        except (*DAMAGE_ERRORS, OSError) as exc:
            try:
                reason = str(exc) or (
                    f"{type(exc).__name__} reading the summary at byte "
                    f"{footer_summary_start(self._stream)} the footer points to; "
                    f"{describe_end(self._stream)}"
                )
            except OSError:
                reason = type(exc).__name__
            self._stream.close()
            raise RecordingError(
                f"recording {str(self.path)!r} is truncated or corrupt ({reason}); "
                f"{recover_command(self.path)} saves the complete chunks"
            ) from exc
        damage = summary_damage(self._stream) if validate_crcs else ""
        if damage:
            self._stream.close()
            raise RecordingError(
                f"recording {str(self.path)!r} is corrupt: {damage}; {recover_command(self.path)} "
                "keeps every message of the undamaged chunks"
            )
        if self.summary is None or self.summary.statistics is None:
            self._stream.close()
            raise RecordingError(
                f"recording {str(self.path)!r} has no summary (the writer did not finish); "
                f"{recover_command(self.path)} rebuilds it"
            )

    def close(self):
        self._stream.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- what is in it ---------------------------------------------------------------------
    def topics(self) -> dict[str, TopicInfo]:
        counts = self.summary.statistics.channel_message_counts
        out = {}
        for channel_id, channel in sorted(self.summary.channels.items()):
            schema = self.summary.schemas.get(channel.schema_id)
            out[channel.topic] = TopicInfo(
                topic=channel.topic,
                type=schema.name if schema else "",
                message_count=counts.get(channel_id, 0),
                schema_encoding=schema.encoding if schema else "",
                message_encoding=channel.message_encoding,
                offered_qos=load_profiles(channel.metadata.get("offered_qos_profiles", "")),
            )
        return out

    @property
    def start_time_ns(self) -> int:
        return self.summary.statistics.message_start_time

    @property
    def end_time_ns(self) -> int:
        return self.summary.statistics.message_end_time

    @property
    def duration_s(self) -> float:
        return max(0, self.end_time_ns - self.start_time_ns) * 1e-9

    @property
    def message_count(self) -> int:
        return self.summary.statistics.message_count

    def _check_topics(self, topics: Iterable[str] | None) -> list[str] | None:
        if topics is None:
            return None
        topics = list(topics)
        known = self.topics()
        missing = [t for t in topics if t not in known]
        if missing:
            raise RecordingError(
                f"{self.path}: topic(s) {missing} not recorded; recorded: {sorted(known)}"
            )
        return topics

    # -- integrity -------------------------------------------------------------------------
    def damaged_chunks(self) -> list[DamagedChunk]:
        """Read every chunk the summary indexes and check its CRC: the damaged ones."""
        damaged = []
        for index in self.summary.chunk_indexes:
            try:
                read_chunk_at(self._stream, index)
            except DAMAGE_ERRORS as exc:
                damaged.append(DamagedChunk.of(index, exc))
        return damaged

    def _damage_error(self, exc: BaseException) -> RecordingError:
        try:
            damaged = self.damaged_chunks()
        except (*DAMAGE_ERRORS, OSError):
            damaged = []
        where = (
            f"{len(damaged)} of {len(self.summary.chunk_indexes)} chunks damaged, first "
            f"{damaged[0]}"
            if damaged
            else describe_damage(exc)
        )
        return RecordingError(
            f"recording {str(self.path)!r} is corrupt: {where}; {recover_command(self.path)} "
            f"keeps every message of the undamaged chunks"
        )

    # -- messages --------------------------------------------------------------------------
    def raw_messages(
        self,
        topics: Iterable[str] | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[tuple[Schema, Channel, Message]]:
        """(schema, channel, message) in log-time order, CDR bytes untouched (for replay)."""
        try:
            yield from self._reader.iter_messages(
                topics=self._check_topics(topics),
                start_time=start_ns,
                end_time=end_ns,
                log_time_order=True,
            )
        except DAMAGE_ERRORS as exc:
            raise self._damage_error(exc) from exc

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, object]]:
        """(topic, log_time_ns, decoded message) in log-time order."""
        try:
            for _schema, channel, message, decoded in self._reader.iter_decoded_messages(
                topics=self._check_topics(topics), log_time_order=True
            ):
                yield channel.topic, message.log_time, decoded
        except DAMAGE_ERRORS as exc:
            raise self._damage_error(exc) from exc

    def arrays(self, topic: str) -> dict[str, object]:
        """All messages of one topic as arrays: {'log_time': s, 'field.sub': array, ...}.

        Scalars stack to 1-D arrays, same-shape arrays (e.g. images) to N-D arrays, and
        ragged ones stay lists of arrays. Times are seconds (float64).
        """
        columns: dict[str, list] = {"log_time": []}
        for _topic, log_time, decoded in self.messages([topic]):
            columns["log_time"].append(log_time * 1e-9)
            for key, value in flatten(decoded).items():
                columns.setdefault(key, []).append(value)
        return {key: _stack(values) for key, values in columns.items()}
