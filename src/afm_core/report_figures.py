"""The figures of a session report, each at the page's width (FIGURE_WIDTH_IN at DPI: 1000
px, inside the report's 1100 px column), everything in one frame per figure and in nm.

- `save_push_figure`: the push zoomed in: the before and after rescans placed in the task
  frame (`afm_core.evaluation.push_image_frames`) with colourbars, the strokes, the goal, the
  verified and the true end; the tip estimate near the push with 3-sigma ellipses.
- `save_map_figure`: the drift-corrected map with the landmarks' 3-sigma ellipses, the true
  centres and the tip's last estimate; beside it the whole session's tip path.
- `save_force_figure`: lateral and normal force along each stroke.
- `save_localizer_figure`: the localizer's error against the truth over time, with its
  3-sigma band.
- `save_pattern_figure`: an assembly: the pattern planned on the map, the order, and each
  particle's end (predicted, verified, true) against its goal.
- `save_tip_figure`: the blind tip estimate, what the image constrained, its sections through
  the apex beside the simulator's true tip (afm_core.imaging.tip_apex says it in numbers).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from afm_core.report import DPI, FIGURE_WIDTH_IN, covariance_ellipse  # noqa: E402

# nm around the push's start, goal and end in the zoomed panels: a particle's diameter and a
# stroke's approach on each side
PUSH_MARGIN = 250e-9


def _legend_below(fig, handles, labels, ncol: int) -> None:
    """One figure legend under the panels, which the constrained layout makes room for.

    matplotlib >= 3.7 does it with loc="outside lower center". Older ones (3.6, Ubuntu 24.04's,
    which the Docker image uses) have no "outside" placement: the legend goes at the figure's
    bottom edge and the layout is kept to the rectangle above it."""
    if matplotlib.__version_info__ >= (3, 7):
        fig.legend(handles, labels, loc="outside lower center", ncol=ncol, fontsize=7)
        return
    legend = fig.legend(handles, labels, loc="lower center", ncol=ncol, fontsize=7)
    height = legend.get_window_extent(fig.canvas.get_renderer()).height / fig.bbox.height
    fig.get_layout_engine().set(rect=(0, height, 1, 1 - height))


def _nm(values) -> np.ndarray:
    return np.asarray(values, float) * 1e9


def _image(fig, ax, height, extent, title: str) -> None:
    shown = ax.imshow(
        _nm(height), origin="lower", cmap="afmhot", extent=list(_nm(extent)), interpolation="none"
    )
    fig.colorbar(shown, ax=ax, label="height (nm)", fraction=0.046, pad=0.02)
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("x (nm)")
    ax.set_ylabel("y (nm)")


def push_box(points, margin: float = PUSH_MARGIN) -> tuple[float, float, float, float]:
    """A square (x0, x1, y0, y1) in m around `points` with `margin`."""
    p = np.asarray(points, float).reshape(-1, 2)
    centre = (p.min(axis=0) + p.max(axis=0)) / 2
    half = float(np.max(p.max(axis=0) - p.min(axis=0))) / 2 + margin
    return centre[0] - half, centre[0] + half, centre[1] - half, centre[1] + half


def _zoom(ax, box) -> None:
    ax.set_xlim(box[0] * 1e9, box[1] * 1e9)
    ax.set_ylim(box[2] * 1e9, box[3] * 1e9)


def _strokes(ax, strokes, label: bool = True) -> None:
    for k, (a, b, contact) in enumerate(strokes):
        ax.plot(
            _nm([a[0], b[0]]),
            _nm([a[1], b[1]]),
            "-" if contact else ":",
            color="tab:cyan" if contact else "grey",
            lw=1.0,
            label="planned stroke" if (label and k == 0) else None,
        )


def save_push_figure(
    path: Path,
    before,
    after,
    start,
    goal,
    achieved,
    true_end=None,
    strokes=(),
    tip_means=(),
    tip_covariances=(),
    true_tip=(),
    particle_track=(),
) -> Path:
    """before/after: (title, height m, extent m) already in the task frame, or None; the rest
    task-frame points in m (`true_end`, `true_tip`, `particle_track`: the truth brought into
    the maps' frame). Panels zoomed on the push."""
    box = push_box([start, goal] + ([achieved] if achieved is not None else []))
    panels = [p for p in (before, after) if p is not None]
    fig, axes = plt.subplots(
        1, len(panels) + 1, figsize=(FIGURE_WIDTH_IN, 3.5), squeeze=False, layout="constrained"
    )
    for ax, (title, height, extent) in zip(axes[0], panels):
        _image(fig, ax, height, extent, title)
        _strokes(ax, strokes)
        ax.plot(*_nm(start), "o", color="deepskyblue", mfc="none", ms=9, label="mapped start")
        ax.plot(*_nm(goal), "g*", ms=12, label="goal")
        if achieved is not None and ax is not axes[0][0]:
            ax.plot(*_nm(achieved), "bx", ms=9, mew=2, label="verified")
        if true_end is not None and ax is not axes[0][0]:
            ax.plot(*_nm(true_end), "m+", ms=11, mew=2, label="true end")
        _zoom(ax, box)
    ax = axes[0][-1]
    means = np.asarray(tip_means, float).reshape(-1, 2)
    near = [
        k for k, m in enumerate(means) if box[0] <= m[0] <= box[1] and box[2] <= m[1] <= box[3]
    ]
    if near:
        ax.plot(*_nm(means[near].T), ".-", color="tab:blue", lw=0.6, ms=3, label="tip estimate")
        for k in near:
            outline = _nm(covariance_ellipse(means[k], tip_covariances[k]))
            ax.plot(outline[:, 0], outline[:, 1], color="tab:blue", lw=0.4, alpha=0.5)
    tip = np.asarray(true_tip, float).reshape(-1, 2)
    if len(tip):
        ax.plot(*_nm(tip.T), ".", color="tab:orange", ms=3, label="true tip")
    _strokes(ax, strokes)
    track = np.asarray(particle_track, float).reshape(-1, 2)
    if len(track):
        ax.plot(*_nm(track.T), "o-", color="tab:green", ms=3, label="true particle")
    ax.plot(*_nm(goal), "g*", ms=12, label="goal")
    _zoom(ax, box)
    ax.set_aspect("equal")
    ax.set_title("tip near the push (3-sigma)", fontsize=9)
    ax.set_xlabel("x (nm)")
    ax.set_ylabel("y (nm)")
    labels: dict = {}  # one legend for the three panels, under them
    for panel in axes[0]:
        for handle, label in zip(*panel.get_legend_handles_labels()):
            labels.setdefault(label, handle)
    _legend_below(fig, labels.values(), labels.keys(), ncol=8)
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def save_map_figure(
    path: Path,
    map_image,
    landmarks,
    truth=(),
    tip_mean=None,
    tip_covariance=None,
    tip_means=(),
) -> Path:
    """map_image: (title, height m, extent m) or None; landmarks: (id, (x, y), 2x2 covariance)
    each; truth: true centres in the maps' frame; the tip's last estimate with its 3-sigma
    ellipse; right: the whole session's tip path."""
    fig, (ax, whole) = plt.subplots(
        1, 2, figsize=(FIGURE_WIDTH_IN, 4.4), layout="constrained", width_ratios=(1.15, 1)
    )
    if map_image is not None:
        _image(fig, ax, *map_image[1:], map_image[0])
    for k, (number, xy, cov) in enumerate(landmarks):
        outline = _nm(covariance_ellipse(xy, cov))
        ax.plot(
            outline[:, 0],
            outline[:, 1],
            "c-",
            lw=1.2,
            label="landmark 3-sigma" if k == 0 else None,
        )
        ax.annotate(str(number), _nm(xy), xytext=(6, 6), textcoords="offset points", color="c")
    truth = np.asarray(truth, float).reshape(-1, 2)
    if len(truth):
        ax.plot(*_nm(truth.T), "g+", ms=10, mew=1.5, label="true centre")
    if tip_mean is not None:
        outline = _nm(covariance_ellipse(tip_mean, tip_covariance))
        ax.plot(*_nm(tip_mean), "b.", ms=6, label="tip, last estimate")
        ax.plot(outline[:, 0], outline[:, 1], "b-", lw=0.8)
    ax.legend(fontsize=7, loc="upper right", framealpha=0.7)
    means = np.asarray(tip_means, float).reshape(-1, 2)
    if len(means):
        whole.plot(*_nm(means.T), ".-", color="tab:blue", lw=0.6, ms=3, label="tip estimate")
        whole.plot(*_nm(means[-1]), "bo", mfc="none", label="last")
    if len(truth):
        whole.plot(*_nm(truth.T), "g+", ms=10, mew=1.5, label="true centre")
    whole.set_aspect("equal", adjustable="datalim")
    whole.set_title("the tip's way over the session (estimate)", fontsize=9)
    whole.set_xlabel("x (nm)")
    whole.set_ylabel("y (nm)")
    whole.legend(fontsize=7)
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


MAX_LEGEND_STROKES = 8  # strokes named in a legend; more are coloured by their order


def save_force_figure(path: Path, strokes) -> Path:
    """strokes: (label, distance along the stroke m, lateral force N, normal force N) each."""
    fig, (lateral, normal) = plt.subplots(
        1, 2, figsize=(FIGURE_WIDTH_IN, 3.2), layout="constrained", sharex=True
    )
    # an assembly has dozens of strokes: a legend of them buries the plot, so past a few the
    # colour says the stroke's place in the session and a colour bar replaces the legend
    by_order = len(strokes) > MAX_LEGEND_STROKES
    colours = plt.get_cmap("viridis")(np.linspace(0.0, 1.0, max(len(strokes), 1)))
    for i, (label, distance, f_lat, f_norm) in enumerate(strokes):
        style = {"lw": 0.9, "label": label} | ({"color": colours[i]} if by_order else {})
        lateral.plot(_nm(distance), _nm(f_lat), **style)
        normal.plot(_nm(distance), _nm(f_norm), **style)
    for ax, what in ((lateral, "lateral force (nN)"), (normal, "normal force (nN)")):
        ax.set_xlabel("distance along the stroke (nm)")
        ax.set_ylabel(what)
        ax.grid(alpha=0.3)
    lateral.set_title("lateral force per stroke (torsion x spring constant)", fontsize=9)
    normal.set_title("normal force per stroke (deflection x spring constant)", fontsize=9)
    if by_order:
        shown = plt.cm.ScalarMappable(
            cmap="viridis", norm=matplotlib.colors.Normalize(1, len(strokes))
        )
        fig.colorbar(shown, ax=normal, label=f"stroke, in order (1-{len(strokes)})")
    elif strokes:
        normal.legend(fontsize=7, ncol=2)
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def save_localizer_figure(path: Path, times, errors, sigmas) -> Path:
    """times (s), errors (n, 2) estimate minus truth (m), sigmas (n, 2) the filter's 1-sigma."""
    t = np.asarray(times, float)
    e = np.asarray(errors, float).reshape(-1, 2)
    s = np.asarray(sigmas, float).reshape(-1, 2)
    fig, axes = plt.subplots(
        1, 2, figsize=(FIGURE_WIDTH_IN, 3.0), layout="constrained", sharex=True
    )
    for axis, (ax, name) in enumerate(zip(axes, "xy")):
        ax.fill_between(
            t,
            -3e9 * s[:, axis],
            3e9 * s[:, axis],
            color="tab:blue",
            alpha=0.2,
            label="3-sigma band",
        )
        ax.plot(t, _nm(e[:, axis]), "k.-", lw=0.6, ms=3, label="estimate - truth")
        ax.axhline(0.0, color="grey", lw=0.5)
        ax.set_xlabel("instrument time since the first estimate (s)")
        ax.set_ylabel(f"{name} error (nm)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle("localizer error against the truth (maps' frame)", fontsize=9)
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def save_tip_figure(
    path: Path,
    tip,
    pixel: float,
    uncertainty,
    unconstrained,
    radius: float,
    depth: float | None,
    true_tip=None,
) -> Path:
    """The blind tip estimate (m, apex 0 at the centre): the grid with the pixels the image did
    not constrain and the radius it constrained all round; its x and y sections through the
    apex with the resolution band below them (`uncertainty`, m; inf where unconstrained) and
    the true tip's (same grid and pixel) where there is one; the width bound 2 x `radius` at
    `depth` below the apex (None: no bound to show)."""
    tip = np.asarray(tip, float)
    k = tip.shape[0]
    h = k // 2
    band = np.where(np.isfinite(uncertainty), uncertainty, np.nan)
    offsets = _nm((np.arange(k) - h) * pixel)
    fig, axes = plt.subplots(
        1, 3, figsize=(FIGURE_WIDTH_IN, 3.3), layout="constrained", width_ratios=[1, 1.3, 1.3]
    )
    half = (h + 0.5) * pixel
    _image(fig, axes[0], tip, (-half, half, -half, half), "estimated tip (apex at 0)")
    axes[0].contourf(
        offsets, offsets, np.asarray(unconstrained, float), levels=[0.5, 1.5], colors="none",
        hatches=["xx"],
    )  # fmt: skip
    circle = np.linspace(0, 2 * np.pi, 90)
    axes[0].plot(
        _nm(radius) * np.cos(circle), _nm(radius) * np.sin(circle), "c--", lw=1,
        label="constrained all round",
    )  # fmt: skip
    axes[0].legend(fontsize=7, loc="lower left", framealpha=0.7)
    for ax, name, cut in ((axes[1], "x", np.s_[h, :]), (axes[2], "y", np.s_[:, h])):
        ax.fill_between(
            offsets, _nm(tip[cut] - band[cut]), _nm(tip[cut]), color="tab:blue", alpha=0.2,
            label="resolution band (threshold + 3 sigma)",
        )  # fmt: skip
        ax.plot(offsets, _nm(tip[cut]), "k.-", lw=1, ms=3, label="estimate (an upper bound)")
        if true_tip is not None:
            ax.plot(offsets, _nm(np.asarray(true_tip, float)[cut]), "g--", lw=1.2,
                    label="simulator's true tip")  # fmt: skip
        ax.axvspan(offsets[0], -_nm(radius), color="grey", alpha=0.15)
        ax.axvspan(_nm(radius), offsets[-1], color="grey", alpha=0.15, label="not constrained")
        if depth is not None:
            ax.plot([-_nm(radius), _nm(radius)], [-_nm(depth)] * 2, "c|-", lw=1.2,
                    label=f"at most {_nm(2 * radius):.0f} nm wide here")  # fmt: skip
        ax.set_xlabel(f"{name} from the apex (nm)")
        ax.set_ylabel("height (nm)")
        ax.set_title(f"section along {name} through the apex", fontsize=9)
        ax.grid(alpha=0.3)
    axes[2].legend(fontsize=6, loc="lower center", framealpha=0.8)
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def save_pattern_figure(
    path: Path,
    map_image,
    starts,
    goals,
    order,
    predicted=None,
    achieved=None,
    true_ends=None,
    obstacles=(),
) -> Path:
    """An assembly: left, the map (title, height m, extent m, or None) with each particle's
    mapped start, its way to its goal numbered in the order pushed, and the other mapped
    objects; right, each particle's end against its goal in nm (predicted by the push model,
    verified by rescan, true), with 10 and 20 nm circles. Points (n, 2) m in the maps' frame,
    rows alike; `order`: row indices in the order pushed; NaN rows are left out."""
    starts, goals = np.asarray(starts, float), np.asarray(goals, float)
    fig, (ax, err) = plt.subplots(
        1, 2, figsize=(FIGURE_WIDTH_IN, 5.0), layout="constrained", width_ratios=(1.2, 1)
    )
    if map_image is not None:
        _image(fig, ax, *map_image[1:], map_image[0])
    others = np.asarray(obstacles, float).reshape(-1, 2)
    if len(others):
        ax.plot(*_nm(others.T), "s", color="grey", mfc="none", ms=7, label="not pushed")
    ax.plot(*_nm(starts.T), "o", color="deepskyblue", mfc="none", ms=8, label="mapped start")
    ax.plot(*_nm(goals.T), "g*", ms=10, label="goal (planned)")
    for rank, row in enumerate(order):
        a, b = _nm(starts[row]), _nm(goals[row])
        ax.annotate("", b, a, arrowprops={"arrowstyle": "->", "color": "c", "lw": 1.0})
        ax.annotate(str(rank + 1), a, xytext=(5, 5), textcoords="offset points", color="c")
    ends = (
        ("predicted", predicted, "^", "tab:orange"),
        ("verified (rescan)", achieved, "x", "b"),
        ("true", true_ends, "+", "m"),
    )
    for label, points, marker, colour in ends:
        if points is None:
            continue
        p = np.asarray(points, float).reshape(-1, 2)
        ax.plot(*_nm(p.T), marker, color=colour, ms=8, mew=1.5, label=f"end, {label}")
        off = _nm(p - goals)
        err.plot(*off.T, marker, color=colour, ms=9, mew=1.5, label=label)
        for rank, row in enumerate(order):
            if np.isfinite(off[row]).all():
                err.annotate(str(rank + 1), off[row], xytext=(4, 4), textcoords="offset points")
    # under the panels: inside, the legend would hide the objects at the map's corners
    _legend_below(fig, *ax.get_legend_handles_labels(), ncol=6)
    for radius in (10, 20):
        circle = radius * np.exp(1j * np.linspace(0, 2 * np.pi, 90))
        err.plot(circle.real, circle.imag, ":", color="grey", lw=0.8)
        err.annotate(f"{radius} nm", (0, radius), ha="center", va="bottom", fontsize=7)
    err.axhline(0, color="grey", lw=0.4)
    err.axvline(0, color="grey", lw=0.4)
    err.set_aspect("equal", adjustable="datalim")
    err.set_title("end minus goal, per particle (order pushed)", fontsize=9)
    err.set_xlabel("x (nm)")
    err.set_ylabel("y (nm)")
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path
