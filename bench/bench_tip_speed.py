"""Speed of the blind tip estimate (issue 35, item 4): ours with the automatic threshold and
with a fixed one, against Gwyddion 2.62's full estimate at the same threshold, with 21x21 and
41x41 tip windows, on bench_tip's 512x512 characteriser image, in one run, single-threaded.

Run: `scripts/with_env.sh python bench/bench_tip_speed.py [--repeat 3] [--image spheres]
[--baseline REV] [--busy N]`. Writes bench/results/tip-speed.json and tip-speed.md (with
--image spheres, the 512x512 4 nm-pixel spheres image of bench_tip_corpus --speed:
tip-speed-spheres.*; with --busy N, N shell loops spin on the CPUs throughout, as other jobs
on a shared machine do: the names end in -busy).
Needs bench_tip's Gwyddion harness (built by bench/gwyddion/build.sh, which apt-installs
Debian's libgwyddion20-dev when missing).

For each window, `--repeat` rounds, each: ours auto, ours fixed at the auto threshold, ours
auto once more with the candidate test's morphology on every CPU (as `afm image tip` runs it),
then Gwyddion at that threshold (its grid: whole steps of image range / 10000); Gwyddion's
41x41 estimate (~3 min) runs in the first round only. Ours: wall (perf_counter) and CPU
(process_time) of the estimate_tip call, medians over the rounds; Gwyddion: the wall time of
the library call, measured in the harness. Both single-threaded except that one column
(OMP_NUM_THREADS=1 before numpy loads; Gwyddion's threads off), so the 2 shared CPUs' other
work slows both: the 1-min load average is recorded around every measurement, and the ratios
of one run are the figures to compare. Peak memory: the tracemalloc peak of one more
(untimed) call of ours (numpy's arrays included), the process's maximum RSS, and the largest
peak RSS (VmHWM) of the Gwyddion harness runs.
The figures hold for this simulated image; the target is auto at 41x41 under 5 s.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402
from datetime import datetime, timezone  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_tip as bt  # noqa: E402
import numpy as np  # noqa: E402
from machine import busy_loops, command_line, cpu_model  # noqa: E402

from afm_core.imaging.tip_estimation import estimate_tip, tip_error  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
TIP_SIZES = (21, 41)
TARGET_S = 5.0  # auto at 41x41


def timed(fn) -> tuple[float, float, object]:
    load = os.getloadavg()[0]
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return time.perf_counter() - w0, time.process_time() - c0, (out, load)


def peak_mib(fn) -> float:
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()


# --baseline: the estimate of another revision's afm_core, timed in a subprocess on the same
# image (saved as .npy), its tip saved for comparison
BASELINE_RUN = """
import json, os, sys, time
sys.path.insert(0, sys.argv[1])
import numpy as np
from afm_core.imaging.tip_estimation import estimate_tip
image = np.load(sys.argv[2])
k, th = int(sys.argv[4]), sys.argv[5]
load = os.getloadavg()[0]
w, c = time.perf_counter(), time.process_time()
est = estimate_tip(image, k, th if th == "auto" else float(th))
w, c = time.perf_counter() - w, time.process_time() - c
np.save(sys.argv[6], est.tip)
print(json.dumps({"wall_s": w, "cpu_s": c, "load": load, "threshold_m": float(est.threshold)}))
"""


class Baseline:
    """Another revision's src/afm_core (git archive into a temporary directory)."""

    def __init__(self, rev: str, workdir: Path):
        self.rev = subprocess.run(
            ["git", "rev-parse", "--short", rev], capture_output=True, text=True, check=True
        ).stdout.strip()
        self.dir = workdir / "baseline"
        self.dir.mkdir()
        archive = subprocess.run(
            ["git", "archive", self.rev, "src/afm_core"], capture_output=True, check=True
        ).stdout
        subprocess.run(["tar", "-x", "-C", str(self.dir)], input=archive, check=True)

    def run(self, image: np.ndarray, k: int, threshold) -> tuple[dict, np.ndarray]:
        out, path = self.dir / "tip.npy", self.dir / "image.npy"
        if not path.exists():
            np.save(path, image)
        args = [str(self.dir / "src"), str(path), "", str(k), str(threshold)]
        done = subprocess.run(
            [sys.executable, "-c", BASELINE_RUN, *args, str(out)],
            capture_output=True,
            text=True,
            check=True,
        )
        return json.loads(done.stdout.strip().splitlines()[-1]), np.load(out)


def measure(image, true_tip, pixel, k: int, repeat: int, gwy, baseline=None) -> dict:
    def error(tip) -> float:
        return float(tip_error(tip, true_tip, bt.DEPTH))  # as bench_tip scores

    rows: dict = {"auto": [], "fixed": [], "auto_all_cpus": [], "gwyddion": []}
    if baseline is not None:
        rows.update(baseline_auto=[], baseline_fixed=[])
        diffs = []
    threshold = steps = None
    for round_ in range(repeat):
        wall, cpu, (auto, load) = timed(lambda: estimate_tip(image, k, "auto", pixel))
        threshold = float(auto.threshold)
        rows["auto"].append({"wall_s": wall, "cpu_s": cpu, "load": load})
        wall, cpu, (fixed, load) = timed(lambda: estimate_tip(image, k, threshold, pixel))
        rows["fixed"].append({"wall_s": wall, "cpu_s": cpu, "load": load})
        same = float(np.abs(fixed.tip - auto.tip).max())  # the limit does not depend on the start
        # the candidate test's morphology in row bands on every CPU, as a user runs it
        os.environ["OMP_NUM_THREADS"] = str(os.cpu_count())
        wall, cpu, (threaded, load) = timed(lambda: estimate_tip(image, k, "auto", pixel))
        os.environ["OMP_NUM_THREADS"] = "1"
        assert np.array_equal(threaded.tip, auto.tip), "the threaded estimate differs"
        rows["auto_all_cpus"].append({"wall_s": wall, "cpu_s": cpu, "load": load})
        if baseline is not None:
            for name, th, ours in (("auto", "auto", auto), ("fixed", threshold, fixed)):
                row, tip = baseline.run(image, k, th)
                rows[f"baseline_{name}"].append(row)
                diffs.append(float(np.abs(tip - ours.tip).max()))
        if k <= 21 or round_ == 0:
            steps = int(round(threshold / gwy.step))
            load = os.getloadavg()[0]
            raw, info = gwy.estimate_full(k, steps)
            rows["gwyddion"].append(
                {"wall_s": info["seconds"], "load": load, "vm_hwm_kib": info.get("vm_hwm_kib")}
            )
            gwy_error = error(bt.gwyddion_estimate_to_ours(raw))
        print(f"  {k}x{k} round {round_ + 1}: {json.dumps(rows)}", flush=True)
    out = {
        "tip_size": k,
        "threshold_m": threshold,
        "gwyddion_threshold_m": steps * gwy.step,
        "auto_error_m": error(auto.tip),
        "fixed_minus_auto_max_abs_m": same,
        "gwyddion_error_m": gwy_error,
        "rounds": rows,
        "peak_tracemalloc_mib": {
            "auto": peak_mib(lambda: estimate_tip(image, k, "auto", pixel)),
            "fixed": peak_mib(lambda: estimate_tip(image, k, threshold, pixel)),
        },
    }
    if baseline is not None:
        out["baseline_max_abs_tip_difference_m"] = max(diffs)
    for name in rows:
        for key in ("wall_s", "cpu_s"):
            values = [r[key] for r in rows[name] if key in r]
            if values:
                out[f"{name}_{key}"] = statistics.median(values)
    g = out["gwyddion_wall_s"]
    out["auto_over_gwyddion"] = out["auto_wall_s"] / g
    out["fixed_over_gwyddion"] = out["fixed_wall_s"] / g
    return out


def render(result: dict) -> str:
    m = result["machine"]
    lines = [
        "# Blind tip estimate: speed against Gwyddion",
        "",
        f"Measured {result['measured']} on {m['cpus']} shared CPUs ({m['cpu']}), Python "
        f"{m['python']}, Gwyddion {m['gwyddion']}, both single-threaded; 1-min load average "
        f"{m['loadavg_start'][0]:.1f} at start, {m['loadavg_end'][0]:.1f} at end"
        + (
            f"; {result['busy']} shell loops spinning on the CPUs throughout (other jobs)."
            if result.get("busy")
            else "."
        ),
        "",
        f"Command: `{result['command']}`",
        "",
        f"Image: {result['image']} ({result['image_n']}x{result['image_n']}, noise "
        f"{result['noise_m'] * 1e9:.2g} nm). Ours: median of {result['repeat']} rounds "
        "(wall and CPU); Gwyddion: its full estimate at the auto threshold on its grid (one "
        "run at 41x41, the median of the rounds at 21x21), wall time of the library call. The "
        "fixed estimate is ours at the auto threshold (the same tip).",
        "",
        "| tip | threshold (nm) | ours auto: wall / CPU (s) | ours fixed: wall / CPU (s) | "
        "Gwyddion (s) | auto / Gwyddion | fixed / Gwyddion | load during ours | "
        "error auto / Gwyddion (nm) | peak traced memory auto / fixed (MiB) | "
        f"ours auto on all {m['cpus']} CPUs: wall (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["sizes"]:
        loads = [x["load"] for name in ("auto", "fixed") for x in r["rounds"][name]]
        lines.append(
            f"| {r['tip_size']}x{r['tip_size']} | {r['threshold_m'] * 1e9:.3f} | "
            f"{r['auto_wall_s']:.2f} / {r['auto_cpu_s']:.2f} | "
            f"{r['fixed_wall_s']:.2f} / {r['fixed_cpu_s']:.2f} | {r['gwyddion_wall_s']:.1f} | "
            f"{r['auto_over_gwyddion']:.4f} | {r['fixed_over_gwyddion']:.4f} | "
            f"{min(loads):.1f}-{max(loads):.1f} | {r['auto_error_m'] * 1e9:.3f} / "
            f"{r['gwyddion_error_m'] * 1e9:.3f} | {r['peak_tracemalloc_mib']['auto']:.0f} / "
            f"{r['peak_tracemalloc_mib']['fixed']:.0f} | {r['auto_all_cpus_wall_s']:.2f} |"
        )
    if result.get("baseline"):
        lines += [
            "",
            f"Before (revision {result['baseline']}, timed in a subprocess in the same rounds, "
            "single-threaded):",
            "",
            "| tip | auto: wall / CPU (s), before -> now | fixed: wall / CPU (s), before -> now | "
            "max abs tip difference (m) |",
            "|---|---|---|---|",
        ]
        for r in result["sizes"]:
            lines.append(
                f"| {r['tip_size']}x{r['tip_size']} | {r['baseline_auto_wall_s']:.2f} / "
                f"{r['baseline_auto_cpu_s']:.2f} -> {r['auto_wall_s']:.2f} / "
                f"{r['auto_cpu_s']:.2f} | {r['baseline_fixed_wall_s']:.2f} / "
                f"{r['baseline_fixed_cpu_s']:.2f} -> "
                f"{r['fixed_wall_s']:.2f} / {r['fixed_cpu_s']:.2f} | "
                f"{r['baseline_max_abs_tip_difference_m']:.1e} |"
            )
    big = next((r for r in result["sizes"] if r["tip_size"] == 41), None)
    lines += [
        "",
        (
            f"Target: auto at 41x41 under {TARGET_S:g} s: {big['auto_wall_s']:.2f} s wall "
            f"({'met' if big['auto_wall_s'] < TARGET_S else 'NOT met'} in this run). "
            if big
            else ""
        )
        + "Fixed and auto tips differ by at most "
        f"{max(r['fixed_minus_auto_max_abs_m'] for r in result['sizes']):.1e} m. Maximum RSS: "
        f"ours (the whole process) {result['max_rss_mib']['process']:.0f} MiB, the Gwyddion "
        f"harness {result['max_rss_mib']['gwyddion_harness']:.0f} MiB (the largest of its runs).",
    ]
    return "\n".join(lines) + "\n"


def characterizer() -> tuple:
    image, _, true_tip, pixel, source = bt.make_image(bt.import_characterizer(required=True))
    return image, true_tip, pixel, source


def spheres() -> tuple:
    from afm_core.sim.tip_corpus import Case, TipModel, make_case

    case = Case(TipModel("hyperboloid", 12e-9, 20.0), "spheres", 4e-9, bt.NOISE, 512, 41, seed=7)
    image, _, true_tip = make_case(case)
    return (
        np.asarray(image, float),
        np.asarray(true_tip, float),
        case.pixel,
        f"afm_core.sim.tip_corpus.make_case({case})",
    )


IMAGES = {"characterizer": characterizer, "spheres": spheres}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=3, help="rounds per tip size (default 3)")
    parser.add_argument(
        "--baseline",
        metavar="REV",
        help="also time another git revision's afm_core in each round (e.g. the last release)",
    )
    parser.add_argument(
        "--image",
        choices=sorted(IMAGES),
        default="characterizer",
        help="bench_tip's characteriser (default) or bench_tip_corpus --speed's spheres",
    )
    parser.add_argument(
        "--sizes", type=int, nargs="+", default=list(TIP_SIZES), help="tip windows (21 41)"
    )
    parser.add_argument("--busy", type=int, default=0, help="busy-looping processes beside")
    args = parser.parse_args()
    if not 0 <= args.busy <= 16:
        parser.error(f"--busy {args.busy}: must be 0-16")
    bt.build_harness()
    image, true_tip, pixel, source = IMAGES[args.image]()
    result = {
        "measured": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": command_line(),
        "machine": {
            "cpus": os.cpu_count(),
            "cpu": cpu_model(),
            "python": platform.python_version(),
            "platform": platform.platform(),
            "gwyddion": bt.gwyddion_version(),
            "loadavg_start": list(os.getloadavg()),
        },
        "image": source,
        "image_n": int(image.shape[0]),
        "noise_m": bt.NOISE,  # both images
        "repeat": args.repeat,
        "busy": args.busy,
        "sources_sha256": bt.source_hashes(),
        "sizes": [],
    }
    with tempfile.TemporaryDirectory(prefix="bench_tip_speed_") as tmp:
        gwy = bt.Gwyddion(image, pixel, Path(tmp))
        baseline = Baseline(args.baseline, Path(tmp)) if args.baseline else None
        result["baseline"] = baseline.rev if baseline else None
        with busy_loops(args.busy):
            for k in args.sizes:
                result["sizes"].append(
                    measure(image, true_tip, pixel, k, args.repeat, gwy, baseline)
                )
    result["machine"]["loadavg_end"] = list(os.getloadavg())
    result["max_rss_mib"] = {  # Linux: ru_maxrss in KiB
        "process": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        # the harness's own VmHWM (the parent's RUSAGE_CHILDREN would count its own pages)
        "gwyddion_harness": max(
            (g["vm_hwm_kib"] or 0) / 1024 for r in result["sizes"] for g in r["rounds"]["gwyddion"]
        ),
    }
    RESULTS.mkdir(exist_ok=True)
    name = "tip-speed" + ("" if args.image == "characterizer" else f"-{args.image}")
    name += "-busy" if args.busy else ""
    (RESULTS / f"{name}.json").write_text(json.dumps(result, indent=2))
    text = render(result)
    (RESULTS / f"{name}.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
