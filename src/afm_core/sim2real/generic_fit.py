"""A generic simulator term fitted where no library term explains the residual, and its
held-out check.

When the library names nothing and the residual exceeds its noise, or a named term leaves the
held-out blocks beyond theirs, the residual's signature (signature.py) says in which signal it
lives and its form; this stage models it with the simulator's generic term family
(sim/generic_terms.py: an additive offset on the height or torsion signal, shaped by a small
basis: a linear trend, a step at the signature's time, a sinusoid of its period, linear or
periodic in x or y; a torsion residual that follows the deflection sample by sample,
signal_relations.py, is k x the measured deflection instead, fitted and checked at the
samples when no feature sees it, deflection_term.py; particle positions displaced as
a function of their place, lateral.py, are a displacement of the scanner's true x or y of that
form, x_position / y_position, applied in the re-simulation's commanded-to-true map).
Its coefficients are fitted by re-simulation columns, one replay per basis
function (the offset is additive, so one step gives the column), like the library's design
columns. The held-out check is heldout.py's: fit on one fold of time blocks, re-simulate the
whole session with that fit, chi^2 of the other fold before and after, the share of its excess
removed, on the groups the term reaches (generic_reach.py): those are judged against their
modelled noise (without the quasi-likelihood factor, which the unexplained effect itself may
have inflated); the others keep theirs and stay out of the share.

The generic term is a description, not a named physical effect: it never enters the updated
configuration; the report writes it to `generic_terms.yaml`, which the simulator loads as a
config file (`generic_terms:`).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import yaml
from scipy import stats

from afm_core.sim.config import merge
from afm_core.sim.generic_terms import GenericTerm, parse_generic_terms
from afm_core.sim2real.deflection_term import deflection_fit, sample_sentence
from afm_core.sim2real.generic_forms import SCAN_FORM, search_form
from afm_core.sim2real.generic_reach import heldout_where, reached_groups
from afm_core.sim2real.heldout import heldout_chi2
from afm_core.sim2real.jitter_fit import jitter_sentence, line_jitter_fit, lives_in_line_shifts
from afm_core.sim2real.lateral import alarms, displacement_form, lateral_lead
from afm_core.sim2real.level_trend import level_trend, trend_sentence
from afm_core.sim2real.noise_model import Whitener, gls
from afm_core.sim2real.per_object import (
    OBJECT_STEP,
    PER_OBJECT_FORM,
    differing,
    object_basis,
    object_offsets,
)
from afm_core.sim2real.periodic_height import periodic_height
from afm_core.sim2real.results import UNEXPLAINED_P, heldout_share_words
from afm_core.sim2real.signal_relations import DEFLECTION, deflection_relation, unseen_signature
from afm_core.sim2real.signature import ALPHA, Signature, describe
from afm_core.sim2real.signature_text import sentences

HELDOUT_QUANTILE = 0.95  # held-out chi^2 above this quantile of chi^2(dof): beyond the noise
# share of the held-out excess above which a generic model of a secondary signal is taken to
# explain the leading one too (the ">= 50 % of the held-out excess")
GENERIC_EXPLAINS = 0.5
# a group the generic term moves by less than this share of its noise sigma keeps its
# overdispersion factor: the term's fit cannot have inflated that factor
ACTS = 0.1
SIGNALS = {"z": "height", "torsion": "torsion"}  # signature kind -> the generic term's signal
SPACE_FORMS = ("linear in x", "linear in y", "linear in x and y", "periodic in x", "periodic in y")
DESCRIPTION = (
    "generic description fitted by the sim2real diagnosis where no library term explains the "
    "residual; not a named physical effect"
)


def needs_description(
    overall: dict, chosen: list, heldout: dict, groups=None, trend: dict | None = None
) -> bool:
    """Whether the residual is left unexplained: nothing named while the residual exceeds the
    noise model — as a whole, or in one group whose noise the diagnosis took as modelled (no
    overdispersion factor) at UNEXPLAINED_P over the groups (an effect in a few dozen features
    is diluted in the chi^2 of several hundred), or the absolute levels change smoothly in time
    (trend: level_trend.level_trend, one more test in that family) —, or a named term leaving
    the held-out blocks beyond their noise. groups: group -> {chi2, dof, p}
    (deviations.group_stats)."""
    if not chosen:
        factors = overall.get("group_factors", {})
        limit = UNEXPLAINED_P / max(len(groups or {}) + bool(trend), 1)
        alone = any(
            row["p"] < limit and factors.get(g, 1.0) <= 1.0 for g, row in (groups or {}).items()
        )
        slow = bool(trend) and trend["p"] < limit
        return overall["p"] < UNEXPLAINED_P or alone or slow
    if "chi2_after" not in heldout:
        return False
    return heldout["chi2_after"] > stats.chi2.ppf(HELDOUT_QUANTILE, max(heldout["dof"], 1))


def basis_for(sig: Signature, t_first: float, centre=(0.0, 0.0)) -> tuple[str, list[GenericTerm]]:
    """(the form chosen, the basis terms at unit amplitude) of the signature's simplest form:
    the family fitted first (signature._forms), its best deterministic form (a random walk
    has no basis)."""
    signal = SIGNALS[sig.kind]
    time_bic = {k: v for k, v in sig.time["bic"].items() if k not in ("none", "random walk")}
    time_form = min(time_bic, key=time_bic.get)
    space_form = sig.space["form"]
    use_space = sig.primary == "space"
    if use_space and space_form != "uniform":
        p = sig.space["all"][space_form]
        axis = space_form.split()[-1]
        if space_form.startswith("periodic"):
            key = f"{axis}0"
            period = p["period"]
            terms = [
                GenericTerm(signal, f"{axis}_sine", 1.0, (("period", period), (key, 0.0))),
                GenericTerm(signal, f"{axis}_sine", 1.0, (("period", period), (key, -period / 4))),
            ]
        elif space_form == "linear in x and y":
            terms = [
                GenericTerm(signal, "x_linear", 1.0, (("x0", centre[0]),)),
                GenericTerm(signal, "y_linear", 1.0, (("y0", centre[1]),)),
            ]
        else:
            origin = centre[0] if axis == "x" else centre[1]
            terms = [GenericTerm(signal, f"{axis}_linear", 1.0, ((f"{axis}0", origin),))]
        return space_form, terms + _constant(signal)
    params = sig.time["all"][time_form]
    if time_form == "linear trend":
        terms = [GenericTerm(signal, "time_linear", 1.0, (("t0", t_first),))]
    elif time_form == "step":
        at = params.get("time", t_first)
        terms = [GenericTerm(signal, "time_step", 1.0, (("t0", at),))]
    elif time_form == "periodic":
        period = params.get("period", 1.0)
        terms = [
            GenericTerm(signal, "time_sine", 1.0, (("period", period), ("t0", 0.0))),
            GenericTerm(signal, "time_sine", 1.0, (("period", period), ("t0", -period / 4))),
        ]
    else:
        terms = []
    return time_form, terms + _constant(signal)


def displacement_basis(sig: Signature, signal: str, centre) -> tuple[str, list[GenericTerm]]:
    """(form, basis at unit amplitude) of a displacement of the scanner's true x or y
    (`signal`) of the signature's form across the sample: a sinusoid of its period (two
    phases), or linear in x or y about the features' centre."""
    form, p = sig.space["form"], sig.space["params"]
    axis = form.split()[-1]
    if form.startswith("periodic"):
        period, key = p["period"], f"{axis}0"
        return form, [
            GenericTerm(signal, f"{axis}_sine", 1.0, (("period", period), (key, 0.0))),
            GenericTerm(signal, f"{axis}_sine", 1.0, (("period", period), (key, -period / 4))),
        ]
    origin = centre[0] if axis == "x" else centre[1]
    return form, [GenericTerm(signal, f"{axis}_linear", 1.0, ((f"{axis}0", origin),))]


PROPORTIONAL_FORM = "proportional to the vertical deflection"


def _tracked(sig: Signature) -> dict | None:
    """The sample-level relation of a torsion residual to the deflection (signal_relations.py),
    None without one."""
    if sig.kind != "torsion":
        return None
    return next((r for r in sig.relations if r.get("covariate") == DEFLECTION), None)


def _constant(signal: str) -> list[GenericTerm]:
    """A constant offset: the torsion's absolute level is measured, the height's is not (every
    height feature is relative to a substrate or to the session's first level)."""
    return [GenericTerm(signal, "constant", 1.0)] if signal == "torsion" else []


def _scaled(term: GenericTerm, amplitude: float) -> GenericTerm:
    return dataclasses.replace(term, amplitude=float(amplitude))


def _config_with(sess, terms: list[GenericTerm]):
    """The reference's config with `terms` added to the generic terms it already has (a model
    that carries an earlier diagnosis' description keeps it)."""
    earlier = list(sess.base.generic_terms)
    return merge(sess.base, {"generic_terms": earlier + [term.as_dict() for term in terms]})


def _step(term: GenericTerm, sess, size: float) -> float:
    """The amplitude whose offset reaches `size` (the residual's rms) over the session's
    features: a column by a step of the effect's own size."""
    t, xy = sess.table.time, sess.table.xy
    reach = float(np.max(np.abs(term.offset(t, xy[:, 0], xy[:, 1], np.ones_like(t)))))
    return size / reach if reach > 0 else size


def _change(sess, terms: list[GenericTerm]) -> np.ndarray:
    """How the features move with the generic terms, by re-simulation (noise statistics: not
    at all, as for the library's columns; NaN where a feature is lost)."""
    sim = sess.features(_config_with(sess, terms))
    change = sim - sess.nominal
    change[sess.noisy] = 0.0
    return change


def _no_form_reason(sig: Signature) -> str:
    """Why a signature gets no generic term: its signal has none, or (a z or torsion signal,
    which has) it lives in too few features to show the form in time and across the sample the
    term is built from (a curvature along x alone lives in the two bow images' raster.bow_xx)."""
    if sig.kind not in SIGNALS:
        return f"no generic term acts on a {sig.kind or 'no'} signal"
    where = ", ".join(sig.groups) or "no group"
    return (
        f"a generic term on the {SIGNALS[sig.kind]} signal needs the residual's form in time and "
        f"across the sample, and its features ({where}) are too few to show one"
    )


def generic_fit(sess, evidence, r0: np.ndarray, sig: Signature, say=lambda m: None) -> dict:
    """The generic term of the signature's form fitted to the residual r0 (after the named
    terms, if any): columns, fit on all features (amplitudes, sigmas, chi^2 gain), the held-out
    check. {"fitted": False, "reason": ...} when the signature's signal has no generic term."""
    per_object = bool(sig.space.get("per_object"))
    displaced = sig.space.get("displaced")
    if not displaced and (
        sig.kind not in SIGNALS or not sig.space or not (sig.time or per_object)
    ):
        return {"fitted": False, "reason": _no_form_reason(sig)}
    signal = f"{displaced}_position" if displaced else SIGNALS[sig.kind]
    centre = tuple(float(v) for v in np.mean(sess.table.xy, axis=0))
    searched = {}
    if displaced:  # the scanner's true x or y as a function of its place (lateral.py)
        form, basis = displacement_basis(sig, signal, centre)
    elif per_object:  # one offset per particle (per_object.py)
        form = PER_OBJECT_FORM
        basis = object_basis(sig.space["tags"], sess.anchors) if sig.kind == "z" else []
    elif sig.kind == "z":
        # the form and its shape by what the samples do (generic_forms.py), on one noise model:
        # the signature's groups without the factors the unexplained effect inflated
        live = {row["group"] for row in sig.signals}
        noise = dataclasses.replace(evidence.unscaled)
        noise.overdispersed(
            {g: f for g, f in evidence.group_factors.items() if g not in live}, sess.table.groups
        )
        form, basis, searched = search_form(sess, noise, evidence.P, r0, sig, say)
    else:
        form, basis = basis_for(sig, float(np.min(sess.table.time)), centre)
    tracked = _tracked(sig)
    if tracked is not None:
        # a residual that follows another signal sample by sample: residual = k x that signal
        form, basis = PROPORTIONAL_FORM, [GenericTerm("torsion", "deflection_proportional", 1.0)]
    if not basis:
        return {"fitted": False, "reason": f"no generic basis for the form {form!r}"}
    size = max(sig.size["amplitude"] if displaced else sig.size["rms"], 1e-12)
    # a proportional term's column at the slope the samples show: the torsion's rms features
    # are not linear in a slope near zero
    steps = (
        [abs(tracked["coefficient"]) or 1.0]
        if tracked is not None
        else [OBJECT_STEP if per_object else _step(term, sess, size) for term in basis]
    )
    fit = fit_basis(sess, evidence, r0, form, signal, basis, steps, say)
    if fit["fitted"]:
        fit["searched"] = searched
    return fit


QUADRATIC_FORM = "quadratic in the measured height"


def quadratic_height_fit(sess, evidence, r0: np.ndarray, sig, say=lambda m: None) -> dict:
    """The generic term proportional to the square of the measured height (a z sensor whose
    sensitivity changes along its range), fitted and checked like generic_fit's: the rival a
    z gain or a tip radius meets besides the signature's own form (rival.py). One amplitude,
    its column at the step that moves the tallest object's top by the residual's size (the
    heights are float32 samples: a step far below that would be lost to their rounding)."""
    # the residual's size sets only the column's step (the term is linear in its amplitude)
    size = max((sig.size if sig is not None else {}).get("rms", 0.0), 1e-9)
    step = size / _tallest(sess.base) ** 2
    basis = [GenericTerm("height", "height_squared", 1.0)]
    return fit_basis(sess, evidence, r0, QUADRATIC_FORM, "height", basis, [step], say)


def _tallest(config) -> float:
    """The tallest object's height (m) in the model's sample (at least 20 nm), the range over
    which the measured height's square grows."""
    sample = config.sample
    heights = [2 * s["radius"] for s in sample.spheres] + [2 * r["radius"] for r in sample.rods]
    heights += [e["thickness"] for e in sample.electrodes]
    heights += [2 * sample.radius_mean] if sample.random_spheres else []
    return max(heights + [20e-9])


def fit_basis(sess, evidence, r0, form, signal, basis, steps, say=lambda m: None) -> dict:
    """The generic `basis` (unit-amplitude terms of `form` on `signal`) fitted to r0 by
    re-simulated columns at `steps` (each term's amplitude for its column): the fit on all
    features and its held-out check on the groups it reaches (module docstring). {"fitted":
    False, "reason"} when the held-out blocks refute it."""
    say(f"generic term: {form} on the {signal} signal ({len(basis)} re-simulations)")
    cols = np.stack(
        [np.nan_to_num(_change(sess, [_scaled(term, a)])) / a for term, a in zip(basis, steps)],
        1,
    )
    # where the term at the residual's size moves a feature by a tenth of its noise or more
    sigma = np.sqrt(np.diag(evidence.unscaled.cov))
    acts = np.abs(cols * np.array(steps)[None, :]).max(axis=1) >= ACTS * sigma
    acted = set(np.unique(sess.table.groups[acts]).tolist())
    # the groups whose chi^2 the term moves: only there may the effect have inflated a factor,
    # and only there is the held-out excess the term's to remove (generic_reach.py)
    reached, reach = reached_groups(sess, evidence, r0, cols)
    noise = dataclasses.replace(evidence.unscaled)
    factors = {g: f for g, f in evidence.group_factors.items() if g not in reached}
    noise.overdispersed(factors, sess.table.groups)
    P = evidence.P
    white = Whitener(noise.cov)
    rw, pw = white(r0), white(P)
    X = np.hstack([pw, white(cols)])
    coef, chi2_fit, cov = gls(rw, X)
    _, chi2_0, _ = gls(rw, pw)
    k = P.shape[1]
    theta, theta_cov = coef[k:], cov[k:, k:]
    where = np.isin(sess.table.groups, sorted(reached))
    heldout = _heldout(sess, noise, P, evidence.folds[0], r0, cols, basis, where)
    if heldout["chi2_after"] > heldout["chi2_before"]:
        # a description the held-out blocks refute is no fit, whatever it gained on its own
        return {
            "fitted": False,
            "form": form,
            "reason": (
                f"the generic {form} fitted on one fold made the other fold's chi2 worse "
                f"({heldout['chi2_before']:.1f} -> {heldout['chi2_after']:.1f} for "
                f"{heldout['dof']} dof)"
            ),
        }
    terms = [
        dict(
            _scaled(term, value).as_dict(),
            sigma=float(math.sqrt(max(theta_cov[j, j], 0.0)))
            if np.isfinite(theta_cov[j, j])
            else float("nan"),
        )
        for j, (term, value) in enumerate(zip(basis, theta))
    ]
    return {
        "fitted": True,
        "signal": signal,
        "form": form,
        "terms": terms,
        "delta_chi2": float(chi2_0 - chi2_fit),
        "parameters": len(basis),
        "p": float(stats.chi2.sf(max(chi2_0 - chi2_fit, 0.0), len(basis))),
        "heldout": heldout,
        "acts_on": sorted(acted),
        "reached": sorted(reached),
        "reach": reach,
        "replays": len(basis) + 1,
    }


def _heldout(sess, noise, P, train, r0, cols, basis, where) -> dict:
    """Fit on the `train` blocks, re-simulate the whole session with that fit, chi^2 of the
    other blocks before and after (heldout.py's check for a generic term), on the features of
    the groups the term reaches (`where`, a mask; generic_reach.py) and, as `all_groups`, on
    the whole session."""
    test = ~train
    w_tr = Whitener(noise.cov[np.ix_(train, train)])
    k = P.shape[1]
    coef, _, _ = gls(w_tr(r0[train]), np.hstack([w_tr(P[train]), w_tr(cols[train])]))
    theta = coef[k:]
    fitted = [_scaled(term, a) for term, a in zip(basis, theta) if a != 0]
    change = _change(sess, fitted) if fitted else np.zeros_like(r0)
    r_after = np.where(np.isfinite(change), r0 - change, r0 - cols @ theta)
    whole = heldout_chi2(noise, P, test, r0, r_after)
    check = heldout_where(noise, P, test, where, r0, r_after) if where.any() else whole
    return {
        **check,
        "all_groups": whole,
        "within_noise": bool(
            check["chi2_after"] <= stats.chi2.ppf(HELDOUT_QUANTILE, max(check["dof"], 1))
        ),
        "train_amplitudes": theta.tolist(),
        "r_after": r_after,
    }


def describe_unexplained(
    sess, evidence, deviations, design_terms, chosen, parameters, heldout, say=lambda m: None
):
    """(Signature, generic fit dict) of what the library leaves unexplained, or (None, {}) when
    it leaves nothing (`needs_description`). The residual is the named terms' at their fitted
    values (re-simulated: ReferenceSession.residual), the nominal model's when none is named."""
    overall = evidence.overall()
    trend = (
        {}
        if chosen
        else level_trend(
            sess.table, sess.r, evidence.unscaled.cov, evidence.P, overall["group_factors"]
        )
    )
    unexplained = needs_description(overall, chosen, heldout, deviations.group_stats, trend)
    if chosen and not unexplained:
        return None, {}
    if chosen:
        terms = [design_terms[name] for name in chosen]
        theta = [parameters[key]["value"] for name in chosen for key in design_terms[name][0].keys]
        r0 = sess.residual(terms, np.array(theta))
    else:
        r0 = sess.r.copy()
    # the nuisance offsets out, as "where" takes them
    white = Whitener(evidence.unscaled.cov)
    coef, _, _ = gls(white(r0), white(evidence.P))
    e = r0 - evidence.P @ coef
    cov, factors = evidence.unscaled.cov, evidence.group_factors
    objects = object_offsets(sess.table, e, cov, evidence.P, sess.anchors, factors)
    lateral = displacement_form(sess.table, e, cov, evidence.P)
    if not unexplained and not alarms(lateral, UNEXPLAINED_P):
        lateral = None
    if not unexplained and not differing(objects) and lateral is None:
        # nothing the features show: a torsion that follows the deflection at the samples
        # still is (signal_relations.py), at the verdict's own level
        unseen = unseen_signature(sess, UNEXPLAINED_P)
        if unseen is not None:
            # no feature sees it: fitted and checked at the samples (deflection_term.py)
            try:
                generic = deflection_fit(sess, say)
            except ValueError as exc:  # no deflection change to fit on, say
                generic = {"fitted": False, "reason": f"no generic fit at the samples: {exc}"}
            unseen.sentences.append(
                sample_sentence(generic) if generic.get("fitted") else generic["reason"] + "."
            )
            return unseen, generic
        # a height signal faster than any feature's sampling, periodic in time
        periodic = periodic_height(sess, UNEXPLAINED_P, say)
        return (None, {}) if periodic is None else periodic
    say("describing the unexplained residual")
    sigma = np.sqrt(np.diag(cov))
    sig = describe(sess.table, e, sigma, sess.recorded, factors, objects)
    sig = lateral_lead(sig, sess.table, e, sigma, sess.recorded, lateral)
    if trend and trend["p"] < UNEXPLAINED_P / (len(deviations.group_stats) + 1) and sig.signals:
        sig.sentences.insert(1, trend_sentence(trend, sig.time.get("form", "")))
    if sig.kind == "torsion":
        # its relation to the deflection at the same moment, read at the samples
        relation = deflection_relation(sess, ALPHA / max(len(sig.relations) + 1, 1))
        if relation is not None:
            sig.relations.append(relation)
            sig.sentences = sentences(sig, ALPHA)
    if lives_in_line_shifts(sig):
        # the lines' own shifts: the noise family's per-line lateral offset (jitter_fit.py)
        generic = line_jitter_fit(sess, evidence, r0, say)
        if generic.get("fitted"):
            sig.sentences.append(jitter_sentence(generic))
        return sig, generic
    fitted = sig
    displaced = bool(sig.space.get("displaced"))
    if (
        sig.kind not in SIGNALS
        and not displaced
        and any(row["kind"] in SIGNALS for row in sig.signals)
    ):
        # the leading signal has no generic term (a lateral one), but a z or torsion part lives
        # too: its generic model is fitted, and the re-simulation says what it does to the rest
        kinds = {row["group"]: row["kind"] for row in sig.signals}
        part = np.where([kinds.get(g) in SIGNALS for g in sess.table.groups], e, np.nan)
        fitted = describe(sess.table, part, sigma, sess.recorded, evidence.group_factors)
        sig.sentences.append(
            f"No generic term acts on a {sig.kind} signal; the generic model is fitted to its "
            f"{fitted.kind} part: " + " ".join(fitted.sentences[:3])
        )
    try:
        generic = generic_fit(sess, evidence, r0, fitted, say)
    except ValueError as exc:  # a fitted amplitude beyond what the simulator takes, say
        generic = {"fitted": False, "reason": f"the generic model cannot be simulated: {exc}"}
    if generic.get("fitted"):
        adopt_sampled_form(fitted, generic)
        sig.sentences.append(model_sentence(generic))
    lead = sig.signals[0]["group"] if sig.signals else None
    if (
        fitted is not sig
        and generic.get("fitted")
        and lead in generic["acts_on"]
        and generic["heldout"]["excess_reduction"] >= GENERIC_EXPLAINS
    ):
        # the z (or torsion) model, re-simulated, accounts for the leading signal too: that
        # signal is a symptom, and the simplest description is the one that explains it
        fitted.sentences.append(
            f"The {sig.signals[0]['words']} follow from it: the generic {fitted.kind} model, "
            "re-simulated, accounts for them too."
        )
        return fitted, generic
    return sig, generic


def adopt_sampled_form(sig: Signature, generic: dict) -> None:
    """When the form chosen on the samples (generic_forms.py) is not the one the signature read
    at the features' labelled places (a fringe the lines' midpoints alias into a gradient), the
    signature takes it, with the fit's parameters, and its sentences are told again; the form
    read at the features is kept (`read_at_features`) and said in the model's sentence."""
    form = generic["form"]
    family = "space" if form in SPACE_FORMS else "time"
    own = getattr(sig, family)
    if not generic.get("searched") or not own or own.get("form") == form or form == SCAN_FORM:
        return  # (an offset by scan direction is no form in time or across the sample)
    terms = parse_generic_terms(
        [{k: v for k, v in term.items() if k != "sigma"} for term in generic["terms"]]
    )
    amplitudes = [term.amplitude for term in terms]
    if "periodic" in form:
        params = {"period": terms[0].param("period"), "amplitude": math.hypot(*amplitudes[:2])}
    elif form.startswith("linear in"):
        params = {"gradient": amplitudes}
    elif form == "linear trend":
        params = {"slope": amplitudes[0]}
    elif form == "step":
        params = {"time": terms[0].param("t0"), "size": amplitudes[0]}
    else:  # smooth: Legendre degrees over one span
        t0, t1 = terms[0].param("t0"), terms[0].param("t1")
        ends = np.array([t0, t1])
        level = sum(term.offset(ends, 0 * ends, 0 * ends) for term in terms)
        degree = int(max(term.param("degree") for term in terms))
        params = {"degree": degree, "t0": t0, "t1": t1, "change": float(level[1] - level[0])}
    generic["read_at_features"] = own.get("form")
    setattr(sig, family, dict(own, form=form, params=params))
    sig.time["primary"] = family == "time"
    sig.space["primary"] = family == "space"
    sig.sentences = sentences(sig, ALPHA)


def model_sentence(generic: dict) -> str:
    """The generic model in words: its form and shape as fitted on the samples the features
    take (which may differ from the form the features show at their labelled places), and
    what it does to the held-out blocks."""
    terms, form = generic["terms"], generic["form"]
    shape = ""
    if "period" in terms[0]:
        amplitude = math.hypot(*(t["amplitude"] for t in terms[:2]))
        unit = "s" if terms[0]["form"] == "time_sine" else "um"
        period = terms[0]["period"] * (1.0 if unit == "s" else 1e6)
        shape = f", period {period:.3g} {unit}, amplitude {amplitude * 1e9:.3g} nm"
    elif terms[0]["form"] == "time_step":
        shape = f" of {terms[0]['amplitude'] * 1e9:.3g} nm at t = {terms[0]['t0']:.0f} s"
    elif terms[0]["form"] == "scan_direction":
        shape = (
            f", forward less backward scan lines {terms[0]['amplitude'] * 1e9:.3g} "
            f"+- {terms[0]['sigma'] * 1e9:.2g} nm"
        )
    if generic["signal"] not in ("height", "x_position", "y_position"):
        shape = ""  # the shapes above are in m
    if terms[0]["form"] == "deflection_proportional":
        shape = f", {terms[0]['amplitude']:.3g} rad per m of deflection"
    h = generic["heldout"]
    read = generic.get("read_at_features")
    read = f" (at the features' labelled places it reads as {read})" if read else ""
    return (
        f"Its simplest generic model, fitted on the {generic['signal']} samples the features "
        f"take, is {form}{shape}{read}; re-simulated, it {heldout_share_words(h)}."
    )


def generic_yaml(generic: dict) -> str:
    """The fitted generic terms as a config file the simulator loads (`generic_terms:`), each
    marked as a generic description."""
    entries = [
        {k: v for k, v in term.items() if k != "sigma"} | {"description": DESCRIPTION}
        for term in generic.get("terms", [])
    ]
    head = f"# {DESCRIPTION}.\n# Load with afm_core.sim.config.load_config(this file).\n"
    return head + yaml.safe_dump({"generic_terms": entries}, sort_keys=False)


def generic_section(diagnosis, out: Path) -> list[str]:
    """The report's section on what no library term explains (its signature, the generic fit
    and its held-out check); writes OUT/generic_terms.yaml. [] when there is nothing."""
    sig, generic = getattr(diagnosis, "signature", None), getattr(diagnosis, "generic", {}) or {}
    if sig is None:
        return []
    lines = ["## What no library term explains", "", *sig.sentences, ""]
    if not generic.get("fitted"):
        lines += [f"No generic term fitted: {generic.get('reason', 'nothing to fit')}.", ""]
        return lines
    h = generic["heldout"]
    lines += [
        f"Generic model ({generic['form']} on the {generic['signal']} signal; a description, "
        "not a library term, so not in `updated_config.yaml`):",
        "",
        "| form | amplitude (SI) | +- | parameters |",
        "|---|---|---|---|",
    ]
    for term in generic["terms"]:
        extra = ", ".join(
            f"{k} = {v:.4g}"
            for k, v in term.items()
            if k not in ("signal", "form", "amplitude", "sigma")
        )
        lines.append(
            f"| {term['form']} | {term['amplitude']:.4g} | {term['sigma']:.2g} | {extra} |"
        )
    where = ", ".join(generic.get("reached", [])) or "all groups"
    whole = h.get("all_groups", h)
    removed = (
        f"{h['excess_reduction']:.0%} of the excess removed"
        if np.isfinite(h["excess_reduction"])
        else f"no share of the excess to give: it {heldout_share_words(h)}"
    )
    lines += [
        "",
        f"Held-out (fitted on the other fold, re-simulated), in the groups the term reaches "
        f"({where}): chi2 {h['chi2_before']:.1f} -> {h['chi2_after']:.1f} for {h['dof']} dof; "
        f"{removed}; "
        f"{'within' if h['within_noise'] else 'still beyond'} the noise "
        f"({HELDOUT_QUANTILE:.0%} quantile). Over the whole session: chi2 "
        f"{whole['chi2_before']:.1f} -> {whole['chi2_after']:.1f} for {whole['dof']} dof.",
        "",
        "The fitted term: `generic_terms.yaml` (load it as a simulator config file).",
        "",
    ]
    (out / "generic_terms.yaml").write_text(generic_yaml(generic))
    return lines
