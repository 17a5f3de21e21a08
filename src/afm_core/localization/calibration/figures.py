"""Figures of a calibration run for a person (issue 37: "the raw data and plots in a report a
person reads"): one PNG per experiment that measured, each showing the raw data and the fit
drawn from the report of `run_calibration` (procedure.py) alone, so a report written earlier
can be drawn again. matplotlib with the Agg backend (no display). Lengths in nm, times in s
(text people read).

- hysteresis_x / _y: the pits' rescanned positions against the raw drive, both branches, the
  fitted PI model at the pits, and the residual (book Fig. 7.6a).
- creep: every run's pit positions against time after the step, relative to its settled
  end, with the fitted curve (Fig. 7.7).
- motion_noise: the variance of the separations against the move distance, along and across
  each axis, with the fitted line sigma^2 = a d + b (Fig. 7.6e).
- drift: each pair's velocity against time, with the mean and +-1 sigma (Fig. 7.9).
- scanner_matrix: imaged against commanded displacements (arrows: the residual, magnified).
- line_deflection / map_errors: histograms of the angles, the relative positions.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

NM = 1e9  # m -> nm for the axes people read


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _hysteresis(ax_pair, entry: dict, name: str) -> None:
    data, p = entry["data"], entry["parameters"]
    drive = np.asarray(data["drive"]) - data.get("centre", 0.0)
    position = np.asarray(data["position"])
    predicted = np.asarray(data["predicted"])
    branch = np.asarray(data["branch"])
    top, bottom = ax_pair
    for label, marker in (("descending", "v"), ("ascending", "^")):
        sel = branch == label
        top.plot(drive[sel] * 1e6, position[sel] * 1e6, marker, ms=4, label=f"pits, {label}")
        bottom.plot(drive[sel] * 1e6, (position[sel] - predicted[sel]) * NM, marker, ms=4)
    order = np.argsort(np.asarray(data["time"]))
    top.plot(drive[order] * 1e6, predicted[order] * 1e6, "-", lw=0.8, color="k", label="PI fit")
    top.set_ylabel("rescanned position (um)")
    top.set_title(
        f"{name}: loop {p['loop_fraction']:.4f} +- {p.get('loop_fraction_sigma', 0.0):.2g} of "
        f"the range, asymmetry {p['asymmetry']:.3f}; {data.get('pits_found', '?')} of "
        f"{data.get('pits_punched', '?')} pits"
    )
    top.legend(fontsize=7)
    bottom.axhline(0.0, color="0.6", lw=0.8)
    bottom.set_xlabel("raw drive from the range centre (um)")
    bottom.set_ylabel("residual (nm)")


def _creep(ax_pair, entry: dict) -> None:
    data, p = entry["data"], entry["parameters"]
    for ax, axis in zip(ax_pair, "xy"):
        for run in data.get(axis, []):
            t = np.asarray(run["t"])
            settled = np.asarray(run.get("model", run["position"]))[-1]
            line = ax.plot(t, (np.asarray(run["position"]) - settled) * NM, "o", ms=3)
            if "model" in run:
                ax.plot(
                    t, (np.asarray(run["model"]) - settled) * NM, "-", color=line[0].get_color()
                )
        response = p["step_response_25s"]["xy".index(axis)] * 100
        ax.set_xscale("log")
        ax.set_xlabel("time after the step (s)")
        ax.set_ylabel(f"{axis} position - last fitted (nm)")
        ax.set_title(
            f"creep {axis}: step response at 25 s {response:.3g} % of the step; time constants "
            + ", ".join(f"{t:.3g}" for t in p["time_constants"])
            + " s",
            fontsize=9,
        )


def _motion_noise(ax, entry: dict) -> None:
    data, p = entry["data"], entry["parameters"]
    d_line = None
    for axis, colour in (("x", "C0"), ("y", "C1")):
        rows = data.get(axis, [])
        if not rows:
            continue
        d = np.array([r["distance"] for r in rows])
        ax.plot(
            d * NM,
            np.array([r["variance_along"] for r in rows]) * NM**2,
            "o",
            color=colour,
            label=f"{axis} moves, along",
        )
        ax.plot(
            d * NM,
            np.array([r["variance_across"] for r in rows]) * NM**2,
            "x",
            color=colour,
            label=f"{axis} moves, across",
        )
        d_line = d if d_line is None else np.union1d(d_line, d)
    if d_line is not None:
        grid = np.linspace(0.0, float(d_line.max()) * 1.05, 50)
        offset = p.get("pooled_offset", 0.0)
        ax.plot(
            grid * NM,
            (p["pooled_slope"] * grid + offset) * NM**2,
            "k-",
            label="pooled fit a d + b",
        )
    ax.set_xlabel("move distance (nm)")
    ax.set_ylabel("variance of the separation (nm^2)")
    ax.set_title(
        f"motion noise: pooled slope {p['pooled_slope'] * NM:.4g} +- "
        f"{p.get('pooled_slope_sigma', 0.0) * NM:.2g} nm^2/nm"
    )
    ax.legend(fontsize=7)


def _drift(ax, entry: dict) -> None:
    data, p = entry["data"], entry["parameters"]
    t = np.asarray(data["time"]) / 3600.0
    v = np.asarray(data["velocity"]) * NM
    for k, (axis, colour) in enumerate((("x", "C0"), ("y", "C1"))):
        mean, sigma = p["mean_velocity"][k] * NM, p["sigma_velocity"][k] * NM
        ax.plot(t, v[:, k], "o-", color=colour, ms=4, label=f"v{axis} per pair")
        ax.axhline(mean, color=colour, lw=1.2, label=f"mean {axis} {mean:.3g} nm/s")
        ax.axhspan(mean - sigma, mean + sigma, color=colour, alpha=0.12)
    ax.set_xlabel("time of the pair (h)")
    ax.set_ylabel("drift velocity (nm/s)")
    ax.set_title(f"drift: {p['pairs']} frame-up/down pairs (band: +-1 sigma of the pairs)")
    ax.legend(fontsize=7)


def _scanner_matrix(ax, entry: dict) -> None:
    data, p = entry["data"], entry["parameters"]
    commanded = np.asarray(data["commanded"])
    imaged = np.asarray(data["imaged"])
    matrix = np.asarray(p["scanner_matrix"])
    c0, i0 = commanded.mean(axis=0), imaged.mean(axis=0)
    predicted = (commanded - c0) @ matrix.T + i0
    residual = imaged - predicted
    magnify = 0.05 * np.ptp(commanded) / max(float(np.abs(residual).max()), 1e-12)
    ax.plot((commanded - c0)[:, 0] * 1e6, (commanded - c0)[:, 1] * 1e6, "k+", label="commanded")
    ax.quiver(
        (predicted - i0)[:, 0] * 1e6,
        (predicted - i0)[:, 1] * 1e6,
        residual[:, 0] * magnify * 1e6,
        residual[:, 1] * magnify * 1e6,
        angles="xy",
        scale_units="xy",
        scale=1.0,
        color="C3",
        label=f"residual x {magnify:.3g}",
    )
    ax.set_aspect("equal")
    ax.set_xlabel("x (um)")
    ax.set_ylabel("y (um)")
    ax.set_title(
        "scanner matrix "
        + str(np.round(matrix, 4).tolist())
        + f"; rms residual {p['rms_residual'] * NM:.0f} nm",
        fontsize=9,
    )
    ax.legend(fontsize=7)


def _histogram(ax, values, xlabel: str, title: str) -> None:
    values = np.asarray(values, float).ravel()
    ax.hist(values[np.isfinite(values)], bins=max(5, int(np.sqrt(values.size))))
    ax.set_xlabel(xlabel)
    ax.set_ylabel("count")
    ax.set_title(title)


def calibration_figures(summary: dict, directory) -> dict[str, Path]:
    """One PNG per experiment of `summary` (run_calibration's report) that measured and has
    the data to draw, written to `directory` (created) as <experiment>.png; returns
    {experiment: path}. A failed experiment has no figure (the report says why)."""
    plt = _pyplot()
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    written = {}
    for name, entry in summary.items():
        if not isinstance(entry, dict) or "data" not in entry or "parameters" not in entry:
            continue
        if name.startswith("hysteresis_") or name == "creep":
            fig, axes = plt.subplots(2, 1, figsize=(8, 7), sharex=name != "creep")
            if name == "creep":
                _creep(axes, entry)
            else:
                _hysteresis(axes, entry, name)
        else:
            fig, ax = plt.subplots(figsize=(8, 4.5))
            if name == "motion_noise":
                _motion_noise(ax, entry)
            elif name == "drift":
                _drift(ax, entry)
            elif name == "scanner_matrix":
                _scanner_matrix(ax, entry)
            elif name == "line_deflection":
                p = entry["parameters"]
                _histogram(
                    ax,
                    entry["data"]["angles_deg"],
                    "line deflection (deg)",
                    f"line deflection: mean {p['mean_deg']:.3f}, sigma {p['sigma_deg']:.3f} deg",
                )
            elif name == "map_errors":
                p = entry["parameters"]
                _histogram(
                    ax,
                    np.asarray(entry["data"]["relative_position"]) * NM,
                    "position relative to the pair's mean (nm), x and y",
                    "map error: sigma "
                    + ", ".join(f"{s * NM:.1f}" for s in p["map_sigma"])
                    + " nm",
                )
            else:
                plt.close(fig)
                continue
        fig.tight_layout()
        path = directory / f"{name}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        written[name] = path
    return written
