"""A recorded session as an ordered stream of operations (command + its measurement): the
driver's vocabulary and the `Operation`.

The driver node publishes, for every action it executes, a TipCommand on /afm/tip_command
(stamped with the instrument time at which the command started) and then the measurement:
a RasterScan on /afm/scan, a ScanLine on /afm/scan_line or a ForceTrace on /afm/force_trace
(a lifted move has none), and in simulation a GroundTruth on /afm/ground_truth.
session_writer.py writes exactly those messages from any core `Instrument`, without ROS
(`RecordingInstrument`, `SessionWriter`); session_reader.py reads a recording back as
`Operation`s in command order (`read_operations`).

Units are SI throughout (m, s, N, m/s). Times of read operations are seconds since the first
command of the recording, on the recording's instrument clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from afm_core.instrument import (
    ForceTraceData,
    LineRequest,
    RasterScanData,
    ScanLineData,
    ScanRequest,
)
from afm_core.recording import QosDescription, RecordingError
from afm_core.recording.qos import RMW_DURATION_INFINITE_NS

TIP_COMMAND = "/afm/tip_command"
SCAN = "/afm/scan"
SCAN_LINE = "/afm/scan_line"
FORCE_TRACE = "/afm/force_trace"
GROUND_TRUTH = "/afm/ground_truth"

TYPES = {
    TIP_COMMAND: "afm_msgs/msg/TipCommand",
    SCAN: "afm_msgs/msg/RasterScan",
    SCAN_LINE: "afm_msgs/msg/ScanLine",
    FORCE_TRACE: "afm_msgs/msg/ForceTrace",
    GROUND_TRUTH: "afm_msgs/msg/GroundTruth",
}


# The QoS the driver offers (afm_ros.qos_profiles), in the form our recorder stores what it
# discovers (history and depth are not sent over the wire: "unknown", 0; durations infinite),
# so a replay republishes each topic as the driver did: commands and scans reliable and
# latched, streams reliable and volatile, truth reliable and latched.
def _offered(reliability: str, durability: str) -> QosDescription:
    return QosDescription(
        history="unknown",
        depth=0,
        reliability=reliability,
        durability=durability,
        liveliness="automatic",
        deadline_ns=RMW_DURATION_INFINITE_NS,
        lifespan_ns=RMW_DURATION_INFINITE_NS,
        liveliness_lease_duration_ns=RMW_DURATION_INFINITE_NS,
    )


OFFERED_QOS = {
    TIP_COMMAND: _offered("reliable", "transient_local"),
    SCAN: _offered("reliable", "transient_local"),
    SCAN_LINE: _offered("reliable", "volatile"),
    FORCE_TRACE: _offered("reliable", "volatile"),
    GROUND_TRUTH: _offered("reliable", "transient_local"),
}

# TipCommand.kind constants (afm_msgs/msg/TipCommand.msg) <-> Operation.kind
KIND_NAMES = {0: "move", 1: "scan_line", 2: "raster", 3: "push", 4: "indent"}
KIND_CODES = {name: code for code, name in KIND_NAMES.items()}
# where each kind's measurement is published, and the ForceTrace.task it carries
DATA_TOPIC = {"scan_line": SCAN_LINE, "raster": SCAN, "push": FORCE_TRACE, "indent": FORCE_TRACE}
TRACE_TASK = {"push": "push", "indent": "indent"}
OBJECT_KINDS = {"sphere": 0, "tube": 1, "rod": 2, "pit": 3, "electrode": 4}  # ObjectState.kind

FRAME_SCANNER = "afm_scanner"
FRAME_TASK = "afm_task"

Request = ScanRequest | LineRequest | dict
Data = RasterScanData | ScanLineData | ForceTraceData | None


class SessionError(RecordingError, ValueError):
    """A recording cannot be read as a session (or written as one); the message names the
    file, the topic and the problem."""


@dataclass
class Operation:
    """One command the instrument executed, with what it measured.

    kind: "move", "push", "scan_line", "raster" or "indent".
    start_time: s when the command started, on the session's instrument clock (read and
        simulated operations: relative to the recording's first command).
    start, end: m, commanded scanner-frame positions (a scan line: its commanded ends; an
        indent: where it indents; a move, push or raster: where the tip was commanded before
        and after).
    speed: m/s along the path (a raster: its path length / duration, as the driver reports it;
        an indent: 0). duration: s the command took, including any approach move.
    request: what reproduces it: a ScanRequest, a LineRequest, or a dict
        {x, y, speed, contact} (move, push) / {x, y, force, dwell} (indent), in m, m/s, N, s.
    data: the measurement (RasterScanData, ScanLineData, ForceTraceData; None for a move);
        its start_time is on the same clock as the operation's.
    landmark_id: the landmark a scan line observes (-1: none); pair_id: a raster's pair.
    lag: s, simulated operations only: how much later than recorded the simulator could start it.
    truth: simulated operations only: the simulator's ground truth after the operation.
    """

    index: int
    kind: str
    start_time: float
    start: tuple[float, float]
    end: tuple[float, float]
    speed: float
    duration: float
    request: Request = field(repr=False)
    data: Data = field(repr=False)
    landmark_id: int = -1
    pair_id: str = ""
    lag: float = 0.0
    truth: dict | None = field(default=None, repr=False)

    @property
    def end_time(self) -> float:
        return self.start_time + self.duration


def operation_from_call(
    index: int,
    kind: str,
    request: Request,
    data: Data,
    *,
    start_time: float,
    end_time: float,
    start_position: tuple[float, float],
    end_position: tuple[float, float],
    landmark_id: int = -1,
    pair_id: str = "",
) -> Operation:
    """The Operation (= the TipCommand fields) for one instrument call, filled as the driver
    fills its TipCommand: start/end are where the scanner was commanded before and after,
    except a scan line (its commanded ends) and an indent (its position); the speed is the
    requested one, a raster's path length / duration, an indent's 0."""
    duration = end_time - start_time
    start, end = tuple(map(float, start_position)), tuple(map(float, end_position))
    if kind in ("move", "push"):
        speed = float(request["speed"])
    elif kind == "scan_line":
        start, end, speed = (
            (request.start_x, request.start_y),
            (request.end_x, request.end_y),
            request.speed,
        )
    elif kind == "raster":
        fast_size = request.size_x if request.scan_angle_deg == 0.0 else request.size_y
        path_length = 2 * fast_size * request.lines + math.dist(
            start, (request.origin_x, request.origin_y)
        )
        speed = path_length / duration if duration > 0 else 0.0
    elif kind == "indent":
        start = end = (float(request["x"]), float(request["y"]))
        speed = 0.0
    else:
        raise ValueError(f"kind={kind!r}: expected one of {sorted(KIND_CODES)}")
    return Operation(
        index=index,
        kind=kind,
        start_time=float(start_time),
        start=start,
        end=end,
        speed=float(speed),
        duration=float(duration),
        request=request,
        data=data,
        landmark_id=int(landmark_id),
        pair_id=str(pair_id),
    )
