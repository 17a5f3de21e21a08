"""A Diagnosis made from a verdict stage's Decision on a fake session, so a test can read its
summary as a user would (shared by the verdict and simpler-term tests)."""

from __future__ import annotations

from afm_core.sim.config import merge
from afm_core.sim2real.results import Diagnosis


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
