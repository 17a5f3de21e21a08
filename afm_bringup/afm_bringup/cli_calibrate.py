"""`afm calibrate`: the calibration experiments on an instrument (book 7.2.2), with progress,
fit checks, reruns of single experiments and a report (afm_core.localization.calibration)."""

from __future__ import annotations

import argparse
import math
import re
import sys
from pathlib import Path

from afm_bringup.cli_errors import refuse
from afm_bringup.progress import Progress
from afm_core import checks


def cmd_calibrate(args):
    from afm_core.backends import open_instrument
    from afm_core.localization.calibration.drift_statistics import check_pairs
    from afm_core.localization.calibration.figures import calibration_figures
    from afm_core.localization.calibration.model import load_calibration, save_calibration
    from afm_core.localization.calibration.procedure import (
        checked_experiments,
        experiment_options,
        merge_calibration,
        report_json,
        report_markdown,
        run_calibration,
    )

    output = Path(args.output)
    try:
        # before any experiment: a bad count or an unwritable file would only fail hours in
        check_outputs(args)
        check_pairs(args.pairs)
        chosen = checked_experiments(args.only)
        options = experiment_options(args.set)
        check_finite_options(options)
        options["drift"] = {"pairs": args.pairs, **options.get("drift", {})}
        previous = load_calibration(args.merge) if args.merge else None
        instrument = open_instrument(
            args.backend, args.sim_config, args.seed, args.daq_device, args.daq_calibration
        )
        print(
            f"calibrating the {args.backend} instrument (book 7.2.2: {', '.join(chosen)}); on "
            "the simulator this takes minutes, on an instrument hours (the drift pairs)",
            flush=True,
        )
        # on stdout, with the results, as before the bar (scripts read the lines there)
        with Progress("calibrate", "experiments", len(chosen), sys.stdout) as bar:
            calibration, report = run_calibration(
                instrument,
                **options,
                source=f"afm calibrate --backend {args.backend}",
                progress=lambda text: _experiment_progress(bar, text),
                only=args.only,
                previous=previous,
            )
    except ValueError as exc:  # a configuration or calibration file, a parameter
        return refuse("calibrate", exc)
    except RuntimeError as exc:
        sys.exit(f"afm calibrate: {exc}")
    if previous is not None:
        calibration = merge_calibration(previous, calibration, chosen)
    save_calibration(calibration, output)
    if args.report:
        # every experiment's parameters, raw data and the fit checks; beside it the same for a
        # person (headline parameters, outcome, checks) with a figure per experiment
        report_path = Path(args.report)
        report_path.write_text(report_json(report))
        figures = calibration_figures(report, report_path.parent / f"{report_path.stem}_figures")
        relative = {name: path.relative_to(report_path.parent) for name, path in figures.items()}
        report_path.with_suffix(".md").write_text(report_markdown(report, relative))
    _print_calibration(output, calibration, report)
    if report.get("interrupted"):
        print("afm calibrate: interrupted; the experiments done are in the file", file=sys.stderr)
    failed = {n: v["failed"] for n, v in report.items() if isinstance(v, dict) and "failed" in v}
    for name, reason in failed.items():
        print(f"afm calibrate: {name} could not measure: {reason}", file=sys.stderr)
    if failed:
        # a geometry that does not fit the scanner fails the same way again: those are named
        # with the options to change, not told to repeat
        misfit = [n for n, reason in failed.items() if reason.startswith("GeometryError")]
        again = [n for n in failed if n not in misfit]
        advice = [
            f"repeat them: afm calibrate --only {' '.join(again)} --merge {output} -o {output} "
            "--overwrite"
        ] * bool(again)
        advice += [
            f"{', '.join(misfit)} do not fit this scanner's range: change the options each "
            "message names (afm calibrate --set EXPERIMENT.OPTION=VALUE), then run them with "
            f"--only ... --merge {output}"
        ] * bool(misfit)
        print(
            f"afm calibrate: {output} keeps the book's defaults for "
            f"{', '.join(calibration.defaults)} (listed under `defaults:` in the file); "
            + "; ".join(advice),
            file=sys.stderr,
        )
        return INTERRUPTED_STATUS if report.get("interrupted") else 1
    return 0


INTERRUPTED_STATUS = 130  # a shell's for Ctrl-C


def check_outputs(args) -> None:
    """ValueError naming the option when the calibration file or the report cannot be written
    where asked: checked before the experiments, which take hours on an instrument."""
    output = Path(args.output)
    targets = [("-o", output)]
    if args.report:
        report = Path(args.report)
        if report.resolve() in {
            output.resolve(),
            *([Path(args.merge).resolve()] if args.merge else []),
        }:
            raise ValueError(f"--report {report}: the calibration file itself; name another file")
        targets += [("--report", report), ("--report", report.with_suffix(".md"))]
    for option, path in targets:
        checks.new_file(option, path, overwrite=args.overwrite, option="--overwrite")


def check_finite_options(options: dict) -> None:
    """ValueError naming the --set option whose value is NaN or infinite: no geometry, time or
    count is, and the experiment refused it only when its turn came, hours into the run on an
    instrument, after the experiments before it (the other limits depend on the instrument's
    range, which only the experiment knows)."""
    for experiment, values in options.items():
        for option, value in values.items():
            numbers = value if isinstance(value, list) else [value]
            if not all(math.isfinite(number) for number in numbers):
                raise ValueError(f"--set {experiment}.{option}={value}: must be finite")


def seed_type(text: str) -> int:
    """argparse type of --seed: -1 (the configuration's seed) or a seed >= 0."""
    try:
        seed = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"seed={text!r}: expected a whole number") from None
    if seed < -1:
        raise argparse.ArgumentTypeError(
            f"seed={seed}: must be >= 0, or -1 for the configuration's seed"
        )
    return seed


# run_calibration's progress texts: "experiment K of N: NAME ..." at the start and
# "experiment K of N: NAME done in ..." (or "failed (...)") at the end of each experiment
_EXPERIMENT = re.compile(r"experiment (\d+) of (\d+): (\w+) (done|failed|\.\.\.)")


def _experiment_progress(bar, text: str) -> None:
    """One line per progress text; on a terminal also the bar of experiments done."""
    match = _EXPERIMENT.match(text)
    if match and bar.interactive:
        number, total, name, state = match.groups()
        done = int(number) - (state == "...")
        bar.update(done, int(total), name if state == "..." else "")
    bar.note(f"afm calibrate: {text}")


def _print_calibration(output, calibration, report) -> None:
    """The headline figures (those measured; the file's `defaults:` lists the rest), every
    warning of the fit checks, and a last line: how many experiments failed (any error check),
    else how many warnings, else that every fit check passed."""
    c, measured = calibration, set(calibration.measured)
    parts = [
        ("hysteresis_x", f"hysteresis loop x {c.hysteresis_x.loop_fraction:.3f} of the range"),
        ("hysteresis_y", f"hysteresis loop y {c.hysteresis_y.loop_fraction:.3f} of the range"),
        (
            "creep_time_constants",
            "creep time constants " + ", ".join(f"{t:.2f}" for t in c.creep_time_constants) + " s",
        ),
        ("motion_noise_slope_x", f"motion noise {c.motion_noise().k_h1 * 1e9:.4f} nm^2/nm"),
        (
            "drift_mean_velocity",
            f"drift {c.drift_mean_velocity[0] * 1e9:.3f}, "
            f"{c.drift_mean_velocity[1] * 1e9:.3f} nm/s",
        ),
        (
            "scanner_matrix",
            "scanner matrix " + str([[round(v, 4) for v in row] for row in c.scanner_matrix]),
        ),
        ("map_sigma", f"map error {c.map_sigma[0] * 1e9:.1f}, {c.map_sigma[1] * 1e9:.1f} nm"),
        ("line_deflection_mean_deg", f"line deflection {c.line_deflection_mean_deg:.3f} deg"),
    ]
    shown = [text for field, text in parts if field in measured]
    print(f"wrote {output}: " + ("; ".join(shown) if shown else "nothing measured"))
    fit_checks = report.get("checks", [])
    warnings = [c for c in fit_checks if c["level"] == "warning"]
    for check in warnings:
        print(f"afm calibrate: WARNING {check['experiment']}: {check['message']}", file=sys.stderr)
    # an experiment that could not measure is an error check (and `{"failed": ...}` in the
    # report): it never passed, whatever the warnings say
    run = [n for n, v in report.items() if isinstance(v, dict)]  # the experiments, in order
    errors = {c["experiment"] for c in fit_checks if c["level"] == "error"}
    failed = [n for n in run if n in errors or "failed" in report[n]]
    failed += sorted(errors - set(failed))
    if failed:
        print(
            f"afm calibrate: {len(failed)} of {len(run)} experiments failed "
            f"({', '.join(failed)}); {len(warnings)} warning(s) (see --report for each check)"
        )
    elif warnings:
        print(f"afm calibrate: {len(warnings)} warning(s) (see --report for each check)")
    else:
        print("afm calibrate: every fit check passed (see --report for each fit's residual)")


def _add_calibrate(sub) -> None:
    p = sub.add_parser(
        "calibrate",
        help="run the calibration experiments on an instrument, write the file the "
        "localizer, planner and nano-hand load",
        description="The book's calibration experiments (7.2.2) on the instrument itself (run it "
        "while no driver node uses the instrument): drift statistics from frame-up/down "
        "pairs, creep and hysteresis from indentation pits, scanner matrix, motion-noise "
        "variance against distance, line deflection, map and scan-region errors.",
    )
    p.add_argument("--output", "-o", required=True, help="calibration YAML to write")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.add_argument(
        "--backend",
        choices=["sim", "daq"],
        default="sim",
        help="the simulated instrument (default) or an NI DAQ card",
    )
    p.add_argument(
        "--sim-config",
        default="",
        help="simulator configuration YAML (sim backend; default: defaults)",
    )
    p.add_argument(
        "--seed",
        type=seed_type,
        default=-1,
        help="simulator seed (sim backend; default -1: the config's)",
    )
    p.add_argument(
        "--daq-device", default="Dev1", help="NI-DAQmx device name (daq backend; default Dev1)"
    )
    p.add_argument("--daq-calibration", default="", help="DAQ calibration YAML (daq backend)")
    p.add_argument(
        "--pairs",
        type=int,
        default=100,
        help="frame-up/down pairs for the drift statistics, one an hour of instrument time "
        "(default 100)",
    )
    p.add_argument(
        "--report",
        default="",
        help="also write every experiment's fitted parameters, raw data and fit checks (JSON), "
        "and beside it a summary a person reads (same name, .md) with a figure of each "
        "experiment's raw data and fit (PNGs in <name>_figures/)",
    )
    p.add_argument(
        "--only",
        nargs="+",
        metavar="EXPERIMENT",
        help="run only these experiments (drift, map_errors, creep, hysteresis_x, "
        "hysteresis_y, scanner_matrix, motion_noise, line_deflection), e.g. one a check flagged",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="EXPERIMENT.OPTION=VALUE",
        help="an experiment's option (SI units; a list as numbers separated by commas), e.g. "
        "its geometry where the defaults (the same fractions of any scanner range) do not fit: "
        "creep.step=4e-6, scanner_matrix.spacing=0.5e-6, motion_noise.distances=0.25e-6,0.5e-6, "
        "hysteresis.pixel=20e-9; EXPERIMENT is drift, creep, hysteresis, scanner_matrix, "
        "motion_noise or line_deflection (repeatable)",
    )
    p.add_argument(
        "--merge",
        default="",
        help="calibration YAML to update: the file written is this one with the fields the "
        "experiments run now measured replaced (each field's `measured:` entry says when)",
    )
    p.set_defaults(func=cmd_calibrate)
