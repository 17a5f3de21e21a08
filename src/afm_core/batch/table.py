"""The batch's results table, DIR/results.csv: one row per item, appended and flushed as each
item completes, so an interrupted batch keeps every row it finished.

A re-run reads the table first: rows that finished (status "ok") are kept and their items
(file hash, or for a seed the item itself, + configuration hash) skipped; failed rows and a
last line cut by an interrupt (SIGKILL mid-write, a full disk: a line without its newline, or
with fewer cells than the header) are dropped, so those items run again and the table keeps
one row per item. A table written before a column was added is read with that column empty.
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path

# every kind's rows begin with these; the kind's own columns follow (COLUMNS in its module)
COMMON_COLUMNS = [
    "item",
    "sha256",
    "config",
    "status",
    "error",
    "seconds",
    "worker",
    "finished_utc",  # when the row was written (ISO 8601, UTC)
]
OK, FAILED = "ok", "failed"
_EXTRA = "\x00extra"  # DictReader's key for cells beyond the header (a garbled line)


def row_key(row: dict) -> tuple[str, str]:
    """What a finished row stands for: the file's hash (recordings) or the item (seeds), and
    the configuration hash."""
    return (row.get("sha256") or row["item"], row["config"])


def _cell(value) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    if isinstance(value, float):
        return repr(value)  # every digit: a re-read row is the same number
    return str(value)


class ResultsTable:
    """DIR/results.csv with the given columns; `done` holds the (sha256, config) keys of the
    rows that finished."""

    def __init__(self, path: str | os.PathLike, columns: list[str]):
        self.path = Path(path)
        self.columns = list(columns)
        self.done: set[tuple[str, str]] = set()
        kept = self._read_kept()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # rewrite what is kept (atomically: an interrupt here must not lose the table)
        partial = self.path.with_suffix(".csv.part")
        with open(partial, "w", newline="") as stream:
            writer = csv.DictWriter(stream, self.columns)
            writer.writeheader()
            writer.writerows(kept)
        os.replace(partial, self.path)
        self._stream = open(self.path, "a", newline="")
        self._writer = csv.DictWriter(self._stream, self.columns)

    def _read_kept(self) -> list[dict]:
        if not self.path.is_file():
            return []
        with open(self.path, newline="") as stream:
            text = stream.read()
        if text and not text.endswith("\n"):
            text = text[: text.rfind("\n") + 1]  # the line an interrupt cut
        reader = csv.DictReader(text.splitlines(keepends=True), restkey=_EXTRA)
        rows = list(reader)
        header = reader.fieldnames or self.columns
        # an older table of this kind lacks only the columns added since: its rows are kept
        if header != self.columns and not set(header) < set(self.columns):
            # name what differs: the common columns come first and are the same for every kind
            theirs = [c for c in header if c not in self.columns][:6]
            ours = [c for c in self.columns if c not in header][:6]
            raise ValueError(
                f"{self.path}: written by another kind of batch (it has {theirs}, this one "
                f"writes {ours}); use another --output"
            )
        # a whole row has every header cell (DictReader fills a short one with None)
        kept = [
            {c: r.get(c) or "" for c in self.columns}
            for r in rows
            if r.get("status") == OK and None not in r.values() and _EXTRA not in r
        ]
        self.done = {row_key(r) for r in kept}
        return kept

    def append(self, row: dict) -> None:
        """Write one row and flush it to the file."""
        unknown = set(row) - set(self.columns)
        if unknown:
            raise ValueError(f"row fields {sorted(unknown)} are not columns of {self.path}")
        self._writer.writerow({c: _cell(row.get(c)) for c in self.columns})
        self._stream.flush()
        os.fsync(self._stream.fileno())
        if row.get("status") == OK:
            self.done.add(row_key(row))

    def close(self) -> None:
        self._stream.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def read_rows(path: str | os.PathLike) -> list[dict]:
    """The rows of a results table (strings, as written)."""
    with open(path, newline="") as stream:
        return list(csv.DictReader(stream))
