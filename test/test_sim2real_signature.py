"""What no library term explains: the generic simulator terms (their config and their effect in
closed form), the residual's signature on synthetic residuals of known form, and whole
diagnoses of effects injected after the recording (sim2real_invented.py), which the library
does not have and the diagnosis cannot see how they were made."""

import math

import numpy as np
import pytest
import sim2real_invented as invented
import yaml

from afm_core.instrument import LineRequest, ScanRequest
from afm_core.sim.config import load_config, merge
from afm_core.sim.generic_terms import parse_generic_terms
from afm_core.sim.instrument import SimulatedAfm
from afm_core.sim2real.candidates import select
from afm_core.sim2real.diagnose import diagnose
from afm_core.sim2real.feature_table import Table
from afm_core.sim2real.generic_fit import basis_for, needs_description
from afm_core.sim2real.generic_forms import with_height_offset
from afm_core.sim2real.protocol import Operation, make_session, session_config
from afm_core.sim2real.signature import describe, structure_p


@pytest.mark.parametrize(
    "entry, words",
    [
        ({"signal": "heigth", "form": "constant"}, "generic_terms[0].signal"),
        ({"signal": "height", "form": "wobble"}, "generic_terms[0].form"),
        ({"signal": "height", "form": "time_sine", "amplitude": 1e-9}, "period: required"),
        ({"signal": "height", "form": "x_sine", "period": -1.0}, "period=-1.0: must be > 0"),
        ({"signal": "torsion", "form": "constant", "amplitude": "a"}, "amplitude='a'"),
        ({"signal": "height", "form": "constant", "amplitude": 1.0}, "must be <= 1e-05"),
        ({"signal": "height", "form": "constant", "t0": 1.0}, "unknown key(s) ['t0']"),
        (
            {"signal": "height", "form": "time_legendre", "degree": 0, "t0": 0.0, "t1": 1.0},
            "generic_terms[0].degree=0.0: must be an integer from 1 to 5",
        ),
        (
            {"signal": "height", "form": "time_legendre", "degree": 2, "t0": 5.0, "t1": 1.0},
            "generic_terms[0].t1=1.0: must be > t0=5.0",
        ),
    ],
)
def test_a_bad_generic_term_is_an_error_naming_its_field(entry, words):
    with pytest.raises(ValueError, match=None) as err:
        merge(load_config(), {"generic_terms": [entry]})
    assert words in str(err.value), str(err.value)


def test_the_generic_height_term_adds_its_offset_to_every_measured_height():
    """Same seed with and without the term: the sensor noise draws are the same, so the
    difference is the term's offset exactly (closed form), in images and scan lines."""
    base = load_config()
    term = {"signal": "height", "form": "time_linear", "amplitude": 3e-12, "t0": 1.0}
    heights = []
    for config in (base, merge(base, {"generic_terms": [term]})):
        sim = SimulatedAfm(config)
        line = sim.local_scan(LineRequest(54.8e-6, 55e-6, 55.2e-6, 55e-6, 200, 1e-6))
        image = sim.raster_scan(ScanRequest(54.5e-6, 54.5e-6, 1e-6, 1e-6, 16, 16, line_rate=4.0))
        heights.append((line, image))
    (line0, image0), (line1, image1) = heights
    t = line1.start_time + np.asarray(line1.times)
    assert np.allclose(line1.height - line0.height, 3e-12 * (t - 1.0), atol=1e-15)
    rows = image1.start_time + np.asarray(image1.line_start_times)
    diff = np.asarray(image1.height, float) - np.asarray(image0.height, float)
    # each line within its own trace time (half a line period at 3 pm/s: < 0.4 pm)
    assert np.allclose(diff, 3e-12 * (rows[:, None] - 1.0), atol=1e-12)
    assert np.ptp(diff) > 10 * 1e-12


def test_the_legendre_term_is_the_legendre_polynomial_over_its_span():
    """time_legendre of degree 2 and 3 against their closed forms, u = 2 (t - t0)/(t1 - t0) - 1."""
    t = np.linspace(100.0, 700.0, 13)
    u = 2 * (t - 100.0) / 600.0 - 1
    closed = {2: (3 * u**2 - 1) / 2, 3: (5 * u**3 - 3 * u) / 2}
    for degree, value in closed.items():
        entry = {"signal": "height", "form": "time_legendre", "amplitude": 2e-9}
        entry |= {"degree": degree, "t0": 100.0, "t1": 700.0}
        term = parse_generic_terms([entry])[0]
        assert np.allclose(term.offset(t, 0 * t, 0 * t), 2e-9 * value, rtol=1e-12, atol=1e-24)


@pytest.mark.parametrize(
    "term, tolerance",
    [
        (
            {"signal": "height", "form": "time_legendre", "amplitude": 1e-9, "degree": 3.0}
            | {"t0": 0.0, "t1": 8.0},
            1e-3,
        ),
        (
            {"signal": "height", "form": "x_sine", "amplitude": 1e-9, "period": 1.5e-6}
            | {"x0": 0.0},
            0.1,
        ),
    ],
    ids=["smooth_in_time", "periodic_in_x"],
)
def test_a_generic_term_added_to_the_samples_is_what_the_simulator_measures(term, tolerance):
    """generic_forms.with_height_offset (the form search's columns without re-simulation)
    against the simulator with the term: the same seed, so the difference of the two
    simulations is the term as the instrument applies it (at the true scanner place and the
    instrument clock), and the sampled offset must reproduce it (rms error over the term's
    rms). In time the sample clock is the simulator's: exact. Across the sample the sampled
    offset is taken at the commanded place, which the scanner's own error (about 10 nm)
    moves from the true one: 5-6 % of a 1.5 um sinusoid, where a pixel place half a pixel off
    (31 nm) gives 13 %."""
    base = load_config()
    got = []
    for config in (base, merge(base, {"generic_terms": [term]})):
        sim = SimulatedAfm(config)
        line = sim.local_scan(LineRequest(54.6e-6, 55e-6, 55.4e-6, 55e-6, 200, 1e-6))
        image = sim.raster_scan(ScanRequest(54.5e-6, 54.5e-6, 1e-6, 1e-6, 16, 16, line_rate=4.0))
        got.append((line, image))
    for k, kind in enumerate(("scan_line", "raster")):
        nominal, with_term = got[0][k], got[1][k]
        op = Operation(0, kind, 0.0, (0.0, 0.0), (0.0, 0.0), data=nominal)
        sampled = np.asarray(with_height_offset(op, parse_generic_terms([term])).data.height)
        simulated = np.asarray(with_term.height, float)
        offset = simulated - np.asarray(nominal.height, float)
        assert np.ptp(offset) > 0.5e-9, kind  # the term acted
        error = np.sqrt(np.mean((sampled - simulated) ** 2)) / np.sqrt(np.mean(offset**2))
        assert error < tolerance, (kind, error)


def contact_traces_without_and_with(term: dict) -> list:
    """The force traces of one contact move on the default simulator, without and with the
    generic `term` (same seed, so they differ by the term alone)."""
    base = load_config()
    traces = []
    for config in (base, merge(base, {"generic_terms": [term]})):
        sim = SimulatedAfm(config)
        sim.move_tip(54.5e-6, 54.2e-6, 1e-5)
        traces.append(sim.move_tip(55.5e-6, 54.2e-6, 1e-6, contact=True).trace)
    return traces


def test_the_generic_torsion_term_adds_its_offset_to_the_push_trace():
    """A torsion offset linear in the commanded x: the trace with it minus the one without is
    that offset at each sample's commanded position (closed form)."""
    term = {"signal": "torsion", "form": "x_linear", "amplitude": 50.0, "x0": 55e-6}
    traces = contact_traces_without_and_with(term)
    x = np.asarray(traces[1].commanded_x)
    diff = np.asarray(traces[1].lateral_torsion) - np.asarray(traces[0].lateral_torsion)
    assert np.allclose(diff, 50.0 * (x - 55e-6), rtol=1e-9, atol=1e-15)
    assert np.ptp(diff) > 1e-5  # rad: the term acted


def test_a_torsion_only_generic_term_leaves_the_scan_lines_heights_alone():
    """A generic term on the torsion alone (the re-simulation of a torsion effect adds one to
    a session with local scan lines): the lines' heights are those of the model without it."""
    base = load_config()
    term = {"signal": "torsion", "form": "x_linear", "amplitude": 50.0, "x0": 55e-6}
    request = LineRequest(54.6e-6, 55.0e-6, 55.4e-6, 55.0e-6, samples=200, speed=2e-6)
    heights = []
    for config in (base, merge(base, {"generic_terms": [term]})):
        sim = SimulatedAfm(config)  # the same seed: the same noise draws
        heights.append(np.asarray(sim.local_scan(request).height))
    assert np.array_equal(heights[0], heights[1])


def _table(n, rng, times=None):
    t = np.sort(rng.uniform(0, 1000, n)) if times is None else times
    xy = np.column_stack([rng.uniform(54e-6, 56e-6, n), rng.uniform(54e-6, 56e-6, n)])
    return Table(
        keys=[(i, "raster.level") for i in range(n)],
        groups=np.array(["raster.level"] * n),
        time=t,
        xy=xy,
        u=np.zeros((n, 2)),
        conditions=[{"angle": 0.0} for _ in range(n)],
        op_index=np.arange(n),
    )


@pytest.mark.parametrize(
    "form, truth",
    [
        ("linear trend", lambda t, x: 2e-12 * t),
        ("step", lambda t, x: 1e-9 * (t >= 600.0)),
        ("periodic", lambda t, x: 0.8e-9 * np.sin(2 * math.pi * t / 250.0)),
    ],
)
def test_the_signature_names_the_form_in_time_of_a_known_residual(form, truth):
    rng = np.random.default_rng(3)
    table = _table(80, rng)
    sigma = np.full(80, 0.2e-9)
    r = truth(table.time, table.xy[:, 0]) + rng.normal(0, 0.2e-9, 80)
    sig = describe(table, r, sigma)
    assert sig.kind == "z" and sig.groups == ["raster.level"], sig.sentences
    assert sig.primary == "time" and sig.time["form"] == form, sig.time["bic"]
    params = sig.time["params"]
    if form == "linear trend":
        assert params["slope"] == pytest.approx(2e-12, rel=0.1)
    elif form == "step":
        assert 550 < params["time"] < 650 and params["size"] == pytest.approx(1e-9, rel=0.2)
    else:
        assert params["period"] == pytest.approx(250.0, rel=0.1)


def test_a_settling_is_described_as_a_smooth_change_of_its_size():
    """An exponential settling (no line, no step): the signature's form in time is "smooth",
    and its change from the first time to the last is the settling's over that span."""
    rng = np.random.default_rng(8)
    table = _table(90, rng)
    settle = invented.z_settling(-4e-9, 250.0)
    r = settle(table.time, 0, 0) + rng.normal(0, 0.2e-9, 90)
    sig = describe(table, r, np.full(90, 0.2e-9))
    assert sig.primary == "time" and sig.time["form"] == "smooth", sig.time["bic"]
    t = np.sort(table.time)
    change = float(settle(t[-1], 0, 0) - settle(t[0], 0, 0))
    assert sig.time["params"]["change"] == pytest.approx(change, rel=0.1)
    assert any("changes smoothly" in s for s in sig.sentences), sig.sentences


def test_a_residual_periodic_across_the_sample_is_described_there_not_in_time():
    rng = np.random.default_rng(4)
    table = _table(120, rng)
    r = 0.8e-9 * np.sin(2 * math.pi * table.xy[:, 0] / 0.5e-6) + rng.normal(0, 0.2e-9, 120)
    sig = describe(table, r, np.full(120, 0.2e-9))
    assert sig.primary == "space" and sig.space["form"] == "periodic in x", sig.space["bic"]
    assert sig.space["params"]["period"] == pytest.approx(0.5e-6, rel=0.1)
    # the generic model takes that form: a sinusoid in x (two phases) of that period
    form, basis = basis_for(sig, 0.0, (55e-6, 55e-6))
    assert [b.form for b in basis] == ["x_sine", "x_sine"] and form == "periodic in x"
    assert basis[0].param("period") == pytest.approx(0.5e-6, rel=0.1)


def test_a_torsion_trend_is_a_torsion_signal_and_its_generic_basis_has_a_constant():
    """The torsion's absolute level is measured, so its generic model carries a constant."""
    rng = np.random.default_rng(7)
    table = _table(60, rng)
    table.groups = np.array(["push.torsion"] * 60)
    r = 2e-7 * table.time + rng.normal(0, 1e-5, 60)
    sig = describe(table, r, np.full(60, 1e-5))
    assert sig.kind == "torsion" and sig.time["form"] == "linear trend", sig.time["bic"]
    _, basis = basis_for(sig, 0.0)
    assert [(b.signal, b.form) for b in basis] == [
        ("torsion", "time_linear"),
        ("torsion", "constant"),
    ]


def test_noise_only_and_noise_a_constant_factor_too_large_describe_nothing():
    """White noise is nothing to describe, even beyond its model by a factor the diagnosis
    has taken as overdispersion (it has no structure)."""
    rng = np.random.default_rng(5)
    table = _table(100, rng)
    sigma = np.full(100, 0.2e-9)
    assert describe(table, rng.normal(0, 0.2e-9, 100), sigma).signals == []
    loud = rng.normal(0, 0.4e-9, 100)
    assert describe(table, loud, sigma, factors={"raster.level": 4.0}).signals == []
    assert describe(table, loud, sigma).signals  # without the factor: beyond the model


def test_structure_p_is_small_for_a_trend_and_uniform_for_noise():
    rng = np.random.default_rng(6)
    t = np.arange(60.0)
    assert structure_p(t, t / 10 + rng.normal(0, 1, 60)) < 1e-3
    ps = [structure_p(t, rng.normal(0, 1, 60)) for _ in range(400)]
    # a test at 5 % rejects about 5 % of pure noise (binomial sd 1.1 %)
    assert 0.02 < np.mean(np.array(ps) < 0.05) < 0.09


SEED = 5
MODEL_CANDIDATES = ("height_gain", "bow", "tip_radius")


@pytest.fixture(scope="module")
def model():
    return merge(session_config(), {"seed": SEED})


@pytest.mark.parametrize(
    "effect, form, truth, injected",
    [
        (invented.thermal_bending(2e-12), "linear trend", {}, {"rate": 2e-12}),
        (
            invented.z_pickup_with_x(1e-9, 2e-6),
            "periodic in x",
            {},
            {"amplitude": 1e-9, "period": 2e-6},
        ),
        (
            invented.thermal_bending(2e-12),
            "linear trend",
            {"tip": {"apex_radius": 26e-9}},
            {"rate": 2e-12},
        ),
        (invented.z_settling(-4e-9, 250.0), "smooth", {}, {}),
        (
            invented.z_pickup_with_x(0.5e-9, 1.8e-6, 5.5),
            "periodic in x",
            {},
            {"amplitude": 0.5e-9, "period": 1.8e-6},
        ),
    ],
    ids=[
        "thermal_bending",
        "z_pickup_with_x",
        "bending_on_a_blunter_tip",
        "settling",
        "pickup_of_a_period_the_lines_alias",
    ],
)
def test_an_invented_z_effect_is_described_and_its_generic_fit_removes_the_heldout_excess(
    model, effect, form, truth, injected, tmp_path
):
    """The whole z signal moves (post-processing the recorded heights): every relative
    feature is blind to it, the absolute levels are not. The signature names a z signal in
    the substrate levels with the injected form (in time, or across the sample); the generic
    term of that form, fitted on one fold and re-simulated, removes at least half of the other
    fold's excess, with the injected size (and period: searched on the samples the features
    take, which a line's level takes at its two edges, not at its labelled midpoint). On a
    blunter tip (a library term) too: the residual described is what the named term leaves."""
    session = make_session(merge(model, truth), protocol_seed=SEED)
    ops = invented.add_to_heights(session, effect)
    d = diagnose(ops, model, candidates=select(MODEL_CANDIDATES))
    sig = d.signature
    assert sig is not None, d.summary()
    assert sig.kind == "z" and set(sig.groups) <= {"line.level", "raster.level"}, sig.sentences
    # the form as the samples take it (a 1.8 um fringe reads as a gradient at the lines'
    # labelled midpoints, seed 5)
    forms = sig.time if sig.primary == "time" else sig.space
    assert forms["form"] == form, (sig.time, sig.space)
    g = d.generic
    assert g["fitted"] and g["signal"] == "height" and g["form"] == form, g
    assert g["heldout"]["excess_reduction"] >= 0.5, g["heldout"]
    amplitudes = [term["amplitude"] for term in g["terms"]]
    if form == "linear trend":
        assert amplitudes[0] == pytest.approx(injected["rate"], rel=0.2)
    elif form == "smooth":  # the fitted polynomial's change over the session: the settling's
        t = np.array([min(op.start_time for op in ops), max(op.start_time for op in ops)])
        entries = [{k: v for k, v in term.items() if k != "sigma"} for term in g["terms"]]
        fitted = sum(term.offset(t, 0 * t, 0 * t) for term in parse_generic_terms(entries))
        assert np.diff(fitted)[0] == pytest.approx(np.diff(effect(t, 0, 0))[0], rel=0.15)
    else:  # the two phases of the sinusoid: its amplitude, and its period
        assert math.hypot(*amplitudes) == pytest.approx(injected["amplitude"], rel=0.2)
        assert g["terms"][0]["period"] == pytest.approx(injected["period"], rel=0.05)
    from afm_core.sim2real.report import write_report

    text = write_report(d, tmp_path, config=model).read_text()
    assert "What no library term explains" in text
    # the generic term is a description the simulator loads, never the updated config
    loaded = load_config(tmp_path / "generic_terms.yaml")
    assert loaded.generic_terms[0]["form"] == g["terms"][0]["form"]
    assert "generic" in loaded.generic_terms[0]["description"]
    assert not (tmp_path / "updated_config.yaml").exists() or not yaml.safe_load(
        (tmp_path / "updated_config.yaml").read_text()
    ).get("generic_terms")


def test_the_description_runs_when_the_library_leaves_the_residual_beyond_its_noise():
    quiet = {"p": 0.5, "group_factors": {"line.dir": 3.0}}
    groups = {"line.level": {"p": 1e-9}, "line.dir": {"p": 1e-9}, "line.pos": {"p": 0.4}}
    assert not needs_description(quiet, [], {}, {"line.pos": {"p": 0.4}})
    assert needs_description({"p": 1e-5}, [], {}, {})
    # a group alone, with no overdispersion factor: diluted in the overall chi^2 but beyond
    assert needs_description(quiet, [], {}, groups)
    # the same excess in a group the diagnosis gave a factor: taken as noise
    assert not needs_description(quiet, [], {}, {"line.dir": {"p": 1e-9}})
    # a named term: by the held-out blocks after its fit (95 % quantile of chi^2(200): 233.99)
    assert needs_description(quiet, ["tip_radius"], {"chi2_after": 240.0, "dof": 200})
    assert not needs_description(quiet, ["tip_radius"], {"chi2_after": 230.0, "dof": 200})
    assert not needs_description(quiet, ["tip_radius"], {})
