"""sim2real: record a session from any instrument, read it back as operations, and re-run
the same commands in the simulator (issue 8's I/O layer)."""

from afm_core.sim2real.resimulate import (
    Resimulation,
    check_config_matches,
    check_operation,
    load_sim_config,
    resimulate,
)
from afm_core.sim2real.session import Operation, SessionError, operation_from_call
from afm_core.sim2real.session_reader import (
    OperationStream,
    indent_request_from_trace,
    read_operations,
)
from afm_core.sim2real.session_writer import RecordingInstrument, SessionWriter

__all__ = [
    "Operation",
    "OperationStream",
    "RecordingInstrument",
    "Resimulation",
    "SessionError",
    "SessionWriter",
    "check_config_matches",
    "check_operation",
    "indent_request_from_trace",
    "load_sim_config",
    "operation_from_call",
    "read_operations",
    "resimulate",
]
