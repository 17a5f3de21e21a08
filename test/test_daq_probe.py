"""DAQ backend probed as a lab would set it up: other scanners and inverted axes, calibrations
in the wrong unit, channels missing or named twice, a card that returns too few or NaN
readings, fails mid-scan or mid-indentation, and a card (stubbed NI-DAQmx) that cannot run the
configured sample rate."""

from __future__ import annotations

import sys
import tracemalloc
import types

import numpy as np
import pytest

from afm_core.daq import (
    DaqCalibration,
    DaqInstrument,
    DaqUnavailable,
    FakeDaq,
    NidaqmxBoundary,
    load_calibration,
)
from afm_core.instrument import InstrumentUnavailable, LineRequest, ScanRequest

FS = 20e3


def lateral_metres(cal, volts):
    return (
        (volts[0] - cal.x_offset_volts) / cal.x_volts_per_metre,
        (volts[1] - cal.y_offset_volts) / cal.y_volts_per_metre,
    )


def card(cal, height=lambda x, y: 0 * x):
    """FakeDaq whose z monitor reads `height` at the written position, through `cal`."""

    def respond(volts):
        x, y = lateral_metres(cal, volts)
        return np.vstack(
            [
                height(x, y) / cal.z_monitor_metres_per_volt + cal.z_monitor_offset_volts,
                np.full_like(x, cal.deflection_offset_volts),
            ]
        )

    return FakeDaq(respond)


def make(cal, height=lambda x, y: 0 * x):
    fake = card(cal, height)
    return DaqInstrument(fake, cal, clock=fake.clock), fake


# ---- calibrations of other instruments, and of the wrong unit ------------------------------

INSTRUMENTS = {
    # 10 um scanner: +-10 V spans 0..10 um
    "10 um scanner": dict(
        x_volts_per_metre=2e6, y_volts_per_metre=2e6, x_offset_volts=-10, y_offset_volts=-10
    ),
    # 100 um scanner: +-10 V spans 0..100 um
    "100 um scanner": dict(
        x_volts_per_metre=0.2e6, y_volts_per_metre=0.2e6, x_offset_volts=-10, y_offset_volts=-10
    ),
    # x wired inverted: +9.9 V at x = 0; a z monitor of the opposite polarity
    "inverted x and z monitor": dict(
        x_volts_per_metre=-0.18e6, x_offset_volts=9.9, z_monitor_metres_per_volt=-0.35e-6
    ),
    "inverted y, +-5 V card": dict(
        x_volts_per_metre=0.09e6,
        x_offset_volts=-4.95,
        y_volts_per_metre=-0.09e6,
        y_offset_volts=4.95,
        x_volts_limits=(-5.0, 5.0),
        y_volts_limits=(-5.0, 5.0),
        ai_range=(-5.0, 5.0),
    ),
}


@pytest.mark.parametrize("name", list(INSTRUMENTS))
def test_other_scanners_image_in_si_units_and_scanner_orientation(name):
    cal = DaqCalibration(sample_rate=FS, **INSTRUMENTS[name])
    ox, oy, size, n = 1e-6, 2e-6, 6e-6, 12

    def height(x, y):  # distinct slopes: a flipped or transposed axis changes the image
        return 1e-3 * (x - ox) - 2.5e-3 * (y - oy)

    inst, fake = make(cal, height)
    data = inst.raster_scan(ScanRequest(ox, oy, size, size, n, n, line_rate=2.0))
    centres = (np.arange(n) + 0.5) * size / n
    assert data.height == pytest.approx(
        1e-3 * centres[None, :] - 2.5e-3 * centres[:, None], abs=2e-11
    )
    volts = fake.samples
    lo_x, hi_x = cal.x_volts_limits
    assert lo_x <= volts[0].min() and volts[0].max() <= hi_x
    # the x output moves the way the calibration's sign says while the trace runs
    trace = [v for kind, v in fake.writes if kind == "ramp"][-1][:, : int(FS / 4)]
    assert np.sign(trace[0, -1] - trace[0, 0]) == np.sign(cal.x_volts_per_metre)
    result = inst.move_tip(ox, oy, 50e-6)
    assert fake.last_levels[:2] == pytest.approx(
        [
            cal.x_offset_volts + cal.x_volts_per_metre * ox,
            cal.y_offset_volts + cal.y_volts_per_metre * oy,
        ]
    )
    assert (result.end_x, result.end_y) == pytest.approx((ox, oy))


def test_a_ten_um_scanner_refuses_a_move_beyond_its_volts_and_writes_nothing():
    cal = DaqCalibration(sample_rate=FS, **INSTRUMENTS["10 um scanner"])
    inst, fake = make(cal)
    before = len(fake.writes)
    with pytest.raises(ValueError, match=r"x output would be 12 V.*x_volts_limits"):
        inst.move_tip(11e-6, 5e-6, 10e-6)
    assert len(fake.writes) == before


WRONG_UNITS = [
    ("x_volts_per_metre", 0.18, r"x_volts_per_metre=0\.18 V/m.*0\.18 V/um is 0\.18e6"),
    ("y_volts_per_metre", 5.5e-6, r"y_volts_per_metre=5\.5e-06 V/m"),  # m/V for V/m
    ("z_volts_per_metre", 2.5, r"z_volts_per_metre=2\.5 V/m"),
    ("z_monitor_metres_per_volt", 0.35, r"z_monitor_metres_per_volt=0\.35 m/V.*0\.35e-6"),
    ("deflection_metres_per_volt", 50.0, r"deflection_metres_per_volt=50 m/V.*50e-9"),
    ("deflection_metres_per_volt", -50.0, r"deflection_metres_per_volt=-50 m/V"),
    ("normal_spring_constant", 2e4, r"normal_spring_constant=20000 N/m"),
    ("sample_rate", 1e9, r"sample_rate=1e\+09 Hz"),
    ("sample_rate", "100e3", r"sample_rate='100e3': must be a number"),
    ("sample_rate", True, r"sample_rate=True: must be a number"),
    ("x_volts_limits", 10.0, r"x_volts_limits=10\.0: must be a pair"),
]


@pytest.mark.parametrize("field,value,message", WRONG_UNITS, ids=[w[0] for w in WRONG_UNITS])
def test_a_calibration_in_the_wrong_unit_is_refused_naming_the_field(field, value, message):
    with pytest.raises(ValueError, match=message):
        DaqInstrument(FakeDaq(), DaqCalibration(**{field: value}))


BAD_CHANNELS = [
    (dict(ao_y="ao0"), r"ao_y='ao0': the same channel as calibration\.ao_x"),
    (dict(ai_deflection="Dev1/ai0"), r"ai_deflection='Dev1/ai0': the same channel as .*ai_z"),
    (dict(ao_z="AO1"), r"ao_z='AO1': the same channel as calibration\.ao_y"),
    (dict(ai_lateral="ai1"), r"ai_lateral='ai1': the same channel as .*ai_deflection"),
    (dict(ao_x=""), r"ao_x='': needs a channel name"),
    (dict(ai_z=None), r"ai_z=None: needs a channel name"),
    (dict(ao_x="ai2"), r"ao_x='ai2': must be an analog output"),
    (dict(ai_deflection="ao3"), r"ai_deflection='ao3': must be an analog input"),
]


@pytest.mark.parametrize("fields,message", BAD_CHANNELS, ids=[str(b[0]) for b in BAD_CHANNELS])
def test_a_channel_missing_named_twice_or_of_the_wrong_kind_is_refused(fields, message):
    fake = FakeDaq()
    with pytest.raises(ValueError, match=message):
        DaqInstrument(fake, DaqCalibration(**fields))
    assert fake.ao_channels == [] and fake.writes == []  # the card was not even configured


def test_optional_channels_may_be_empty_and_full_names_are_accepted():
    cal = DaqCalibration(ao_x="Dev1/ao0", ao_z="", ai_lateral=None, sample_rate=FS)
    inst, fake = make(cal)
    assert fake.ao_channels == ["Dev1/ao0", "ao1"] and fake.ai_channels == ["ai0", "ai1"]


def test_a_calibration_file_in_um_per_volt_names_the_file_and_the_field(tmp_path):
    path = tmp_path / "lab_daq.yaml"
    path.write_text("z_monitor_metres_per_volt: 0.35\nsample_rate: 50e3\n")
    with pytest.raises(ValueError) as caught:
        load_calibration(path)
    message = str(caught.value)
    assert str(path) in message and "z_monitor_metres_per_volt=0.35 m/V" in message
    assert "malformed" not in message


# ---- the card misbehaving ------------------------------------------------------------------


class Card(FakeDaq):
    """FakeDaq without its shape guard: readings from `reader(volts, call)`, as a lab's own
    boundary or a misbehaving driver might return them."""

    def __init__(self, reader):
        super().__init__(None)
        self.reader, self.calls = reader, 0

    def write_read(self, ao_samples):
        super().write_read(ao_samples)
        self.calls += 1
        return self.reader(np.asarray(ao_samples), self.calls)


def zeros(volts, rows=2):
    return np.zeros((rows, volts.shape[1]))


READERS = {
    "three samples short": lambda v, k: zeros(v)[:, :-3],
    "one row": lambda v, k: zeros(v, 1),
    "a row too many": lambda v, k: zeros(v, 3),
    "flat": lambda v, k: np.zeros(2),
    "None": lambda v, k: None,
    "NaN": lambda v, k: np.where(np.arange(v.shape[1]) == 7, np.nan, zeros(v)),
}
REQUESTS = {
    "raster": lambda i: i.raster_scan(ScanRequest(55e-6, 55e-6, 4e-6, 4e-6, 8, 8, line_rate=5.0)),
    "local scan": lambda i: i.local_scan(LineRequest(55e-6, 55e-6, 59e-6, 55e-6, 20, 10e-6)),
    "push": lambda i: i.move_tip(56e-6, 55e-6, 10e-6, contact=True),
}


@pytest.mark.parametrize("request_name", list(REQUESTS))
@pytest.mark.parametrize("reader_name", list(READERS))
def test_readings_of_the_wrong_shape_or_nan_fail_the_request_clearly(reader_name, request_name):
    cal = DaqCalibration(sample_rate=FS)
    fake = Card(READERS[reader_name])
    inst = DaqInstrument(fake, cal, clock=fake.clock)
    with pytest.raises(InstrumentUnavailable, match=r"DAQ during .*(shape|not finite)"):
        REQUESTS[request_name](inst)
    # the ramp itself was done: the commanded position is where its outputs now hold
    x, y = lateral_metres(cal, fake.last_levels)
    assert inst.commanded_position() == pytest.approx((x, y), abs=1e-12)


def failing_on(call_number, error=TimeoutError("DAQmx: read timed out (-200284)")):
    def reader(volts, call):
        if call == call_number:
            raise error
        return zeros(volts)

    return reader


def test_a_card_failing_mid_scan_holds_the_last_levels_and_the_next_move_starts_there():
    cal = DaqCalibration(sample_rate=FS)
    fake = Card(failing_on(4))  # travel to the origin, two lines, then the third fails
    inst = DaqInstrument(fake, cal, clock=fake.clock)
    with pytest.raises(InstrumentUnavailable, match=r"TimeoutError: DAQmx: read timed out"):
        inst.raster_scan(ScanRequest(10e-6, 10e-6, 4e-6, 4e-6, 8, 8, line_rate=5.0))
    kind, held = fake.writes[-1]
    assert kind == "static"
    assert held[:, 0] == pytest.approx(fake.writes[-3][1][:, -1])  # the end of line two
    x, y = lateral_metres(cal, held[:, 0])
    assert inst.commanded_position() == pytest.approx((x, y), abs=1e-12)
    fake.reader = lambda v, k: zeros(v)
    before = len(fake.writes)
    inst.move_tip(20e-6, 20e-6, 50e-6)
    fx, fy = lateral_metres(cal, fake.writes[before][1][:, 0])
    assert np.hypot(fx - x, fy - y) * FS <= 50e-6 * (1 + 1e-9)  # no jump from where it held


def test_a_card_failing_during_an_indentation_retracts_z():
    cal = DaqCalibration(sample_rate=FS, ao_z="ao2")
    fake = Card(failing_on(4, RuntimeError("device removed")))
    inst = DaqInstrument(fake, cal, clock=fake.clock)
    with pytest.raises(InstrumentUnavailable, match="device removed"):
        inst.indent(55e-6, 55e-6, 500e-9, 1.0)  # 2.5 um of z: the press takes several chunks
    assert fake.samples[2].max() > cal.z_offset_volts + 0.1  # it had pressed in
    assert fake.writes[-1][0] == "static" and fake.last_levels[2] == pytest.approx(
        cal.z_offset_volts
    )


def test_a_startup_driver_error_becomes_daq_unavailable():
    class Broken(FakeDaq):
        def configure(self, *args):
            raise OSError("DAQmx error -50103: the specified resource is reserved")

    with pytest.raises(DaqUnavailable, match=r"set-up failed: OSError: .*-50103"):
        DaqInstrument(Broken(), DaqCalibration(sample_rate=FS))


# ---- slow requests: time and memory --------------------------------------------------------


def test_a_move_too_slow_to_finish_is_refused_before_anything_is_written():
    inst, fake = make(DaqCalibration(sample_rate=FS))
    before = len(fake.writes)
    with pytest.raises(ValueError, match=r"target / speed: the motion would take 5\.5e\+07 s"):
        inst.move_tip(0.0, 55e-6, 1e-12)
    assert len(fake.writes) == before


class Quiet(FakeDaq):
    """A card that keeps no record of its samples (a long move's memory is the instrument's)."""

    def write_read(self, ao_samples):
        self.now += ao_samples.shape[1] / self.sample_rate
        return np.zeros((len(self.ai_channels), ao_samples.shape[1]))

    def write_static(self, volts):
        pass


def test_a_long_move_holds_one_chunk_in_memory_not_its_whole_path():
    fake = Quiet()
    inst = DaqInstrument(fake, DaqCalibration(sample_rate=FS), clock=fake.clock)
    tracemalloc.start()
    try:
        inst.move_tip(55e-6, 55.5e-6, 1e-8)  # 50 s: 1e6 samples, 8 MB an axis whole
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert fake.now == pytest.approx(50.0, abs=1e-3)
    assert peak < 2e6


def test_a_line_longer_than_max_ramp_samples_is_refused_naming_the_cause():
    inst, fake = make(DaqCalibration(sample_rate=FS, max_ramp_samples=10_000))
    before = len(fake.writes)
    with pytest.raises(ValueError, match=r"line_rate=0\.5 Hz: a line .*40000 DAQ samples"):
        inst.raster_scan(ScanRequest(10e-6, 10e-6, 4e-6, 4e-6, 8, 8, line_rate=0.5))
    with pytest.raises(ValueError, match=r"speed=1\.0000e-06 m/s: the line .*max_ramp_samples"):
        inst.local_scan(LineRequest(10e-6, 10e-6, 11e-6, 10e-6, 10, 1e-6))
    assert len(fake.writes) == before


# ---- NI-DAQmx boundary: the set-up is checked at start-up ----------------------------------


class StubTask:
    """Just enough of nidaqmx.Task for configure; `rate_of` is the card's clock coercion."""

    made: list[StubTask] = []
    rate_of = staticmethod(lambda rate: rate)
    fail_on_channel: str | None = None

    def __init__(self, name):
        self.name, self.closed, self.rate = name, False, None
        self.ao_channels = types.SimpleNamespace(add_ao_voltage_chan=self._add)
        self.ai_channels = types.SimpleNamespace(add_ai_voltage_chan=self._add)
        self.out_stream, self.in_stream = types.SimpleNamespace(), types.SimpleNamespace()
        task = self

        class Timing:
            def cfg_samp_clk_timing(self, rate, **_):
                task.rate = StubTask.rate_of(rate)

            @property
            def samp_clk_rate(self):
                return task.rate

        self.timing = Timing()
        StubTask.made.append(self)

    def _add(self, channel, **_):
        if channel == StubTask.fail_on_channel:
            raise RuntimeError(f"DaqError -200170: physical channel {channel} does not exist")

    def control(self, _action):
        pass

    def close(self):
        self.closed = True


def stub_nidaqmx(monkeypatch):
    StubTask.made, StubTask.fail_on_channel = [], None
    StubTask.rate_of = staticmethod(lambda rate: rate)
    names = {
        "TerminalConfiguration": {"DEFAULT": 0},
        "RegenerationMode": types.SimpleNamespace(DONT_ALLOW_REGENERATION=0),
        "AcquisitionType": types.SimpleNamespace(FINITE=0),
        "TaskMode": types.SimpleNamespace(TASK_VERIFY=0, TASK_UNRESERVE=1),
    }
    package = types.ModuleType("nidaqmx")
    system = types.ModuleType("nidaqmx.system")
    devices = types.SimpleNamespace(device_names=["Dev1"])
    system.System = types.SimpleNamespace(local=lambda: types.SimpleNamespace(devices=devices))
    constants = types.ModuleType("nidaqmx.constants")
    constants.__dict__.update(names)
    readers = types.ModuleType("nidaqmx.stream_readers")
    readers.AnalogMultiChannelReader = lambda stream: None
    writers = types.ModuleType("nidaqmx.stream_writers")
    writers.AnalogMultiChannelWriter = lambda stream, auto_start: None
    package.system, package.Task = system, StubTask
    for name, module in {
        "nidaqmx": package,
        "nidaqmx.system": system,
        "nidaqmx.constants": constants,
        "nidaqmx.stream_readers": readers,
        "nidaqmx.stream_writers": writers,
    }.items():
        monkeypatch.setitem(sys.modules, name, module)


def configure(boundary, rate=30e3):
    boundary.configure(["ao0", "ao1"], ["ai0", "ai1"], rate, (-10.0, 10.0), (-10.0, 10.0))


def test_nidaqmx_refuses_a_sample_rate_the_card_would_coerce(monkeypatch):
    stub_nidaqmx(monkeypatch)
    StubTask.rate_of = staticmethod(lambda rate: 20e6 / round(20e6 / rate))  # 20 MHz timebase
    boundary = NidaqmxBoundary("Dev1")
    with pytest.raises(DaqUnavailable, match=r"sample_rate=30000 Hz.*29985\.0075"):
        configure(boundary, 30e3)
    assert StubTask.made and all(task.closed for task in StubTask.made)
    configure(boundary, 40e3)  # 20 MHz / 500 exactly
    assert boundary.sample_rate == 40e3


def test_nidaqmx_set_up_errors_name_the_set_up_and_free_the_tasks(monkeypatch):
    stub_nidaqmx(monkeypatch)
    StubTask.fail_on_channel = "Dev1/ai1"
    boundary = NidaqmxBoundary("Dev1")
    with pytest.raises(
        DaqUnavailable, match=r"refused the set-up on Dev1 .*ai1.*-200170: physical channel"
    ):
        configure(boundary)
    assert StubTask.made and all(task.closed for task in StubTask.made)


def test_a_long_dwell_is_recorded_averaged_in_blocks_with_bounded_memory():
    cal = DaqCalibration(sample_rate=FS, ao_z="ao2", max_trace_samples=10_000)
    fake = Quiet()
    inst = DaqInstrument(fake, cal, clock=fake.clock)
    tracemalloc.start()
    try:  # 0.5 s press, 20 s dwell, 0.5 s retract: 420 000 samples at 20 kHz
        result = inst.indent(55e-6, 55e-6, 100e-9, 20.0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    trace = result.trace
    assert result.completed and 9_000 < len(trace.times) <= 10_001
    assert trace.sample_rate == pytest.approx(FS / 42)
    assert np.all(np.diff(trace.times) > 0) and trace.times[-1] == pytest.approx(21.0, abs=0.01)
    assert trace.commanded_z.max() == pytest.approx(500e-9)  # the dwell, exact in its blocks
    assert trace.commanded_z[-1] < 5e-9 and fake.now == pytest.approx(21.0, abs=1e-3)
    assert peak < 3e6  # the whole record at full rate would be about 30 MB


class DeadAfter(Card):
    """A card whose every write fails from its `call_number`-th ramp on, static holds too."""

    def __init__(self, call_number):
        super().__init__(failing_on(call_number, RuntimeError("device removed")))
        self.dead_from = call_number

    def write_static(self, volts):
        if self.calls >= self.dead_from:
            raise RuntimeError("device removed")
        super().write_static(volts)


def test_an_indentation_whose_retract_fails_too_says_the_tip_may_be_pressed_in():
    fake = DeadAfter(4)
    inst = DaqInstrument(fake, DaqCalibration(sample_rate=FS, ao_z="ao2"), clock=fake.clock)
    with pytest.raises(InstrumentUnavailable, match=r"device removed.*tip may still be pressed"):
        inst.indent(55e-6, 55e-6, 500e-9, 1.0)


def test_a_hold_that_fails_after_a_cancel_is_reported_as_the_card_failing():
    fake = DeadAfter(2)
    fake.reader = lambda v, k: zeros(v)  # the ramps answer; the hold after the cancel fails
    inst = DaqInstrument(fake, DaqCalibration(sample_rate=FS), clock=fake.clock)
    stops = iter([False, False, True])
    with pytest.raises(InstrumentUnavailable, match=r"holding the outputs after a cancel"):
        inst.move_tip(5e-6, 5e-6, 50e-6, should_stop=lambda: next(stops))
