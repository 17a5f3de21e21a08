"""Read a recording into numpy arrays without a ROS runtime (mcap + mcap_ros2's decoder).

Streams: messages are decoded one at a time from the chunks they live in; only what a
caller asks for (e.g. one topic's arrays) is ever held in memory.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory

from afm_core.recording.errors import RecordingError
from afm_core.recording.qos import QosDescription, load_profiles
from afm_core.recording.writer import RecordingWriter

IMAGE_DTYPES = {
    "32FC1": np.float32,
    "64FC1": np.float64,
    "8UC1": np.uint8,
    "mono8": np.uint8,
    "16UC1": np.uint16,
    "mono16": np.uint16,
    "32SC1": np.int32,
}


@dataclass
class TopicInfo:
    topic: str
    type: str
    message_count: int
    schema_encoding: str
    message_encoding: str
    offered_qos: list[QosDescription] = field(default_factory=list)


def image_to_array(image) -> np.ndarray:
    """sensor_msgs/Image (decoded) -> 2-D array, honouring encoding, step and endianness."""
    if image.encoding not in IMAGE_DTYPES:
        raise RecordingError(
            f"image encoding {image.encoding!r} not supported; "
            f"expected one of {sorted(IMAGE_DTYPES)}"
        )
    dtype = np.dtype(IMAGE_DTYPES[image.encoding]).newbyteorder(">" if image.is_bigendian else "<")
    raw = np.frombuffer(bytes(image.data), dtype=np.uint8)
    if image.height == 0 or image.width == 0:
        return np.zeros((image.height, image.width), dtype=dtype.newbyteorder("="))
    rows = raw[: image.height * image.step].reshape(image.height, image.step)
    row_bytes = image.width * dtype.itemsize
    return (
        rows[:, :row_bytes]
        .copy()
        .view(dtype)
        .reshape(image.height, image.width)
        .astype(dtype.newbyteorder("="))
    )


def _is_image(value) -> bool:
    slots = getattr(value, "__slots__", ())
    return {"height", "width", "encoding", "is_bigendian", "step", "data"} <= set(slots)


def flatten(message, prefix: str = "") -> dict:
    """Decoded message -> {dotted.field: value}; images become arrays, numeric lists arrays."""
    out = {}
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


class RecordingReader:
    """Open an MCAP recording (ours or rosbag2's) for offline evaluation."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        if not self.path.is_file():
            raise RecordingError(f"recording {str(self.path)!r} does not exist")
        self._stream = open(self.path, "rb")
        try:
            self._reader = make_reader(self._stream, decoder_factories=[DecoderFactory()])
            self.summary = self._reader.get_summary()
        except (McapError, ValueError, EOFError, OSError) as exc:
            self._stream.close()
            raise RecordingError(
                f"recording {str(self.path)!r} is truncated or corrupt ({exc}); "
                f"`afm recover {self.path}` saves the complete chunks"
            ) from exc
        if self.summary is None or self.summary.statistics is None:
            self._stream.close()
            raise RecordingError(
                f"recording {str(self.path)!r} has no summary (the writer did not finish); "
                f"`afm recover {self.path}` rebuilds it"
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
        except McapError as exc:
            raise RecordingError(f"{self.path}: corrupt data while reading ({exc})") from exc

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, object]]:
        """(topic, log_time_ns, decoded message) in log-time order."""
        try:
            for _schema, channel, message, decoded in self._reader.iter_decoded_messages(
                topics=self._check_topics(topics), log_time_order=True
            ):
                yield channel.topic, message.log_time, decoded
        except McapError as exc:
            raise RecordingError(f"{self.path}: corrupt data while reading ({exc})") from exc

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


def recover_recording(
    source: str | os.PathLike, output: str | os.PathLike | None = None
) -> tuple[Path, int]:
    """Copy every complete message of an unfinished or truncated file into a new recording.

    Returns the new file and its message count. The source is never modified.
    """
    source = Path(source)
    if output is None:
        name = source.name[: -len(".part")] if source.name.endswith(".part") else source.name
        stem = name[: -len(".mcap")] if name.endswith(".mcap") else name
        output = source.with_name(stem + ".recovered.mcap")
    if not source.is_file():
        raise RecordingError(f"recording {str(source)!r} does not exist")
    schemas: dict[int, Schema] = {}
    channel_map: dict[int, int] = {}
    with open(source, "rb") as stream, RecordingWriter(output) as writer:
        try:
            for record in StreamReader(stream).records:
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel) and record.id not in channel_map:
                    schema = schemas.get(record.schema_id)
                    if schema is None:
                        continue
                    profiles = load_profiles(record.metadata.get("offered_qos_profiles", ""))
                    channel_map[record.id] = writer.add_channel(
                        record.topic, schema.name, profiles, definition=schema.data.decode()
                    )
                elif isinstance(record, Message) and record.channel_id in channel_map:
                    writer.write(
                        channel_map[record.channel_id],
                        record.log_time,
                        record.data,
                        record.publish_time,
                        record.sequence,
                    )
        except RecordingError:
            raise
        except Exception:  # noqa: BLE001 - the stream ends wherever the file was cut
            pass
        count = writer.message_count
    return Path(output), count
