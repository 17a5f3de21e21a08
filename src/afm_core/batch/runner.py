"""Run a batch on Dask: an embedded LocalCluster (one single-threaded worker process per core,
each with a memory limit) or a lab's existing scheduler, named by its address; nothing else
changes between the two.

The items' hashes are computed on the workers (a recording is read where it lies, by whoever
runs the task); an item whose (file hash, configuration hash) already has a finished row is
skipped, every other one runs as one task. A sweep's items are seeds, keyed by (seed,
configuration hash), submitted at once. Rows are appended to DIR/results.csv as tasks
complete, each with the time it was written; a task's exception becomes a failed row with its
error on one line, so one bad recording never stops the batch.
"""

from __future__ import annotations

import contextlib
import os
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from afm_core.batch import evaluate, plots, sim2real, sweeps
from afm_core.batch.items import config_hash, expand_items, file_sha256, local_file, parse_seeds
from afm_core.batch.table import COMMON_COLUMNS, FAILED, OK, ResultsTable, read_rows

RECORDING_KINDS = ("evaluate", "sim2real")  # items: recordings, keyed by their content's hash
SEED_KINDS = (
    "push",
    "montecarlo",
    "localize",
)  # items: seeds of a benchmark sweep, keyed by the seed
KINDS = RECORDING_KINDS + SEED_KINDS
ERROR_CHARS = 300  # an error cell is one line, this long at most (the full text is in the log)
WORKER_SETUP = "afm_core.batch.worker_setup"
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
    unit: str = "recordings"

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
            f"{self.skipped} done before), {self.per_minute:.1f} {self.unit}/min"
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


def _options(kind: str, model, effects, settings: dict) -> tuple[dict, dict]:
    """(what the task gets, what the configuration hash is of)."""
    if kind not in KINDS:
        raise ValueError(f"batch kind {kind!r}: expected one of {list(KINDS)}")
    allowed = {
        "evaluate": {"push_tolerance"},
        "sim2real": set(),
        "push": {"strategy", "estimate_sigma", "goal_distance", "tolerance"},
        "montecarlo": {"plan", "samples", "sigma", "tolerance"},
        "localize": {"mode", "calibration"},
    }[kind]
    unknown = sorted(k for k, v in settings.items() if k not in allowed and v is not None)
    if unknown:
        raise ValueError(f"batch kind {kind!r}: no setting {unknown} (it has {sorted(allowed)})")
    settings = {k: v for k, v in settings.items() if v is not None}
    if kind == "evaluate":
        return evaluate.options(**settings)
    if kind == "push":
        return sweeps.push_options(**settings)
    if kind == "montecarlo":
        return sweeps.monte_carlo_options(**settings)
    if kind == "localize":
        return sweeps.localize_options(**settings)
    if model and not Path(model).is_file():
        raise ValueError(f"model {str(model)!r}: no such simulator configuration file")
    model_hash = file_sha256(str(model)) if model else "defaults"
    effects = sorted(effects or [])
    if effects:
        from afm_core.sim2real.candidates import select

        select(effects)  # a misspelt effect is refused before any recording is read
    task = {"model": str(Path(model).resolve()) if model else None, "effects": effects}
    return task, {"model": model_hash, "effects": effects}


def run_item(
    kind: str, item: str, sha: str, config: str, options: dict, output: str, shared=None
) -> dict:
    """One item's row on a worker; never raises (a failure is the row's status and error).
    shared: what every item of the batch needs, computed once (localize: the calibration)."""
    start = time.perf_counter()
    row = {"item": item, "sha256": sha, "config": config, "worker": _worker_name()}
    try:
        if kind == "push":
            row.update(sweeps.push_row(int(item), options))
        elif kind == "montecarlo":
            row.update(sweeps.monte_carlo_row(int(item), options))
        elif kind == "localize":
            row.update(sweeps.localize_row(int(item), options, shared))
        else:
            with local_file(item) as path:
                row.update(_recording_row(kind, path, item, sha, config, options, output))
        row["status"] = OK
    except Exception as exc:  # noqa: BLE001 - any failure is this item's row, not the batch's
        row.update(status=FAILED, error=one_line(exc))
    row["seconds"] = time.perf_counter() - start
    return row


def _recording_row(
    kind: str, path: Path, item: str, sha: str, config: str, options: dict, output: str
):
    # reports are named by the item as given (a URL's file is a temporary copy), its content
    # and the settings: a re-run with other settings keeps the earlier row's report its own
    report = Path(output) / "reports" / f"{Path(item).stem}-{sha[:12]}-{config[:8]}"
    if kind == "evaluate":
        row = evaluate.evaluate_recording(path, **options)
        report = report.with_name(report.name + ".md")
        report.parent.mkdir(parents=True, exist_ok=True)
        report.write_text(evaluate.session_report(row, item))
        return {**row, "report": str(report.relative_to(output))}  # the same on every cluster
    return sim2real.diagnose_recording(path, options["model"], options["effects"], report)


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return f"{socket.gethostname()}:{os.getpid()}"


# a worker's peak RSS was 140-212 MiB (bench/results/batch.md); below twice that Dask's nanny
# kills and restarts it without end, and the batch hangs with no row
MIN_WORKER_MEMORY = 512 * 2**20  # bytes


def check_cluster(workers: int | None, scheduler: str | None, memory_limit="auto") -> None:
    """ValueError naming the option when the embedded cluster would not run: fewer than one
    worker, a memory limit that is no size, or too little memory per worker."""
    if workers is not None and workers < 1:
        raise ValueError(f"workers={workers}: must be at least 1")
    if scheduler:
        return
    from dask.utils import parse_bytes
    from distributed.system import MEMORY_LIMIT

    count = workers or os.cpu_count() or 1
    if memory_limit == "auto":
        per_worker = MEMORY_LIMIT / count
    else:
        try:
            per_worker = (
                parse_bytes(memory_limit) if isinstance(memory_limit, str) else memory_limit
            )
        except ValueError:
            raise ValueError(
                f"memory_limit={memory_limit!r}: not a size (e.g. 2GiB, or auto)"
            ) from None
        if per_worker == 0:  # Dask's "no limit"
            return
    if per_worker < MIN_WORKER_MEMORY:
        raise ValueError(
            f"memory_limit: {per_worker / 2**20:.0f} MiB per worker ({count} workers"
            + (f" sharing {MEMORY_LIMIT / 2**30:.1f} GiB" if memory_limit == "auto" else "")
            + f") is below the {MIN_WORKER_MEMORY / 2**20:.0f} MiB a worker needs: fewer "
            "workers or a larger --memory-limit"
        )


@contextlib.contextmanager
def dask_client(workers: int | None = None, scheduler: str | None = None, memory_limit="auto"):
    """A Client on an embedded LocalCluster (`workers` processes, default one per core, one
    thread each: the evaluations are Python-bound; `memory_limit` per worker, "auto" = the
    machine's memory shared out), or on the scheduler at `scheduler` (then `workers`, if
    given, is how many workers to wait for before starting)."""
    from distributed import Client, LocalCluster

    check_cluster(workers, scheduler, memory_limit)
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
            preload=[WORKER_SETUP],  # the workers leave Ctrl-C to this process
        ) as cluster,
        Client(cluster) as client,
    ):
        yield client


@dataclass(frozen=True)
class _Kind:
    columns: list
    row_format: int
    summarise: Callable
    markdown: Callable


def _kind(kind: str) -> _Kind:
    if kind in RECORDING_KINDS:
        module = evaluate if kind == "evaluate" else sim2real
        return _Kind(module.COLUMNS, module.ROW_FORMAT, module.summarise, module.summary_markdown)
    if kind == "push":
        return _Kind(
            sweeps.PUSH_COLUMNS, sweeps.ROW_FORMAT, sweeps.summarise_push, sweeps.push_markdown
        )
    if kind == "montecarlo":
        return _Kind(
            sweeps.MONTE_CARLO_COLUMNS,
            sweeps.ROW_FORMAT,
            sweeps.summarise_monte_carlo,
            sweeps.monte_carlo_markdown,
        )
    return _Kind(
        sweeps.LOCALIZE_COLUMNS,
        sweeps.ROW_FORMAT,
        sweeps.summarise_localize,
        sweeps.localize_markdown,
    )


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
    **settings,
) -> BatchResult:
    """Run `kind` over its items, writing OUTPUT/results.csv (a row per item) and
    OUTPUT/summary.md. Recording kinds ("evaluate", "sim2real"): `paths` names recordings
    (files, folders, URLs). Seed kinds ("push", "localize"): `paths` is the seeds (ints, or
    text such as "0-99" or "0,1,5"). `settings`: the kind's own (evaluate: push_tolerance;
    push: strategy, estimate_sigma, goal_distance, tolerance; montecarlo: plan, samples,
    sigma, tolerance; localize: mode, calibration; SI units). `client`: an existing dask
    Client to use instead of making one."""
    task_options, hashed = _options(kind, model, effects, settings)
    spec = _kind(kind)
    config = config_hash(kind, spec.row_format, hashed)
    items = parse_seeds(paths) if kind in SEED_KINDS else expand_items(paths)
    if client is None:  # before anything is written: a refusal leaves no results.csv
        check_cluster(workers, scheduler, memory_limit)
    output = Path(output).absolute()  # the workers write the sim2real reports into it
    output.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    unit = "seeds" if kind in SEED_KINDS else "recordings"
    state = Progress(total=len(items), started=started, unit=unit)
    with ResultsTable(output / "results.csv", COMMON_COLUMNS + spec.columns) as table:
        with contextlib.ExitStack() as stack:
            if client is None:
                client = stack.enter_context(dask_client(workers, scheduler, memory_limit))
            batch = _Batch(client, kind, config, task_options, output, table, state, progress)
            batch.run(items)
    rows = read_rows(output / "results.csv")
    summary = output / "summary.md"
    text = spec.markdown(spec.summarise(rows))
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
        if kind == "push":
            return plots.push_errors(rows, output)
        if kind == "montecarlo":
            return plots.monte_carlo_success(rows, output)
        if kind == "localize":
            return plots.localization_errors(rows, output)
        return plots.errors_by_session(rows, output)
    except ImportError:  # pragma: no cover - matplotlib is a project dependency
        return None


@dataclass
class _Batch:
    """One batch on a client: items submitted, rows written as their tasks complete."""

    client: object
    kind: str
    config: str
    options: dict
    output: Path
    table: ResultsTable
    state: Progress
    progress: Callable | None

    def run(self, items: list) -> None:
        """Recordings: hash every item on the workers; as each hash arrives, skip the item or
        submit its task. Seeds: skip or submit at once. Write each task's row as it ends."""
        from distributed import as_completed

        self.pending = as_completed()
        self.role: dict = {}
        self.shared = None
        if self.kind in SEED_KINDS:
            todo = [s for s in items if (str(s), self.config) not in self.table.done]
            self.state.skipped += len(items) - len(todo)
            if self.state.skipped:
                _say(self.progress, self.state)
            if todo and self.kind == "localize":  # the calibration: once, on a worker
                self.shared = self.client.submit(
                    sweeps.prepare_calibration,
                    self.options["calibration"],
                    self.options["mode"],
                    pure=False,
                )
            for seed in todo:
                self._submit(str(seed), "")
        else:
            hashes = self.client.map(file_sha256, items, pure=False)
            for future, item in zip(hashes, items):
                self.role[future.key] = ("hash", item, "")
                self.pending.add(future)
        for future in self.pending:
            self._completed(future)

    def _submit(self, item: str, sha: str) -> None:
        work = self.client.submit(
            run_item,
            self.kind,
            item,
            sha,
            self.config,
            self.options,
            str(self.output),
            self.shared,
            pure=False,
        )
        self.role[work.key] = ("work", item, sha)
        self.pending.add(work)

    def _completed(self, future) -> None:
        what, item, sha = self.role.pop(future.key)
        try:
            result = future.result()
        except Exception as exc:  # noqa: BLE001 - unreadable file, lost worker: the item's row
            row = {"item": item, "sha256": sha, "config": self.config, "status": FAILED}
            _record(self.table, self.state, {**row, "error": one_line(exc)}, self.progress)
            return
        if what == "work":
            _record(self.table, self.state, result, self.progress)
        elif (result, self.config) in self.table.done:
            self.state.skipped += 1
            _say(self.progress, self.state)
        else:
            self._submit(item, result)


def _record(table: ResultsTable, state: Progress, row: dict, progress) -> None:
    # when the row was written: a re-run tells the rows it kept from those it computed
    row = {**row, "finished_utc": datetime.now(timezone.utc).isoformat(timespec="microseconds")}
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
