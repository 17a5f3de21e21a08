"""A displacement of the scanner's true position as a function of its place: the generic
lateral terms (config and closed form in the simulator) and the describer's reading of it
from position residuals under a drift-like noise covariance (lateral.py), compared with the
form that made them."""

import dataclasses
import math

import numpy as np
import pytest

from afm_core.sim.config import load_config, merge
from afm_core.sim.instrument import SimulatedAfm
from afm_core.sim2real.candidates import select
from afm_core.sim2real.diagnose import diagnose
from afm_core.sim2real.feature_table import Table
from afm_core.sim2real.generic_fit import displacement_basis
from afm_core.sim2real.lateral import alarms, derivative, displacement_form, widths
from afm_core.sim2real.protocol import make_session, session_config
from afm_core.sim2real.results import NAMED
from afm_core.sim2real.signature import Signature

NM = 1e-9


@pytest.mark.parametrize(
    "entry, words",
    [
        (
            {"signal": "x_position", "form": "time_linear", "amplitude": 1e-12},
            "generic_terms[0].form=time_linear: the x_position signal takes only",
        ),
        (
            {"signal": "y_position", "form": "constant", "amplitude": 1e-9},
            "generic_terms[0].form=constant: the y_position signal takes only",
        ),
        (
            {"signal": "x_position", "form": "x_linear", "amplitude": 0.5},
            "generic_terms[0].amplitude=0.5: |amplitude| must be <= 0.1",
        ),
        (
            {"signal": "x_position", "form": "x_sine", "amplitude": 1e-3, "period": 1e-6},
            "must be <= 1e-05",
        ),
    ],
)
def test_a_bad_lateral_term_is_an_error_naming_its_field(entry, words):
    with pytest.raises(ValueError) as err:
        merge(load_config(), {"generic_terms": [entry]})
    assert words in str(err.value), str(err.value)


def test_the_x_position_term_displaces_the_true_x_by_its_closed_form():
    """Same seed with and without the term, one commanded path: the true x differs by
    A sin(2 pi (x - x0) / L) at the undisplaced true x, the true y not at all."""
    base = load_config()
    a, period, x0 = 8 * NM, 1.5e-6, 50e-6
    term = {"signal": "x_position", "form": "x_sine", "amplitude": a, "period": period, "x0": x0}
    cmd_x = np.linspace(53e-6, 57e-6, 400)
    cmd_y = np.full_like(cmd_x, 55e-6)
    paths = []
    for config in (base, merge(base, {"generic_terms": [term]})):
        sim = SimulatedAfm(config)
        _, true_x, true_y = sim._drive(cmd_x, cmd_y, 1e-3)
        paths.append((true_x, true_y))
    (x0_path, y0_path), (x1_path, y1_path) = paths
    closed = a * np.sin(2 * math.pi * (x0_path - x0) / period)
    assert np.allclose(x1_path - x0_path, closed, atol=1e-15)
    assert np.array_equal(y1_path, y0_path)
    assert np.ptp(x1_path - x0_path) > 1.9 * a


def _synthetic(seed: int, amplitude: float, period: float, frames: int = 5, per_frame: int = 6):
    """Position features of `frames` images of the same particles (x and y centroids) and
    their residual: a displacement A sin(2 pi x / L + 0.7) along x, plus per image a drift
    offset common to its features (sd 40 nm, in the covariance: what whitening cancels) and
    measurement noise (sd 1 nm). Returns (table, residual, covariance, nuisance columns)."""
    rng = np.random.default_rng(seed)
    places = rng.uniform(53e-6, 57e-6, size=(per_frame, 2))
    rows, groups, ops, u = [], [], [], []
    for frame in range(frames):
        for axis, group in ((0, "raster.x"), (1, "raster.y")):
            for k in range(per_frame):
                rows.append(places[k] + rng.normal(0, 20 * NM, 2))
                groups.append(group)
                ops.append(frame)
                u.append((1.0, 0.0) if axis == 0 else (0.0, 1.0))
    n = len(rows)
    xy, ops, u = np.array(rows), np.array(ops), np.array(u)
    same = (ops[:, None] == ops[None, :]) & np.all(u[:, None, :] == u[None, :, :], axis=2)
    cov = (1 * NM) ** 2 * np.eye(n) + (40 * NM) ** 2 * same
    r = np.linalg.cholesky(cov) @ rng.normal(size=n)
    along_x = u[:, 0] == 1.0
    r[along_x] += amplitude * np.sin(2 * math.pi * xy[along_x, 0] / period + 0.7)
    table = Table(
        keys=[(int(o), g, k) for k, (o, g) in enumerate(zip(ops, groups))],
        groups=np.array(groups),
        time=10.0 * ops + 0.1 * np.arange(n),
        xy=xy,
        u=u,
        conditions=[{"particle": str(k % per_frame)} for k in range(n)],
        op_index=ops,
    )
    return table, r, cov, np.zeros((n, 0))


def test_a_periodic_x_displacement_is_read_with_its_period_and_amplitude():
    """Under a per-image drift of 40 nm (its diagonal noise), a 6 nm ripple of period 1.7 um
    is found along x, periodic in x, its period and amplitude near the truth; the y positions
    carry nothing."""
    table, r, cov, P = _synthetic(3, 6 * NM, 1.7e-6)
    row = displacement_form(table, r, cov, P)
    assert row is not None
    assert (row["axis"], row["form"]) == ("x", "periodic in x")
    assert row["params"]["period"] == pytest.approx(1.7e-6, rel=0.05)
    assert row["params"]["amplitude"] == pytest.approx(6 * NM, rel=0.15)


def test_without_a_displacement_the_positions_rarely_show_a_form():
    """Drift and noise alone (the covariance's own draws): a form passes at ALPHA (5 %) on at
    most 4 of 30 seeds (binomial: 4 or more in 30 at 5 % has probability 0.06)."""
    found = sum(
        displacement_form(*_synthetic(seed, 0.0, 1.7e-6)) is not None for seed in range(30)
    )
    assert found <= 4


def test_the_widths_along_the_axis_follow_the_displacement_derivative():
    """Widths of lines along x change by w d'(x) (closed form of the fitted form): slope 1,
    consistent; along y they do not change; widths that change by nothing are not
    consistent with the stretch."""
    params = {"period": 1.5e-6, "amplitude": 9 * NM, "phase": 0.3}
    row = {"axis": "x", "form": "periodic in x", "params": params}
    rng = np.random.default_rng(1)
    n = 24
    xy = np.column_stack([rng.uniform(53e-6, 57e-6, n), rng.uniform(53e-6, 57e-6, n)])
    recorded = rng.uniform(150e-9, 250e-9, n)
    stretch = (
        recorded * 9 * NM * (2 * math.pi / 1.5e-6) * np.cos(2 * math.pi * xy[:, 0] / 1.5e-6 + 0.3)
    )
    assert np.allclose(derivative("periodic in x", params, "x", xy) * recorded, stretch)
    assert np.all(derivative("periodic in x", params, "y", xy) == 0.0)
    sigma = np.full(n, 0.5 * NM)
    table = Table(
        keys=list(range(n)),
        groups=np.array(["line.width"] * n),
        time=np.arange(n, dtype=float),
        xy=xy,
        u=np.zeros((n, 2)),
        conditions=[{"axis": "x"}] * n,
        op_index=np.arange(n),
    )
    seen = widths(table, stretch + rng.normal(0, 0.5 * NM, n), sigma, recorded, row)
    assert seen["slope"] == pytest.approx(1.0, abs=3 * seen["sigma"])
    assert seen["consistent"]
    flat = widths(table, rng.normal(0, 0.5 * NM, n), sigma, recorded, row)
    assert not flat["consistent"]


def test_a_linear_displacement_alone_raises_no_alarm_a_periodic_one_does():
    """A displacement linear across the sample is the library's scanner terms' and the
    drift's; alone it is no missing physics, however small its p; a periodic one is, below
    the level."""
    periodic = {"form": "periodic in x", "p": 1e-6}
    assert alarms(periodic, 1e-3)
    assert not alarms(dict(periodic, p=2e-3), 1e-3)
    assert not alarms({"form": "linear in y", "p": 1e-12}, 1e-3)
    assert not alarms(None, 1e-3)


def test_the_displacement_basis_is_the_sinusoid_of_the_read_period_on_the_x_position():
    """Two x_sine terms a quarter period apart on the x_position signal: their sum at
    amplitudes (a, b) is a sin(2 pi x / L) + b sin(2 pi (x + L/4) / L), i.e. a sin + b cos."""
    sig = Signature(kind="lateral")
    sig.space = {"form": "periodic in x", "params": {"period": 1.4e-6}, "displaced": "x"}
    form, basis = displacement_basis(sig, "x_position", (55e-6, 55e-6))
    assert form == "periodic in x"
    assert [(t.signal, t.form) for t in basis] == [("x_position", "x_sine")] * 2
    x = np.linspace(53e-6, 57e-6, 50)
    w = 2 * math.pi * x / 1.4e-6
    zeros = np.zeros_like(x)
    a, b = 3e-9, -2e-9
    total = sum(
        dataclasses.replace(t, amplitude=v).offset(zeros, x, zeros) for t, v in zip(basis, (a, b))
    )
    assert np.allclose(total, a * np.sin(w) + b * np.cos(w), atol=1e-18)


def test_a_rippling_x_scanner_is_described_as_lateral_and_its_generic_fit_removes_the_excess():
    """The truth's scanner x ripples (a generic x_position sine in the truth's config, which the
    model lacks and the diagnosis cannot see): no library scanner term is named with a
    confident fit; the signature is lateral, periodic in x, with the ripple's period; its
    generic term, on the x_position signal, fitted on one fold and re-simulated, removes at
    least half of the other fold's excess, with the ripple's size."""
    model = merge(session_config(), {"seed": 5})
    a, period = 10 * NM, 1.5e-6
    ripple = {"signal": "x_position", "form": "x_sine", "amplitude": a, "period": period}
    ops = make_session(merge(model, {"generic_terms": [ripple | {"x0": 50e-6}]}), 5)
    d = diagnose(ops, model, candidates=select(("hysteresis_width", "coupling", "rotation")))
    assert d.verdict != NAMED, d.summary()
    sig = d.signature
    assert sig is not None and sig.kind == "lateral", d.summary()
    assert sig.space["form"] == "periodic in x", sig.sentences
    assert sig.space["params"]["period"] == pytest.approx(period, rel=0.1)
    g = d.generic
    assert g["fitted"] and g["signal"] == "x_position" and g["form"] == "periodic in x", g
    assert g["heldout"]["excess_reduction"] >= 0.5, g["heldout"]
    assert math.hypot(*(term["amplitude"] for term in g["terms"])) == pytest.approx(a, rel=0.3)
