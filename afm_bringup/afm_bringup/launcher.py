"""Start graph nodes as separate processes and stop them cleanly (our `ros2 launch`).

Children die with the launcher: each runs in its own session (Ctrl-C in the terminal reaches
only the launcher, which stops them in order) and asks the kernel for SIGTERM when the
launcher dies, even by SIGKILL (PR_SET_PDEATHSIG, set by the child itself at start, see
afm_ros.node_main.die_with_parent). A node that dies is reported; the recorder is restarted
on a new file (its unfinished one stays for `afm recover`), any other death stops the graph.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class NodeSpec:
    module: str
    package: str
    params_file: str


NODES = {
    "driver": NodeSpec("afm_driver.driver_node", "afm_driver", "driver.yaml"),
    "imaging": NodeSpec("afm_imaging.imaging_node", "afm_imaging", "imaging.yaml"),
    "localizer": NodeSpec("afm_localization.localizer_node", "afm_localization", "localizer.yaml"),
    "planner": NodeSpec("afm_planning.planner_node", "afm_planning", "planner.yaml"),
    "nano_hand": NodeSpec("afm_manipulation.nano_hand_node", "afm_manipulation", "nano_hand.yaml"),
    "teleop": NodeSpec("afm_manipulation.teleop_node", "afm_manipulation", "teleop.yaml"),
    "recorder": NodeSpec("afm_bringup.recorder_node", "afm_bringup", "recorder.yaml"),
    "replay": NodeSpec("afm_bringup.replay_node", "afm_bringup", "replay.yaml"),
    "sim2real": NodeSpec("afm_bringup.sim2real_node", "afm_bringup", "sim2real.yaml"),
    "viewer": NodeSpec("afm_viewer.viewer_node", "afm_viewer", "viewer.yaml"),
}
GRAPH = ["driver", "imaging", "localizer", "planner", "nano_hand", "teleop", "sim2real", "viewer"]
# The recorder only listens: a new one loses nothing but the gap. More restarts than this in a
# row mean it cannot run (a full disk, a bad path): the graph stops instead of looping.
RESTARTABLE = {"recorder"}
MAX_RESTARTS = 3
REFUSED_STATUS = 2  # afm_ros.node_main.REFUSED_STATUS, not imported: it would load rclpy here
PARENT_PID_ENV = "AFM_LAUNCHER_PID"  # read by afm_ros.node_main.die_with_parent in each child


# The nodes that load the localization calibration (the driver for its wait for creep).
CALIBRATED_NODES = ("driver", "localizer", "planner", "nano_hand", "teleop")


def sim_calibration_file() -> str:
    """The calibration the experiments produced on the default simulated instrument."""
    from ament_index_python.packages import get_package_share_directory

    return str(
        Path(get_package_share_directory("afm_localization")) / "config" / "sim_calibration.yaml"
    )


def with_sim_calibration(nodes, overrides: dict[str, dict[str, str]], calibration: str) -> list:
    """On the simulator (the driver's backend left at 'sim'), give every calibrated node in
    `nodes` the simulator's calibration unless the user set one: without it the localizer
    runs on the book's figures and the driver does not wait for creep. Changes `overrides`;
    returns the nodes it gave the file to."""
    if overrides.get("driver", {}).get("backend", "sim") != "sim":
        return []
    given = []
    for node in CALIBRATED_NODES:
        if node in nodes and "calibration_file" not in overrides.get(node, {}):
            overrides.setdefault(node, {})["calibration_file"] = calibration
            given.append(node)
    return given


VIEWER_PORT = 8765  # Foxglove's default WebSocket port (afm_viewer's default)


def port_free(host: str, port: int) -> bool:
    """True when a server could listen on host:port now (no one else does)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        try:
            probe.bind((host, port))
        except OSError:
            return False
    return True


def viewer_overrides(
    port_file: str | os.PathLike, host: str = "127.0.0.1", port: int = VIEWER_PORT
) -> dict[str, str]:
    """The viewer on `port` (Foxglove's default), or on any free port when another program (a
    second graph, another demo) has it; the port served is written to `port_file`."""
    return {"port": str(port if port_free(host, port) else 0), "port_file": str(port_file)}


def read_port(port_file: str | os.PathLike, timeout: float = 10.0) -> int | None:
    """The port a viewer wrote to `port_file`, once it has (None after `timeout` s)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            return int(Path(port_file).read_text())
        except (OSError, ValueError):
            time.sleep(0.05)
    return None


def restart_output(output: str, attempt: int) -> str:
    """session.mcap -> session.restart1.mcap, ...: never the old name (its .part is kept)."""
    path = Path(output)
    return str(path.with_name(f"{path.stem}.restart{attempt}{path.suffix}"))


def check_no_restart_outputs(output: str | os.PathLike) -> None:
    """RecordingError when a file a restarted recorder of `output` would write (or its .part)
    exists already: an earlier session's. The restarted recorder would refuse that name and
    the graph stop, and Sim2Real's live recording (latest_output) would be the old file."""
    from afm_core.recording import RecordingError

    path = Path(output)
    found = []
    for attempt in range(1, MAX_RESTARTS + 1):
        restarted = Path(restart_output(str(path), attempt))
        found += [
            f for f in (restarted, restarted.with_name(restarted.name + ".part")) if f.exists()
        ]
    if found:
        raise RecordingError(
            f"{', '.join(str(f) for f in found)} exists from an earlier session; a restarted "
            f"recorder of {path.name} writes there: choose another name, or move that file away"
        )


def latest_output(output: str | os.PathLike) -> Path:
    """The file the newest recorder of `output` writes (or wrote): the highest
    restart_output(output, n) whose file or .part exists, else `output` itself."""
    path = Path(output)
    newest = path
    for attempt in range(1, MAX_RESTARTS + 1):
        candidate = Path(restart_output(str(path), attempt))
        if candidate.exists() or candidate.with_name(candidate.name + ".part").exists():
            newest = candidate
    return newest


def default_params_file(name: str) -> Path | None:
    from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

    spec = NODES[name]
    try:
        path = Path(get_package_share_directory(spec.package)) / "config" / spec.params_file
    except PackageNotFoundError:
        return None
    return path if path.is_file() else None


def node_command(
    name: str,
    params_file: str | os.PathLike | None = None,
    overrides: dict[str, str] | None = None,
) -> list[str]:
    """The command line that runs one node (what `ros2 run` would exec)."""
    if name not in NODES:
        raise ValueError(f"node {name!r}: expected one of {sorted(NODES)}")
    command = [sys.executable, "-m", NODES[name].module, "--ros-args"]
    params_file = params_file or default_params_file(name)
    if params_file:
        command += ["--params-file", str(params_file)]
    for key, value in (overrides or {}).items():
        command += ["-p", f"{key}:={yaml_quoted(value) if key in PATH_PARAMETERS else value}"]
    return command


# parameters whose value is a path: ROS reads a -p value as YAML, so "run #3.mcap" was "run"
# (a comment) and "a: b.mcap" a mapping; quoted, any path is the string it is
PATH_PARAMETERS = ("output", "input", "live_recording", "calibration_file")


def yaml_quoted(text) -> str:
    """`text` as a YAML single-quoted string (a quote inside doubled)."""
    return "'" + str(text).replace("'", "''") + "'"


class Graph:
    """Processes of a running graph. Stops in reverse start order, so a recorder started
    first still hears everything the others say while they shut down."""

    def __init__(self, log_dir: str | os.PathLike | None = None, environment: dict | None = None):
        from afm_ros import exposure

        self.processes: dict[str, subprocess.Popen] = {}
        self.specs: dict[str, tuple[str, dict[str, str], object]] = {}
        self.restarts: dict[str, int] = {}
        self.first_outputs: dict[str, str] = {}
        self.log_dir = Path(log_dir) if log_dir else None
        if self.log_dir:
            self.log_dir.mkdir(parents=True, exist_ok=True)
        # localhost-only DDS unless the caller's environment says otherwise (exposure)
        self.environment = (
            environment if environment is not None else exposure.apply(dict(os.environ))
        )

    def start(
        self,
        name: str,
        overrides: dict[str, str] | None = None,
        alias: str | None = None,
        params_file=None,
    ) -> subprocess.Popen:
        alias = alias or name
        if alias in self.processes:
            raise ValueError(f"{alias} is already running")
        output = open(self.log_dir / f"{alias}.log", "ab") if self.log_dir else None
        self.specs[alias] = (name, dict(overrides or {}), params_file)
        self.processes[alias] = subprocess.Popen(
            node_command(name, params_file, overrides),
            stdout=output,
            stderr=subprocess.STDOUT if output else None,
            start_new_session=True,  # Ctrl-C in the terminal reaches us; we stop them in order
            env={**self.environment, PARENT_PID_ENV: str(os.getpid())},
        )
        return self.processes[alias]

    def restart(self, alias: str) -> subprocess.Popen | None:
        """Start a dead restartable node again (a recorder on a new file); None when it may
        not be (not restartable, MAX_RESTARTS used, or it refused its configuration, which it
        would refuse again)."""
        name, overrides, params_file = self.specs[alias]
        attempt = self.restarts.get(alias, 0) + 1
        refused = self.processes[alias].returncode == REFUSED_STATUS
        if name not in RESTARTABLE or attempt > MAX_RESTARTS or refused:
            return None
        self.restarts[alias] = attempt
        place = list(self.processes).index(alias)
        self.processes.pop(alias)
        first = self.first_outputs.setdefault(alias, overrides.get("output", ""))
        if first:
            overrides = {**overrides, "output": restart_output(first, attempt)}
        process = self.start(name, overrides, alias, params_file)
        # keep its place in the start order: a recorder started first is still stopped last
        items = list(self.processes.items())
        items.insert(place, items.pop())
        self.processes = dict(items)
        return process

    def dead(self) -> dict[str, int]:
        """Nodes that exited, with their exit codes."""
        return {name: p.returncode for name, p in self.processes.items() if p.poll() is not None}

    def stop(self, name: str, timeout: float = 10.0) -> int:
        process = self.processes.pop(name)
        for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
            if process.poll() is not None:
                break
            process.send_signal(sig)
            try:
                process.wait(wait)
            except subprocess.TimeoutExpired:
                print(f"afm: {name} did not stop on {signal.Signals(sig).name}", file=sys.stderr)
        return process.returncode

    def stop_all(self, timeout: float = 10.0) -> dict[str, int]:
        return {name: self.stop(name, timeout) for name in reversed(list(self.processes))}

    def wait(self, poll: float = 0.2) -> dict[str, int]:
        """Block until a node that cannot be restarted exits, or we are interrupted; then stop
        the rest. Every death is reported; a restartable node (the recorder) is started
        again."""
        interrupted = []
        previous = {
            sig: signal.signal(sig, lambda s, _f: interrupted.append(s))
            for sig in (signal.SIGINT, signal.SIGTERM)
        }
        died: dict[str, int] = {}
        try:
            while not interrupted and not died:
                time.sleep(poll)
                for name, code in self.dead().items():
                    print(f"afm: {name} exited with status {code}", file=sys.stderr)
                    if self.restart(name) is not None:
                        output = self.specs[name][1].get("output")
                        print(
                            f"afm: {name} restarted (restart {self.restarts[name]} of "
                            f"{MAX_RESTARTS})" + (f", recording to {output}" if output else ""),
                            file=sys.stderr,
                        )
                        continue
                    died[name] = code
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        return {**died, **self.stop_all()}
