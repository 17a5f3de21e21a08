"""The teleop node's parameters (defaults: afm_core.manipulation.teleop)."""

from __future__ import annotations

from afm_core.instrument import ScannerLimits
from afm_core.manipulation.execute import TIP_HEIGHT
from afm_core.manipulation.plans import DEFAULT_TIP_RADIUS
from afm_core.manipulation.teleop import JoyMapping, TeleopSettings
from afm_core.parameters import Parameter, ParameterTable

_SETTINGS = TeleopSettings()
_JOY = JoyMapping()
_SLEW = ScannerLimits().max_speed

PARAMETERS = ParameterTable(
    Parameter(
        "calibration_file",
        "",
        "Calibration YAML (afm calibrate): its scanner matrix maps task-frame velocities to "
        "scanner commands; empty: identity.",
    ),
    Parameter(
        "max_speed",
        _SETTINGS.max_speed,
        "Speed limit of the tip in the task frame; a faster command keeps its direction.",
        unit="m/s",
        minimum=0.0,
        above_minimum=True,
        maximum=_SLEW,
        runtime=True,
    ),
    Parameter(
        "max_acceleration",
        _SETTINGS.max_acceleration,
        "Largest change of the tip's velocity per second (rate limit).",
        unit="m/s^2",
        minimum=0.0,
        above_minimum=True,
        runtime=True,
    ),
    Parameter(
        "command_timeout",
        _SETTINGS.command_timeout,
        "Dead-man: with no command for this long the tip stands still.",
        unit="s",
        minimum=0.0,
        above_minimum=True,
        maximum=5.0,
        runtime=True,
    ),
    Parameter(
        "rate",
        1.0 / _SETTINGS.period,
        "Segments per second (each one MoveTip goal).",
        unit="Hz",
        minimum=1.0,
        maximum=100.0,
    ),
    Parameter(
        "range_margin",
        _SETTINGS.range_margin,
        "Kept clear of each edge of the scanner range.",
        unit="m",
        minimum=0.0,
        maximum=10e-6,
    ),
    Parameter(
        "twist_scale",
        1.0,
        "Twist linear.x/.y are multiplied by this (1: m/s as sent; 1e-6: the panel's 1 is "
        "1 um/s).",
        minimum=0.0,
        above_minimum=True,
        runtime=True,
    ),
    Parameter(
        "tip_radius",
        DEFAULT_TIP_RADIUS,
        "Effective contact radius of the tip in the push model's prediction.",
        unit="m",
        minimum=0.0,
        above_minimum=True,
    ),
    Parameter(
        "tip_height",
        TIP_HEIGHT,
        "Lever arm of the lateral force: lateral force = torsion x lateral_spring_constant / "
        "tip_height.",
        unit="m",
        minimum=0.0,
        above_minimum=True,
    ),
    Parameter("joy_axis_x", _JOY.axis_x, "Joy axis that drives x.", minimum=0, runtime=True),
    Parameter("joy_axis_y", _JOY.axis_y, "Joy axis that drives y.", minimum=0, runtime=True),
    Parameter(
        "joy_scale_x",
        _JOY.scale_x,
        "x speed at full deflection, in units of max_speed (sign: direction).",
        minimum=-1.0,
        maximum=1.0,
        runtime=True,
    ),
    Parameter(
        "joy_scale_y",
        _JOY.scale_y,
        "y speed at full deflection, in units of max_speed (sign: direction).",
        minimum=-1.0,
        maximum=1.0,
        runtime=True,
    ),
    Parameter(
        "joy_deadzone",
        _JOY.deadzone,
        "Axis values below this in magnitude count as 0.",
        minimum=0.0,
        maximum=0.5,
        runtime=True,
    ),
    Parameter(
        "joy_enable_button",
        _JOY.enable_button,
        "Joy button held to move (released: velocity 0); -1: none.",
        minimum=-1,
        runtime=True,
    ),
    Parameter(
        "joy_contact_button",
        _JOY.contact_button,
        "Joy button that toggles contact / lifted when pressed; -1: none.",
        minimum=-1,
        runtime=True,
    ),
    Parameter(
        "server_timeout",
        10.0,
        "Longest wait for the driver's answer to a segment or an ownership request.",
        unit="s",
        minimum=0.0,
        above_minimum=True,
    ),
)

# running-node changes that go straight into the controller's settings (parameter -> field)
RUNTIME_SETTINGS = {
    "max_speed": "max_speed",
    "max_acceleration": "max_acceleration",
    "command_timeout": "command_timeout",
}
