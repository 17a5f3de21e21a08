"""Run a batch on Dask: an embedded LocalCluster (one single-threaded worker process per core,
each with a memory limit) or a lab's existing scheduler, named by its address; nothing else
changes between the two.

The items' hashes are computed on the workers (a recording is read where it lies, by whoever
runs the task); an item whose (file hash, configuration hash) already has a finished row is
skipped, every other one runs as one task. Rows are appended to DIR/results.csv as tasks
complete; a task's exception becomes a failed row with its error on one line, so one bad
recording never stops the batch.
"""

from __future__ import annotations

import contextlib
import os
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from afm_core.batch import evaluate, plots, sim2real
from afm_core.batch.items import config_hash, expand_items, file_sha256, local_file
from afm_core.batch.table import COMMON_COLUMNS, FAILED, OK, ResultsTable, read_rows

KINDS = ("evaluate", "sim2real")
ERROR_CHARS = 300  # an error cell is one line, this long at most (the full text is in the log)
CONNECT_TIMEOUT = 30.0  # s to reach a --scheduler (a wrong address must not hang the command)


@dataclass
class Progress:
    """Where a batch is: items finished (run now, skipped as done before) of the total."""

    total: int
    ok: int = 0
    failed: int = 0
    skipped: int = 0
    started: float = 0.0
    last: dict | None = None  # the row just written

    @property
    def finished(self) -> int:
        return self.ok + self.failed + self.skipped

    @property
    def per_minute(self) -> float:
        """Items run (not skipped) per minute of wall time since the batch started."""
        elapsed = time.perf_counter() - self.started
        return 60.0 * (self.ok + self.failed) / elapsed if elapsed > 0 else 0.0

    def line(self) -> str:
        return (
            f"{self.finished}/{self.total} ({self.ok} ok, {self.failed} failed, "
            f"{self.skipped} done before), {self.per_minute:.1f} recordings/min"
        )


@dataclass
class BatchResult:
    table: Path
    summary: Path
    total: int
    computed: int  # items run by this call (the others were done before)
    ok: int
    failed: int
    skipped: int
    seconds: float


def one_line(exc: BaseException) -> str:
    text = " ".join(f"{type(exc).__name__}: {exc}".split())
    return text[:ERROR_CHARS]


def _options(kind: str, model, effects) -> tuple[dict, dict]:
    """(what the task gets, what the configuration hash is of)."""
    if kind not in KINDS:
        raise ValueError(f"batch kind {kind!r}: expected one of {list(KINDS)}")
    if kind == "evaluate":
        return {}, {}
    if model and not Path(model).is_file():
        raise ValueError(f"model {str(model)!r}: no such simulator configuration file")
    model_hash = file_sha256(str(model)) if model else "defaults"
    effects = sorted(effects or [])
    if effects:
        from afm_core.sim2real.candidates import select

        select(effects)  # a misspelt effect is refused before any recording is read
    task = {"model": str(Path(model).resolve()) if model else None, "effects": effects}
    return task, {"model": model_hash, "effects": effects}


def run_item(kind: str, item: str, sha: str, config: str, options: dict, output: str) -> dict:
    """One item's row on a worker; never raises (a failure is the row's status and error)."""
    start = time.perf_counter()
    row = {"item": item, "sha256": sha, "config": config, "worker": _worker_name()}
    try:
        with local_file(item) as path:
            if kind == "evaluate":
                row.update(evaluate.evaluate_recording(path))
            else:
                report = Path(output) / "reports" / f"{Path(path).stem}-{sha[:12]}"
                row.update(
                    sim2real.diagnose_recording(path, options["model"], options["effects"], report)
                )
        row["status"] = OK
    except Exception as exc:  # noqa: BLE001 - any failure is this item's row, not the batch's
        row.update(status=FAILED, error=one_line(exc))
    row["seconds"] = time.perf_counter() - start
    return row


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return f"{socket.gethostname()}:{os.getpid()}"


@contextlib.contextmanager
def dask_client(workers: int | None = None, scheduler: str | None = None, memory_limit="auto"):
    """A Client on an embedded LocalCluster (`workers` processes, default one per core, one
    thread each: the evaluations are Python-bound; `memory_limit` per worker, "auto" = the
    machine's memory shared out), or on the scheduler at `scheduler` (then `workers`, if
    given, is how many workers to wait for before starting)."""
    from distributed import Client, LocalCluster

    if workers is not None and workers < 1:
        raise ValueError(f"workers={workers}: must be at least 1")
    if scheduler:
        with Client(scheduler, timeout=CONNECT_TIMEOUT) as client:
            if workers:
                client.wait_for_workers(workers, timeout=CONNECT_TIMEOUT)
            yield client
        return
    with (
        LocalCluster(
            n_workers=workers or os.cpu_count() or 1,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",  # the embedded cluster serves this machine, not its network
            memory_limit=memory_limit,
            # an ephemeral port: the scheduler always serves HTTP (health, metrics), and the
            # default 8787 would collide with another cluster on the machine; this machine only
            dashboard_address="127.0.0.1:0",
        ) as cluster,
        Client(cluster) as client,
    ):
        yield client


def run_batch(
    kind: str,
    paths,
    output,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    memory_limit="auto",
    model: str | None = None,
    effects: list | None = None,
    progress: Callable[[Progress], None] | None = None,
    client=None,
) -> BatchResult:
    """Evaluate (kind "evaluate") or diagnose ("sim2real") every recording `paths` name,
    writing OUTPUT/results.csv (a row per item) and OUTPUT/summary.md. `client`: an existing
    dask Client to use instead of making one from workers/scheduler."""
    task_options, hashed = _options(kind, model, effects)
    module = evaluate if kind == "evaluate" else sim2real
    config = config_hash(kind, module.ROW_FORMAT, hashed)
    items = expand_items(paths)
    output = Path(output).absolute()  # the workers write the sim2real reports into it
    output.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    state = Progress(total=len(items), started=started)
    with ResultsTable(output / "results.csv", COMMON_COLUMNS + module.COLUMNS) as table:
        with contextlib.ExitStack() as stack:
            if client is None:
                client = stack.enter_context(dask_client(workers, scheduler, memory_limit))
            _run(client, kind, items, config, task_options, output, table, state, progress)
    rows = read_rows(output / "results.csv")
    summary = output / "summary.md"
    text = module.summary_markdown(module.summarise(rows))
    figure = _figure(kind, rows, output)
    summary.write_text(text + (f"\n![{figure}]({figure})\n" if figure else ""))
    return BatchResult(
        table=output / "results.csv",
        summary=summary,
        total=len(items),
        computed=state.ok + state.failed,
        ok=state.ok,
        failed=state.failed,
        skipped=state.skipped,
        seconds=time.perf_counter() - started,
    )


def _figure(kind: str, rows: list[dict], output: Path) -> str | None:
    try:
        if kind == "sim2real":
            return plots.effects_by_date(rows, output)
        return plots.errors_by_session(rows, output)
    except ImportError:  # pragma: no cover - matplotlib is a project dependency
        return None


def _run(client, kind, items, config, options, output, table, state, progress) -> None:
    """Hash every item on the workers; as each hash arrives, skip the item or submit its task;
    write each task's row as it completes."""
    from distributed import as_completed

    hashes = client.map(file_sha256, items, pure=False)
    role = {h.key: ("hash", item, "") for h, item in zip(hashes, items)}
    pending = as_completed(hashes)
    for future in pending:
        what, item, sha = role.pop(future.key)
        try:
            result = future.result()
        except Exception as exc:  # noqa: BLE001 - unreadable file, lost worker: the item's row
            row = {"item": item, "sha256": sha, "config": config, "status": FAILED}
            _record(table, state, {**row, "error": one_line(exc)}, progress)
            continue
        if what == "work":
            _record(table, state, result, progress)
        elif (result, config) in table.done:
            state.skipped += 1
            _say(progress, state)
        else:
            work = client.submit(
                run_item, kind, item, result, config, options, str(output), pure=False
            )
            role[work.key] = ("work", item, result)
            pending.add(work)


def _record(table: ResultsTable, state: Progress, row: dict, progress) -> None:
    table.append(row)
    if row["status"] == OK:
        state.ok += 1
    else:
        state.failed += 1
    state.last = row
    _say(progress, state)


def _say(progress, state: Progress) -> None:
    if progress is not None:
        progress(state)
