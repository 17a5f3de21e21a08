"""The demo's report: report.html (summary, the assembled pattern (demo_assembly), its first
push zoomed in the task frame, the map with its landmarks, the estimated tip's shape
(demo_tip), forces per stroke, the localizer's error, timings, scans, particles, landmarks,
recorded topics, replay check, memory, how to reproduce the run and how to open the recording
in Foxglove), its figures (each the page's width) and summary.json.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from afm_bringup.demo_assembly import (
    assembly_section,
    assembly_truth,
    first_push,
    predicted_ends,
)
from afm_bringup.demo_evaluation import (
    MEMORY_LIMIT,
    PUSH_TOLERANCE,
    push_truth,
    truth_in_maps,
)
from afm_bringup.demo_reproduce import foxglove_section, reproducibility_section
from afm_bringup.demo_tip import tip_shape_section, tip_shape_summary
from afm_bringup.units import nm
from afm_core.evaluation import push_image_frames
from afm_core.instrument import RasterScanData
from afm_core.report import save_height_maps, table, write_html
from afm_core.report_figures import (
    save_force_figure,
    save_localizer_figure,
    save_map_figure,
    save_push_figure,
)


def write_report(
    run_dir: Path,
    result: dict,
    memory: dict,
    codes: dict,
    elapsed: float,
    assembly: dict,
    timings: dict,
) -> Path:
    """The figures (scans.png, pattern.png, push.png of the assembly's first push, ...),
    summary.json and report.html of a run; takes the scan arrays out of `result`."""
    scans = result.pop("scan_arrays")
    assembly["predicted"] = predicted_ends(
        result.pop("believed", {}), assembly.get("particle_ids", [])
    )
    push = first_push(assembly)
    images, local = _scan_images(scans)
    anchor = result["truth_anchor"]
    save_height_maps(
        run_dir / "scans.png",
        images,
        markers=truth_in_maps(result["truth_xy"], anchor),
        marker_label="true centre at the start",
    )
    truth = push_truth(result, push)
    pattern_truth = assembly_truth(result, assembly, lambda p: truth_in_maps(p, anchor))
    if pattern_truth:  # the figure in the frame used before 2026-11-28, beside it
        pattern_truth["rms_creep_free"] = assembly_truth(
            result, assembly, lambda p: truth_in_maps(p, anchor, creep_free=True)
        )["rms"]
    tip = result.get("tip") or {}
    sections = [_summary_section(result, memory, codes, elapsed, assembly)]
    if assembly.get("order"):
        sections.append(assembly_section(run_dir / "pattern.png", result, assembly, pattern_truth))
    if push.get("ran"):
        frames_note = _save_push_figure(run_dir / "push.png", local, result, push, tip, truth)
        sections.append(_push_section(push, truth, frames_note))
    sections.append(_map_section(run_dir / "map.png", result, tip))
    if result.get("tip_shape"):
        sections.append(tip_shape_section(run_dir / "tip.png", result["tip_shape"]))
    if result.get("force_strokes"):
        save_force_figure(run_dir / "forces.png", result["force_strokes"])
        sections.append(_force_section(result["force_strokes"]))
    if tip:
        save_localizer_figure(
            run_dir / "localizer.png", tip["times"], tip["errors"], tip["sigmas"]
        )
        sections.append(_tip_section(tip, result.get("tip_first_push") or {}))
    sections += [
        (
            "Timings",
            table(["stage", "wall time"], [[k, f"{v:.1f} s"] for k, v in timings.items()]),
        ),
        (
            "Scans (commanded scanner coordinates, the maps' frame)",
            "<img src='scans.png' alt='height maps'><p>+: the true particle centres at the "
            "start, brought into the maps' frame (about where the session started, by the "
            "simulated scanner's image scale).</p>",
        ),
        _particles_section(result),
        _landmarks_section(result),
        *_recording_sections(result, memory),
        reproducibility_section(run_dir),
        foxglove_section(run_dir),
    ]
    _write_summary(
        run_dir / "summary.json",
        result,
        memory,
        codes,
        elapsed,
        timings,
        {"push": push, "push_truth": truth},
        {"assembly": assembly, "assembly_truth": pattern_truth},
    )
    return write_html(run_dir / "report.html", "AFM nano-manipulation demo", sections)


def _scan_images(scans: dict) -> tuple[list, list]:
    """(title, height, extent) of every scan: (the graph's scans, the nano-hand's local ones,
    these with their RasterScanData too)."""
    images, local = [], []
    for i in range(len(scans["scan_id"])):
        x0, y0 = scans["origin.x"][i], scans["origin.y"][i]
        h = scans["height"][i]
        extent = (
            x0,
            x0 + h.shape[1] * scans["pixel_size_x"][i],
            y0,
            y0 + h.shape[0] * scans["pixel_size_y"][i],
        )
        title = (
            f"scan {scans['scan_id'][i]}: {scans['scan_angle_deg'][i]:.0f} deg, "
            f"frame-{'up' if scans['slow_scan_up'][i] else 'down'}"
        )
        if str(scans["pair_id"][i]).startswith("local"):  # with its record, to place it
            local.append((title, h, extent, _raster(scans, i)))
        else:
            images.append((title, h, extent))
    return images, local


def _raster(scans: dict, i: int) -> RasterScanData:
    return RasterScanData(
        height=np.asarray(scans["height"][i], float),
        pixel_size_x=float(scans["pixel_size_x"][i]),
        pixel_size_y=float(scans["pixel_size_y"][i]),
        origin_x=float(scans["origin.x"][i]),
        origin_y=float(scans["origin.y"][i]),
        scan_angle_deg=float(scans["scan_angle_deg"][i]),
        slow_scan_up=bool(scans["slow_scan_up"][i]),
        line_period=float(scans["line_period"][i]),
        line_start_times=np.asarray(scans["line_start_times"][i], float),
        start_time=0.0,
        mode=str(scans["mode"][i]),
    )


def _shifted(panel, shift):
    title, height, extent = panel
    dx, dy = shift
    return title, height, (extent[0] + dx, extent[1] + dx, extent[2] + dy, extent[3] + dy)


def _save_push_figure(path: Path, local: list, result: dict, push: dict, tip: dict, truth: dict):
    """The nano-hand's before and after rescans of the push (the first two local scans) in the
    task frame, zoomed on the push, with the strokes, goal, verified and true end, and the tip
    estimate near the push. Returns a sentence on how the images were placed."""
    before = (f"before ({local[0][0]})", *local[0][1:3]) if local else None
    after = (f"after ({local[1][0]})", *local[1][1:3]) if len(local) > 1 else None
    note = "the rescans placed in the task frame as the nano-hand's verification does"
    try:
        frames = push_image_frames(
            local[0][3],
            local[1][3] if after is not None else None,
            push["start"],
            push["goal"],
        )
        before = _shifted(before, frames.before_shift)
        if after is not None:
            after = _shifted(after, frames.after_shift)
        note += (
            f": before shifted by ({nm(frames.before_shift[0])}, {nm(frames.before_shift[1])})"
            + (
                f", after by ({nm(frames.after_shift[0])}, {nm(frames.after_shift[1])}) with "
                f"{frames.control_points} control point(s)"
                if frames.after_shift is not None
                else ""
            )
        )
    except (ValueError, IndexError) as exc:  # no particle to tie them by: left as scanned
        note = f"the rescans could not be placed in the task frame ({exc}); shown as scanned"
    anchor = result["truth_anchor"]
    track = np.asarray(truth.get("track", []), float).reshape(-1, 2)
    # the truth's track in the maps' frame, started where the map has the particle
    maps_track = (
        np.asarray(push["start"]) + truth_in_maps(track, anchor) - truth_in_maps(track[:1], anchor)
        if len(track)
        else track
    )
    save_push_figure(
        path,
        before,
        after,
        push["start"],
        push["goal"],
        push["achieved"],
        true_end=maps_track[-1] if len(maps_track) else None,
        strokes=result.get("strokes_by_particle", {}).get(push["particle_id"], []),
        tip_means=tip.get("means", []),
        tip_covariances=tip.get("covariances", []),
        true_tip=tip.get("true_tip", []),
        particle_track=maps_track,
    )
    return note


def _map_section(path: Path, result: dict, tip: dict):
    landmarks = [
        (m["id"], (m["x"], m["y"]), np.reshape(m["covariance"], (2, 2)))
        for m in result["landmarks"]
    ]
    means = np.asarray(tip.get("means", []), float).reshape(-1, 2)
    save_map_figure(
        path,
        result.get("map_image"),
        landmarks,
        truth=truth_in_maps(result["final_particles_xy"], result["truth_anchor"]),
        tip_mean=means[-1] if len(means) else None,
        tip_covariance=tip["covariances"][-1] if len(means) else None,
        tip_means=means,
    )
    return (
        "The map, its landmarks and the tip",
        "<img src='map.png' alt='map'><p>Left: the imaging node's drift-corrected map (task "
        "frame) with each landmark's 3-sigma ellipse (the pushed particle where the nano-hand's "
        "rescan found it), the true centres at the end (maps' frame) and the localizer's last "
        "tip estimate with its 3-sigma ellipse. Right: the tip's estimated way over the whole "
        "session.</p>",
    )


def _force_section(strokes: list):
    rows = [
        [label, nm(float(d[-1])), f"{np.max(np.abs(f)) * 1e9:.2f} nN", f"{np.max(n) * 1e9:.2f} nN"]
        for label, d, f, n in strokes
    ]
    return "Forces per stroke", "<img src='forces.png' alt='forces'>" + table(
        ["stroke", "length", "peak |lateral force|", "peak normal force"], rows
    )


def _summary_section(result: dict, memory: dict, codes: dict, elapsed: float, assembly: dict):
    replay_ok = all(v["identical"] for v in result["replay"].values())
    recording = (
        f"session.mcap, {sum(result['topics'].values())} messages, {result['duration_s']:.1f} s"
    )
    rows = [
        [
            "nodes started and stopped cleanly",
            "yes" if all(c == 0 for c in codes.values()) else f"no: {codes}",
        ],
        ["recording", recording],
        [
            "replay reproduced every payload (evaluation reads the replayed copy)",
            "yes" if replay_ok else "NO",
        ],
        ["assembly", assembly.get("message", "not run")],
        [
            "graph peak memory (sum of node peaks)",
            f"{sum(memory.values()) / 2**20:.0f} MiB (limit {MEMORY_LIMIT / 2**30:.0f} GiB)",
        ],
        ["demo wall time", f"{elapsed:.1f} s"],
    ]
    return "Summary", table(["check", "value"], rows)


def _push_section(push: dict, truth: dict, frames_note: str):
    verification_error = float(
        np.linalg.norm(np.subtract(truth["verified_displacement"], truth["true_displacement"]))
    )
    rows = [
        ["particle (landmark id)", push["particle_id"]],
        ["mapped start", f"({nm(push['start'][0])}, {nm(push['start'][1])})"],
        ["goal", f"({nm(push['goal'][0])}, {nm(push['goal'][1])})"],
        [
            "verified position (rescan, control points)",
            f"({nm(push['achieved'][0])}, {nm(push['achieved'][1])})",
        ],
        [
            "verified error to the goal",
            f"{nm(push['error'])} (tolerance {nm(PUSH_TOLERANCE)}): "
            f"{'within' if push['success'] else 'outside'}",
        ],
        [
            "true displacement along / sideways",
            f"{nm(truth['along'])} / {nm(truth['sideways'])} (planned "
            f"{nm(float(np.hypot(*np.subtract(push['goal'], push['start']))))} / 0)",
        ],
        ["true error (displacement against the planned one)", nm(truth["true_error"])],
        ["verification error (verified against true displacement)", nm(verification_error)],
        ["push strokes", push["steps"]],
        ["planner", push["plan_message"]],
    ]
    caption = (
        "<img src='push.png' alt='push'><p>Everything in the task frame, zoomed on the push. "
        "Left and middle: the nano-hand's own before and after rescans with the mapped start "
        "(o), the planned strokes (cyan: in contact), the goal (*), the verified position (x) "
        "and the true end (+, the truth brought into the maps' frame); "
        f"{frames_note}. Right: the localizer's tip estimates near the push with their "
        "3-sigma ellipses, the true tip and the true particle track.</p>"
    )
    return "The assembly's first push, zoomed in", table(["", "value"], rows) + caption


def _tip_section(tip: dict, first: dict):
    rows = [
        ["estimates compared with the truth (one per driver command)", tip["compared"]],
        ["RMS error of the estimate", nm(tip["error_rms"])],
        ["mean NEES (2 dof; consistent filter: about 2)", f"{tip['mean_nees']:.2f}"],
        ["the truth judged in the frame of", tip.get("frame_basis", "-")],
        [
            "the same over the map and the first push",
            f"{first['mean_nees']:.2f} ({first['compared']} compared)" if first else "-",
        ],
        [
            "final 1-sigma x / y",
            f"{nm(tip['final_sigma'][0])} / {nm(tip['final_sigma'][1])}",
        ],
    ]
    return "Tip localization against ground truth", table(["", "value"], rows) + (
        "<img src='localizer.png' alt='localizer error'><p>The localizer's estimate minus the "
        "true tip (brought into the maps' frame) at each driver command, with the filter's "
        "own 3-sigma band: a consistent filter keeps about 99 % of the points inside.</p>"
    )


def _particles_section(result: dict):
    header = [
        "scan",
        "angle",
        "slow axis",
        "pair id",
        "found",
        "matched",
        "centre error RMS",
        "peak height",
        "apparent radius",
    ]
    rows = [
        [
            v["scan_id"],
            f"{v['angle']:.0f} deg",
            "up" if v["frame_up"] else "down",
            v["pair_id"],
            v["found"],
            v["matched"],
            nm(v["centre_error_rms"]),
            nm(v["peak_height_mean"]),
            nm(v["apparent_radius_mean"]),
        ]
        for v in result["scans"]
    ]
    note = (
        f"<p>True radii: {', '.join(nm(r) for r in result['truth_radius'])}. The apparent "
        "radius at half height exceeds the true one by the tip's broadening. Images are in "
        "commanded scanner coordinates: the centre errors are the simulated instrument's "
        "positioning errors (hysteresis residue after the controller's feed-forward, creep, "
        "x/y coupling, scan-line rotation, thermal drift), which drift compensation and "
        "landmark localization are there to remove.</p>"
    )
    return "Particles in each scan against ground truth", table(header, rows) + note


def _landmarks_section(result: dict):
    header = [
        "id",
        "x",
        "y",
        "sigma x",
        "sigma y",
        "height",
        "distance to the nearest true centre",
    ]
    rows = [
        [
            m["id"],
            nm(m["x"]),
            nm(m["y"]),
            nm(m["sigma_x"]),
            nm(m["sigma_y"]),
            nm(m["height"]),
            nm(m["nearest_truth"]),
        ]
        for m in result["landmarks"]
    ]
    return (
        "Landmarks at the end (imaging node's map, the pushed particle updated by the nano-hand)",
        table(header, rows),
    )


def _recording_sections(result: dict, memory: dict) -> list:
    """The recorded topics, the replay check and the processes' peak memory."""
    replay_rows = [
        [t, v["count_a"], v["count_b"], "yes" if v["identical"] else "NO"]
        for t, v in result["replay"].items()
    ]
    return [
        (
            "Recorded topics",
            table(["topic", "messages"], [[t, n] for t, n in result["topics"].items()]),
        ),
        (
            "Replay check (original vs replayed recording)",
            table(["topic", "original", "replayed", "identical payloads"], replay_rows),
        ),
        (
            "Peak resident memory per process",
            table(
                ["process", "peak RSS"], [[n, f"{m / 2**20:.0f} MiB"] for n, m in memory.items()]
            ),
        ),
    ]


def _write_summary(
    path: Path,
    result: dict,
    memory: dict,
    codes: dict,
    elapsed: float,
    timings: dict,
    push: dict,
    assembly: dict,
) -> None:
    """summary.json: the evaluation without its arrays, and the run's own numbers; `push`:
    {"push", "push_truth"}, `assembly`: {"assembly", "assembly_truth"}."""
    tip = result.get("tip") or {}
    first = result.get("tip_first_push") or {}
    arrays = (
        "tip",
        "truth_objects",
        "force_strokes",
        "map_image",
        "tip_shape",
        "truth_by_id",
        "strokes_by_particle",
    )
    summary = {key: value for key, value in result.items() if key not in arrays}
    summary.update(
        memory_bytes=memory,
        exit_codes=codes,
        elapsed_s=elapsed,
        timings=timings,
        push=push["push"],
        push_truth={k: v for k, v in push["push_truth"].items() if k != "track"},
        **assembly,
        tip_shape=tip_shape_summary(result.get("tip_shape")),
        tip={
            k: v
            for k, v in tip.items()
            if k not in ("means", "covariances", "true_tip", "times", "errors", "sigmas")
        },
        tip_first_push={
            k: v
            for k, v in first.items()
            if k not in ("means", "covariances", "true_tip", "times", "errors", "sigmas")
        },
    )
    path.write_text(json.dumps(summary, indent=2, default=float))
