"""Save what can be trusted of an unfinished (.part), truncated or damaged recording.

Two routes to the chunks, the better first:
- the summary's chunk index (a finished file): every indexed chunk is read at its offset, so
  a damaged chunk, even one whose length field is garbage, costs only its own messages;
- otherwise (a `.part` of a killed recorder, a cut file) the records in file order, until
  the stream ends or stops making sense; a chunk whose CRC fails is skipped and the walk
  goes on behind it.
Every chunk's CRC is checked: a message is kept only from a chunk that passed. Schemas and
channels come from the summary when there is one and its CRC holds, else from the chunks as
they pass.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

from afm_core.recording.errors import RecordingError
from afm_core.recording.qos import load_profiles
from afm_core.recording.reader import (
    DAMAGE_ERRORS,
    DamagedChunk,
    check_recording_file,
    describe_damage,
    describe_end,
    has_footer,
    read_chunk_at,
    summary_damage,
)
from afm_core.recording.writer import RecordingWriter


@dataclass
class Recovery:
    path: Path
    messages: int
    damaged: list[DamagedChunk] = field(default_factory=list)
    stopped: str = ""  # why the walk through the file ended early ("" = it reached the end)
    orphaned: int = 0  # messages of intact chunks whose channel was defined in a damaged one


class _Copier:
    def __init__(self, writer: RecordingWriter):
        self.writer = writer
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, int] = {}
        self.orphaned = 0

    def take(self, record) -> None:
        if isinstance(record, Schema):
            self.schemas.setdefault(record.id, record)
        elif isinstance(record, Channel) and record.id not in self.channels:
            schema = self.schemas.get(record.schema_id)
            if schema is None:
                return
            profiles = load_profiles(record.metadata.get("offered_qos_profiles", ""))
            self.channels[record.id] = self.writer.add_channel(
                record.topic, schema.name, profiles, definition=schema.data.decode()
            )
        elif isinstance(record, Message):
            if record.channel_id not in self.channels:
                self.orphaned += 1
                return
            self.writer.write(
                self.channels[record.channel_id],
                record.log_time,
                record.data,
                record.publish_time,
                record.sequence,
            )


def _summary(stream):
    """The summary when it is there and its CRC holds (a damaged one could send the walk to
    the wrong offsets or name the wrong topics), else None."""
    try:
        if not has_footer(stream) or summary_damage(stream):
            return None  # unfinished (a .part, a cut file): no summary to trust
        summary = make_reader(stream).get_summary()
    except (*DAMAGE_ERRORS, OSError):  # e.g. EINVAL: a seek before the start of a tiny file
        return None
    return summary if summary is not None and summary.chunk_indexes else None


def _by_index(stream, summary, copier: _Copier, damaged: list) -> None:
    for schema in summary.schemas.values():
        copier.take(schema)
    for channel in summary.channels.values():
        copier.take(channel)
    for index in sorted(summary.chunk_indexes, key=lambda i: i.chunk_start_offset):
        try:
            records = read_chunk_at(stream, index)
        except DAMAGE_ERRORS as exc:
            damaged.append(DamagedChunk.of(index, exc))
            continue
        for record in records:
            copier.take(record)


def _by_stream(stream, copier: _Copier, damaged: list) -> str:
    """Walk the records in file order; returns why it stopped early ("" at the end)."""
    stream.seek(0)
    try:
        for record in StreamReader(stream, emit_chunks=True).records:
            if not isinstance(record, Chunk):
                copier.take(record)
                continue
            try:
                records = breakup_chunk(record, validate_crc=True)
            except DAMAGE_ERRORS as exc:
                damaged.append(
                    DamagedChunk(
                        -1,
                        record.message_start_time,
                        record.message_end_time,
                        describe_damage(exc),
                    )
                )
                continue
            for inner in records:
                copier.take(inner)
    except RecordingError:
        raise
    except DAMAGE_ERRORS as exc:  # the file was cut, or a record's length is garbage
        return describe_damage(exc)
    return ""


def recover(source: str | os.PathLike, output: str | os.PathLike | None = None) -> Recovery:
    """Copy every message of the undamaged chunks into a new recording. The source is never
    modified; the output is a new file (default NAME.recovered.mcap)."""
    source = Path(source)
    if output is None:
        name = source.name[: -len(".part")] if source.name.endswith(".part") else source.name
        stem = name[: -len(".mcap")] if name.endswith(".mcap") else name
        output = source.with_name(stem + ".recovered.mcap")
    check_recording_file(source, ": nothing to recover, no file written")
    damaged: list[DamagedChunk] = []
    stopped = ""
    with open(source, "rb") as stream:
        writer = RecordingWriter(output, flush_interval=None)  # refuses an existing output
        try:
            copier = _Copier(writer)
            summary = _summary(stream)
            if summary is not None:
                _by_index(stream, summary, copier, damaged)
            else:
                stopped = _by_stream(stream, copier, damaged)
            count = writer.message_count
            if count == 0:
                raise RecordingError(_nothing_recoverable(source, stream, damaged, copier))
            writer.close()
        except BaseException as exc:
            writer.discard()  # no output on any failure: a second run must not find one
            if isinstance(exc, OSError):
                raise RecordingError(
                    f"{str(source)!r}: recovery failed ({exc.strerror or exc}); no file written"
                ) from exc
            raise
    return Recovery(Path(output), count, damaged, stopped, copier.orphaned)


def _nothing_recoverable(source: Path, stream, damaged: list, copier: _Copier) -> str:
    try:
        where = "it is finished and holds none" if has_footer(stream) else describe_end(stream)
    except OSError:
        where = ""
    why = [
        f"{len(damaged)} damaged chunks skipped" if damaged else "",
        f"{copier.orphaned} messages without their channel" if copier.orphaned else "",
        where,
    ]
    return (
        f"{str(source)!r} holds nothing to recover: no complete chunk with a message ("
        + "; ".join(w for w in why if w)
        + "); no file written"
    )


def recover_recording(
    source: str | os.PathLike, output: str | os.PathLike | None = None
) -> tuple[Path, int]:
    """`recover` as (new file, message count)."""
    recovery = recover(source, output)
    return recovery.path, recovery.messages
