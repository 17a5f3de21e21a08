"""Probe: effects outside the library, injected after the recording (test/sim2real_invented.py),
diagnosed with a restricted library; one line per case with the verdict, the signature (kind,
signals, form in time and across the sample), the generic fit's form and the share of the
held-out excess it removes, and the diagnosis' CPU time.

    scripts/with_env.sh python bench/probe_unexplained.py --seeds 11 5 --cases null bend jump
    (--whole-library: every library term instead of height_gain, bow, tip_radius, friction)
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

import sim2real_invented as invented  # noqa: E402

from afm_core.sim.config import merge  # noqa: E402
from afm_core.sim2real.candidates import select  # noqa: E402
from afm_core.sim2real.diagnose import diagnose  # noqa: E402
from afm_core.sim2real.protocol import make_session, session_config  # noqa: E402

CANDIDATES = ("height_gain", "bow", "tip_radius", "friction")


def _mid(ops) -> float:
    return 0.5 * (ops[0].start_time + ops[-1].start_time)


CASES = {
    # name -> (what is injected, into the truth config, the truth in words)
    "null": (lambda ops: ops, {}, "nothing"),
    "bend": (
        lambda ops: invented.add_to_heights(ops, invented.thermal_bending(2e-12)),
        {},
        "z: linear trend 2 pm/s",
    ),
    "jump": (
        lambda ops: invented.add_to_heights(ops, invented.z_jump(1e-9, _mid(ops))),
        {},
        "z: step 1 nm mid-session",
    ),
    "pickup": (
        lambda ops: invented.add_to_heights(ops, invented.z_pickup_with_x(1e-9, 2e-6)),
        {},
        "z: periodic in x, 1 nm, 2 um",
    ),
    "pickup-small": (
        lambda ops: invented.add_to_heights(ops, invented.z_pickup_with_x(0.5e-9, 2e-6)),
        {},
        "z: periodic in x, 0.5 nm, 2 um",
    ),
    "torsion": (
        lambda ops: invented.add_to_torsion(ops, invented.torsion_drift(2e-7)),
        {},
        "torsion: linear trend 0.2 urad/s",
    ),
    "bend+tip": (
        lambda ops: invented.add_to_heights(ops, invented.thermal_bending(2e-12)),
        {"tip": {"apex_radius": 26e-9}},
        "z: linear trend 2 pm/s on a blunter tip (library)",
    ),
}


def _cpu() -> float:
    self, children = (
        resource.getrusage(w) for w in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
    )
    return self.ru_utime + self.ru_stime + children.ru_utime + children.ru_stime


def run(case: str, seed: int, whole_library: bool = False) -> str:
    inject, truth_overrides, words = CASES[case]
    model = merge(session_config(), {"seed": seed})
    ops = inject(make_session(merge(model, truth_overrides), protocol_seed=seed))
    c0, w0 = _cpu(), time.perf_counter()
    d = diagnose(ops, model, candidates=None if whole_library else select(CANDIDATES))
    cpu, wall = _cpu() - c0, time.perf_counter() - w0
    sig, g = d.signature, d.generic or {}
    described = "-"
    if sig is not None:
        described = (
            f"{sig.kind or 'nothing'} in {'+'.join(sig.groups) or '-'}; time: "
            f"{sig.time.get('form', '-')}; space: {sig.space.get('form', '-')} "
            f"(first: {sig.primary})"
        )
    fit = "-"
    if g.get("fitted"):
        h = g["heldout"]
        amps = ", ".join(f"{t['form']} {t['amplitude']:.3g}" for t in g["terms"])
        fit = (
            f"{amps}; held-out {h['chi2_before']:.0f} -> {h['chi2_after']:.0f} / {h['dof']}, "
            f"{h['excess_reduction']:.0%} of the excess"
        )
    elif g:
        fit = g.get("reason", "-")
    chosen = ",".join(d.chosen) or "none"
    return (
        f"| {case} | {seed} | {words} | {chosen} | {described} | {fit} | {cpu:.0f} / {wall:.0f} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[11])
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--whole-library", action="store_true", help="every library term")
    args = parser.parse_args()
    print("| case | seed | truth | named | signature | generic fit | CPU / wall s |")
    print("|---|---|---|---|---|---|---|")
    for seed in args.seeds:
        for case in args.cases:
            print(run(case, seed, args.whole_library), flush=True)


if __name__ == "__main__":
    main()
