"""A session report a lab can read: HTML with PNG figures (nm in everything shown)."""
from __future__ import annotations

import html
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def save_height_maps(path: Path, images: list[tuple[str, np.ndarray, tuple[float, float, float, float]]],
                     markers: list[tuple[float, float]] = ()) -> Path:
    """images: (title, height in m, extent (x0, x1, y0, y1) in m); markers: true positions in m."""
    fig, axes = plt.subplots(1, len(images), figsize=(4.2 * len(images), 4), squeeze=False)
    for ax, (title, height, extent) in zip(axes[0], images):
        shown = ax.imshow(height * 1e9, origin="lower", cmap="afmhot", extent=[e * 1e9 for e in extent])
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
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def write_html(path: Path, title: str, sections: list[tuple[str, str]]) -> Path:
    """sections: (heading, html body)."""
    style = ("body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}"
             "table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #bbb;padding:3px 8px;"
             "text-align:left}th{background:#eee}.ok{color:#070}.bad{color:#b00}")
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{style}</style></head><body><h1>{html.escape(title)}</h1>"]
    for heading, body in sections:
        parts.append(f"<h2>{html.escape(heading)}</h2>{body}")
    parts.append("</body></html>")
    path.write_text("\n".join(parts))
    return path
