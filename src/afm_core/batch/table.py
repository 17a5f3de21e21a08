"""The batch's results table, DIR/results.csv: one row per item, appended and flushed as each
item completes, so an interrupted batch keeps every row it finished.

A re-run reads the table first: rows that finished (status "ok") are kept and their items
(file hash + configuration hash) skipped; failed rows and a last line cut by the interrupt
are dropped, so the failed items run again and the table keeps one row per item.
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
]
OK, FAILED = "ok", "failed"


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
        rows = list(csv.DictReader(text.splitlines(keepends=True)))
        header = text.splitlines()[0].split(",") if text else self.columns
        if header != self.columns:
            raise ValueError(
                f"{self.path}: its columns {header[:8]}... are not this batch's "
                f"{self.columns[:8]}... (another kind of batch?); use another --output"
            )
        kept = [r for r in rows if r.get("status") == OK]
        self.done = {(r["sha256"], r["config"]) for r in kept}
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
            self.done.add((row["sha256"], row["config"]))

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
