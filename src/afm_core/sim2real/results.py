"""What a sim-to-real diagnosis found (`Diagnosis`: where the recording deviates, the missing
physics, its fitted parameters, the held-out check) and each candidate term's evidence
(`CandidateResult`), as the report and the callers read them."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from afm_core.sim.config import SimConfig

# overall chi^2 p below which a residual no term explains is not called noise
UNEXPLAINED_P = 1e-3

# the verdicts (verdict.py says when each is given)
NAMED = "named"  # the terms' fit leaves the held-out blocks within their noise
PARTLY_EXPLAINED = "partly explained"  # the terms remove most of the held-out excess, not all
NOT_EXPLAINED = "not explained by the library"  # beyond the noise, no term qualifies
NO_MISSING_PHYSICS = "no missing physics"  # residuals consistent with the noise model


@dataclass
class CandidateResult:
    name: str
    words: str
    keys: list
    units: list
    size: int
    estimate: np.ndarray = None  # config values (linearised fit, all data)
    sigma: np.ndarray = None
    delta_chi2: float = 0.0  # over the nuisance-only model, scaled
    statistic_threshold: float = 0.0
    bic_gain: float = 0.0
    heldout_gain: float = 0.0  # chi^2 improvement on held-out blocks
    significant: bool = False
    accepted: bool = False
    note: str = ""


@dataclass
class Diagnosis:
    n_features: int
    groups: dict  # group -> {n, chi2, dof, p}
    overall: dict  # chi2, dof, p, variance factor
    where: list  # deviations by condition, most significant first
    change_points: list
    candidates: list  # CandidateResult, best first
    chosen: list  # names of the named terms (named or partly explained; else [])
    parameters: dict  # key -> {value, sigma, nominal}
    overrides: dict  # nested config overrides of the fitted terms
    updated_config: SimConfig | None
    heldout: dict  # before/after on held-out operations
    missing_candidates: list
    timings: dict
    residuals: dict = field(default_factory=dict)  # arrays for plots
    message: str = ""
    drift: dict = field(default_factory=dict)  # the recorded drift trajectory (times, offsets)
    not_considered: list = field(default_factory=list)  # library terms left out by the caller
    # NAMED, PARTLY_EXPLAINED, NOT_EXPLAINED or NO_MISSING_PHYSICS ("": from `chosen` and the
    # overall p, for a Diagnosis made by hand)
    verdict: str = ""
    remaining: list = field(default_factory=list)  # partly explained: where the excess remains
    verdict_note: str = ""  # what was tried and why it was not named (or what it could be)

    def __post_init__(self):
        if not self.verdict:
            self.verdict = (
                NAMED
                if self.chosen
                else NOT_EXPLAINED
                if self.overall.get("p", 1.0) < UNEXPLAINED_P
                else NO_MISSING_PHYSICS
            )

    # features the re-simulation cannot reproduce, left out: {what, count, reason}
    excluded: list = field(default_factory=list)
    # terms this session cannot inform: {term, reason} (session_scope.py)
    cannot_tell: list = field(default_factory=list)
    signature: object = None  # signature.Signature of what no term explains (None: nothing left)
    generic: dict = field(default_factory=dict)  # generic_fit.generic_fit: the generic term
    # rival.compare_rival: the named terms against the generic form of the nominal residual
    # ({} when none was compared); library_better False: this session cannot tell them apart
    rival: dict = field(default_factory=dict)

    @property
    def cannot_tell_generic(self) -> bool:
        """Whether the chosen terms are no better than a generic form of the same residual
        (rival.py): partly explained, no updated configuration."""
        return bool(self.rival) and not self.rival.get("library_better", True)

    @property
    def missing_physics(self) -> bool:
        """Whether the recording shows physics the model lacks (named, partly explained or not
        explained by the library)."""
        return self.verdict != NO_MISSING_PHYSICS

    def summary(self) -> str:
        tried = f" ({self.verdict_note})" if self.verdict_note else ""
        if not self.chosen:
            fit = (
                f"chi2 {self.overall['chi2']:.1f} for {self.overall['dof']} dof, "
                f"p = {self.overall['p']:.3g}"
            )
            if self.verdict == NOT_EXPLAINED:
                among = (
                    f"of those considered ({len(self.not_considered)} library terms left out)"
                    if self.not_considered
                    else "in the library"
                )
                # a signal no feature shows (at the samples), or one in a few features (a
                # slow change of the levels, say), leaves the features as a whole within noise
                seen = [
                    row["group"]
                    for row in (self.signature.signals if self.signature is not None else [])
                    if row["group"] in self.groups
                ]
                beyond = (
                    f"exceeds the noise model ({fit})"
                    if self.overall["p"] < UNEXPLAINED_P
                    else f"is beyond its noise in {', '.join(seen)} (all features: {fit})"
                    if seen
                    else f"is beyond its noise where no feature looks (the features: {fit})"
                )
                return (
                    f"{NOT_EXPLAINED}: no candidate {among} explains the residual, which "
                    f"{beyond}: physics the library lacks or a noise "
                    f"model too optimistic (see where it deviates){tried}"
                    f"{self._signature_words()}"
                )
            if self.overall["p"] < UNEXPLAINED_P:  # an excess without structure (diagnose.py)
                return f"{NO_MISSING_PHYSICS} ({fit}){tried}"
            consistent = "residuals consistent with the noise model"
            return f"{NO_MISSING_PHYSICS}: {consistent} ({fit}){tried}"
        parts = []
        for name in self.chosen:
            c = next(c for c in self.candidates if c.name == name)
            values = ", ".join(
                f"{k.split('.')[-1]} = {v['value']:.4g} +- {v['sigma']:.2g} "
                f"(model {v['nominal']:.4g}"
                f"{'; ' + UNRESOLVED if unresolved(v) else ''})"
                for k, v in self.parameters.items()
                if v.get("candidate") == name
            )
            parts.append(f"{c.words}: {values}")
        text = "; ".join(parts) + self._heldout_words()
        if self.cannot_tell_generic:
            r = self.rival
            return (
                f"{PARTLY_EXPLAINED} (this session cannot tell): {' + '.join(self.chosen)} or a "
                f"generic {r['form']} on the {r['signal']} signal; the library does not explain "
                f"the held-out blocks better (chi2 {r['chi2_library']:.1f} with it, "
                f"{r['chi2_generic']:.1f} with the generic form, for {r['dof']} dof; it must do "
                f"better by {r['bound']:.1f}), so no configuration is updated. The library "
                f"term's fit: {text}{self._signature_words()}"
            )
        if self.verdict == PARTLY_EXPLAINED:
            where = "; ".join(
                f"{row['where']} (chi2 {row['chi2']:.1f} for {row['n']})" for row in self.remaining
            )
            where = f", most in {where}" if where else ""
            return (
                f"{PARTLY_EXPLAINED}: {text}; the held-out blocks stay beyond the noise{where}"
                f"{'; ' + self.verdict_note if self.verdict_note else ''}"
                f"{self._signature_words()}"
            )
        # a simpler term named over one the session cannot tell it from says so (simpler_term)
        also = f"; {self.verdict_note}" if self.verdict_note else ""
        return f"{NAMED} (missing physics): {text}{also}"

    def _signature_words(self) -> str:
        """What the residual looks like and how much a generic term of that form explains."""
        if self.signature is None:
            return ""
        text = ". What remains: " + " ".join(self.signature.sentences[:2])
        generic = self.generic or {}
        if generic.get("fitted"):
            text += (
                f" A generic {generic['form']} on the {generic['signal']} signal "
                f"{heldout_share_words(generic['heldout'])} (generic_terms.yaml)"
            )
        return text

    def _heldout_words(self) -> str:
        h = self.heldout
        if not h or "chi2_after" not in h:
            return ""
        share = h.get("excess_reduction", float("nan"))
        return (
            f" (held-out chi2 {h['chi2_before']:.1f} -> {h['chi2_after']:.1f} for {h['dof']} "
            f"dof, {100 * share:.0f} % of the excess over the noise removed)"
        )


def heldout_share_words(h: dict) -> str:
    """A held-out check's share in words: "removes N % of the held-out excess", or why there is
    none (excess_reduction NaN): no held-out degree of freedom where the term acts, or no
    held-out excess over the noise to remove."""
    share = h.get("excess_reduction", float("nan"))
    if np.isfinite(share):
        return f"removes {100 * share:.0f} % of the held-out excess"
    if h.get("dof", 0) <= 0:
        return "cannot be checked on held-out blocks (no held-out degree of freedom where it acts)"
    return (
        f"has no held-out excess to remove (held-out chi2 {h['chi2_before']:.1f} for "
        f"{h['dof']} dof)"
    )


# a fitted change from the model's value within this many sigma is "cannot tell": a null
# session gives a change beyond it with probability 4.6 % per parameter (two-sided normal; the
# 5 % point, evidence.ALPHA's, is 1.96), so a term named on a change within it would be a false
# alarm at more than the rate the diagnosis states
CANNOT_TELL_SIGMAS = 2.0
UNRESOLVED = f"within {CANNOT_TELL_SIGMAS:g} sigma of the model: this session cannot tell"


def unresolved(parameter: dict) -> bool:
    """Whether a fitted parameter of a named term is within CANNOT_TELL_SIGMAS of the model's
    value (one component of a drift whose other one is clear, say: left for the lab to judge,
    not news; a term whose every parameter is so is never named, verdict.py)."""
    change = abs(parameter["value"] - parameter["nominal"])
    return change < CANNOT_TELL_SIGMAS * parameter["sigma"]
