"""The suite's out-of-library injections (bench/sim2real_injections.py) change exactly what they
say by their closed-form amount, and nothing else; no diagnosis runs here.

Synthetic measurements with known fields: a raster at 0 and at 90 deg (the pixel times and
positions computed here by plain loops, independently of the module's vectorised convention),
a scan line and a push trace; the simulator extension against the simulator's own scanner;
the MCAP rewrite on a small recorded session, read back as the diagnosis reads it.
"""

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import sim2real_injections as inj  # noqa: E402

from afm_core.instrument import ForceTraceData, RasterScanData, ScanLineData  # noqa: E402
from afm_core.sim2real.session import Operation  # noqa: E402

NM = 1e-9
# float32 heights (the RasterScan message's encoding) of ~100 nm resolve ~1e-14 m
F32 = 1e-14


def _raster(angle: float, start: float, ramp: float = 0.0) -> RasterScanData:
    rows, columns = 6, 8
    px, py = 20 * NM, 30 * NM
    height = np.zeros((rows, columns))
    if ramp:  # a ramp along the fast axis: h = ramp * s, s the pixel centre along it
        for r in range(rows):
            for c in range(columns):
                height[r, c] = ramp * ((c + 0.5) * px if angle == 0.0 else (r + 0.5) * py)
    lines = rows if angle == 0.0 else columns
    return RasterScanData(
        height=(height + 50 * NM).astype(np.float32),
        pixel_size_x=px,
        pixel_size_y=py,
        origin_x=55e-6,
        origin_y=54e-6,
        scan_angle_deg=angle,
        slow_scan_up=True,
        line_period=0.25,
        line_start_times=0.25 * np.arange(lines)[::-1] + 0.01,
        start_time=start,
        mode="tapping",
    )


def _pixel(scan: RasterScanData, r: int, c: int) -> tuple[float, float, float]:
    """(t, x, y) of pixel (r, c), by the module docstring's convention, one pixel at a time."""
    if scan.scan_angle_deg == 0.0:
        line, k, n_fast = r, c, scan.height.shape[1]
    else:
        line, k, n_fast = c, r, scan.height.shape[0]
    t = scan.start_time + scan.line_start_times[line] + (k + 1) * scan.line_period / (2 * n_fast)
    return (
        t,
        scan.origin_x + (c + 0.5) * scan.pixel_size_x,
        scan.origin_y + (r + 0.5) * (scan.pixel_size_y),
    )


def _line(start: float) -> ScanLineData:
    n = 40
    x = np.linspace(55.0e-6, 55.4e-6, n)
    return ScanLineData(
        times=np.linspace(0.0, 0.4, n),
        x=x,
        y=np.full(n, 54.5e-6),
        height=30 * NM + 0.1 * (x - x[0]),  # a ramp along the line: 0.1 m per m
        deflection=np.zeros(n),
        amplitude=np.zeros(n),
        start_time=start,
        mode="tapping",
    )


def _trace(start: float) -> ForceTraceData:
    n = 50
    t = np.linspace(0.0, 0.5, n)
    return ForceTraceData(
        times=t,
        commanded_x=np.linspace(55e-6, 56e-6, n),
        commanded_y=np.full(n, 54.3e-6),
        commanded_z=np.zeros(n),
        vertical_deflection=50 * NM + 0.2 * NM * np.sin(7 * t),
        lateral_torsion=1e-5 + 1e-7 * np.cos(3 * t),
        normal_spring_constant=0.2,
        lateral_spring_constant=1e-9,
        sample_rate=100.0,
        start_time=start,
        task="push",
    )


def _operations(ramp: float = 0.0) -> list:
    def op(index, kind, start, data, duration):
        return Operation(index, kind, start, (0, 0), (0, 0), 1e-6, duration, {}, data)

    return [
        op(0, "raster", 0.0, _raster(0.0, 0.0, ramp), 2.0),
        op(1, "scan_line", 100.0, _line(100.0), 0.5),
        op(2, "push", 300.0, _trace(300.0), 0.6),
        op(3, "raster", 500.0, _raster(90.0, 500.0, ramp), 2.2),
        op(4, "scan_line", 900.0, _line(900.0), 0.5),
    ]


def _changes(name: str, seed: int = 3, ramp: float = 0.0):
    """(injection, operations before, after) for a post-processing injection."""
    effect = inj.make_injection(name, seed)
    return effect, _operations(ramp), effect.rewrite(_operations(ramp))


def _expect_heights(before, after, dz) -> None:
    """Every height sample changed by dz(t, x, y) (computed sample by sample), nothing else."""
    for b, a in zip(before, after):
        if b.kind == "raster":
            rows, columns = b.data.height.shape
            for r in range(rows):
                for c in range(columns):
                    want = float(b.data.height[r, c]) + dz(*_pixel(b.data, r, c))
                    assert float(a.data.height[r, c]) == pytest.approx(want, abs=F32)
        elif b.kind == "scan_line":
            for i, t in enumerate(b.data.times):
                want = b.data.height[i] + dz(b.data.start_time + t, b.data.x[i], b.data.y[i])
                assert a.data.height[i] == pytest.approx(want, abs=1e-18)
        else:
            np.testing.assert_array_equal(a.data.lateral_torsion, b.data.lateral_torsion)
            np.testing.assert_array_equal(a.data.vertical_deflection, b.data.vertical_deflection)


def test_mains_pickup_adds_a_50_hz_sine_in_time_to_every_height_sample():
    effect, before, after = _changes("mains_pickup")
    p = effect.parameters
    assert p["frequency"] == 50.0 and 0.3 * NM <= p["amplitude"] <= 0.6 * NM
    _expect_heights(
        before,
        after,
        lambda t, x, y: p["amplitude"] * math.sin(2 * math.pi * 50.0 * t + p["phase"]),
    )


def test_thermal_bending_moves_the_absolute_level_by_an_exponential_settling():
    effect, before, after = _changes("thermal_bending")
    p = effect.parameters
    assert 2 * NM <= abs(p["level"]) <= 5 * NM
    _expect_heights(
        before, after, lambda t, x, y: p["level"] * (1 - math.exp(-t / p["time_constant"]))
    )


def test_debris_step_raises_every_height_after_its_time_by_the_step():
    effect, before, after = _changes("debris_step")
    p = effect.parameters
    when = 0.0 + p["at_fraction"] * (900.5 - 0.0)  # the session: first start to last end
    _expect_heights(before, after, lambda t, x, y: p["height"] if t >= when else 0.0)
    assert before[0].start_time < when < before[-1].start_time  # some samples before, some after


def test_interference_fringes_are_periodic_in_x_and_the_same_at_every_time():
    effect, before, after = _changes("interference_fringes")
    p = effect.parameters
    _expect_heights(
        before,
        after,
        lambda t, x, y: p["amplitude"] * math.sin(2 * math.pi * x / p["period"] + p["phase"]),
    )


@pytest.mark.parametrize("name", ["torsion_crosstalk", "torsion_drift"])
def test_torsion_injections_change_the_torsion_alone_by_their_closed_form(name):
    effect, before, after = _changes(name)
    p = effect.parameters
    for b, a in zip(before, after):
        if b.kind != "push":
            np.testing.assert_array_equal(a.data.height, b.data.height)
            continue
        t = b.data.start_time + b.data.times
        added = (
            p["rad_per_m"] * b.data.vertical_deflection
            if name == "torsion_crosstalk"
            else p["rad_per_s"] * t
        )
        np.testing.assert_allclose(
            a.data.lateral_torsion - b.data.lateral_torsion, added, rtol=1e-12, atol=1e-20
        )
        np.testing.assert_array_equal(a.data.vertical_deflection, b.data.vertical_deflection)
    if name == "torsion_crosstalk":  # 10-25 % of the default 1e-5 rad friction torsion at 50 nm
        assert 0.1 <= abs(p["rad_per_m"]) * 50 * NM / 1e-5 <= 0.25


def test_line_jitter_shifts_each_line_along_its_fast_axis_by_its_own_random_offset():
    ramp = 0.2  # m per m along the fast axis: a shift d changes an inner pixel by 0.2 d
    effect, before, after = _changes("line_jitter", ramp=ramp)
    sigma, seed = effect.parameters["sigma"], effect.parameters["seed"]
    for b, a in zip(before, after):
        if b.kind == "raster":
            fast_is_x = b.data.scan_angle_deg == 0.0
            lines = b.data.height.shape[0] if fast_is_x else b.data.height.shape[1]
            offsets = inj.jitter_offsets(seed, b.index, lines, sigma)
            assert len(set(np.round(offsets / NM, 6))) == lines  # independent from line to line
            delta = (a.data.height.astype(float) - b.data.height.astype(float)) / ramp
            per_line = delta if fast_is_x else delta.T
            # inner pixels (a shift under one pixel keeps them off the ends)
            for line, d in enumerate(offsets):
                np.testing.assert_allclose(per_line[line, 1:-1], d, atol=F32 / ramp)
        elif b.kind == "scan_line":
            d = inj.jitter_offsets(seed, b.index, 1, sigma)[0]
            np.testing.assert_allclose((a.data.height - b.data.height)[1:-1], 0.1 * d, atol=1e-18)


def test_x_nonlinearity_displaces_the_true_x_by_its_ripple_and_nothing_else():
    from afm_core.pzt import LateralScanner
    from afm_core.sim.config import load_config

    effect = inj.make_injection("x_nonlinearity", 5)
    p = effect.parameters
    params = load_config().scanner
    plain, rippled = LateralScanner(params), LateralScanner(params)
    wrapped = inj._NonlinearScanner(rippled, p["amplitude"], p["period"])
    cmd_x, cmd_y = np.linspace(53e-6, 57e-6, 400), np.linspace(54e-6, 55e-6, 400)
    x0, y0 = plain.apply(cmd_x, cmd_y, 1e-3)
    x1, y1 = wrapped.apply(cmd_x, cmd_y, 1e-3)
    centre = params.range_x / 2
    np.testing.assert_allclose(
        x1 - x0, p["amplitude"] * np.sin(2 * np.pi * (x0 - centre) / p["period"]), atol=1e-18
    )
    np.testing.assert_array_equal(y1, y0)
    assert 5 * NM <= p["amplitude"] <= 12 * NM
    # the simulator subclass puts the ripple in its scanner
    sim = effect.simulator(load_config(), **effect.simulator_kwargs)
    assert isinstance(sim.scanner, inj._NonlinearScanner)


def test_particle_heights_resize_each_truth_sphere_by_its_own_factor_in_place():
    from afm_core.sim.config import load_config, merge

    model = load_config()
    effect = inj.make_injection("particle_heights", 8, model)
    truth = merge(model, effect.truth_overrides)
    factors = effect.parameters["radius_factors"]
    assert len(set(factors)) == len(model.sample.spheres) > 1
    for m, t, f in zip(model.sample.spheres, truth.sample.spheres, factors):
        assert (t["x"], t["y"]) == (m["x"], m["y"])
        assert t["radius"] == pytest.approx(m["radius"] * f, rel=1e-12)
        assert 0.9 <= f <= 1.1


def test_an_unknown_injection_is_refused_with_the_names():
    with pytest.raises(ValueError, match="mains_pickup"):
        inj.make_injection("gremlins", 0)


def test_the_rewrite_keeps_a_recording_exactly_and_injects_only_what_it_says(tmp_path):
    from afm_core.instrument import LineRequest, ScanRequest
    from afm_core.sim.config import load_config
    from afm_core.sim.instrument import SimulatedAfm
    from afm_core.sim2real import RecordingInstrument
    from afm_core.sim2real.session_reader import read_operations

    recording = RecordingInstrument(SimulatedAfm(load_config()), tmp_path / "raw.mcap")
    recording.raster_scan(ScanRequest(54.5e-6, 54.5e-6, 1e-6, 1e-6, 16, 16, line_rate=20.0))
    recording.local_scan(LineRequest(54.6e-6, 55e-6, 55.4e-6, 55e-6, 80, 4e-6))
    recording.move_tip(55.5e-6, 54.2e-6, 1e-5)
    recording.move_tip(55.9e-6, 54.2e-6, 2e-6, contact=True)
    recording.close()
    effect = inj.make_injection("mains_pickup", 1)
    inj.rewrite_recording(tmp_path / "raw.mcap", tmp_path / "same.mcap", None)
    inj.rewrite_recording(tmp_path / "raw.mcap", tmp_path / "mains.mcap", effect.rewrite)

    def read(name):
        with read_operations(tmp_path / name) as stream:
            return list(stream)

    raw, same, mains = read("raw.mcap"), read("same.mcap"), read("mains.mcap")
    assert [o.kind for o in raw] == [o.kind for o in same] == [o.kind for o in mains]
    assert [o.kind for o in raw] == ["raster", "scan_line", "move", "push"]
    for a, b in zip(raw, same):
        assert (a.start_time, a.duration, a.start, a.end) == (
            b.start_time,
            b.duration,
            b.start,
            b.end,
        )
        if a.data is not None:
            for field in ("height", "lateral_torsion", "times", "line_start_times"):
                if hasattr(a.data, field):
                    np.testing.assert_array_equal(getattr(a.data, field), getattr(b.data, field))
    # the injected file: the closed form at the read-back sample times (stamps are whole ns)
    dz = inj.sine_in_time(effect.parameters["amplitude"], 50.0, effect.parameters["phase"])
    _expect_heights(raw[:2], mains[:2], dz)
    np.testing.assert_array_equal(mains[3].data.lateral_torsion, raw[3].data.lateral_torsion)


def test_the_signature_truths_tell_a_description_in_time_from_one_in_space():
    import sim2real_scoring as scoring

    class Described:  # a diagnosis with a describer's output
        def __init__(self, signature):
            self.signature = signature

    in_time = Described({"signal": "height", "form": "periodic in time, 50 Hz"})
    in_space = Described({"signal": "height", "form": "periodic along x, wavelength 1.8 um"})
    mains = inj.SIGNATURES["mains_pickup"]
    fringes = inj.SIGNATURES["interference_fringes"]
    assert scoring.signature_of(in_time, mains)["described"] is True
    assert scoring.signature_of(in_space, mains)["described"] is False
    assert scoring.signature_of(in_space, fringes)["described"] is True
    assert scoring.signature_of(in_time, fringes)["described"] is False
    assert scoring.signature_of(object(), mains)["described"] is None  # no describer


def test_a_structured_signature_is_judged_by_its_fields_not_by_the_forms_it_rejected():
    from types import SimpleNamespace

    import sim2real_scoring as scoring

    def described(kind, time_form, space_form, particles=None):
        signature = SimpleNamespace(
            kind=kind,
            time={"form": time_form},
            space={"form": space_form},
            particles=particles or {},
            relations=[],
            # its sentences name the forms it weighed, the rejected ones too
            text=lambda: "periodic in x weighed against periodic in time, step, linear trend",
        )
        return SimpleNamespace(signature=signature)

    truth = inj.SIGNATURES
    periodic_in_time = described("z", "periodic", "uniform")
    assert scoring.signature_of(periodic_in_time, truth["mains_pickup"])["described"] is True
    assert scoring.signature_of(periodic_in_time, truth["interference_fringes"])["described"] is (
        False
    )
    assert scoring.signature_of(periodic_in_time, truth["debris_step"])["described"] is False
    # a smooth change in time (signature.py's low-degree polynomial) is a settling's kind of
    # form, not a step's
    smooth = described("z", "smooth", "uniform")
    assert scoring.signature_of(smooth, truth["thermal_bending"])["described"] is True
    assert scoring.signature_of(smooth, truth["debris_step"])["described"] is False
    fringes = described("z", "none", "periodic in x")
    assert scoring.signature_of(fringes, truth["interference_fringes"])["described"] is True
    assert scoring.signature_of(fringes, truth["x_nonlinearity"])["described"] is False  # z
    unlike = described("z", "constant", "uniform", {"raster.height": {"alike": False}})
    assert scoring.signature_of(unlike, truth["particle_heights"])["described"] is True
    alike = described("z", "constant", "uniform", {"raster.height": {"alike": True}})
    assert scoring.signature_of(alike, truth["particle_heights"])["described"] is False
    nothing = SimpleNamespace(signature=None)  # a describer that found nothing to describe
    assert scoring.signature_of(nothing, truth["mains_pickup"])["described"] is False
    # the generic fit's share: its held-out check's; none fitted on this recording: NaN
    held = SimpleNamespace(generic={"heldout": {"excess_reduction": 0.7}})
    assert scoring.generic_share(held) == 0.7
    assert math.isnan(scoring.generic_share(SimpleNamespace(generic={})))
    assert scoring.generic_share(object()) is None


def test_the_families_hold_what_the_issue_asks_and_their_layouts_keep_clear():
    import sim2real_families as families

    from afm_core.sim.config import load_config

    cases = families.family_cases(list(families.FAMILIES), load_config())
    kinds = [c.kind for c in cases]
    assert kinds.count("null") >= 10 and kinds.count("out_of_library") >= 8
    assert sum(c.kind == "library" and c.session == "work" for c in cases) >= 4
    assert len({c.name for c in cases}) == len(cases) and len({c.seed for c in cases}) == len(
        cases
    )
    assert {c.injection for c in cases if c.injection} == set(inj.NAMES)
    for case in cases:
        points = np.asarray(case.layout)
        gaps = [np.hypot(*(p - q)) for i, p in enumerate(points) for q in points[i + 1 :]]
        spacing = (
            families.PROTOCOL_SPACING if case.session == "protocol" else families.WORK_SPACING
        )
        assert min(gaps) >= spacing  # the protocol's own sample too (1.6 um at the closest)
        if case.name.startswith("null-protocol") and case.name != "null-protocol-0":
            for x0, x1, y0, y1 in families.SLIDE_KEEP_OUT:  # off the protocol's slides
                assert not np.any(
                    (points[:, 0] >= x0)
                    & (points[:, 0] <= x1)
                    & (points[:, 1] >= y0)
                    & (points[:, 1] <= y1)
                )
    with pytest.raises(ValueError, match="null_protocol"):
        families.family_cases(["nulls"], load_config())
