"""What a sim-to-real diagnosis found (`Diagnosis`: where the recording deviates, the missing
physics, its fitted parameters, the held-out check) and each candidate term's evidence
(`CandidateResult`), as the report and the callers read them."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from afm_core.sim.config import SimConfig

# overall chi^2 p below which a residual no term explains is not called noise
UNEXPLAINED_P = 1e-3


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
    chosen: list  # names of the chosen terms ([] = no missing physics)
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
    signature: object = None  # signature.Signature of what no term explains (None: nothing left)
    generic: dict = field(default_factory=dict)  # generic_fit.generic_fit: the generic term

    @property
    def missing_physics(self) -> bool:
        return bool(self.chosen)

    def summary(self) -> str:
        if not self.chosen:
            fit = (
                f"chi2 {self.overall['chi2']:.1f} for {self.overall['dof']} dof, "
                f"p = {self.overall['p']:.3g}"
            )
            if self.overall["p"] < UNEXPLAINED_P or self.signature is not None:
                among = (
                    f"of those considered ({len(self.not_considered)} library terms left out)"
                    if self.not_considered
                    else "in the library"
                )
                return (
                    f"no candidate {among} explains the residual, which exceeds the noise model "
                    f"({fit}): physics the library lacks or a noise model too optimistic (see "
                    "where it deviates)"
                )
            return f"no missing physics: residuals consistent with the noise model ({fit})"
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
        return "missing physics: " + "; ".join(parts)


UNRESOLVED = "within 2 sigma of the model: this session cannot tell"


def unresolved(parameter: dict) -> bool:
    """Whether a fitted parameter of a named term is within 2 sigma of the model's value (one
    component of a drift whose other one is clear, say: left for the lab to judge, not news)."""
    return abs(parameter["value"] - parameter["nominal"]) < 2 * parameter["sigma"]
