"""Write ROS 2 CDR messages to an MCAP file that rosbag2, Foxglove and mcap_ros2 open.

Safety rules, because a recording is often the only copy of an experiment:
- never overwrite: the final name must not exist; data goes to `<name>.part` (created
  exclusively) and is linked to `<name>` only when the file is complete;
- a recording is closed (summary, statistics, indexes written) before free space runs out:
  below `min_free_bytes` the writer finishes the file and raises RecordingError;
- an I/O failure mid-file leaves only the `.part` file, never a broken `<name>`;
  `afm recover` turns a `.part` into a readable recording;
- a killed process loses at most `flush_interval` seconds of messages: the open chunk is
  compressed and handed to the operating system once its oldest message is that old (checked
  on every write and by `flush_if_due`, which a recorder calls from a timer every
  `poll_period` s, so an idle stream is not held back either).
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path

from mcap.well_known import MessageEncoding, Profile, SchemaEncoding
from mcap.writer import CompressionType, Writer

from afm_core.recording.definitions import full_message_definition
from afm_core.recording.errors import RecordingError, recover_command
from afm_core.recording.qos import QosDescription, dump_profiles

PART_SUFFIX = ".part"
LIBRARY = "afm_core recorder 0.1"
COMPRESSIONS = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}
# A chunk is closed once its oldest message is this share of flush_interval old, and the poll
# comes every remaining share: a message then waits at most DUE + POLL = flush_interval.
FLUSH_DUE_SHARE = 0.75
FLUSH_POLL_SHARE = 1.0 - FLUSH_DUE_SHARE


def part_path(path: Path) -> Path:
    return path.with_name(path.name + PART_SUFFIX)


def check_output_path(path: str | os.PathLike) -> Path:
    """Validate a new recording's name; raise RecordingError naming the problem."""
    path = Path(path)
    if path.suffix != ".mcap":
        raise RecordingError(f"output {str(path)!r}: the file name must end in .mcap")
    if path.exists():
        raise RecordingError(
            f"output {str(path)!r} already exists; recordings are never overwritten"
        )
    if part_path(path).exists():
        # never suggest removing it: it may be another recorder's file, being written now
        raise RecordingError(
            f"output {str(path)!r}: an unfinished recording {part_path(path).name!r} is in "
            "the way; it may be a recording in progress (another recorder writing it: choose "
            "another name) or a killed recorder's, which "
            f"{recover_command(part_path(path))} saves"
        )
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise RecordingError(f"output {str(path)!r}: directory {str(parent)!r} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise RecordingError(f"output {str(path)!r}: directory {str(parent)!r} is not writable")
    return path


class RecordingWriter:
    """Chunked, compressed, fully indexed MCAP with ros2msg schemas and cdr messages.

    Usage:
        with RecordingWriter("session.mcap") as rec:
            ch = rec.add_channel("/afm/scan", "afm_msgs/msg/RasterScan", [QosDescription()])
            rec.write(ch, log_time_ns, cdr_bytes)
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        compression: str = "zstd",
        chunk_size: int = 4 * 1024 * 1024,
        min_free_bytes: int = 64 * 1024 * 1024,
        free_space_check_bytes: int = 8 * 1024 * 1024,
        flush_interval: float | None = 1.0,
        clock: Callable[[], float] = time.monotonic,
    ):
        """flush_interval: s a written message may wait in memory before its chunk is closed
        and written (None: only when the chunk is full, as a plain MCAP writer does); clock:
        the s it is measured in (a benchmark passes the recording's time)."""
        if compression not in COMPRESSIONS:
            raise RecordingError(
                f"compression={compression!r}: expected one of {sorted(COMPRESSIONS)}"
            )
        if chunk_size < 1024:
            raise RecordingError(f"chunk_size={chunk_size}: must be at least 1024 bytes")
        if flush_interval is not None and not flush_interval > 0:
            raise RecordingError(f"flush_interval={flush_interval}: must be > 0 s (or None)")
        self.flush_interval = flush_interval
        self._clock = clock
        self._oldest_unflushed: float | None = None  # clock time of the open chunk's first
        self.flush_count = 0
        self.path = check_output_path(path)
        self.part = part_path(self.path)
        self.min_free_bytes = int(min_free_bytes)
        self._check_every = int(free_space_check_bytes)
        self._bytes_since_check = 0
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.message_count = 0
        self.closed = False
        self._check_free_space()
        try:
            self._stream = open(self.part, "xb")
        except OSError as exc:
            raise RecordingError(
                f"output {str(self.part)!r}: cannot create: {exc.strerror}"
            ) from exc
        self._writer = Writer(
            self._stream, chunk_size=chunk_size, compression=COMPRESSIONS[compression]
        )
        self._guard(lambda: self._writer.start(profile=Profile.ROS2, library=LIBRARY))

    # -- channels -------------------------------------------------------------------------
    def add_channel(
        self,
        topic: str,
        type_name: str,
        offered_qos: list[QosDescription],
        definition: str | None = None,
    ) -> int:
        """Register a topic; `definition` defaults to the full .msg text from the ament index."""
        if topic in self._channels:
            raise RecordingError(f"topic {topic!r} is already recorded")
        if not topic.startswith("/"):
            raise RecordingError(f"topic {topic!r}: must be absolute (start with '/')")
        if type_name not in self._schemas:
            text = definition if definition is not None else full_message_definition(type_name)
            self._schemas[type_name] = self._guard(
                lambda: self._writer.register_schema(
                    name=type_name, encoding=SchemaEncoding.ROS2, data=text.encode()
                )
            )
        metadata = {"offered_qos_profiles": dump_profiles(offered_qos)}
        channel_id = self._guard(
            lambda: self._writer.register_channel(
                topic=topic,
                message_encoding=MessageEncoding.CDR,
                schema_id=self._schemas[type_name],
                metadata=metadata,
            )
        )
        self._channels[topic] = channel_id
        return channel_id

    @property
    def topics(self) -> dict[str, int]:
        return dict(self._channels)

    # -- messages -------------------------------------------------------------------------
    def write(
        self,
        channel_id: int,
        log_time_ns: int,
        data: bytes,
        publish_time_ns: int | None = None,
        sequence: int = 0,
    ) -> None:
        if self.closed:
            raise RecordingError(f"{self.path}: recording is closed")
        self._guard(
            lambda: self._writer.add_message(
                channel_id=channel_id,
                log_time=int(log_time_ns),
                data=data,
                publish_time=int(log_time_ns if publish_time_ns is None else publish_time_ns),
                sequence=sequence,
            )
        )
        self.message_count += 1
        if self._oldest_unflushed is None:
            self._oldest_unflushed = self._clock()
        self.flush_if_due()
        self._bytes_since_check += len(data)
        if self._bytes_since_check >= self._check_every:
            self._bytes_since_check = 0
            self._check_free_space(closing_on_low=True)

    @property
    def poll_period(self) -> float | None:
        """How often a caller should call flush_if_due to keep the flush_interval bound."""
        return None if self.flush_interval is None else FLUSH_POLL_SHARE * self.flush_interval

    def flush_if_due(self) -> bool:
        """Close the open chunk and hand it to the OS (no fsync) when its oldest message is
        due; True when it did. What reaches the OS survives the process being killed."""
        if (
            self.closed
            or self.flush_interval is None
            or self._oldest_unflushed is None
            or self._clock() - self._oldest_unflushed < FLUSH_DUE_SHARE * self.flush_interval
        ):
            return False
        self._oldest_unflushed = None
        self._guard(self._writer.flush)
        self.flush_count += 1
        return True

    # -- closing --------------------------------------------------------------------------
    def close(self) -> Path:
        """Write the summary and indexes, then give the file its final name."""
        if self.closed:
            return self.path
        self.closed = True
        self._guard(
            lambda: self._writer.add_metadata(
                "rosbag2", {"serialized_metadata": "", "ROS_DISTRO": "jazzy"}
            ),
            closing=True,
        )
        self._guard(self._writer.finish, closing=True)
        self._guard(self._stream.flush, closing=True)
        self._guard(lambda: os.fsync(self._stream.fileno()), closing=True)
        self._stream.close()
        try:
            os.link(self.part, self.path)  # fails rather than overwrite a file that appeared
        except FileExistsError as exc:
            raise RecordingError(
                f"{self.path} appeared while recording; the recording stays at {self.part}"
            ) from exc
        os.unlink(self.part)
        self._fsync_directory()  # the new name, and the .part's removal, survive a power cut
        return self.path

    def discard(self) -> None:
        """Stop and delete what this writer created (its .part, or the finished file it
        linked), for a caller whose output is worthless (`afm recover` that saved nothing).
        Never a file of the same name that someone else made."""
        if not self.closed:
            self.closed = True
            try:
                self._stream.close()
            except OSError:
                pass
        linked = self.path.exists() and (
            not self.part.exists() or os.path.samefile(self.part, self.path)
        )
        for path in (self.part, self.path) if linked else (self.part,):
            try:
                path.unlink()
            except FileNotFoundError:
                pass

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if not self.closed:
            self.close()

    # -- internals ------------------------------------------------------------------------
    def _fsync_directory(self) -> None:
        fd = os.open(self.path.parent if str(self.path.parent) else ".", os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    def _check_free_space(self, closing_on_low: bool = False) -> None:
        parent = self.path.parent if str(self.path.parent) else Path(".")
        free = shutil.disk_usage(parent).free
        if free >= self.min_free_bytes:
            return
        message = (
            f"{self.path}: only {free / 2**20:.1f} MiB free on {parent}, below "
            f"min_free_bytes={self.min_free_bytes / 2**20:.1f} MiB"
        )
        if closing_on_low:
            self.close()
            raise RecordingError(
                message + f"; recording stopped and closed with {self.message_count} messages"
            )
        raise RecordingError(message + "; not starting")

    def _guard(self, action, closing: bool = False):
        try:
            return action()
        except OSError as exc:
            self.closed = True
            try:
                self._stream.close()
            except OSError:
                pass
            raise RecordingError(
                f"{self.path}: write failed ({exc.strerror or exc}); the incomplete data is in "
                f"{self.part}; {recover_command(self.part)} saves what reached the disk"
            ) from exc
