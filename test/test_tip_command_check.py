"""Which reported TipCommands no driver can have run (action_instrument.tip_command_problem),
and that ActionInstrument.observe_command ignores them (the nano-hand and teleop follow
/afm/tip_command through it)."""

import math
from types import SimpleNamespace

import pytest

from afm_core.instrument import ScannerLimits
from afm_msgs.msg import TipCommand
from afm_ros.action_instrument import ActionInstrument, tip_command_problem

pytestmark = pytest.mark.ros

LIMITS = ScannerLimits()


def command(**fields) -> TipCommand:
    msg = TipCommand(
        kind=fields.pop("kind", TipCommand.MOVE), duration=fields.pop("duration", 1.0)
    )
    msg.header.stamp.sec = fields.pop("sec", 1000)
    msg.start.x, msg.start.y = fields.pop("start", (50e-6, 50e-6))
    msg.end.x, msg.end.y = fields.pop("end", (51e-6, 50e-6))
    assert not fields
    return msg


@pytest.mark.parametrize(
    "msg, says",
    [
        (command(), None),
        (command(end=(LIMITS.range_x, 0.0)), None),  # the range's corner is reachable
        (command(kind=42), "kind=42: not a TipCommand kind"),
        (command(sec=0), "header.stamp=0.0 s: must be after the epoch"),
        (command(duration=-1.0), "duration=-1.0: must be finite and >= 0"),
        (command(duration=math.inf), "duration=inf"),
        (command(end=(1.0, 50e-6)), "end.x=1.0000e+00 m: outside the scanner range"),
        (command(start=(50e-6, -1e-9)), "start.y=-1.0000e-09 m: outside the scanner range"),
        (command(end=(math.nan, 50e-6)), "end.x"),
    ],
)
def test_a_command_no_driver_can_have_run_is_named(msg, says):
    problem = tip_command_problem(msg, LIMITS)
    assert (problem is None) if says is None else (says in problem), problem


def test_observe_command_ignores_it_and_keeps_where_the_tip_was():
    errors = []
    node = SimpleNamespace(get_logger=lambda: SimpleNamespace(error=errors.append))
    instrument = ActionInstrument.__new__(ActionInstrument)  # no ROS clients needed here
    instrument.node, instrument.limits = node, LIMITS
    instrument._lock, instrument.time, instrument._commanded = (
        __import__("threading").Lock(),
        0,
        None,
    )
    instrument.last_command = None
    assert instrument.observe_command(command(sec=1000, end=(51e-6, 50e-6)))
    assert not instrument.observe_command(command(sec=2000, end=(1.0, 50e-6)))
    assert instrument.commanded_position() == (51e-6, 50e-6)
    assert instrument.time == 1001.0
    assert len(errors) == 1 and "end.x=1.0000e+00 m" in errors[0], errors
