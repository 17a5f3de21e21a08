"""`afm batch evaluate|sim2real PATHS... --output DIR`: many recordings at once on Dask, an
embedded cluster by default or a lab's scheduler with --scheduler (afm_core.batch)."""

from __future__ import annotations

import sys

from afm_bringup.cli_errors import refuse

INTERRUPTED = 130  # the shell's status for a command stopped by Ctrl-C (128 + SIGINT)


def cmd_batch(args):
    from afm_core.batch import run_batch

    def show(state):
        row = state.last
        if row is not None and row.get("status") == "failed":
            print(f"afm batch: {row['item']} failed: {row.get('error', '')}", file=sys.stderr)
        print(f"afm batch: {state.line()}", flush=True)

    effects = [e.strip() for e in args.effects.split(",") if e.strip()] if args.effects else []
    try:
        result = run_batch(
            args.kind,
            args.paths,
            args.output,
            workers=args.workers,
            scheduler=args.scheduler or None,
            memory_limit=args.memory_limit,
            model=getattr(args, "model", "") or None,
            effects=effects,
            progress=show,
        )
    except (ValueError, OSError) as exc:  # an input that names nothing, a bad model or effect
        return refuse("batch", exc)
    except KeyboardInterrupt:
        # the rows written so far are in the table (each flushed as it came); the cluster was
        # closed by the context managers on the way out
        print(
            f"afm batch: interrupted; the finished rows are in {args.output}/results.csv and "
            "the same command goes on from there",
            file=sys.stderr,
        )
        return INTERRUPTED
    print(
        f"afm batch: {result.total} items: {result.computed} run now in {result.seconds:.0f} s "
        f"({result.ok} ok, {result.failed} failed), {result.skipped} done before; "
        f"{result.table}, {result.summary}"
    )
    return 1 if result.failed else 0


def _add_batch(sub) -> None:
    p = sub.add_parser(
        "batch",
        help="evaluate or diagnose many recordings at once (Dask: this machine or a cluster)",
        description="Run an offline evaluation (evaluate: localization error and NEES against "
        "ground truth where recorded, scans against truth, pushes) or the sim-to-real "
        "diagnosis (sim2real) of every recording PATHS name (files, folders of *.mcap, "
        "fsspec URLs), one row per recording in OUTPUT/results.csv, written as each "
        "completes, and a summary across them in OUTPUT/summary.md. A failed recording "
        "is a row with its error; a re-run skips the recordings done (same file content "
        "and configuration). Runs on an embedded Dask cluster, or on the lab's own with "
        "--scheduler.",
    )
    p.add_argument("kind", choices=["evaluate", "sim2real"], help="what to run per recording")
    p.add_argument("paths", nargs="+", metavar="PATH", help="recording, folder or URL")
    p.add_argument("--output", "-o", required=True, help="folder for results.csv, summary.md")
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        help="worker processes of the embedded cluster (default: one per core); with "
        "--scheduler, how many workers to wait for before starting",
    )
    p.add_argument(
        "--scheduler",
        default="",
        metavar="tcp://HOST:PORT",
        help="an existing Dask scheduler (its workers must have this project installed and "
        "see the recordings and OUTPUT at the same paths)",
    )
    p.add_argument(
        "--memory-limit",
        default="auto",
        help="per worker of the embedded cluster, e.g. 2GiB (default: memory / workers)",
    )
    p.add_argument(
        "--model",
        default="",
        help="sim2real: simulator configuration YAML (default: the simulator's defaults)",
    )
    p.add_argument(
        "--effects",
        default="",
        metavar="NAME,NAME",
        help="sim2real: consider only these library terms (default: all of them)",
    )
    p.set_defaults(func=cmd_batch)
