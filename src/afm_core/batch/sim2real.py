"""`afm batch sim2real`: the sim-to-real diagnosis (afm_core.sim2real.diagnose.run_sim2real) of
each recording as one table row, and what the rows say together: which effects are named in
how many sessions, and how they and their fitted values move from one recording date to the
next (summary.md)."""

from __future__ import annotations

import statistics
from collections import Counter, defaultdict
from pathlib import Path

from afm_core.batch.evaluate import recording_date
from afm_core.recording import RecordingReader

ROW_FORMAT = 1  # bump when a column's meaning changes: the rows computed before are redone

COLUMNS = [
    "recording_date",
    "verdict",
    "named",
    "parameters",
    "n_features",
    "chi2",
    "dof",
    "p",
    "heldout_excess_reduction",
    "report",
]


def diagnose_recording(path, model: str | None, effects: list | None, report_dir) -> dict:
    """One recording's row (COLUMNS): the verdict, the named terms (';'-separated), their
    fitted values 'key=value+-sigma', the overall chi^2, the held-out excess reduction; the
    report with its plots in report_dir."""
    from afm_core.sim2real.diagnose import run_sim2real

    with RecordingReader(path) as reader:  # the date; and a corrupt file fails here, cheaply
        date = recording_date(reader.start_time_ns)
    diagnosis = run_sim2real(path, model or None, report_dir, effects=effects or None)
    parameters = ";".join(
        f"{key}={p['value']!r}+-{p['sigma']!r}" for key, p in sorted(diagnosis.parameters.items())
    )
    return {
        "recording_date": date,
        "verdict": diagnosis.verdict,
        "named": ";".join(diagnosis.chosen),
        "parameters": parameters,
        "n_features": diagnosis.n_features,
        "chi2": float(diagnosis.overall.get("chi2", float("nan"))),
        "dof": diagnosis.overall.get("dof"),
        "p": float(diagnosis.overall.get("p", float("nan"))),
        "heldout_excess_reduction": diagnosis.heldout.get("excess_reduction"),
        "report": str(report_dir),
    }


def _parameters(text: str) -> dict[str, float]:
    out = {}
    for part in filter(None, text.split(";")):
        key, value = part.split("=", 1)
        out[key] = float(value.split("+-")[0])
    return out


def summarise(rows: list[dict]) -> dict:
    """Across the finished rows: verdict counts, sessions naming each effect, and by recording
    date the sessions, the effects named and the median fitted value of each parameter."""
    done = [r for r in rows if r.get("status") == "ok"]
    by_date: dict[str, dict] = defaultdict(lambda: {"sessions": 0, "named": Counter()})
    values: dict[tuple, list] = defaultdict(list)
    for row in done:
        day = by_date[row.get("recording_date") or "unknown"]
        day["sessions"] += 1
        day["named"].update(filter(None, row.get("named", "").split(";")))
        for key, value in _parameters(row.get("parameters", "")).items():
            values[(row.get("recording_date") or "unknown", key)].append(value)
    return {
        "sessions": len(done),
        "failed": sum(1 for r in rows if r.get("status") == "failed"),
        "verdicts": dict(Counter(r["verdict"] for r in done)),
        "effects": dict(Counter(n for r in done for n in filter(None, r["named"].split(";")))),
        "by_date": {d: by_date[d] for d in sorted(by_date)},
        "parameter_medians": {k: statistics.median(v) for k, v in sorted(values.items())},
    }


def summary_markdown(summary: dict) -> str:
    lines = [
        "# Sim-to-real diagnoses across sessions",
        "",
        f"{summary['sessions']} sessions diagnosed, {summary['failed']} failed "
        "(results.csv has each one's error).",
        "",
        "| verdict | sessions |",
        "| --- | --- |",
        *(f"| {v} | {n} |" for v, n in sorted(summary["verdicts"].items())),
        "",
        "## Effects named",
        "",
    ]
    if not summary["effects"]:
        lines.append("No session named an effect.")
    else:
        lines += ["| effect | sessions | share |", "| --- | --- | --- |"]
        lines += [
            f"| {name} | {n} | {n / summary['sessions']:.0%} |"
            for name, n in sorted(summary["effects"].items(), key=lambda e: -e[1])
        ]
    lines += ["", "## By recording date", "", "| date | sessions | effects named |"]
    lines.append("| --- | --- | --- |")
    for date, day in summary["by_date"].items():
        named = ", ".join(f"{k} ({n})" for k, n in sorted(day["named"].items())) or "none"
        lines.append(f"| {date} | {day['sessions']} | {named} |")
    if summary["parameter_medians"]:
        lines += ["", "Fitted values (median of the sessions of a date):", ""]
        lines += ["| date | parameter | median |", "| --- | --- | --- |"]
        lines += [f"| {d} | {k} | {v:.6g} |" for (d, k), v in summary["parameter_medians"].items()]
    return "\n".join(lines) + "\n"


def write_summary(rows: list[dict], folder: Path) -> Path:
    path = Path(folder) / "summary.md"
    path.write_text(summary_markdown(summarise(rows)))
    return path
