"""`afm batch evaluate|sim2real PATHS... --output DIR` and `afm batch
push|montecarlo|localize --seeds 0-99 --output DIR`: many recordings, or the benchmark sweeps'
seeds, at once on Dask, an embedded cluster by default or a lab's scheduler with --scheduler
(afm_core.batch)."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

from afm_bringup.cli_errors import refuse
from afm_bringup.units import length_type

INTERRUPTED = 130  # the shell's status for a command stopped by Ctrl-C (128 + SIGINT)


def cmd_batch(args):
    from afm_core.batch import run_batch

    def show(state):
        row = state.last
        if row is not None and row.get("status") == "failed":
            print(f"afm batch: {row['item']} failed: {row.get('error', '')}", file=sys.stderr)
        print(f"afm batch: {state.line()}", flush=True)

    effects = [e.strip() for e in args.effects.split(",") if e.strip()] if args.effects else []
    seeds = args.kind in ("push", "montecarlo", "localize")
    if seeds != bool(args.seeds) or (not seeds and not args.paths) or (seeds and args.paths):
        return refuse(
            "batch",
            ValueError(
                f"batch {args.kind}: "
                + ("give --seeds (e.g. 0-99), no PATH" if seeds else "give PATHs, no --seeds")
            ),
        )
    output = Path(args.output)
    existed = output.exists()
    try:
        check_arguments(args)
        result = run_batch(
            args.kind,
            args.seeds if seeds else args.paths,
            args.output,
            workers=args.workers,
            scheduler=args.scheduler or None,
            memory_limit=args.memory_limit,
            model=getattr(args, "model", "") or None,
            effects=effects,
            progress=show,
            **_settings(args),
        )
    except (ValueError, OSError) as exc:  # an input that names nothing, a bad model or effect
        if not existed:
            _remove_if_empty(output)
        return refuse("batch", _named(exc, args))
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


# the options that belong to some kinds only, and those kinds; given to another kind they were
# dropped without a word (`batch montecarlo --strategy centre` ran the default plan)
KIND_OPTIONS = {
    "tolerance": ("evaluate", "push", "montecarlo"),
    "strategy": ("push",),
    "estimate_sigma": ("push", "montecarlo"),
    "plan": ("montecarlo",),
    "samples": ("montecarlo",),
    "goal_distance": ("push",),
    "mode": ("localize",),
    "calibration": ("localize",),
    "model": ("sim2real",),
    "effects": ("sim2real",),
}


def check_arguments(args) -> None:
    """ValueError naming the option: one the kind does not use, a scheduler that is no
    address, or a file every item reads (read once here, not failed once per item)."""
    for dest, kinds in KIND_OPTIONS.items():
        if args.kind not in kinds and getattr(args, dest, None) not in (None, ""):
            option = "--" + dest.replace("_", "-")
            raise ValueError(f"{option}: {args.kind} does not use it (only {', '.join(kinds)})")
    output = Path(args.output)
    if output.exists() and not output.is_dir():
        raise ValueError(f"--output {output}: a file; name a folder (made if missing)")
    if args.scheduler:
        _check_scheduler(args.scheduler)
    if args.kind == "localize" and args.calibration:
        from afm_core.localization.calibration.model import load_calibration

        load_calibration(args.calibration)
    if args.kind == "sim2real" and args.model:
        from afm_core.sim.config import load_config

        load_config(args.model)


def _check_scheduler(address: str) -> None:
    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        scheme, location = parse_address(address)
        if scheme in ("tcp", "tls"):
            parse_host_port(location)  # the port is required: there is no default one
    except (ValueError, TypeError) as exc:
        raise ValueError(
            f"--scheduler {address!r}: expected an address such as tcp://HOST:PORT ({exc})"
        ) from None


def _named(exc: BaseException, args) -> BaseException:
    """An OS error under --output, with the option (the OS names only the path)."""
    if isinstance(exc, OSError) and exc.filename is not None:
        output = Path(args.output).absolute()
        where = Path(exc.filename).absolute()
        if where == output or output in where.parents or where in output.parents:
            return ValueError(f"--output {args.output}: cannot write there: {exc.strerror or exc}")
    return exc


def _remove_if_empty(output: Path) -> None:
    """The folder a refused run made, when it holds no result yet (a header at most): a
    refusal leaves nothing behind. A row computed is kept: the same command goes on from it."""
    if not output.is_dir():
        return
    files = [p for p in output.rglob("*") if p.is_file()]
    table = output / "results.csv"
    if all(p == table for p in files) and (
        not table.exists() or len(table.read_text().splitlines()) <= 1
    ):
        shutil.rmtree(output, ignore_errors=True)


def _settings(args) -> dict:
    """The kind's own settings (SI units); None: the kind's default."""
    if args.kind == "evaluate":
        return {"push_tolerance": args.tolerance}
    if args.kind == "push":
        return {
            "strategy": args.strategy or "nano_hand",
            "estimate_sigma": args.estimate_sigma,
            "goal_distance": args.goal_distance,
            "tolerance": args.tolerance,
        }
    if args.kind == "montecarlo":
        return {
            "plan": args.plan or "nano_hand",
            "samples": args.samples,
            "sigma": args.estimate_sigma,
            "tolerance": args.tolerance,
        }
    if args.kind == "localize":
        return {"mode": args.mode or "via_landmark_toward_x8", "calibration": args.calibration}
    return {}


def _add_batch(sub) -> None:
    p = sub.add_parser(
        "batch",
        help="evaluate or diagnose many recordings at once (Dask: this machine or a cluster)",
        description="Run an offline evaluation (evaluate: localization error and NEES against "
        "ground truth where recorded, scans against truth, pushes and push goals) or the "
        "sim-to-real diagnosis (sim2real) of every recording PATHS name (files, folders of "
        "*.mcap, fsspec URLs), or a benchmark sweep over --seeds (push: a push strategy on "
        "the simulated AFM per seed; montecarlo: the stochastic pushing model's draws per "
        "seed; localize: the book's tip-localization trials), one "
        "row per item in OUTPUT/results.csv, written as each completes, and a summary "
        "across them in OUTPUT/summary.md. A failed item is a row with its error; a re-run "
        "skips the items done (same file content or seed, same configuration). Runs on an "
        "embedded Dask cluster, or on the lab's own with --scheduler.",
    )
    p.add_argument(
        "kind",
        choices=["evaluate", "sim2real", "push", "montecarlo", "localize"],
        help="what to run per item",
    )
    p.add_argument("paths", nargs="*", metavar="PATH", help="recording, folder or URL")
    p.add_argument(
        "--seeds",
        default="",
        help="push, montecarlo, localize: the seeds, e.g. 0-99 or 0,1,5 (inclusive)",
    )
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
    _add_sweep_options(p)
    p.set_defaults(func=cmd_batch)


def _add_sweep_options(p) -> None:
    p.add_argument(
        "--tolerance",
        type=length_type("tolerance"),
        default=None,
        help="evaluate, push, montecarlo: success radius around a push goal (m, or with a "
        "unit; default 20nm)",
    )
    p.add_argument(
        "--strategy",
        default=None,
        choices=["nano_hand", "centre", "centre_single", "table_7_6"],
        help="push: the plan (default nano_hand, the aimed zigzag)",
    )
    p.add_argument(
        "--estimate-sigma",
        type=length_type("estimate-sigma"),
        default=None,
        help="push, montecarlo: the particle estimate's error per axis (m, or with a unit; "
        "default 10nm)",
    )
    p.add_argument(
        "--plan",
        default=None,
        choices=["centre", "nano_hand", "nano_hand_aimed_300nm", "table_7_6_13_steps"],
        help="montecarlo: the bench's plan (default nano_hand, the Table 7.6 zigzag)",
    )
    p.add_argument(
        "--samples", type=int, default=None, help="montecarlo: draws per seed (default 500)"
    )
    p.add_argument(
        "--goal-distance",
        type=length_type("goal-distance", positive=True),
        default=None,
        help="push: the goal's distance from the estimate along +y (m, or with a unit; "
        "default 500nm)",
    )
    p.add_argument(
        "--mode",
        default=None,
        choices=[
            "direct",
            "via_landmark",
            "via_landmark_straight",
            "via_landmark_toward_x8",
            "table_7_3_book",
            "table_7_3_line_ends_at_pit",
        ],
        help="localize: the trial (Tables 7.1/7.2 modes, or Table 7.3's pit; default "
        "via_landmark_toward_x8)",
    )
    p.add_argument(
        "--calibration",
        default=None,
        help="localize: calibration YAML (default: the simulator's oracle calibration)",
    )
