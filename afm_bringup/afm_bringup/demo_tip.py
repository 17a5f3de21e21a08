"""The demo report's tip shape: the blind estimate from the session's last drift-corrected map,
with the imaging node's own parameters (afm_imaging/config/imaging.yaml: tip_size,
tip_threshold), what the image constrained (afm_core.imaging.tip_guard) and what that is good
for in numbers (afm_core.imaging.tip_apex), beside the simulator's true tip when the simulator
was the backend (its configuration's shape, the ground truth's last apex radius, which wear
changes).

Offline, after the session: estimating in the graph costs seconds the demo's timing does not
need, and the report is where the numbers are read.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import yaml

# the imaging node's defaults (imaging.yaml), when its parameter file is not installed
TIP_SIZE, TIP_THRESHOLD = 21, "auto"


def _node_params(name: str) -> dict:
    from afm_bringup.launcher import default_params_file

    path = default_params_file(name)
    if path is None:
        return {}
    loaded = yaml.safe_load(Path(path).read_text()) or {}
    return next(iter(loaded.values()), {}).get("ros__parameters", {})


def sim_tip_params():
    """The simulated tip's parameters the demo's driver runs with (its sim_config or the
    defaults)."""
    from afm_core.sim.config import load_config

    return load_config(_node_params("driver").get("sim_config") or None).tip


def estimate_run_tip(
    map_image, truth_apex_radius: float | None, tip_params=None, tip_size=None, threshold=None
) -> dict | None:
    """The tip estimate of `map_image` ((title, height m, extent m) as evaluate has it, or
    None): arrays, the reading's numbers and the true tip on the same grid (None without a
    simulator: `truth_apex_radius` None). Parameters default to the imaging node's."""
    from afm_core.imaging.tip_apex import read_tip, width_at
    from afm_core.imaging.tip_estimation import estimate_tip
    from afm_core.imaging.tip_thresholds import RULES
    from afm_core.sim.tip import paraboloid_cone_tip

    if map_image is None:
        return None
    params = _node_params("imaging")
    tip_size = int(tip_size or params.get("tip_size", TIP_SIZE))
    threshold = threshold if threshold is not None else params.get("tip_threshold", TIP_THRESHOLD)
    _, height, extent = map_image
    height = np.asarray(height, float)
    pixel = (extent[1] - extent[0]) / height.shape[1]
    with warnings.catch_warnings():  # the guard's warnings are kept in estimate.warnings
        warnings.simplefilter("ignore")
        try:
            estimate = estimate_tip(
                height,
                tip_size,
                threshold=threshold if threshold in RULES else float(threshold),
                pixel_size=pixel,
            )
        except ValueError as exc:  # the guard refuses an estimate with no constrained ring
            return {"refused": str(exc), "tip_size": tip_size}
    reading = read_tip(estimate, pixel, height)
    out = {
        "tip": estimate.tip,
        "pixel": pixel,
        "uncertainty": estimate.uncertainty,
        "unconstrained": estimate.unconstrained,
        "warnings": list(estimate.warnings),
        "tip_size": tip_size,
        "seconds": estimate.seconds,
        "reading": reading,
        "true_tip": None,
    }
    if truth_apex_radius is not None:
        p = tip_params if tip_params is not None else sim_tip_params()
        true_tip = paraboloid_cone_tip(
            float(truth_apex_radius),
            p.half_angle_deg,
            pixel,
            # deep enough to leave the window at every pixel: the window's corner at the
            # cone's steepest slope
            2 * tip_size * pixel / np.tan(np.radians(p.half_angle_deg * (1 - abs(p.asymmetry)))),
            p.asymmetry,
            tip_size // 2,
            p.apex_shape,
        )
        out.update(
            true_tip=true_tip,
            true_apex_radius=float(truth_apex_radius),
            true_width=width_at(true_tip, pixel, reading.depth),
        )
    return out


def tip_shape_caption(shape: dict) -> str:
    """The figure's caption: what the estimate is good for, in numbers (nm), and the truth."""
    r = shape["reading"]
    k = shape["tip_size"]
    text = (
        f"Blind estimate ({k} x {k} pixels of {shape['pixel'] * 1e9:.2f} nm) from the last "
        f"drift-corrected map, as the imaging node makes it: {r.sentence()}."
    )
    if shape.get("true_tip") is not None and r.below_noise:
        text += f" The simulator's tip: apex radius {shape['true_apex_radius'] * 1e9:.0f} nm."
    elif shape.get("true_tip") is not None:
        inside = "within" if shape["true_width"] <= r.max_width else "OUTSIDE"
        text += (
            f" The simulator's tip: apex radius {shape['true_apex_radius'] * 1e9:.0f} nm, "
            f"{shape['true_width'] * 1e9:.0f} nm wide {r.depth * 1e9:.1f} nm below its apex "
            f"({inside} the bound)."
        )
    return text


def tip_shape_section(path: Path, shape: dict) -> tuple[str, str]:
    """(heading, html) of the report's tip-shape section; draws `path` (tip.png)."""
    import html

    from afm_core.report_figures import save_tip_figure

    heading = "The estimated tip (blind estimate from the map)"
    if "refused" in shape:
        return heading, f"<p>No tip estimate: {html.escape(shape['refused'])}</p>"
    r = shape["reading"]
    save_tip_figure(
        path,
        shape["tip"],
        shape["pixel"],
        shape["uncertainty"],
        shape["unconstrained"],
        r.radius,
        None if r.below_noise else r.depth,
        shape.get("true_tip"),
    )
    notes = "".join(f"<li>{html.escape(w)}</li>" for w in shape["warnings"])
    return heading, (
        f"<img src='{path.name}' alt='estimated tip'><p>{html.escape(tip_shape_caption(shape))}"
        " Left: the estimate (hatched: pixels the image did not constrain; dashed circle: the "
        "radius constrained all round). Middle and right: its sections through the apex; the "
        "true tip lies below the estimate (it is an upper bound), the band is the estimate's "
        "resolution, grey is outside the constrained radius.</p>"
        + (f"<p>The estimate's own warnings:</p><ul>{notes}</ul>" if notes else "")
    )


def tip_shape_summary(shape: dict | None) -> dict | None:
    """summary.json's numbers of the tip shape (m)."""
    if not shape or "refused" in shape:
        return shape
    from dataclasses import asdict

    reading = {  # JSON has no NaN or inf: an unmeasured apex, a flat top
        k: (None if isinstance(v, float) and not np.isfinite(v) else v)
        for k, v in asdict(shape["reading"]).items()
    }
    out = {"tip_size": shape["tip_size"], "pixel": shape["pixel"], **reading}
    out["warnings"] = shape["warnings"]
    if shape.get("true_tip") is not None:
        out.update(true_apex_radius=shape["true_apex_radius"], true_width=shape["true_width"])
    return out
