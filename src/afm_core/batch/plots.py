"""The figures beside a batch's summary.md: for sim2real the effects named per recording date
(how they come and go over days), for evaluate each session's localization error and NEES
and its scans' centre error, by recording date."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

EFFECTS_FIGURE = "effects_by_date.png"
EVALUATION_FIGURE = "errors_by_session.png"


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def effects_by_date(rows: list[dict], folder: Path) -> str | None:
    """Stacked bars: per date, the sessions naming each effect (and those naming none)."""
    done = [r for r in rows if r.get("status") == "ok"]
    if not done:
        return None
    dates = sorted({r.get("recording_date") or "unknown" for r in done})
    counts = {d: Counter() for d in dates}
    for row in done:
        names = [n for n in row.get("named", "").split(";") if n] or ["(none named)"]
        counts[row.get("recording_date") or "unknown"].update(names)
    effects = sorted({e for c in counts.values() for e in c})
    plt = _pyplot()
    figure, axes = plt.subplots(figsize=(max(4.0, 0.8 * len(dates) + 2), 3.5))
    bottom = [0] * len(dates)
    for effect in effects:
        heights = [counts[d][effect] for d in dates]
        axes.bar(dates, heights, bottom=bottom, label=effect)
        bottom = [b + h for b, h in zip(bottom, heights)]
    axes.set_ylabel("sessions")
    axes.set_title("effects named, by recording date", fontsize="medium")
    axes.yaxis.get_major_locator().set_params(integer=True)
    axes.legend(fontsize="small")
    figure.autofmt_xdate()
    figure.tight_layout()
    figure.savefig(Path(folder) / EFFECTS_FIGURE, dpi=100)
    plt.close(figure)
    return EFFECTS_FIGURE


def errors_by_session(rows: list[dict], folder: Path) -> str | None:
    """Per session (in date order): localization error RMS and scans' centre error RMS (nm),
    and the mean NEES against its consistent value 2."""
    done = sorted(
        (r for r in rows if r.get("status") == "ok"),
        key=lambda r: (r.get("recording_date", ""), r["item"]),
    )

    def column(name, scale=1.0):
        return [float(r[name]) * scale if r.get(name) not in (None, "") else None for r in done]

    series = {
        "localization error RMS (nm)": column("localization_error_rms_m", 1e9),
        "scans' centre error RMS (nm)": column("centre_error_rms_m", 1e9),
    }
    nees = column("localization_mean_nees")
    if not done or all(v is None for s in [*series.values(), nees] for v in s):
        return None
    plt = _pyplot()
    with_nees = any(v is not None for v in nees)
    figure, panels = plt.subplots(1, 2 if with_nees else 1, figsize=(9 if with_nees else 5, 3.5))
    left, right = (panels[0], panels[1]) if with_nees else (panels, None)
    index = range(len(done))
    for label, values in series.items():
        points = [(i, v) for i, v in zip(index, values) if v is not None]
        if points:
            left.plot(*zip(*points), "o", label=label)
    left.set_xlabel("session (by recording date)")
    left.set_ylabel("nm")
    left.legend(fontsize="small")
    if right is not None:
        _nees_panel(right, [(i, v) for i, v in zip(index, nees) if v is not None])
    figure.tight_layout()
    figure.savefig(Path(folder) / EVALUATION_FIGURE, dpi=100)
    plt.close(figure)
    return EVALUATION_FIGURE


def _nees_panel(right, points: list) -> None:
    right.plot(*zip(*points), "o")
    right.axhline(2.0, color="grey", linestyle="--", label="consistent (2 dof)")
    right.set_xlabel("session (by recording date)")
    right.set_ylabel("mean NEES")
    right.legend(fontsize="small")


PUSH_FIGURE = "push_errors.png"
LOCALIZATION_FIGURE = "localization_errors.png"


def _ok(rows: list[dict], column: str) -> list[dict]:
    return [r for r in rows if r.get("status") == "ok" and r.get(column) not in (None, "")]


def push_errors(rows: list[dict], folder: Path) -> str | None:
    """Per strategy, the final error of every seed (nm, by seed) against the tolerance."""
    done = _ok(rows, "error_m")
    if not done:
        return None
    plt = _pyplot()
    figure, axes = plt.subplots(figsize=(6, 3.5))
    for strategy in sorted({r["strategy"] for r in done}):
        group = sorted(
            (r for r in done if r["strategy"] == strategy), key=lambda r: int(r["seed"])
        )
        axes.plot(
            [int(r["seed"]) for r in group], [float(r["error_m"]) * 1e9 for r in group], "o",
            label=strategy,
        )  # fmt: skip
    for tolerance in sorted({float(r["tolerance_m"]) for r in done}):
        axes.axhline(tolerance * 1e9, color="grey", linestyle="--", label="tolerance")
    axes.set_xlabel("seed")
    axes.set_ylabel("final error to the goal (nm)")
    axes.legend(fontsize="small")
    figure.tight_layout()
    figure.savefig(Path(folder) / PUSH_FIGURE, dpi=100)
    plt.close(figure)
    return PUSH_FIGURE


def localization_errors(rows: list[dict], folder: Path) -> str | None:
    """Per mode, the NEES of every seed against its dof (its mean when consistent)."""
    done = _ok(rows, "nees")
    if not done:
        return None
    plt = _pyplot()
    figure, axes = plt.subplots(figsize=(6, 3.5))
    for mode in sorted({r["mode"] for r in done}):
        group = sorted((r for r in done if r["mode"] == mode), key=lambda r: int(r["seed"]))
        axes.plot([int(r["seed"]) for r in group], [float(r["nees"]) for r in group], "o",
                  label=mode)  # fmt: skip
    for dof in sorted({int(float(r["nees_dof"])) for r in done}):
        axes.axhline(dof, color="grey", linestyle="--", label=f"consistent mean ({dof} dof)")
    axes.set_yscale("log")
    axes.set_xlabel("seed")
    axes.set_ylabel("NEES")
    axes.legend(fontsize="small")
    figure.tight_layout()
    figure.savefig(Path(folder) / LOCALIZATION_FIGURE, dpi=100)
    plt.close(figure)
    return LOCALIZATION_FIGURE


MONTE_CARLO_FIGURE = "monte_carlo_success.png"


def monte_carlo_success(rows: list[dict], folder: Path) -> str | None:
    """Per plan, each seed's Monte Carlo success probability (its seed-to-seed scatter)."""
    done = _ok(rows, "success_probability")
    if not done:
        return None
    plt = _pyplot()
    figure, axes = plt.subplots(figsize=(6, 3.5))
    for plan in sorted({r["plan"] for r in done}):
        group = sorted((r for r in done if r["plan"] == plan), key=lambda r: int(r["seed"]))
        axes.plot([int(r["seed"]) for r in group],
                  [float(r["success_probability"]) for r in group], "o", label=plan)  # fmt: skip
    axes.set_xlabel("seed")
    axes.set_ylabel("success probability (Monte Carlo)")
    axes.set_ylim(0, 1.02)
    axes.legend(fontsize="small")
    figure.tight_layout()
    figure.savefig(Path(folder) / MONTE_CARLO_FIGURE, dpi=100)
    plt.close(figure)
    return MONTE_CARLO_FIGURE
