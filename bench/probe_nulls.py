"""False alarms on null sessions the suite has never drawn (issue 29, the naming rule).

Null recordings (the model is the truth; only the seed, the sample layout and the substrate
differ from the suite's) of the diagnostic protocol and of normal-work sessions, diagnosed
through `run_sim2real` one after the other, one line per case: the verdict, the terms named,
the held-out chi^2, whether an updated configuration was written. The seeds (1900 on) and the
variants are not the families' (sim2real_families.py: 700-729), so a rule tuned to those would
show here.

Run: `scripts/with_env.sh python bench/probe_nulls.py [--protocol N] [--work N] [--first SEED]
[--keep DIR] [--effects NAME,...] [--name RESULTS]`.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from datetime import datetime, timezone  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import sim2real_families as families  # noqa: E402
import sim2real_scoring as scoring  # noqa: E402
from machine import command_line, machine_record  # noqa: E402


def null_cases(n_protocol: int, n_work: int, first: int) -> list:
    """Nulls with layouts and substrates drawn from each case's seed (particle count 4-7,
    radius 80-120 nm, roughness 0.2-0.5 nm rms, correlation 10-40 nm)."""
    cases = []
    for k in range(n_protocol + n_work):
        seed = first + k
        rng = np.random.default_rng(seed)
        work = k >= n_protocol
        count = int(rng.integers(4, 6 if work else 8))
        substrate = {
            "roughness_sigma": float(rng.uniform(0.2e-9, 0.5e-9)),
            "roughness_correlation": float(rng.uniform(10e-9, 40e-9)),
        }
        if work:
            layout = families.draw_layout(rng, count, families.WORK_SPACING, half=1.5e-6)
            radius = 100e-9
        else:
            layout = families.draw_layout(
                rng, count, families.PROTOCOL_SPACING, families.SLIDE_KEEP_OUT
            )
            radius = float(rng.uniform(80e-9, 120e-9))
        kind = "work" if work else "protocol"
        cases.append(
            families.FamilyCase(
                f"probe-null-{kind}-{seed}", f"null_{kind}", seed, kind, layout, radius, substrate
            )
        )
    return cases


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--protocol", type=int, default=5, help="protocol nulls")
    parser.add_argument("--work", type=int, default=3, help="normal-work nulls")
    parser.add_argument("--first", type=int, default=1900, help="first seed")
    parser.add_argument("--keep", default="", help="keep recordings and reports here")
    parser.add_argument(
        "--effects",
        default="",
        help="library terms to consider, comma-separated (default: all); a library of one "
        "term has the lowest family-wise threshold, the naming rule's hardest case",
    )
    parser.add_argument(
        "--name", default="", help="results name (default sim2real-fresh-nulls-<first>)"
    )
    args = parser.parse_args(argv)
    workdir = args.keep or tempfile.mkdtemp(prefix="probe-nulls-")
    alarms = named = 0
    load = os.getloadavg()
    started = datetime.now(timezone.utc)
    lines = []
    cases = null_cases(args.protocol, args.work, args.first)
    for case in cases:
        effects = [e for e in args.effects.split(",") if e] or None
        row = families.run_family_case(case, workdir, effects=effects)
        alarm = row.get("verdict") in scoring.MISSING_PHYSICS
        alarms += alarm
        named += bool(row.get("chosen"))
        chi2 = row.get("heldout_chi2") or [float("nan")] * 3
        lines.append(
            f"{case.name:26s} {row.get('verdict', '?'):30s} "
            f"{','.join(row.get('chosen', [])) or 'none':28s} "
            f"held-out {chi2[0] or float('nan'):.1f} -> {chi2[1] or float('nan'):.1f} "
            f"({chi2[2]}) config {'written' if row.get('config_written') else 'no'} "
            f"{row.get('cpu_seconds', float('nan')):5.1f} s  {row.get('verdict_words', '')[:300]}"
        )
        print(lines[-1], flush=True)
    n = len(cases)
    lines.append(f"false 'missing physics' {alarms} of {n}; a term named {named} of {n}")
    print(lines[-1])
    write_results(args, started, load, lines)
    return 0


def write_results(args, started, load, lines) -> Path:
    """bench/results/sim2real-fresh-nulls-<first>.md: date, machine, command, one line a case."""
    machine = machine_record(load)
    name = args.name or f"sim2real-fresh-nulls-{args.first}"
    out = Path(__file__).resolve().parent / "results" / f"{name}.md"
    out.write_text(
        "\n".join(
            [
                f"# Sim-to-real on fresh null sessions (seeds {args.first} on; library: "
                f"{args.effects or 'all terms'})",
                "",
                f"Date: {started:%Y-%m-%d %H:%M} UTC  ",
                f"Machine: {json.dumps(machine)}  ",
                f"Command: `{command_line()}`",
                "",
                "Our own simulator: the model is the truth, only the seed, the sample layout "
                "and the substrate differ from the suite's.",
                "",
                "```",
                *lines,
                "```",
                "",
            ]
        )
    )
    print(f"wrote {out}")
    return out


if __name__ == "__main__":
    raise SystemExit(main())
