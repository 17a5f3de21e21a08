"""The demo's report: report.html (summary, the push, tip localization, timings, scans,
particles, landmarks, recorded topics, replay check, memory), its figures and summary.json.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from afm_bringup.demo_evaluation import MEMORY_LIMIT, PUSH_DISTANCE, PUSH_TOLERANCE, push_truth
from afm_bringup.units import nm
from afm_core.report import save_height_maps, save_push_figure, table, write_html


def write_report(
    run_dir: Path,
    result: dict,
    memory: dict,
    codes: dict,
    elapsed: float,
    push: dict,
    timings: dict,
) -> Path:
    """The figures (scans.png, push.png), summary.json and report.html of a run; takes the
    scan arrays out of `result`."""
    scans = result.pop("scan_arrays")
    images, local = _scan_images(scans)
    save_height_maps(run_dir / "scans.png", images, markers=result["truth_xy"])
    truth = push_truth(result, push)
    tip = result.get("tip") or {}
    if push.get("ran"):
        _save_push_figure(run_dir / "push.png", local, result, push, tip, truth)
    sections = [_summary_section(result, memory, codes, elapsed, push)]
    if push.get("ran"):
        sections.append(_push_section(push, truth))
    if tip:
        sections.append(_tip_section(tip))
    sections += [
        (
            "Timings",
            table(["stage", "wall time"], [[k, f"{v:.1f} s"] for k, v in timings.items()]),
        ),
        (
            "Scans (true particle centres at the start marked +)",
            "<img src='scans.png' alt='height maps'>",
        ),
        _particles_section(result),
        _landmarks_section(result),
        *_recording_sections(result, memory),
    ]
    _write_summary(run_dir / "summary.json", result, memory, codes, elapsed, timings, push, truth)
    return write_html(run_dir / "report.html", "AFM nano-manipulation demo", sections)


def _scan_images(scans: dict) -> tuple[list, list]:
    """(title, height, extent) of every scan: (the graph's scans, the nano-hand's local ones)."""
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
        (local if str(scans["pair_id"][i]).startswith("local") else images).append(
            (title, h, extent)
        )
    return images, local


def _save_push_figure(path: Path, local: list, result: dict, push: dict, tip: dict, truth: dict):
    """The nano-hand's before and after rescans, and the tip and particle paths."""
    before = (f"before the push ({local[0][0]})", *local[0][1:]) if local else None
    after = (f"after the push ({local[-1][0]})", *local[-1][1:]) if len(local) > 1 else None
    save_push_figure(
        path,
        before,
        after,
        tip.get("means", []),
        tip.get("covariances", []),
        tip.get("true_tip", []),
        truth.get("track", []),
        push["goal"],
        push["achieved"],
        result.get("strokes", []),
    )


def _summary_section(result: dict, memory: dict, codes: dict, elapsed: float, push: dict):
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
        ["push", push.get("message", "not run")],
        [
            "graph peak memory (sum of node peaks)",
            f"{sum(memory.values()) / 2**20:.0f} MiB (limit {MEMORY_LIMIT / 2**30:.0f} GiB)",
        ],
        ["demo wall time", f"{elapsed:.1f} s"],
    ]
    return "Summary", table(["check", "value"], rows)


def _push_section(push: dict, truth: dict):
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
            f"{nm(truth['along'])} / {nm(truth['sideways'])} (planned {nm(PUSH_DISTANCE)} / 0)",
        ],
        ["true error (displacement against the planned one)", nm(truth["true_error"])],
        ["verification error (verified against true displacement)", nm(verification_error)],
        ["push strokes", push["steps"]],
        ["planner", push["plan_message"]],
    ]
    caption = (
        "<img src='push.png' alt='push'><p>Left and middle: the nano-hand's own before and "
        "after rescans (scanner coordinates) with the goal (*) and the verified position (x). "
        "Right: the localizer's tip estimate over the session with 3-sigma ellipses, the true "
        "tip, the planned strokes (red: in contact) and the true particle track.</p>"
    )
    return "The push (virtual nano-hand, PushParticle action)", table(
        ["", "value"], rows
    ) + caption


def _tip_section(tip: dict):
    rows = [
        ["estimates compared with the truth (one per driver command)", tip["compared"]],
        ["RMS error of the estimate", nm(tip["error_rms"])],
        ["mean NEES (2 dof; consistent filter: about 2)", f"{tip['mean_nees']:.2f}"],
        [
            "final 1-sigma x / y",
            f"{nm(tip['final_sigma'][0])} / {nm(tip['final_sigma'][1])}",
        ],
    ]
    return "Tip localization against ground truth", table(["", "value"], rows)


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
    truth: dict,
) -> None:
    """summary.json: the evaluation without its arrays, and the run's own numbers."""
    tip = result.get("tip") or {}
    summary = {key: value for key, value in result.items() if key not in ("tip", "truth_objects")}
    summary.update(
        memory_bytes=memory,
        exit_codes=codes,
        elapsed_s=elapsed,
        timings=timings,
        push=push,
        push_truth={k: v for k, v in truth.items() if k != "track"},
        tip={k: v for k, v in tip.items() if k not in ("means", "covariances", "true_tip")},
    )
    path.write_text(json.dumps(summary, indent=2, default=float))
