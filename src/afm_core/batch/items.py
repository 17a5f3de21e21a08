"""What a batch runs over: recordings named by local paths or fsspec URLs, each identified by
the SHA-256 of its bytes (streamed), and the hash of the configuration it is evaluated with.

A folder (local or remote) stands for every *.mcap file below it, in sorted order; a URL
(s3://, gcs://, http://, ... whatever fsspec and its plug-ins installed here reach) is read
where it lies: hashed by streaming, and copied block by block to a worker's temporary file for
the readers that need a seekable local file (the MCAP summary is at the file's end).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

BLOCK = 1 << 20  # bytes read at a time: hashing and copying never hold a recording in memory
RECORDING_SUFFIX = ".mcap"


def is_url(item: str) -> bool:
    """A URL with a scheme fsspec resolves (file:// counts as local)."""
    return "://" in item and not item.startswith("file://")


def _local(item: str) -> Path:
    return Path(item[len("file://") :] if item.startswith("file://") else item)


def expand_items(paths: Iterable[str | os.PathLike]) -> list[str]:
    """Paths and URLs -> the recordings they name, in order, each once: a file as given (a
    local one made absolute), a folder as every *.mcap below it (sorted). A name that
    matches nothing is an error naming it (a typo must not make an empty batch)."""
    items: list[str] = []
    for path in paths:
        text = os.fspath(path)
        found = _expand_url(text) if is_url(text) else _expand_local(_local(text))
        if not found:
            raise ValueError(f"batch input {text!r}: no such file, or a folder without *.mcap")
        items += [f for f in found if f not in items]
    return items


def _expand_local(path: Path) -> list[str]:
    # absolute: a worker of a lab's cluster does not run in this directory
    path = path.absolute()
    if path.is_file():
        return [str(path)]
    if path.is_dir():
        return [str(p) for p in sorted(path.rglob(f"*{RECORDING_SUFFIX}")) if p.is_file()]
    return []


def _expand_url(url: str) -> list[str]:
    fs, root = _filesystem(url)
    if fs.isfile(root):
        return [url]
    if not fs.isdir(root):
        return []
    protocol = fs.protocol if isinstance(fs.protocol, str) else fs.protocol[0]
    found = sorted(fs.glob(f"{root.rstrip('/')}/**/*{RECORDING_SUFFIX}"))
    return [f"{protocol}://{f}" if "://" not in f else f for f in found]


def _filesystem(url: str):
    try:
        from fsspec.core import url_to_fs
    except ImportError as exc:  # pragma: no cover - dask installs fsspec
        raise ValueError(f"batch input {url!r}: a URL needs fsspec (pip install fsspec)") from exc
    return url_to_fs(url)


def _open(item: str):
    if is_url(item):
        fs, path = _filesystem(item)
        return fs.open(path, "rb")
    return open(_local(item), "rb")


def file_sha256(item: str) -> str:
    """SHA-256 (hex) of a recording's bytes, read BLOCK at a time."""
    digest = hashlib.sha256()
    with _open(item) as stream:
        while block := stream.read(BLOCK):
            digest.update(block)
    return digest.hexdigest()


@contextlib.contextmanager
def local_file(item: str) -> Iterator[Path]:
    """A local path to read the recording from: the file itself, or for a URL a temporary copy
    made block by block (deleted afterwards)."""
    if not is_url(item):
        yield _local(item)
        return
    folder = tempfile.mkdtemp(prefix="afm-batch-")
    try:
        target = Path(folder) / Path(item.split("?")[0]).name
        with _open(item) as source, open(target, "wb") as sink:
            shutil.copyfileobj(source, sink, BLOCK)
        yield target
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def config_hash(kind: str, row_format: int, options: dict) -> str:
    """16 hex digits naming what a row was computed with: the batch kind, its row format and
    the options (a model file enters by its content hash, so an edited model is redone)."""
    text = json.dumps({"kind": kind, "format": row_format, **options}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


MAX_SEEDS = 1_000_000  # one batch's seeds at most: a typo such as 0-1e9 must not fill memory
MAX_SEED = 2**32 - 1 - 20_000  # the trials seed generators with seed + up to 20000 (< 2^32)


def parse_seeds(seeds) -> list[int]:
    """The seeds of a sweep, in order, each once: an int, text such as "0-99", "0,1,5" or
    "0-9,20-29" (ranges inclusive), or a list of those."""
    parts = [seeds] if isinstance(seeds, (int, str)) else list(seeds)
    out: list[int] = []
    for part in parts:
        for piece in str(part).split(","):
            out += _seed_range(piece.strip(), str(part))
            if len(out) > MAX_SEEDS:
                raise ValueError(f"seeds {str(part)!r}: more than {MAX_SEEDS} seeds")
    if not out:
        raise ValueError("seeds: none given (e.g. 0-99 or 0,1,5)")
    return list(dict.fromkeys(out))


def _seed_range(piece: str, given: str) -> list[int]:
    low, dash, high = piece.partition("-")
    try:
        first, last = int(low), int(high if dash else low)
    except ValueError:
        raise ValueError(
            f"seeds {given!r}: {piece!r} is not a seed or a range such as 0-99"
        ) from None
    if not 0 <= first <= last <= MAX_SEED:
        raise ValueError(f"seeds {given!r}: {piece!r} must be 0 <= first <= last <= {MAX_SEED}")
    if last - first >= MAX_SEEDS:
        raise ValueError(f"seeds {given!r}: more than {MAX_SEEDS} seeds")
    return list(range(first, last + 1))
