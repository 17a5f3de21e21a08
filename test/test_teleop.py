"""Teleoperation core (afm_core.manipulation.teleop, .teleop_model) against closed forms."""

import math

import numpy as np
import pytest

from afm_core.instrument import ScannerLimits
from afm_core.manipulation.execute import force_summary
from afm_core.manipulation.teleop import (
    JoyMapping,
    TeleopController,
    TeleopSettings,
    joy_command,
    segment_wrench,
)
from afm_core.manipulation.teleop_model import BelievedTip, PushPredictor
from afm_core.physics.contact import ContactParams

# a*T = 0.5 um/s: full speed (1 um/s) from rest in two steps
SETTINGS = TeleopSettings(max_speed=1e-6, max_acceleration=1e-5, period=0.05)
LIMITS = ScannerLimits()


def run(controller, position, times):
    segments = []
    for t in times:
        step = controller.step(t, position)
        if step.segment is not None:
            segments.append(step)
            position = step.segment.end
    return segments, np.array(position)


def test_velocity_ramps_at_the_acceleration_limit_to_the_command():
    controller = TeleopController(SETTINGS, LIMITS)
    u = np.array([0.6, 0.8])
    assert controller.command(*(0.8e-6 * u), 0.0) == ""
    segments, end = run(controller, (50e-6, 50e-6), [0.0, 0.05, 0.10, 0.15])
    speeds = [math.hypot(*s.segment.velocity) for s in segments]
    # closed form: v_k = min(k a T, |v|) with a T = 0.5 um/s
    assert speeds == pytest.approx([0.5e-6, 0.8e-6, 0.8e-6, 0.8e-6], rel=1e-12)
    travelled = sum(speeds) * SETTINGS.period
    assert end - np.array([50e-6, 50e-6]) == pytest.approx(travelled * u, rel=1e-12, abs=1e-18)
    for s in segments:
        assert s.segment.speed == pytest.approx(math.hypot(*s.segment.velocity), rel=1e-12)
        assert not s.segment.contact and s.clip == "" and s.stop == ""


def test_a_command_above_the_speed_limit_keeps_its_direction_and_is_reported():
    controller = TeleopController(SETTINGS, LIMITS)
    clip = controller.command(3e-6, -4e-6, 0.0)
    assert "speed: 5000 nm/s asked, limited to 1000 nm/s" in clip
    assert controller.wanted == pytest.approx([0.6e-6, -0.8e-6], rel=1e-12)
    segments, _ = run(controller, (50e-6, 50e-6), [0.0, 0.05, 0.1])
    assert math.hypot(*segments[-1].segment.velocity) == pytest.approx(1e-6, rel=1e-12)


def test_dead_man_no_segment_runs_past_the_timeout_after_the_last_command():
    controller = TeleopController(SETTINGS, LIMITS)
    controller.command(1e-6, 0.0, 0.0)
    ticks = [0.013 + k * SETTINGS.period for k in range(15)]  # not aligned with the command
    steps = [controller.step(t, (50e-6, 50e-6)) for t in ticks]
    moving = [(t, s.segment) for t, s in zip(ticks, steps) if s.segment is not None]
    last_t, last = moving[-1]
    # the last segment ends exactly at command time + timeout, and nothing runs after it
    assert last_t + last.duration == pytest.approx(SETTINGS.command_timeout, abs=1e-12)
    assert last.duration < SETTINGS.period
    stops = [s.stop for s in steps if s.stop]
    assert stops == ["dead-man: no command for 0.5 s"]  # said once, when it stopped
    assert not controller.velocity.any() and controller.last_command is None
    # a new command starts from rest (the acceleration limit again)
    controller.command(1e-6, 0.0, 2.0)
    first = controller.step(2.0, (50e-6, 50e-6)).segment
    assert first.velocity[0] == pytest.approx(0.5e-6, rel=1e-12)


def test_a_move_that_would_leave_the_range_ends_on_the_edge_and_slides_along_it():
    controller = TeleopController(SETTINGS, LIMITS)
    controller.command(1e-6, 1e-6, 0.0)
    controller.velocity = controller.wanted.copy()  # already at the (limited) speed
    start = (LIMITS.range_x - 10e-9, 40e-6)
    step = controller.step(0.0, start)
    vy = 1e-6 / math.sqrt(2)  # the command speed-limited to 1 um/s along the diagonal
    assert step.segment.end[0] == LIMITS.range_x  # held at the edge, never past it
    assert step.segment.end[1] == pytest.approx(40e-6 + vy * SETTINGS.period, rel=1e-12)
    assert step.clip.startswith("range: x=") and "would leave [0, 110] um" in step.clip
    # the outward part is dropped: along the edge only from now on, still reported
    assert step.segment.velocity[0] == pytest.approx(200e-9, rel=1e-9)  # 10 nm in 50 ms
    nxt = controller.step(0.05, step.segment.end)
    assert nxt.segment.end[0] == LIMITS.range_x and nxt.clip.startswith("range: x=")
    # the lower corner: both axes clipped at 0
    low = TeleopController(SETTINGS, LIMITS)
    low.command(-1e-6, -1e-6, 0.0)
    low.velocity = low.wanted.copy()
    corner = low.step(0.0, (5e-9, 5e-9))
    assert corner.segment.end == (0.0, 0.0) and "x=" in corner.clip and "y=" in corner.clip


def test_a_tip_outside_the_margin_may_move_back_in_but_not_further_out():
    settings = TeleopSettings(max_speed=1e-6, max_acceleration=1.0, range_margin=1e-6)
    out = TeleopController(settings, LIMITS)
    out.command(-1e-6, 0.0, 0.0)
    assert out.step(0.0, (0.5e-6, 50e-6)).segment is None  # stays at 0.5 um, not pulled in
    back = TeleopController(settings, LIMITS)
    back.command(1e-6, 0.0, 0.0)
    step = back.step(0.0, (0.5e-6, 50e-6))
    assert step.clip == "" and step.segment.end[0] == pytest.approx(0.55e-6, rel=1e-12)


def test_the_scanner_matrix_maps_the_task_displacement_to_the_command():
    matrix = np.array([[1.1, 0.05], [-0.02, 0.9]])
    controller = TeleopController(
        TeleopSettings(max_speed=1e-6, max_acceleration=1.0), LIMITS, matrix
    )
    controller.command(0.3e-6, -0.4e-6, 0.0)
    seg = controller.step(0.0, (50e-6, 50e-6)).segment
    commanded = np.subtract(seg.end, seg.start)
    # the true (task) displacement M c is the commanded velocity x period
    assert matrix @ commanded == pytest.approx(np.array([0.3e-6, -0.4e-6]) * 0.05, rel=1e-9)


def test_stop_and_bad_input():
    controller = TeleopController(SETTINGS, LIMITS)
    controller.command(1e-6, 0.0, 0.0)
    controller.step(0.0, (50e-6, 50e-6))
    controller.stop()
    assert controller.step(0.01, (50e-6, 50e-6)).segment is None
    with pytest.raises(ValueError, match="linear.x"):
        controller.command(float("nan"), 0.0, 0.1)
    with pytest.raises(ValueError, match="max_speed=.*slew limit"):
        TeleopController(TeleopSettings(max_speed=1e-3), LIMITS)
    with pytest.raises(ValueError, match="range_margin"):
        TeleopController(TeleopSettings(range_margin=60e-6), LIMITS)


def test_the_wrench_is_the_trace_force_resisting_the_motion_and_pressing_up():
    torsion, deflection = np.full(50, 2e-3), np.full(50, 5e-8)
    k_lat, k_n, height = 1e-9, 0.2, 10e-6
    force = segment_wrench((3.0, 4.0), torsion, deflection, k_lat, k_n, height)
    lateral = 2e-3 * k_lat / height  # 0.2 nN
    assert force == pytest.approx([-0.6 * lateral, -0.8 * lateral, 5e-8 * k_n], rel=1e-12)

    class Trace:
        lateral_torsion, vertical_deflection = torsion, deflection
        lateral_spring_constant, normal_spring_constant = k_lat, k_n

    # the same conversion as the push executor's (a constant trace: peak = mean)
    assert math.hypot(*force[:2]) == pytest.approx(force_summary(Trace, height)[0], rel=1e-12)
    assert force[2] == pytest.approx(force_summary(Trace, height)[1], rel=1e-12)
    assert segment_wrench((1, 0), [], [], k_lat, k_n, height).tolist() == [0.0, 0.0, 0.0]


def test_joy_mapping_enable_button_deadzone_and_contact_toggle():
    mapping = JoyMapping()
    held = [0, 0, 0, 0, 1, 0]
    cmd = joy_command([0.5, -1.0], held, mapping, 1e-6, False)
    assert (cmd.vx, cmd.vy) == pytest.approx((-0.5e-6, -1e-6), rel=1e-12)
    assert joy_command([0.02, 0.04], held, mapping, 1e-6, False).vx == 0.0  # deadzone
    released = joy_command([0.5, -1.0], [0] * 6, mapping, 1e-6, False)
    assert (released.vx, released.vy) == (0.0, 0.0)
    press = joy_command([0, 0], [0, 0, 0, 0, 1, 1], mapping, 1e-6, False)
    assert press.contact_pressed and press.contact_down
    still = joy_command([0, 0], [0, 0, 0, 0, 1, 1], mapping, 1e-6, True)
    assert not still.contact_pressed
    with pytest.raises(ValueError, match="enable_button=4: the message has only 2 buttons"):
        joy_command([0, 0], [0, 0], mapping, 1e-6, False)


class Mark:
    def __init__(self, id, x, y, radius=100e-9, kind="sphere", sigma=10e-9):
        self.id, self.x, self.y, self.radius, self.kind = id, x, y, radius, kind
        self.covariance = np.diag([sigma**2, (sigma / 2) ** 2])
        self.length = self.orientation = 0.0


def test_the_predictor_pushes_a_sphere_head_on_to_contact_distance():
    predictor = PushPredictor(ContactParams(tip_radius=50e-9))
    predictor.load([Mark(3, 10e-6, 10e-6), Mark(4, 12e-6, 10e-6)])
    # a straight push through the centre: the sphere stays on the line and ends R_P + R_T
    # ahead of the tip
    assert predictor.push((9.7e-6, 10e-6), (10.1e-6, 10e-6), 0.4) == [3]
    (obj,) = predictor.objects()
    assert obj.id == 3 and obj.kind == "sphere" and obj.sigma == pytest.approx(10e-9)
    assert obj.x == pytest.approx(10.1e-6 + 150e-9, abs=1e-9)
    assert obj.y == pytest.approx(10e-6, abs=1e-12)
    # a path that passes 500 nm away moves nothing
    assert predictor.push((10.5e-6, 10.5e-6), (11e-6, 10.5e-6), 0.5) == []
    assert [o.id for o in predictor.objects(only_pushed=False)] == [3, 4]


def test_believed_tip_maps_commands_through_the_pose_and_the_scanner_matrix():
    tip = BelievedTip(2 * np.eye(2))
    assert tip.to_task((1e-6, 2e-6)) == pytest.approx([1e-6, 2e-6])  # before a pose: identity
    tip.observe((10e-6, 20e-6), (11e-6, 19e-6))
    assert tip.to_task((12e-6, 19e-6)) == pytest.approx([12e-6, 20e-6], rel=1e-12)
