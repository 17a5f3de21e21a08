"""What a demo report needs so someone can run the same session again (seed, configurations,
commit, versions) and look at its recording in Foxglove."""

from __future__ import annotations

import hashlib
import html
import platform
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import yaml

from afm_core.report import table

# the libraries whose versions change what a session computes or records
VERSIONED = ("numpy", "scipy", "filterpy", "matplotlib", "mcap", "mcap-ros2-support", "tqdm")


def _digest(path: Path) -> str:
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:12]
    except OSError:
        return "unreadable"


def _git(*args: str) -> str:
    root = Path(__file__).resolve().parents[2]
    try:
        done = subprocess.run(
            ["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10
        )
    except (OSError, subprocess.TimeoutExpired):
        return ""
    return done.stdout.strip() if done.returncode == 0 else ""


def commit() -> str:
    """The commit the run's code is at, "+ local changes" when the tree differs from it."""
    head = _git("rev-parse", "HEAD")
    if not head:
        return "unknown (not a git checkout)"
    dirty = _git("status", "--porcelain", "--untracked-files=no")
    return head + (" + local changes" if dirty else "")


def _version(name: str) -> str:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


def seed_and_configs() -> list[list[str]]:
    """The simulator's seed and configuration, and every node's parameter file with a digest
    (the demo runs each node on its default file plus the simulator's calibration)."""
    from afm_bringup.launcher import GRAPH, default_params_file, sim_calibration_file
    from afm_core.sim.config import load_config

    rows = []
    driver_file = default_params_file("driver")
    params = {}
    if driver_file is not None:
        loaded = yaml.safe_load(Path(driver_file).read_text()) or {}
        params = next(iter(loaded.values()), {}).get("ros__parameters", {})
    sim_config = params.get("sim_config") or ""
    config = load_config(sim_config or None)
    seed = params.get("seed", -1)
    rows.append(
        [
            "simulator seed",
            f"{config.seed} (the configuration's; driver seed -1)" if seed == -1 else str(seed),
        ]
    )
    rows.append(
        [
            "simulator configuration",
            f"{sim_config} (sha256 {_digest(sim_config)})" if sim_config else "the defaults",
        ]
    )
    calibration = sim_calibration_file()
    rows.append(["calibration", f"{calibration} (sha256 {_digest(calibration)})"])
    for name in ["recorder", *GRAPH]:
        path = default_params_file(name)
        if path is not None:
            rows.append([f"{name} parameters", f"{path} (sha256 {_digest(path)})"])
    return rows


def reproducibility_section(run_dir: Path):
    rows = [
        ["command", " ".join(sys.argv)],
        ["commit", commit()],
        *seed_and_configs(),
        *(
            [["the demo's sample (merged into it)", f"{sample} (sha256 {_digest(sample)})"]]
            if (sample := Path(run_dir) / "sample.yaml").is_file()
            else []
        ),
        ["python", f"{platform.python_version()} ({platform.platform()})"],
        ["ROS 2 rclpy", _version("ros-jazzy-rclpy")],
        *[[name, _version(name)] for name in VERSIONED],
    ]
    return (
        "Reproducibility",
        table(["", "value"], rows)
        + "<p>The same commit, seed and files give the same simulated instrument; the graph's "
        "timing (two cores shared) can still change what the nodes see when.</p>",
    )


def foxglove_section(run_dir: Path):
    session = html.escape(str(Path(run_dir).resolve() / "session.mcap"))
    layout = html.escape(str(foxglove_layout()))
    return (
        "Open the recording in Foxglove",
        "<ol><li>Open Foxglove (the desktop app, or the web app in Chrome) and choose "
        f"<b>Open local file</b>: <code>{session}</code> (or drag it into the window).</li>"
        "<li>Layouts &gt; <b>Import from file</b>: "
        f"<code>{layout}</code>: the map and scan images, the landmarks with their 3-sigma "
        "ellipses, the planned path and the tip in <code>afm_task</code>, and plots of the tip "
        "path, the strokes and each stroke's deflection and torsion. The timeline is the "
        "instrument's clock.</li>"
        "<li>Or replay it into a running graph: <code>afm replay "
        f"{session}</code> (<code>--rate 2</code> for twice the speed).</li></ol>",
    )


def foxglove_layout() -> Path:
    """The installed layout (share/afm_bringup/foxglove), else the source tree's."""
    try:
        from ament_index_python.packages import get_package_share_directory

        installed = Path(get_package_share_directory("afm_bringup")) / "foxglove"
    except (ImportError, LookupError):
        installed = None
    name = "afm_session.json"
    if installed is not None and (installed / name).is_file():
        return installed / name
    return Path(__file__).resolve().parents[1] / "foxglove" / name
