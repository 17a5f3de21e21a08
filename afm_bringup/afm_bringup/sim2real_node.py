"""Sim-to-real node: the action /afm/sim2real runs afm_core.sim2real.run_sim2real on a
recording, by default on what the graph's own recorder has written so far.

A live recording is still `NAME.mcap.part` (the recorder renames it when it closes); the
node copies its complete chunks into a snapshot (afm_core.recording.recover_recording) and
diagnoses that, so the recorder is never disturbed. All the analysis is in the core
library; this node only resolves paths, reports the phase as feedback and turns a cancel
request into a clean stop between analysis steps. A goal reads only under the `read_roots`
folders and writes only under `report_root` (a goal is anyone on the ROS network).
"""

from __future__ import annotations

import math
import threading
from datetime import datetime
from pathlib import Path

from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node

from afm_bringup.launcher import latest_output
from afm_core.checks import inside
from afm_core.parameters import Parameter, ParameterTable
from afm_core.sim.config import check_config_file
from afm_msgs.action import Sim2Real
from afm_ros import topics
from afm_ros.node_main import run
from afm_ros.params import declare

PARAMETERS = ParameterTable(
    Parameter(
        "model",
        "",
        "Simulator configuration YAML the recording is compared with ('' = the simulator's "
        "defaults); a goal's `model` overrides it. A missing or broken file is refused.",
        check=check_config_file,
        runtime=True,
    ),
    Parameter(
        "read_roots",
        ["."],
        "Folders a goal's `recording` and `model` must lie in (symlinks followed; relative to "
        "the node's working folder); a path outside is refused. The parameters' own files "
        "(model, live_recording) are the operator's and not limited.",
        runtime=True,
    ),
    Parameter(
        "live_recording",
        "",
        "The graph recorder's output file (its `output` parameter); a goal with an empty "
        "`recording` diagnoses a snapshot of it.",
        runtime=True,
    ),
    Parameter(
        "report_root",
        "sim2real_reports",
        "Folder under which a goal without `report_dir` gets a new report folder; a goal's "
        "`report_dir` must lie in it (symlinks followed).",
        runtime=True,
    ),
)
ROOTS_HINT = "a goal reads only under the node's read_roots and writes only under report_root"


class Cancelled(Exception):
    """The client cancelled the goal; raised from the progress callback between steps."""


class Sim2RealNode(Node):
    def __init__(self):
        super().__init__("sim2real")
        self.config = declare(self, PARAMETERS)
        self._busy = threading.Lock()  # one diagnosis at a time: each takes both cores for a while
        ActionServer(
            self,
            Sim2Real,
            topics.ACTION_SIM2REAL,
            self.execute,
            callback_group=ReentrantCallbackGroup(),
            goal_callback=self.accept,
            cancel_callback=lambda _g: CancelResponse.ACCEPT,
        )

    def accept(self, _goal) -> GoalResponse:
        return GoalResponse.REJECT if self._busy.locked() else GoalResponse.ACCEPT

    def recording_for(self, goal) -> tuple[Path, str]:
        """(file to diagnose, note); raises ValueError naming what is missing."""
        from afm_core.recording import RecordingError, recover_recording
        from afm_core.recording.bag_folder import recording_file

        if goal.recording:
            path = inside("recording", goal.recording, self.config["read_roots"], ROOTS_HINT)
            try:
                path = recording_file(path)  # a rosbag2 folder: its MCAP file
            except RecordingError as exc:
                raise ValueError(f"recording={goal.recording!r}: {exc}") from None
            if not path.is_file():
                raise ValueError(f"recording={goal.recording!r}: no such file")
            return path, ""
        live = self.config["live_recording"]
        if not live:
            raise ValueError(
                "recording is empty and the node's live_recording parameter is not set: "
                "name a recording, or start the node with live_recording = the recorder's output"
            )
        named = Path(live)
        live = latest_output(named)  # a restarted recorder writes on under a new name
        restarted = f" (the recorder restarted; {named.name} has what came before)"
        restarted = restarted if live != named else ""
        part = live.with_name(live.name + ".part")
        if live.is_file():
            return live, restarted.strip(" ()")
        if not part.is_file():
            raise ValueError(
                f"live_recording={str(live)!r}: neither it nor {part.name} exists "
                "(is the recorder running?)"
            )
        stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
        try:  # a recorder that has just started has no complete chunk yet
            snapshot, count = recover_recording(
                part, part.with_name(f"{live.stem}.snapshot-{stamp}.mcap")
            )
        except RecordingError as exc:
            raise ValueError(f"live_recording: {exc}") from None
        return snapshot, f"snapshot of {part.name} ({count} messages){restarted}"

    def paths_for(self, goal) -> tuple[Path | None, Path]:
        """(model to compare with, report folder); a goal's own paths only under the roots."""
        roots = self.config["read_roots"]
        model = (
            inside("model", goal.model, roots, ROOTS_HINT)
            if goal.model
            else (self.config["model"] or None)
        )
        root = self.config["report_root"]
        report_dir = (
            inside("report_dir", goal.report_dir, [root], ROOTS_HINT)
            if goal.report_dir
            else Path(root) / datetime.now().strftime("%Y%m%d-%H%M%S-%f")
        )
        return model, report_dir

    def execute(self, goal_handle) -> Sim2Real.Result:
        from afm_core.sim2real.diagnose import run_sim2real

        goal, result = goal_handle.request, Sim2Real.Result()
        result.heldout_reduction = math.nan
        if not self._busy.acquire(blocking=False):
            goal_handle.abort()
            result.message = "refused: another diagnosis is running"
            return result
        try:
            try:
                recording, note = self.recording_for(goal)
                model, report_dir = self.paths_for(goal)
            except ValueError as exc:
                goal_handle.abort()
                result.message = f"refused: {exc}"
                return result

            def progress(phase: str) -> None:
                if goal_handle.is_cancel_requested:
                    raise Cancelled()
                goal_handle.publish_feedback(Sim2Real.Feedback(phase=str(phase)))

            try:
                # a snapshot ends wherever the recorder had got to: its last command may lack
                # its data
                diagnosis = run_sim2real(
                    recording,
                    model,
                    report_dir,
                    progress=progress,
                    missing_data="skip" if note else "error",
                    effects=list(goal.effects),
                )
            except Cancelled:
                goal_handle.canceled()
                result.message = (
                    "cancelled; nothing written beyond what the report folder already had"
                )
                return result
            except (ValueError, OSError, RuntimeError) as exc:
                goal_handle.abort()
                result.message = f"failed: {exc}"
                return result
            result.success = True
            result.missing_physics = diagnosis.missing_physics
            by_name = {c.name: c for c in diagnosis.candidates}
            result.effects = [by_name[name].words for name in diagnosis.chosen if name in by_name]
            result.summary = diagnosis.summary()
            result.report = str(report_dir / "report.md")
            updated = report_dir / "updated_config.yaml"
            result.updated_config = str(updated) if updated.is_file() else ""
            reduction = diagnosis.heldout.get("excess_reduction") if diagnosis.chosen else None
            result.heldout_reduction = float(reduction) if reduction is not None else math.nan
            result.message = "; ".join(
                part
                for part in (f"verdict: {diagnosis.verdict}", note, f"report in {report_dir}")
                if part
            )
            goal_handle.succeed()
            return result
        finally:
            self._busy.release()


def main(args=None):
    return run(Sim2RealNode, "sim2real", args, threads=2)  # ValueError at start: exit 2


if __name__ == "__main__":
    raise SystemExit(main())
