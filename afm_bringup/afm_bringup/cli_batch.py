"""`afm batch evaluate|sim2real PATHS... --output DIR` and `afm batch
push|montecarlo|localize --seeds 0-99 --output DIR`: many recordings, or the benchmark sweeps'
seeds, at once on Dask, an embedded cluster by default or a lab's scheduler with --scheduler
(afm_core.batch)."""

from __future__ import annotations

import sys

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
    try:
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
        type=length_type("goal-distance"),
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
