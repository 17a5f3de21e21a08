"""A session report a lab can read: HTML with PNG figures (nm in everything shown)."""

from __future__ import annotations

import html
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

FIGURE_WIDTH_IN = 10.0  # in; at DPI, 1000 px: the report's column (write_html) is 1100 px
DPI = 100


def save_height_maps(
    path: Path,
    images: list[tuple[str, np.ndarray, tuple[float, float, float, float]]],
    markers: list[tuple[float, float]] = (),
    marker_label: str = "true centre",
    columns: int = 3,
) -> Path:
    """images: (title, height in m, extent (x0, x1, y0, y1) in m); markers: positions in m in
    the images' frame. `columns` images a row, at the page's width (report_figures)."""
    columns = max(1, min(columns, len(images)))
    rows = -(-len(images) // columns)
    fig, axes = plt.subplots(
        rows,
        columns,
        figsize=(FIGURE_WIDTH_IN, 3.3 * rows),
        squeeze=False,
        layout="constrained",
    )
    for ax, (title, height, extent) in zip(axes.flat, images):
        shown = ax.imshow(
            height * 1e9, origin="lower", cmap="afmhot", extent=[e * 1e9 for e in extent]
        )
        if len(markers):
            mx, my = np.asarray(markers).T * 1e9
            ax.plot(mx, my, "c+", ms=10, mew=1.5, label=marker_label)
            ax.legend(fontsize=7, loc="upper right", framealpha=0.7)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("x (nm)")
        ax.set_ylabel("y (nm)")
        fig.colorbar(shown, ax=ax, label="height (nm)", fraction=0.046, pad=0.02)
    for ax in list(axes.flat)[len(images) :]:
        ax.set_visible(False)
    fig.savefig(path, dpi=DPI)
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
        "img{max-width:100%;height:auto}pre{background:#f6f6f6;padding:0.5em;overflow-x:auto}"
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
