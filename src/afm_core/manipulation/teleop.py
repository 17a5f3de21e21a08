"""Teleoperation: a stream of velocity commands from a person turned into bounded tip moves.

Book 2.2.2 and 7.1.2 (the operator's joystick with force feedback). Nothing here moves anything:
`TeleopController.step` says which short segment the tip should run next, and the caller (the
teleop node) runs it on the instrument (one MoveTip per segment, lifted or in contact).

The bounds, applied in this order on every step of `period` seconds:

* speed: a command faster than `max_speed` keeps its direction at `max_speed` (clip "speed");
* acceleration: the velocity changes by at most `max_acceleration` x period per step, so a
  jump of the stick never jerks the piezos (a stop is limited the same way, except the
  dead-man stop and `stop()`, which are immediate);
* dead-man: a segment never runs past `command_timeout` after the newest command, so with no
  command for that long the tip stands still at that moment (not a period later), and the
  velocity is reset (a later command starts from rest);
* range: a segment that would leave the scanner range [margin, range - margin] on an axis
  ends on its edge, and the velocity's outward part on that axis is dropped (the tip slides
  along the edge); the clip is reported. A tip already outside the band (margin > 0) may move
  back in but never further out.

Frames: commands are velocities in the afm_task frame (what the operator sees); segments are
commanded scanner positions (afm_scanner). A displacement d in the task frame is the command
inv(M) d, M the calibration's scanner matrix (true displacement per commanded one, as
push_steps.task_to_command uses), so the tip moves as asked in the task frame.

Force feedback (`segment_wrench`): the force the sample exerts on the tip during a contact
segment, from its force trace as execute.force_summary converts it: lateral force = torsion x
lateral_spring_constant / tip_height, positive resisting the motion, so along -u (u the
segment's task-frame direction); normal force = deflection x normal_spring_constant, along +z
(the sample pushes the tip up). Means over the segment's samples: one value per segment, what a
haptic device renders at the segment rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from afm_core import checks
from afm_core.instrument import ScannerLimits
from afm_core.manipulation.execute import cantilever_forces

# s without a command after which the tip stands still (issue 33: "no command for 0.5 s")
DEFAULT_COMMAND_TIMEOUT = 0.5


@dataclass(frozen=True)
class TeleopSettings:
    """The operator's envelope (SI units)."""

    max_speed: float = 1e-6  # m/s of the tip in the task frame
    # m/s^2: full speed from rest in 0.05 s, one segment at the default rate
    max_acceleration: float = 20e-6
    command_timeout: float = DEFAULT_COMMAND_TIMEOUT  # s, dead-man
    period: float = 0.05  # s per segment (20 Hz)
    range_margin: float = 0.0  # m kept clear of each edge of the scanner range

    def validate(self, limits: ScannerLimits = ScannerLimits()) -> None:
        checks.positive("max_speed", self.max_speed, "m/s")
        if self.max_speed > limits.max_speed:
            raise ValueError(
                f"max_speed={self.max_speed:.4e} m/s: must be at most the slew limit "
                f"{limits.max_speed:.4e} m/s"
            )
        checks.positive("max_acceleration", self.max_acceleration, "m/s^2")
        checks.positive("command_timeout", self.command_timeout, "s")
        checks.positive("period", self.period, "s")
        checks.non_negative("range_margin", self.range_margin, "m")
        if 2 * self.range_margin >= min(limits.range_x, limits.range_y):
            raise ValueError(
                f"range_margin={self.range_margin:.4e} m: leaves no room in the scanner range "
                f"({limits.range_x:.4e} x {limits.range_y:.4e} m)"
            )


@dataclass(frozen=True)
class Segment:
    """One move to run: commanded (scanner) start and end, in `duration` s, in contact or
    lifted; `velocity` the task-frame velocity it realises."""

    start: tuple[float, float]
    end: tuple[float, float]
    duration: float
    velocity: tuple[float, float]
    contact: bool

    @property
    def speed(self) -> float:
        """m/s of the commanded motion (what MoveTip's speed takes)."""
        return math.dist(self.start, self.end) / self.duration


@dataclass(frozen=True)
class Step:
    """What `step` decided: a segment (None: the tip stands still) and why not, if so."""

    segment: Segment | None
    clip: str = ""  # a bound that changed the command this step ("" none)
    stop: str = ""  # why the tip stopped this step ("" it did not)


class TeleopController:
    """Velocity commands in, bounded segments out (module docstring). Times are the caller's
    clock in s (monotonic wall time in the node: the operator's time)."""

    def __init__(
        self,
        settings: TeleopSettings = TeleopSettings(),
        limits: ScannerLimits = ScannerLimits(),
        scanner_matrix=None,
    ):
        settings.validate(limits)
        self.settings = settings
        self.limits = limits
        matrix = np.eye(2) if scanner_matrix is None else np.asarray(scanner_matrix, float)
        if matrix.shape != (2, 2) or not np.all(np.isfinite(matrix)):
            raise ValueError(f"scanner_matrix={matrix.tolist()}: need a finite 2x2 matrix")
        self.matrix = matrix
        self.inverse = np.linalg.inv(matrix)
        self.velocity = np.zeros(2)  # task frame, m/s, as realised by the last segment
        self.wanted = np.zeros(2)  # the newest command, speed-limited
        self.last_command: float | None = None
        self.contact = False

    def command(self, vx: float, vy: float, now: float) -> str:
        """Take a task-frame velocity command (m/s) at time `now`; returns the speed clip ("" if
        none). ValueError naming the field for a component that is not finite."""
        checks.finite("linear.x", vx, "m/s")
        checks.finite("linear.y", vy, "m/s")
        wanted = np.array([vx, vy], float)
        # scaled before the norm: hypot(1e308, 1e308) is inf, and wanted * (max / inf) was a
        # stop where the operator asked for full speed
        largest = float(np.max(np.abs(wanted)))
        speed = largest * float(np.hypot(*(wanted / largest))) if largest > 0 else 0.0
        clip = ""
        if speed > self.settings.max_speed:
            wanted = wanted / largest
            wanted *= self.settings.max_speed / float(np.hypot(*wanted))
            clip = (
                f"speed: {speed * 1e9:.0f} nm/s asked, limited to "
                f"{self.settings.max_speed * 1e9:.0f} nm/s (max_speed)"
            )
        self.wanted = wanted
        self.last_command = now
        return clip

    def stop(self) -> None:
        """Stand still now and forget the command (hand-back, a refused move)."""
        self.velocity = np.zeros(2)
        self.wanted = np.zeros(2)
        self.last_command = None

    def deadline(self) -> float | None:
        """When the newest command stops holding the tip in motion (None: no command)."""
        if self.last_command is None:
            return None
        return self.last_command + self.settings.command_timeout

    def step(self, now: float, position) -> Step:
        """The segment to run from the commanded scanner `position` (m) at time `now`. A
        position that is not finite stops the tip (the range clip cannot hold a NaN end, and
        a raise would end the caller's loop with the tip still held)."""
        if not np.all(np.isfinite(np.asarray(position, float))):
            self.stop()
            return Step(None, stop=f"position {tuple(position)} m is not finite: tip stopped")
        deadline = self.deadline()
        if deadline is None:
            return Step(None)
        if now >= deadline:
            moving = bool(np.any(self.velocity) or np.any(self.wanted))
            self.stop()
            stop = (
                f"dead-man: no command for {self.settings.command_timeout:g} s" if moving else ""
            )
            return Step(None, stop=stop)
        duration = min(self.settings.period, deadline - now)
        change = self.wanted - self.velocity
        largest = self.settings.max_acceleration * self.settings.period
        size = float(np.hypot(*change))
        if size > largest:
            change *= largest / size
        self.velocity = self.velocity + change
        start = np.asarray(position, float)
        end, clip = self._in_range(start, start + self.inverse @ (self.velocity * duration))
        if clip:  # the outward part is dropped: the velocity the clipped segment realises
            self.velocity = self.matrix @ ((end - start) / duration)
        if np.allclose(end, start, rtol=0.0, atol=1e-15):
            return Step(None, clip=clip)
        segment = Segment(
            (float(start[0]), float(start[1])),
            (float(end[0]), float(end[1])),
            duration,
            (float(self.velocity[0]), float(self.velocity[1])),
            self.contact,
        )
        return Step(segment, clip=clip)

    def _in_range(self, start: np.ndarray, end: np.ndarray) -> tuple[np.ndarray, str]:
        """`end` held inside [margin, range - margin] on each axis (never further out than
        `start` already is), and the clip in words ("" when none)."""
        margin = self.settings.range_margin
        clipped = end.copy()
        said = []
        for axis, (name, size) in enumerate(
            (("x", self.limits.range_x), ("y", self.limits.range_y))
        ):
            low = min(margin, start[axis])
            high = max(size - margin, start[axis])
            clipped[axis] = min(max(end[axis], low), high)
            if clipped[axis] != end[axis]:
                said.append(
                    f"{name}={end[axis] * 1e6:.4f} um would leave "
                    f"[{margin * 1e6:g}, {(size - margin) * 1e6:g}] um"
                )
        return clipped, ("range: " + "; ".join(said) + ", held at the edge") if said else ""


def segment_wrench(
    direction,
    lateral_torsion,
    vertical_deflection,
    lateral_spring_constant: float,
    normal_spring_constant: float,
    tip_height: float,
) -> np.ndarray:
    """(Fx, Fy, Fz) in N on the tip during a contact segment moving along task-frame
    `direction` (module docstring); zeros for an empty trace or a segment that did not move.
    Samples that are not finite (a DAQ glitch) are left out of the means, and a component
    with no finite sample is 0: a haptic device must never be handed a NaN force to render."""
    checks.positive("tip_height", tip_height, "m")
    torsion = np.asarray(lateral_torsion, float)
    deflection = np.asarray(vertical_deflection, float)
    u = np.asarray(direction, float)
    norm = float(np.hypot(*u))
    if torsion.size == 0 or not (math.isfinite(norm) and norm > 0.0):
        return np.zeros(3)
    lateral_n, normal_n = cantilever_forces(
        torsion, deflection, lateral_spring_constant, normal_spring_constant, tip_height
    )
    lateral, normal = _finite_mean(lateral_n), _finite_mean(normal_n)
    return np.array([-lateral * u[0] / norm, -lateral * u[1] / norm, normal])


def _finite_mean(values: np.ndarray) -> float:
    finite = values[np.isfinite(values)]
    return float(np.mean(finite)) if finite.size else 0.0


@dataclass(frozen=True)
class JoyMapping:
    """Which sensor_msgs/Joy axes and buttons drive the tip. Defaults: the ROS `joy` driver on
    an Xbox-style pad (left stick: axis 0 is +1 to the LEFT, axis 1 is +1 UP, so x takes axis 0
    with scale -1); hold LB (button 4) to move, press RB (button 5) to toggle contact. An axis
    at full deflection asks for scale x max_speed; |axis| below `deadzone` is 0 (stick noise).
    A button index of -1: no such button (always enabled / no toggle)."""

    axis_x: int = 0
    axis_y: int = 1
    scale_x: float = -1.0
    scale_y: float = 1.0
    deadzone: float = 0.05
    enable_button: int = 4
    contact_button: int = 5


@dataclass(frozen=True)
class JoyCommand:
    vx: float  # m/s, task frame
    vy: float
    contact_pressed: bool  # the contact button went down in this message
    contact_down: bool  # it is down (pass it back as contact_was_down with the next message)


def joy_command(
    axes, buttons, mapping: JoyMapping, max_speed: float, contact_was_down: bool
) -> JoyCommand:
    """The velocity a Joy message asks for (0 while the enable button is not held), and whether
    the contact button was pressed now (down here, up in the previous message). ValueError
    naming the index when the message has no such axis or button."""
    for name, index, values in (
        ("axis_x", mapping.axis_x, axes),
        ("axis_y", mapping.axis_y, axes),
        ("enable_button", mapping.enable_button, buttons),
        ("contact_button", mapping.contact_button, buttons),
    ):
        if index >= len(values):
            raise ValueError(
                f"joy {name}={index}: the message has only {len(values)} "
                f"{'axes' if values is axes else 'buttons'}"
            )
    contact_down = mapping.contact_button >= 0 and bool(buttons[mapping.contact_button])
    pressed = contact_down and not contact_was_down
    if mapping.enable_button >= 0 and not buttons[mapping.enable_button]:
        return JoyCommand(0.0, 0.0, pressed, contact_down)

    def speed(index: int, scale: float) -> float:
        value = float(axes[index])
        if not math.isfinite(value) or abs(value) < mapping.deadzone:
            return 0.0
        return max(-1.0, min(1.0, value)) * scale * max_speed

    return JoyCommand(
        speed(mapping.axis_x, mapping.scale_x),
        speed(mapping.axis_y, mapping.scale_y),
        pressed,
        contact_down,
    )
