"""DAQ backend against FakeDaq: calibration, clamps, feed-forward, images, timing, cancel,
refusals."""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest

from afm_core.daq import DaqCalibration, DaqInstrument, DaqUnavailable, FakeDaq, NidaqmxBoundary
from afm_core.instrument import LineRequest, ScannerLimits, ScanRequest

FS = 20e3


def calibration(**overrides) -> DaqCalibration:
    return DaqCalibration(sample_rate=FS, **overrides)


def to_metres(cal: DaqCalibration, volts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Invert the lateral calibration (identity feed-forward)."""
    return (
        (volts[0] - cal.x_offset_volts) / cal.x_volts_per_metre,
        (volts[1] - cal.y_offset_volts) / cal.y_volts_per_metre,
    )


def surface(cal: DaqCalibration, height, deflection=lambda x, y, z: np.zeros_like(x)) -> FakeDaq:
    """A fake card whose z monitor reports `height(x, y)` at the written position."""

    def respond(volts):
        x, y = to_metres(cal, volts)
        z = (
            (volts[2] - cal.z_offset_volts) / cal.z_volts_per_metre
            if cal.ao_z
            else np.zeros_like(x)
        )
        return np.vstack(
            [
                height(x, y) / cal.z_monitor_metres_per_volt + cal.z_monitor_offset_volts,
                deflection(x, y, z) / cal.deflection_metres_per_volt + cal.deflection_offset_volts,
            ]
        )

    return FakeDaq(respond)


def make(cal=None, height=lambda x, y: np.zeros_like(x), **kwargs):
    cal = cal or calibration()
    fake = surface(cal, height, **kwargs)
    return DaqInstrument(fake, cal, clock=fake.clock), fake, cal


def ramps(fake: FakeDaq) -> list[np.ndarray]:
    return [v for kind, v in fake.writes if kind == "ramp"]


def test_start_up_holds_the_zero_volt_position_and_configures_channels():
    inst, fake, cal = make()
    assert len(fake.writes) == 1 and fake.writes[0][0] == "static"
    assert fake.last_levels == pytest.approx([0.0, 0.0])  # the DAQ's power-up level
    assert inst.commanded_position() == pytest.approx((55e-6, 55e-6))
    assert fake.ao_channels == ["ao0", "ao1"] and fake.ai_channels == ["ai0", "ai1"]
    assert fake.sample_rate == FS and inst.time == 0.0


def test_move_volts_follow_the_calibration_and_the_speed():
    inst, fake, cal = make()
    result = inst.move_tip(20e-6, 30e-6, 50e-6)
    assert result.completed and (result.end_x, result.end_y) == pytest.approx((20e-6, 30e-6))
    volts = np.concatenate(ramps(fake), axis=1)
    assert volts[:, -1] == pytest.approx(
        [
            cal.x_offset_volts + 20e-6 * cal.x_volts_per_metre,
            cal.y_offset_volts + 30e-6 * cal.y_volts_per_metre,
        ]
    )
    x, y = to_metres(cal, volts)
    path = np.hypot(np.diff(x, prepend=55e-6), np.diff(y, prepend=55e-6))
    assert path.max() * FS <= 50e-6 * (1 + 1e-9)  # never faster than asked
    assert fake.now == pytest.approx(np.hypot(35e-6, 25e-6) / 50e-6, abs=2 / FS)
    assert all(r.shape[1] <= 0.1 * FS + 1 for r in ramps(fake))  # chunked for cancel


def test_contact_move_returns_the_force_trace():
    inst, fake, cal = make(deflection=lambda x, y, z: 1e-9 + 0 * x)
    result = inst.move_tip(56e-6, 55e-6, 10e-6, contact=True)
    trace = result.trace
    n = sum(r.shape[1] for r in ramps(fake))
    assert trace.task == "push" and len(trace.times) == n == len(trace.vertical_deflection)
    assert trace.vertical_deflection == pytest.approx(np.full(n, 1e-9))
    assert trace.times[-1] == pytest.approx(1e-6 / 10e-6, abs=2 / FS)
    assert trace.commanded_x[-1] == pytest.approx(56e-6) and trace.sample_rate == FS
    assert inst.move_tip(50e-6, 50e-6, 50e-6).trace is None


def test_no_sample_ever_leaves_the_clamps():
    cal = calibration(x_volts_limits=(-9.9, 2.0), y_volts_limits=(-9.9, 9.9))
    inst, fake, _ = make(cal)
    inst.raster_scan(ScanRequest(1e-6, 1e-6, 10e-6, 10e-6, 8, 8, line_rate=4.0))
    inst.local_scan(LineRequest(0.0, 0.0, 60e-6, 100e-6, 50, 80e-6))
    inst.move_tip(0.0, 110e-6, 100e-6)
    samples = fake.samples
    assert samples[0].min() >= -9.9 and samples[0].max() <= 2.0
    assert samples[1].min() >= -9.9 and samples[1].max() <= 9.9
    before = len(fake.writes)
    with pytest.raises(ValueError, match=r"target.*x output.*x_volts_limits"):
        inst.move_tip(100e-6, 50e-6, 50e-6)  # in range, but 8.1 V > 2 V clamp
    assert len(fake.writes) == before


def test_feed_forward_is_applied_to_every_commanded_sample():
    inst, fake, cal = make(calibration(x_feed_forward=lambda x: 1.1 * x))
    inst.move_tip(50e-6, 40e-6, 100e-6)
    vx, vy = fake.samples[:, -1]
    assert vx == pytest.approx(cal.x_offset_volts + cal.x_volts_per_metre * 1.1 * 50e-6)
    assert vy == pytest.approx(cal.y_offset_volts + cal.y_volts_per_metre * 40e-6)
    with pytest.raises(ValueError, match="x_volts_limits"):  # 1.1 * 100 um -> 9.9+ V: beyond +10 V
        inst.move_tip(105e-6, 40e-6, 100e-6)


class RecordingInverse:
    """A stateful feed-forward whose output depends on its history, as a hysteresis model's
    does."""

    def __init__(self):
        self.calls: list[np.ndarray] = []

    def apply(self, desired):
        self.calls.append(np.array(desired))
        return np.asarray(desired) + 1e-9 * len(self.calls)

    def reset(self):
        self.calls.clear()


def test_stateful_feed_forward_sees_exactly_the_written_path_once():
    inverse = RecordingInverse()
    inst, fake, cal = make(calibration(x_feed_forward=inverse))
    inst.move_tip(40e-6, 50e-6, 100e-6)
    inst.raster_scan(ScanRequest(30e-6, 30e-6, 5e-6, 5e-6, 4, 4, line_rate=5.0))
    assert len(inverse.calls) == len(fake.writes)  # validation ran on a copy of the state
    for m, ((_, volts), desired) in enumerate(zip(fake.writes, inverse.calls)):
        assert volts[0] == pytest.approx(
            cal.x_offset_volts + cal.x_volts_per_metre * (desired + 1e-9 * (m + 1))
        )


PLANE_A, PLANE_B = 1e-3, -2.5e-3  # m/m: distinct slopes so a transposed image fails


@pytest.mark.parametrize("angle", [0.0, 90.0])
def test_raster_reconstructs_the_surface_in_scanner_orientation(angle):
    ox, oy, size, n = 10e-6, 20e-6, 16e-6, 16
    bump = (ox + 11.5e-6, oy + 5.5e-6)  # centre of row 5, column 11

    def height(x, y):
        return (
            PLANE_A * (x - ox)
            + PLANE_B * (y - oy)
            + 50e-9 * np.exp(-((x - bump[0]) ** 2 + (y - bump[1]) ** 2) / (2 * 0.3e-6**2))
        )

    inst, fake, cal = make(height=height)
    lines_seen = []
    data = inst.raster_scan(
        ScanRequest(ox, oy, size, size, n, n, scan_angle_deg=angle, line_rate=2.0),
        on_line=lambda done, total: lines_seen.append((done, total)),
    )
    assert data.complete and data.height.shape == (n, n)
    assert lines_seen == [(i + 1, n) for i in range(n)]
    xc = (np.arange(n) + 0.5) * size / n
    expected = PLANE_A * xc[None, :] + PLANE_B * xc[:, None]
    far = np.ones((n, n), bool)
    far[3:8, 9:14] = False
    assert data.height[far] == pytest.approx(
        expected[far], abs=1e-11
    )  # within a sample step of slope
    residual = data.height - expected
    assert np.unravel_index(np.argmax(residual), residual.shape) == (5, 11)
    assert residual[5, 11] > 20e-9
    assert data.line_period == pytest.approx(0.5) and data.line_start_times == pytest.approx(
        np.arange(n) * 0.5
    )
    trace_x, trace_y = to_metres(cal, ramps(fake)[-1])
    fast = trace_x if angle == 0.0 else trace_y
    assert fast.min() >= (ox if angle == 0.0 else oy) - 1e-15
    assert fast.max() == pytest.approx((ox if angle == 0.0 else oy) + size)


def test_frame_down_scans_lines_top_first():
    inst, fake, cal = make()
    data = inst.raster_scan(
        ScanRequest(10e-6, 10e-6, 4e-6, 4e-6, 4, 4, slow_scan_up=False, line_rate=5.0)
    )
    assert data.line_start_times == pytest.approx([0.6, 0.4, 0.2, 0.0])
    lines = [v for v in ramps(fake) if v.shape[1] == 2 * 2000]
    _, first_y = to_metres(cal, lines[0])
    assert first_y[0] == pytest.approx(10e-6 + 3.5e-6)  # top row first
    _, last_y = to_metres(cal, lines[-1])
    assert last_y[0] == pytest.approx(10e-6 + 0.5e-6)


def test_local_scan_sample_count_and_timing():
    inst, fake, cal = make(height=lambda x, y: PLANE_A * x)
    inst.move_tip(1e-6, 2e-6, 100e-6)
    t_before = fake.now
    data = inst.local_scan(LineRequest(1e-6, 2e-6, 5e-6, 2e-6, 100, 10e-6))
    assert data.complete and len(data.times) == len(data.x) == len(data.height) == 100
    assert len(ramps(fake)[-1][0]) == 8000  # one synchronised ramp: 0.4 s at 20 kHz
    assert data.start_time == pytest.approx(t_before) and fake.now - t_before == pytest.approx(0.4)
    assert data.times == pytest.approx((np.arange(100) * 80 + 40.5) / FS)
    assert np.all(np.diff(data.x) > 0) and data.x[0] == pytest.approx(1e-6 + 0.02e-6, abs=1e-9)
    assert data.height == pytest.approx(PLANE_A * data.x, abs=1e-15)
    assert data.amplitude.size == 0


def test_cancel_mid_raster_stops_between_lines_and_holds():
    inst, fake, cal = make()
    done = []
    data = inst.raster_scan(
        ScanRequest(10e-6, 10e-6, 4e-6, 4e-6, 8, 8, line_rate=5.0),
        on_line=lambda d, t: done.append(d),
        should_stop=lambda: len(done) >= 3,
    )
    assert not data.complete and done == [1, 2, 3]
    assert np.all(np.isfinite(data.height[:3])) and np.all(np.isnan(data.height[3:]))
    assert sum(v.shape[1] == 4000 for v in ramps(fake)) == 3  # no fourth line was written
    kind, held = fake.writes[-1]
    assert kind == "static" and held[:, 0] == pytest.approx(fake.writes[-2][1][:, -1])
    x, y = to_metres(cal, held)
    assert inst.commanded_position() == pytest.approx((x[0], y[0]))


def test_cancel_during_a_move_holds_where_it_stopped():
    inst, fake, _ = make()
    calls = []
    result = inst.move_tip(
        5e-6, 5e-6, 50e-6, should_stop=lambda: calls.append(1) or len(calls) > 2
    )
    assert not result.completed and len(ramps(fake)) == 2
    assert fake.writes[-1][0] == "static" and fake.last_levels == pytest.approx(
        ramps(fake)[-1][:, -1]
    )
    assert 5e-6 < result.end_x < 55e-6


def z_calibration(**overrides):
    return calibration(ao_z="ao2", **overrides)


def test_indent_ramps_z_dwells_and_retracts():
    cal = z_calibration()
    inst, fake, _ = make(cal, deflection=lambda x, y, z: z)  # hard sample: deflection = z travel
    result = inst.indent(30e-6, 40e-6, 100e-9, 0.05)  # 100 nN / 0.2 N/m = 500 nm
    trace = result.trace
    assert result.completed and trace.task == "indent"
    assert trace.commanded_z.max() == pytest.approx(500e-9) and trace.commanded_z[
        -1
    ] == pytest.approx(0.0)
    assert trace.vertical_deflection.max() * cal.normal_spring_constant == pytest.approx(100e-9)
    assert np.sum(np.isclose(trace.commanded_z, 500e-9, rtol=0, atol=1e-15)) >= 0.05 * FS
    assert trace.commanded_x == pytest.approx(np.full(len(trace.times), 30e-6))
    assert fake.samples[2].max() == pytest.approx(
        cal.z_offset_volts + 500e-9 * cal.z_volts_per_metre
    )
    assert fake.samples[2, -1] == pytest.approx(cal.z_offset_volts)


def test_cancelled_indent_still_retracts():
    inst, fake, cal = make(z_calibration())
    stops = iter([False] * 10 + [True] * 1000)
    result = inst.indent(
        55e-6, 55e-6, 100e-9, 10.0, should_stop=lambda: next(stops)
    )  # stop in the dwell
    assert not result.completed and fake.writes[-1][0] == "ramp"
    assert (
        result.trace.commanded_z.max() == pytest.approx(500e-9)
        and result.trace.commanded_z[-1] == 0.0
    )
    assert fake.samples[2, -1] == pytest.approx(cal.z_offset_volts)
    assert fake.now < 2.0


def raster(**kw):
    base = dict(
        origin_x=10e-6,
        origin_y=10e-6,
        size_x=10e-6,
        size_y=10e-6,
        pixels_x=16,
        pixels_y=16,
        line_rate=1.0,
    )
    base.update(kw)
    return ScanRequest(**base)


BAD = [
    (
        "nan origin",
        lambda i: i.raster_scan(raster(origin_x=float("nan"))),
        r"origin_x=nan.*finite",
    ),
    (
        "outside range",
        lambda i: i.raster_scan(raster(origin_x=105e-6)),
        r"origin \+ size\.x.*1\.1000e-04",
    ),
    ("too many pixels", lambda i: i.raster_scan(raster(pixels_x=5000)), r"pixels_x=5000.*4096"),
    (
        "pixels vs sample rate",
        lambda i: i.raster_scan(raster(pixels_x=4000, line_rate=4.0)),
        r"pixels_x=4000.*sample_rate 20000 Hz.*2\.5 Hz",
    ),
    (
        "raster speed",
        lambda i: i.raster_scan(raster(line_rate=10.0)),
        r"line_rate=10.0.*slew limit",
    ),
    (
        "move speed",
        lambda i: i.move_tip(20e-6, 20e-6, 1e-3),
        r"speed=1\.0000e-03.*slew limit 1\.0000e-04",
    ),
    ("move target", lambda i: i.move_tip(-1e-6, 20e-6, 1e-5), r"target\.x=.*scanner range"),
    ("move nan", lambda i: i.move_tip(20e-6, float("nan"), 1e-5), r"target\.y=nan.*finite"),
    (
        "local samples",
        lambda i: i.local_scan(LineRequest(1e-6, 1e-6, 2e-6, 1e-6, 5000, 50e-6)),
        r"samples=5000.*only 400 DAQ samples",
    ),
    ("indent without z", lambda i: i.indent(20e-6, 20e-6, 1e-7, 0.0), r"ao_z"),
    ("indent force", lambda i: i.indent(20e-6, 20e-6, 2e-6, 0.0), r"force=2\.000e-06.*1\.000e-06"),
]


@pytest.mark.parametrize("name,call,message", BAD, ids=[b[0] for b in BAD])
def test_bad_requests_raise_naming_the_field_and_write_nothing(name, call, message):
    inst, fake, _ = make()
    before = [(k, v.copy()) for k, v in fake.writes]
    with pytest.raises(ValueError, match=message):
        call(inst)
    assert len(fake.writes) == len(before)


def test_requests_beyond_the_clamps_write_nothing():
    cal = z_calibration(x_feed_forward=lambda x: 1.1 * x, z_volts_limits=(-1.0, 1.0))
    inst, fake, _ = make(cal)
    n = len(fake.writes)
    with pytest.raises(
        ValueError, match=r"x output would be 1\d\.\d+ V.*\[-10, 10\] V.*x_volts_limits"
    ):
        inst.raster_scan(raster(origin_x=95e-6, size_x=10e-6, line_rate=0.5))
    with pytest.raises(
        ValueError,
        match=r"force=1\.000e-07 N: the z output would be 1\.25 V.*"
        r"\[-1, 1\] V.*z_volts_limits",
    ):
        inst.indent(20e-6, 20e-6, 1e-7, 0.0)  # 500 nm * 2.5 V/um = 1.25 V > 1 V
    assert len(fake.writes) == n


# ---- NI-DAQmx boundary without hardware ----------------------------------------------------


def stub_nidaqmx(monkeypatch, local):
    package = types.ModuleType("nidaqmx")
    system = types.ModuleType("nidaqmx.system")
    system.System = types.SimpleNamespace(local=local)
    package.system = system
    monkeypatch.setitem(sys.modules, "nidaqmx", package)
    monkeypatch.setitem(sys.modules, "nidaqmx.system", system)


def test_nidaqmx_missing_package(monkeypatch):
    monkeypatch.setitem(sys.modules, "nidaqmx", None)
    with pytest.raises(DaqUnavailable, match="package 'nidaqmx' is not installed"):
        NidaqmxBoundary("Dev1")


def test_nidaqmx_missing_driver(monkeypatch):
    class DaqNotFoundError(Exception):  # what nidaqmx.errors raises when the C library is absent
        pass

    def local():
        raise DaqNotFoundError("Could not find an installation of NI-DAQmx.")

    stub_nidaqmx(monkeypatch, local)
    with pytest.raises(
        DaqUnavailable, match="NI-DAQmx driver/runtime not found.*Could not find an installation"
    ):
        NidaqmxBoundary("Dev1")


def test_nidaqmx_missing_device_names_the_present_ones(monkeypatch):
    devices = types.SimpleNamespace(device_names=["Dev2", "PXI1Slot3"])
    stub_nidaqmx(monkeypatch, lambda: types.SimpleNamespace(devices=devices))
    with pytest.raises(
        DaqUnavailable, match='device "Dev1" not present; NI-DAQmx sees: Dev2, PXI1Slot3'
    ):
        NidaqmxBoundary("Dev1")
    stub_nidaqmx(
        monkeypatch, lambda: types.SimpleNamespace(devices=types.SimpleNamespace(device_names=[]))
    )
    with pytest.raises(DaqUnavailable, match="no devices"):
        NidaqmxBoundary("Dev1")


def test_fake_daq_refuses_samples_outside_its_range():
    fake = FakeDaq()
    fake.configure(["ao0"], ["ai0"], 1e3, (-1.0, 1.0), (-10.0, 10.0))
    with pytest.raises(ValueError, match="range"):
        fake.write_read(np.array([[0.0, 1.5]]))
    assert fake.writes == [] and fake.write_read(np.array([[0.0, 0.5]])).shape == (1, 2)


def test_limits_are_exposed_and_used():
    fake = FakeDaq()
    inst = DaqInstrument(fake, calibration(), ScannerLimits(max_speed=10e-6), clock=fake.clock)
    assert inst.limits.max_speed == 10e-6
    with pytest.raises(ValueError, match="slew limit 1.0000e-05"):
        inst.move_tip(20e-6, 20e-6, 20e-6)
