"""Which generic form the unexplained z residual takes, and its shape (a period, a span), found
by sampling: the form's offset added to the nominal re-simulation's own height samples and the
features extracted again.

The signature (signature.py) fits its forms to the features at their labelled times and places,
but a feature does not sample the z signal there: a scan line's absolute level is the median of
its two edges (a fringe of period L seen at a line's midpoint is a fringe of the same period
scaled by cos(pi l / L) for a line of length l, and lines of several lengths alias it: 0.675 um
read for 1.80 um), a particle's height is its top less its line's edges. A generic term acts on
the samples, so its form is chosen, and its period searched, on what the features do when the
samples move. The simulator adds a generic height term to the measured samples after the
feedback (sim/instrument.py), so adding it to the nominal re-simulation's samples (at their
commanded places, on the instrument clock) and extracting again gives its column without a
re-simulation: 0.15 s against 0.5 s per column on the protocol, which is what lets a period be
searched. The chosen form's final columns are re-simulated (generic_fit.py) all the same.

The forms, all on the height signal (generic_terms.py's family): a linear trend, a step at the
signature's time, a smooth change (Legendre degrees 1 to signature.SMOOTH_DEGREE over the span),
periodic in time at the signature's period; when the signature's form is across the sample:
linear in x, y or both, and periodic in x or y with the period searched; when the scan lines'
forward less backward level (`line.updown`) lives, a z offset by scan direction (SCAN_FORM:
+-half of it on the lines scanned along and against their axis). The one of least BIC
(chi^2 of the GLS fit with the nuisance columns, plus its number of amplitudes times ln N) on
one noise model for all of them (the signature's groups without their overdispersion factors,
which the unexplained effect inflated) is the form.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import optimize

from afm_core.sim.generic_terms import GenericTerm
from afm_core.sim2real.feature_table import by_key, values_at
from afm_core.sim2real.features import extract_features
from afm_core.sim2real.features_absolute import UPDOWN_GROUP
from afm_core.sim2real.noise_model import Whitener, gls
from afm_core.sim2real.protocol import replay
from afm_core.sim2real.sample_times import raster_samples
from afm_core.sim2real.signature import SMOOTH_DEGREE, Signature

SEARCH_PERIODS = 10  # log-spaced periods tried between 3 feature spacings and the span
REFINE_EVALUATIONS = 6  # bounded search between the best grid period's neighbours
SCAN_FORM = "a z offset by scan direction"


def with_height_offset(op, terms: list[GenericTerm]):
    """A copy of operation `op` with the height terms' offset added to its height samples
    (rasters and scan lines; other operations as they are)."""
    if op.kind not in ("raster", "scan_line") or op.data is None:
        return op
    data = op.data
    if hasattr(data, "line_start_times"):
        t, x, y = raster_samples(data)
    else:
        t = data.start_time + np.asarray(data.times, float)
        x, y = np.asarray(data.x, float), np.asarray(data.y, float)
    height = np.asarray(data.height)
    extra = sum(term.offset(t, x, y) for term in terms if term.signal == "height")
    moved = (height + extra).astype(height.dtype)
    return dataclasses.replace(op, data=dataclasses.replace(data, height=moved))


class OffsetSampler:
    """Columns of generic height terms from the nominal re-simulation's samples (module
    docstring): `column(term)` is how the features move per unit amplitude."""

    def __init__(self, sess):
        self.sess = sess
        sess.replays += 1
        self.ops = replay(sess.ops, sess.base, drift=sess.drift).operations
        self.f0 = self._features(self.ops)
        self.extractions = 1

    def _features(self, ops) -> np.ndarray:
        return values_at(by_key(extract_features(ops, self.sess.anchors)), self.sess.keys)

    def column(self, term: GenericTerm, size: float) -> np.ndarray:
        """The features' change per unit amplitude, from an offset whose largest value over
        the session's features is `size` (m: the residual's own scale keeps the features'
        medians in their linear range)."""
        t, xy = self.sess.table.time, self.sess.table.xy
        reach = float(np.max(np.abs(term.offset(t, xy[:, 0], xy[:, 1]))))
        amplitude = size / reach if reach > 0 else size
        scaled = dataclasses.replace(term, amplitude=amplitude)
        self.extractions += 1
        moved = self._features([with_height_offset(op, [scaled]) for op in self.ops])
        change = np.nan_to_num(moved - self.f0)
        change[self.sess.noisy] = 0.0
        return change / amplitude


def _time_bases(sig: Signature, t_first: float, t_last: float) -> dict:
    """form -> basis terms (unit amplitude) of the forms in time."""
    out = {"linear trend": [GenericTerm("height", "time_linear", 1.0, (("t0", t_first),))]}
    step = sig.time.get("all", {}).get("step")
    if step and "time" in step:
        out["step"] = [GenericTerm("height", "time_step", 1.0, (("t0", step["time"]),))]
    if t_last > t_first:
        span = (("t0", t_first), ("t1", t_last))
        out["smooth"] = [
            GenericTerm("height", "time_legendre", 1.0, (("degree", float(d)), *span))
            for d in range(1, SMOOTH_DEGREE + 1)
        ]
    periodic = sig.time.get("all", {}).get("periodic")
    if periodic and "period" in periodic:
        out["periodic"] = _sines("time", periodic["period"], "t0", 0.0)
    return out


def _sines(axis: str, period: float, key: str, origin: float) -> list[GenericTerm]:
    form = f"{axis}_sine"
    return [
        GenericTerm("height", form, 1.0, (("period", period), (key, origin))),
        GenericTerm("height", form, 1.0, (("period", period), (key, origin - period / 4))),
    ]


def _linear_bases(centre) -> dict:
    x = GenericTerm("height", "x_linear", 1.0, (("x0", centre[0]),))
    y = GenericTerm("height", "y_linear", 1.0, (("y0", centre[1]),))
    return {"linear in x": [x], "linear in y": [y], "linear in x and y": [x, y]}


class _Scorer:
    """BIC of a basis' columns fitted (GLS, with the nuisance columns) to the residual."""

    def __init__(self, sampler, white: Whitener, rw, pw, size: float):
        self.sampler, self.white, self.rw, self.pw, self.size = sampler, white, rw, pw, size
        self.ln = math.log(max(len(rw), 2))

    def columns(self, basis) -> np.ndarray:
        return np.stack([self.sampler.column(term, self.size) for term in basis], 1)

    def bic(self, cols) -> float:
        _, chi2, _ = gls(self.rw, np.hstack([self.pw, self.white(cols)]))
        return float(chi2) + cols.shape[1] * self.ln

    def periodic(self, axis: str, coord: np.ndarray, origin: float) -> tuple[float, list]:
        """(BIC, basis) of the best sinusoid along `axis` (x or y): a grid of periods, then a
        bounded search between the best one's neighbours."""
        c = np.sort(np.unique(coord))
        if c.size < 4:
            return math.inf, []
        span = float(c[-1] - c[0])
        lo = max(3 * float(np.median(np.diff(c))), span / 50)
        if span <= lo:
            return math.inf, []
        periods = np.logspace(math.log10(lo), math.log10(span), SEARCH_PERIODS)
        key = f"{axis}0"
        scores = [self.bic(self.columns(_sines(axis, p, key, origin))) for p in periods]
        k = int(np.argmin(scores))
        best = (scores[k], float(periods[k]))
        lo_p, hi_p = periods[max(k - 1, 0)], periods[min(k + 1, len(periods) - 1)]
        if hi_p > lo_p:
            found = optimize.minimize_scalar(
                lambda q: self.bic(self.columns(_sines(axis, math.exp(q), key, origin))),
                bounds=(math.log(lo_p), math.log(hi_p)),
                method="bounded",
                options={"maxiter": REFINE_EVALUATIONS, "xatol": 1e-3},
            )
            if found.fun < best[0]:
                best = (float(found.fun), math.exp(float(found.x)))
        return best[0], _sines(axis, best[1], key, origin)


def search_form(sess, noise, P, r0: np.ndarray, sig: Signature, say=lambda m: None):
    """(form, basis at unit amplitude, {form: BIC}) of the z residual r0 (module docstring);
    `noise`: the one noise model the forms are compared on."""
    sampler = OffsetSampler(sess)
    white = Whitener(noise.cov)
    size = max(sig.size.get("rms", 0.0), 1e-12)
    scorer = _Scorer(sampler, white, white(r0), white(P), size)
    t = sess.table.time
    bases = _time_bases(sig, float(np.min(t)), float(np.max(t)))
    if UPDOWN_GROUP in {row["group"] for row in sig.signals}:
        bases[SCAN_FORM] = [GenericTerm("height", "scan_direction", 1.0)]
    if sig.primary == "space":
        centre = tuple(float(v) for v in np.mean(sess.table.xy, axis=0))
        bases.update(_linear_bases(centre))
    scores = {form: scorer.bic(scorer.columns(basis)) for form, basis in bases.items()}
    if sig.primary == "space":
        sel = np.isin(sess.table.groups, sig.groups)
        # the axis the signature's own sinusoid preferred: its period may be aliased, its axis
        # (the direction the level changes along) is not
        own = sig.space.get("bic", {})
        axes = [a for a in ("x", "y") if f"periodic in {a}" in own]
        axes = sorted(axes, key=lambda a: own[f"periodic in {a}"])[:1]
        for axis in axes:
            k = "xy".index(axis)
            centre_k = float(np.mean(sess.table.xy[:, k]))
            bic, basis = scorer.periodic(axis, sess.table.xy[sel, k], centre_k)
            if basis:
                bases[f"periodic in {axis}"], scores[f"periodic in {axis}"] = basis, bic
    form = min(scores, key=scores.get)
    say(f"generic form by sampling: {form} ({sampler.extractions} feature extractions)")
    return form, bases[form], scores
