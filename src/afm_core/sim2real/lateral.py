"""Positions displaced as a function of where the scanner is: the lateral part of an
unexplained residual, read across the sample.

A scanner whose commanded-to-true map has a form the library lacks (a sensitivity that ripples
with position, a gain that changes across the range) displaces every particle by an amount that
depends on its place, the same in every image and in both scan directions. The position
features (scan-line crossings, raster centroids) measure it along their direction u: a feature
along x reads the x displacement at its place (its residual over u_x), one along y the y
displacement. Their diagonal noise is the drift's wander (tens of nm, common to a frame and
growing with time), which hides a displacement of a few nm between particles of one image; the
full noise covariance does not: whitened by it, what the wander shares cancels, which is the
comparison of particles within a frame and of passes over one place.

Per axis (x, y), on the features measuring along it (|u| component >= ALONG), generalized least
squares under the full noise model, with the nuisance columns and a constant (a uniform
displacement is the drift's), of the forms across the sample that signature.space_form tries
on a z residual (linear in x, in y, periodic in x, in y; its period grid and penalties), by
BIC; the best form's chi^2 gain over none is judged against the features' own scatter about
it (an F test: a noise model too optimistic by a constant factor inflates both alike), at
ALPHA over the axes. The displacement's derivative along its axis stretches what is measured
there: a line along x across a particle of width w at x is w (1 + d'(x)) wide, so `widths`
says whether the widths measured along the axis change as the form predicts.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import optimize, stats

from afm_core.sim2real.features import POSITION_GROUPS
from afm_core.sim2real.noise_model import Whitener, gls
from afm_core.sim2real.signature import (
    ALPHA,
    MIN_FEATURES,
    SINE_PENALTY,
    Signature,
    _best,
    _localized,
    _periods,
)
from afm_core.sim2real.signature_text import sentences

ALONG = 0.9  # |u component| of a position feature that measures along an axis
AXES = ("x", "y")
FORMS = ("linear in x", "linear in y", "periodic in x", "periodic in y")
# the width features measured along a line (their line's axis is the condition "axis")
WIDTH_GROUP = "line.width"
# the measured width change over the first-order stretch w d'(x) that is still "the same
# stretch": a profile's half-height width follows the stretch only to first order
STRETCH_RANGE = (0.5, 2.0)


def along(table, axis: int, finite) -> tuple[np.ndarray, np.ndarray]:
    """(indices, sign) of the position features measuring along `axis` (0: x, 1: y): their
    residual over the sign is the displacement along the axis."""
    u = np.asarray(table.u, float)
    sel = np.isin(table.groups, POSITION_GROUPS) & finite & (np.abs(u[:, axis]) >= ALONG)
    idx = np.flatnonzero(sel)
    return idx, np.sign(u[idx, axis])


def _frames(table, idx: np.ndarray) -> np.ndarray:
    """Per image showing several of the features, the drift's velocity during its frame: a
    displacement linear in the time each feature was taken there (so linear in the slow-axis
    coordinate; a null session's y centroids read as a y scale of 6e-4 without it)."""
    ops, t = table.op_index[idx], table.time[idx]
    cols = []
    for op in np.unique(ops):
        here = ops == op
        if here.sum() >= 3 and np.ptp(t[here]) > 0:
            cols.append(np.where(here, t - t[here].mean(), 0.0))
    return np.stack(cols, 1) if cols else np.zeros((idx.size, 0))


def _columns(form: str, xy: np.ndarray, period: float | None = None) -> np.ndarray:
    k = 0 if form.endswith("x") else 1
    coord = xy[:, k] - xy[:, k].mean()
    if form.startswith("linear"):
        return coord[:, None]
    w = 2 * math.pi * xy[:, k] / period
    return np.stack([np.sin(w), np.cos(w)], 1)


class _Fit:
    """chi^2 of form columns fitted (GLS, whitened) beside the base columns."""

    def __init__(self, white: Whitener, rw: np.ndarray, base_w: np.ndarray):
        self.white, self.rw, self.base_w = white, rw, base_w

    def __call__(self, cols: np.ndarray) -> tuple[float, np.ndarray]:
        coef, chi2, _ = gls(self.rw, np.hstack([self.base_w, self.white(cols)]))
        return float(chi2), coef[self.base_w.shape[1] :]

    def periodic(self, form: str, xy: np.ndarray) -> tuple[float, float, np.ndarray] | None:
        """(chi^2, period, [a_sin, a_cos]) of the best sinusoid along the form's axis: the
        signature's period grid, then a bounded search between the best period's
        neighbours."""
        periods = _periods(xy[:, 0 if form.endswith("x") else 1])
        if not periods.size:
            return None
        scores = [self(_columns(form, xy, p))[0] for p in periods]
        k = int(np.argmin(scores))
        best = (scores[k], float(periods[k]))
        lo, hi = periods[max(k - 1, 0)], periods[min(k + 1, len(periods) - 1)]
        if hi > lo:
            found = optimize.minimize_scalar(
                lambda q: self(_columns(form, xy, math.exp(q)))[0],
                bounds=(math.log(lo), math.log(hi)),
                method="bounded",
                options={"xatol": 1e-4},
            )
            if found.fun < best[0]:
                best = (float(found.fun), math.exp(float(found.x)))
        chi2, coef = self(_columns(form, xy, best[1]))
        return chi2, best[1], coef


def _one_axis(table, e, cov, P, axis: int, n_axes: int) -> dict | None:
    finite = np.isfinite(e)
    idx, sign = along(table, axis, finite)
    if idx.size < 2 * MIN_FEATURES:
        return None
    y = e[idx] * sign
    xy = table.xy[idx]
    white = Whitener(np.asarray(cov)[np.ix_(idx, idx)])
    base = np.asarray(P)[idx]
    base = np.hstack(
        [base[:, np.any(base != 0, axis=0)], np.ones((idx.size, 1)), _frames(table, idx)]
    )
    fit = _Fit(white, white(y), white(base))
    chi2_none, _ = fit(np.zeros((idx.size, 0)))
    n, ln = idx.size, math.log(idx.size)
    out = {"none": (chi2_none, {}, np.zeros(n))}
    found = {}
    for form in FORMS:
        if form.startswith("linear"):
            cols = _columns(form, xy)
            chi2, coef = fit(cols)
            found[form] = (chi2, 1, cols @ coef)
            out[form] = (chi2 + ln, {"gradient": coef.tolist()}, cols @ coef)
            continue
        best = fit.periodic(form, xy)
        if best is None:
            continue
        chi2, period, coef = best
        cols = _columns(form, xy, period)
        found[form] = (chi2, 2, cols @ coef)
        params = {
            "period": period,
            "amplitude": float(np.hypot(*coef)),
            "phase": float(math.atan2(coef[1], coef[0])),
        }
        out[form] = (chi2 + SINE_PENALTY * ln, params, cols @ coef)
    chosen = _best(out)
    form = chosen["form"]
    if form == "none":
        return None
    chi2, k, fitted = found[form]
    dof_within = n - base.shape[1] - k
    if dof_within <= 0:
        return None
    scatter = max(1.0, chi2 / dof_within)
    gain = max(chi2_none - chi2, 0.0)
    # a sinusoid's searched period is one more parameter than its two amplitudes
    dof = k + (1 if form.startswith("periodic") else 0)
    p = float(stats.f.sf(gain / dof / scatter, dof, dof_within)) * n_axes
    return {
        "axis": AXES[axis],
        "form": form,
        "bic": chosen["bic"],
        "params": chosen["params"],
        "all": chosen["all"],
        "p": min(1.0, p),
        "n": n,
        "chi2": gain / scatter,
        "dof": dof,
        "scatter": scatter,
        "groups": sorted(set(table.groups[idx].tolist())),
        "indices": idx,
        "displacement": y,
        "fitted": fitted,
    }


def displacement_form(table, e, cov, P) -> dict | None:
    """The form across the sample of the position features' displacement (module docstring)
    on the axis whose form passes and gains most; None when none passes at ALPHA.
    e: residual (N, SI, NaN where missing), after the nuisance columns P (N, k); cov: its noise
    covariance (N, N), the model's (unscaled)."""
    e = np.asarray(e, float)
    rows = [_one_axis(table, e, cov, P, axis, len(AXES)) for axis in range(len(AXES))]
    rows = [row for row in rows if row is not None and row["p"] < ALPHA]
    return max(rows, key=lambda row: row["chi2"] - row["dof"]) if rows else None


def alarms(lateral: dict | None, level: float) -> bool:
    """Whether a displacement alone (nothing else left unexplained) is missing physics: a
    form no library term has (periodic) passing at the verdict's `level`. A displacement
    linear across the sample is what the library's scanner terms (gain, creep, hysteresis,
    coupling, rotation) and the drift give: a null session's y positions read as a y scale of
    -6.5e-4 at p = 5e-4 (null-protocol-0), so alone it raises no alarm; beside an unexplained
    residual it is still described."""
    return lateral is not None and lateral["p"] < level and lateral["form"].startswith("periodic")


def derivative(form: str, params: dict, axis: str, xy: np.ndarray) -> np.ndarray:
    """d'(place) along `axis` of the displacement form (dimensionless): the local stretch."""
    if not form.endswith(axis):
        return np.zeros(len(xy))
    if form.startswith("linear"):
        return np.full(len(xy), float(params["gradient"][0]))
    k = 0 if axis == "x" else 1
    w = 2 * math.pi / params["period"]
    a = params["amplitude"]
    return a * w * np.cos(w * xy[:, k] + params["phase"])


def widths(table, e, sigma, recorded, row: dict) -> dict | None:
    """Whether the widths of the lines along the displacement's axis change as its derivative
    predicts (w d'(x), w the recorded width): the weighted slope k of their residual on that
    prediction, with its sigma scaled by the scatter about it; consistent when k is beyond two
    sigmas of 0 and within STRETCH_RANGE. None without such widths, or a form with no
    stretch."""
    if recorded is None:
        return None
    axis = row["axis"]
    sel = np.flatnonzero(
        (table.groups == WIDTH_GROUP)
        & np.isfinite(e)
        & np.isfinite(recorded)
        & (sigma > 0)
        & np.array([c.get("axis") == axis for c in table.conditions])
    )
    if sel.size < MIN_FEATURES:
        return None
    predicted = recorded[sel] * derivative(row["form"], row["params"], axis, table.xy[sel])
    w = 1 / sigma[sel] ** 2
    norm = float(np.sum(w * predicted**2))
    if norm <= 0:
        return None
    k = float(np.sum(w * predicted * e[sel]) / norm)
    chi2 = float(np.sum(w * (e[sel] - k * predicted) ** 2))
    scatter = max(1.0, chi2 / max(sel.size - 1, 1))
    sigma_k = math.sqrt(scatter / norm)
    return {
        "n": int(sel.size),
        "slope": k,
        "sigma": sigma_k,
        "consistent": bool(k > 2 * sigma_k and STRETCH_RANGE[0] <= k <= STRETCH_RANGE[1]),
    }


def row_of(lateral: dict) -> dict:
    """The signature's signal row (signature._significant_groups' shape) of a displacement."""
    words = f"particle positions along {lateral['axis']} ({', '.join(lateral['groups'])})"
    return {
        "group": f"lateral {lateral['axis']}",
        "words": words,
        "kind": "lateral",
        "n": lateral["dof"],
        "chi2": lateral["chi2"],
        "excess": lateral["chi2"] - lateral["dof"],
        "structure_p": lateral["p"],
        "lateral": True,
    }


def lateral_lead(sig: Signature, table, e, sigma, recorded, lateral: dict | None) -> Signature:
    """The signature with the displacement among its signals; when it leads (the largest
    excess, or the widths along its axis change as its stretch predicts: they are its symptom),
    the signature is the displacement's: kind lateral, its form across the sample, the
    widths' agreement, in words."""
    if lateral is None:
        return sig
    row = row_of(lateral)
    rows = sorted([*sig.signals, row], key=lambda r: -r["excess"])
    total = sum(r["excess"] for r in rows) or 1.0
    for r in rows:
        r["share"] = r["excess"] / total
    sig.signals = rows
    stretch = widths(table, e, sigma, recorded, lateral)
    if rows[0] is not row and not (stretch and stretch["consistent"]):
        return sig
    sig.signals = [row] + [r for r in rows if r is not row]
    idx, y, fitted = lateral["indices"], lateral["displacement"], lateral["fitted"]
    xy, s = table.xy[idx], sigma[idx]
    sig.kind, sig.groups = "lateral", lateral["groups"]
    sig.space = {
        "form": lateral["form"],
        "bic": lateral["bic"],
        "params": lateral["params"],
        "all": lateral["all"],
        "primary": True,
        "displaced": lateral["axis"],
        "localized": _localized(xy, y - fitted - np.mean(y - fitted), s),
    }
    sig.time, sig.conditions, sig.along_scan, sig.relations = {}, [], {}, []
    # the centroids' per-particle test reads them against their diagonal noise, the drift's
    # wander, which hides what the displacement does: its finding is the form above
    sig.particles = {g: v for g, v in sig.particles.items() if g not in POSITION_GROUPS}
    sig.size = {
        "rms": float(np.sqrt(np.mean((fitted - fitted.mean()) ** 2))),
        "rms_sigma": float(math.sqrt(lateral["chi2"] / lateral["n"])),
        "amplitude": float(lateral["params"].get("amplitude", np.ptp(fitted))),
        "noise_sigma": float(np.sqrt(np.mean(s**2))),
        "left_rms_sigma": float(math.sqrt(lateral["scatter"])),
    }
    sig.sentences = [
        text.replace("(better than any form in time)", "(as a function of the scanner's place)")
        for text in sentences(sig, ALPHA)
        if text
    ]
    sig.sentences[1] = _size_sentence(lateral)
    sig.sentences.insert(2, _stretch_sentence(lateral, stretch))
    return sig


def _size_sentence(lateral: dict) -> str:
    a = lateral["axis"]
    return (
        f"The particles' positions along {a} (scan-line crossings and raster centroids) are "
        f"displaced by an amount that depends on where the scanner is, fitted on all images "
        f"and scan lines together (both scan directions of a pair in its mean), under the full "
        f"noise model, in which the drift's wander common to a frame cancels: chi2 gain "
        f"{lateral['chi2']:.1f} for {lateral['dof']} parameters over {lateral['n']} position "
        f"features (p = {lateral['p']:.2g}), leaving {math.sqrt(lateral['scatter']):.3g} times "
        "the noise."
    )


def _stretch_sentence(lateral: dict, stretch: dict | None) -> str:
    a = lateral["axis"]
    if stretch is None:
        return f"No widths measured along {a} tell whether the scan is stretched there."
    verdict = (
        "consistent with the same displacement stretching the scan"
        if stretch["consistent"]
        else "not what the same displacement would do to them"
    )
    return (
        f"Its derivative along {a} stretches the scan: the widths of the {stretch['n']} line "
        f"runs along {a} change by {stretch['slope']:.3g} +- {stretch['sigma']:.2g} times the "
        f"width times that derivative, {verdict}."
    )
