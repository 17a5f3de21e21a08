"""A session report a lab can read: HTML with PNG figures (nm in everything shown)."""

from __future__ import annotations

import html
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def save_height_maps(
    path: Path,
    images: list[tuple[str, np.ndarray, tuple[float, float, float, float]]],
    markers: list[tuple[float, float]] = (),
) -> Path:
    """images: (title, height in m, extent (x0, x1, y0, y1) in m); markers: true positions in m."""
    fig, axes = plt.subplots(1, len(images), figsize=(4.2 * len(images), 4), squeeze=False)
    for ax, (title, height, extent) in zip(axes[0], images):
        shown = ax.imshow(
            height * 1e9, origin="lower", cmap="afmhot", extent=[e * 1e9 for e in extent]
        )
        if markers:
            mx, my = np.asarray(markers).T * 1e9
            ax.plot(mx, my, "c+", ms=10, mew=1.5, label="true centre")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("x (nm)")
        ax.set_ylabel("y (nm)")
        fig.colorbar(shown, ax=ax, label="height (nm)", shrink=0.8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def table(headers: list[str], rows: list[list]) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in headers)
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows
    )
    return f"<table><tr>{head}</tr>{body}</table>"


def write_html(path: Path, title: str, sections: list[tuple[str, str]]) -> Path:
    """sections: (heading, html body)."""
    style = (
        "body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}"
        "table{border-collapse:collapse;margin:0.5em 0}"
        "td,th{border:1px solid #bbb;padding:3px 8px;"
        "text-align:left}th{background:#eee}.ok{color:#070}.bad{color:#b00}"
    )
    parts = [
        f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
        f"<style>{style}</style></head><body><h1>{html.escape(title)}</h1>"
    ]
    for heading, body in sections:
        parts.append(f"<h2>{html.escape(heading)}</h2>{body}")
    parts.append("</body></html>")
    path.write_text("\n".join(parts))
    return path


def covariance_ellipse(mean, covariance, n_sigma: float = 3.0, points: int = 48) -> np.ndarray:
    """(points, 2) outline of the n-sigma ellipse of a 2-D Gaussian."""
    values, vectors = np.linalg.eigh(np.asarray(covariance, float))
    angle = np.linspace(0, 2 * np.pi, points)
    circle = np.stack([np.cos(angle), np.sin(angle)])
    return (
        np.asarray(mean, float)[:, None]
        + vectors @ (n_sigma * np.sqrt(np.clip(values, 0, None)))[:, None] * circle
    ).T


def save_push_figure(
    path: Path,
    before,
    after,
    tip_means,
    tip_covariances,
    true_tip,
    particle_track,
    goal,
    achieved,
    strokes=(),
    ellipses: int = 25,
) -> Path:
    """Before/after height maps ((title, height m, extent m) each, or None) with the goal and the
    verified position, and the session's tip path: the estimate with its 3-sigma ellipses, the
    true tip, the true particle track and the planned strokes (all in m; shown in nm)."""
    panels = [p for p in (before, after) if p is not None]
    fig, axes = plt.subplots(
        1, len(panels) + 1, figsize=(4.6 * (len(panels) + 1), 4.4), squeeze=False
    )
    for ax, (title, height, extent) in zip(axes[0], panels):
        ax.imshow(height * 1e9, origin="lower", cmap="afmhot", extent=[e * 1e9 for e in extent])
        ax.plot(goal[0] * 1e9, goal[1] * 1e9, "g*", ms=12, label="goal")
        if achieved is not None:
            ax.plot(achieved[0] * 1e9, achieved[1] * 1e9, "bx", ms=10, mew=2, label="verified")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("x (nm)")
        ax.set_ylabel("y (nm)")
        ax.legend(fontsize=8, loc="upper right")
    ax = axes[0][-1]
    means = np.asarray(tip_means, float).reshape(-1, 2)
    if len(means):
        ax.plot(*(means.T * 1e9), "-", color="tab:blue", lw=0.8, label="tip estimate")
        for k in np.unique(np.linspace(0, len(means) - 1, min(ellipses, len(means))).astype(int)):
            outline = covariance_ellipse(means[k], tip_covariances[k]) * 1e9
            ax.plot(outline[:, 0], outline[:, 1], color="tab:blue", lw=0.5, alpha=0.6)
    true_tip = np.asarray(true_tip, float).reshape(-1, 2)
    if len(true_tip):
        ax.plot(*(true_tip.T * 1e9), ".", color="tab:orange", ms=2, label="true tip")
    for k, (a, b, contact) in enumerate(strokes):
        ax.plot(
            [a[0] * 1e9, b[0] * 1e9],
            [a[1] * 1e9, b[1] * 1e9],
            "-" if contact else ":",
            color="tab:red" if contact else "grey",
            lw=1.0,
            label="planned push" if k == 0 else None,
        )
    track = np.asarray(particle_track, float).reshape(-1, 2)
    if len(track):
        ax.plot(*(track.T * 1e9), "o-", color="tab:green", ms=3, label="true particle")
    ax.plot(goal[0] * 1e9, goal[1] * 1e9, "g*", ms=12)
    ax.set_title("tip path (3-sigma ellipses), strokes, particle", fontsize=10)
    ax.set_xlabel("x (nm)")
    ax.set_ylabel("y (nm)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
