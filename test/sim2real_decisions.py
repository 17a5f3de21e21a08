"""A Diagnosis made from a verdict stage's Decision on a fake session, so a test can read its
summary as a user would (shared by the verdict and simpler-term tests)."""

from __future__ import annotations

import numpy as np

from afm_core.sim.config import merge
from afm_core.sim2real.results import CandidateResult, Diagnosis


def accepted_results(lib: dict, names, config, offset: float = 0.0, **extra) -> list:
    """An accepted CandidateResult per named library term, estimated at its nominal value plus
    `offset`, sigma 1 (the earlier stages' output on a fake session)."""
    return [
        CandidateResult(
            n,
            lib[n].words,
            lib[n].keys,
            lib[n].units,
            lib[n].size,
            estimate=lib[n].nominal(config) + offset,
            sigma=np.ones(lib[n].size),
            accepted=True,
            **extra,
        )
        for n in names
    ]


def diagnosis_of(decision, evidence, config, n_features: int) -> Diagnosis:
    return Diagnosis(
        n_features=n_features,
        groups={},
        overall=evidence.overall(),
        where=[],
        change_points=[],
        candidates=evidence.results,
        chosen=decision.chosen,
        parameters=decision.parameters,
        overrides=decision.overrides,
        updated_config=merge(config, decision.overrides) if decision.chosen else None,
        heldout=decision.heldout,
        missing_candidates=[],
        timings={},
        verdict=decision.verdict,
        remaining=decision.remaining,
        verdict_note=decision.note,
    )
