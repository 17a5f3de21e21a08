"""Sim-to-real diagnosis: where a recording deviates from the nominal simulation, which physics
is missing, its fitted parameters, and the improvement on held-out operations.

The stages, in the order `diagnose` runs them (all SI; each module's docstring says its method):

1. Features of every operation (features.py), recorded and re-simulated, compared key by key
   (feature_table.py).
2. The reference at the recorded geometry (reference.py), without the features the
   re-simulation cannot reproduce in an ordinary session (exclusions.py: pushed particles'
   contact history, single lines' chords): the drift trajectory that puts the
   particles where the recording saw them (drift_trajectory.py), the deterministic
   re-simulation with it, each feature's drift sensitivity J, the sensor-noise replicas, and
   the shape features' covariance from the substrate's surface, which the model never knows
   (sample_realization.py).
3. Sensor noise first (noise_term.py): the noise terms tested on the noise statistics alone;
   a named noise level redraws the replicas. Then the noise model and GLS (noise_model.py).
4. Candidates (candidates.py: config keys): design columns by re-simulation
   (design_columns.py; the friction patch from the data: region_candidate.py); the terms the
   session cannot tell are set aside, and a session that can tell none, or has too few
   features, is refused with the protocol suggested (session_scope.py); the evidence
   of each alone (evidence.py: Bonferroni, BIC, held-out blocks), the leaders compared
   re-simulated at their refined values (refinement.py), a second term on top of the first
   (second_term.py).
5. Where the nominal model deviates, by condition (deviations.py); the chosen terms' values,
   sigmas and the updated configuration.
6. Held-out demonstration (heldout.py): fit on one fold only, re-simulate the whole session
   with that fit, residuals on the other fold before and after; the naming rule and the
   verdict on it (verdict.py: named, partly explained, not explained by the library, no
   missing physics); a named set then meets the simplest generic form of the same residual
   (rival.py): no better than it, "partly explained (this session cannot tell)", no update.
7. What no library term explains (generic_fit.py): its signature (signature.py) and a generic
   simulator term of that form, fitted and checked on held-out blocks the same way.
"""

from __future__ import annotations

import contextlib
import time as _time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from afm_core.recording import RecordingError
from afm_core.recording.bag_folder import recording_file
from afm_core.sim.config import SimConfig, load_config, merge
from afm_core.sim2real.candidates import available, library, select
from afm_core.sim2real.design_columns import design_columns
from afm_core.sim2real.deviations import nominal_deviations
from afm_core.sim2real.drift_trajectory import nominal_drift
from afm_core.sim2real.evidence import ALPHA, weigh_candidates
from afm_core.sim2real.generic_fit import (
    describe_unexplained,
    model_sentence,
    quadratic_height_fit,
)
from afm_core.sim2real.heldout import fold_blocks
from afm_core.sim2real.noise_model import nuisance_columns, session_noise_model
from afm_core.sim2real.noise_term import sensor_noise_first
from afm_core.sim2real.reference import NoFeaturesError, build_reference
from afm_core.sim2real.refinement import compare_leaders
from afm_core.sim2real.replication import heldout_confirms
from afm_core.sim2real.report import write_report
from afm_core.sim2real.results import (
    NAMED,
    NO_MISSING_PHYSICS,
    NOT_EXPLAINED,
    PARTLY_EXPLAINED,
    Diagnosis,
)
from afm_core.sim2real.rival import (
    HEIGHT_SHAPE_TERMS,
    closest_rival,
    compare_rival,
    rival_words,
    ruling,
)
from afm_core.sim2real.second_term import add_second_term
from afm_core.sim2real.session import SessionError
from afm_core.sim2real.session_reader import read_operations
from afm_core.sim2real.session_scope import (
    cannot_tell,
    check_enough_features,
    check_something_to_tell,
)
from afm_core.sim2real.simpler_term import prefer_simpler
from afm_core.sim2real.verdict import decide, runner_up


def diagnose(
    recorded_ops,
    config: SimConfig,
    *,
    sensor_replicas: int = 2,
    candidates: list | None = None,
    n_blocks: int = 6,
    refine_iterations: int = 2,
    heldout_resimulation: bool = True,
    progress: Callable[[str], None] | None = None,
) -> Diagnosis:
    """The four answers for a recorded session (a list of Operations) against `config`, by the
    stages of this module's docstring. The noise is modelled at the recorded geometry from
    `sensor_replicas` re-simulations and the analytic drift and walk terms."""
    say = progress or (lambda message: None)
    timed = _Timings()
    with timed("reference"):
        sess = build_reference(recorded_ops, config, sensor_replicas, say)
    check_enough_features(sess)
    blocks = fold_blocks(sess.table, sess.ops, n_blocks)
    folds = [blocks % 2 == 0, blocks % 2 == 1]
    cands, missing = available(config, candidates)
    m = max(1, len(cands) + 1)  # the library and the searched friction region
    with timed("noise"):
        noise_first = sensor_noise_first(sess, cands, folds, m, missing, say)
    cands = [c for c in cands if c.analytic != "sensor_noise"]
    noise = session_noise_model(sess, noise_first.config, noise_first.replicas)
    P = nuisance_columns(sess.table, sess.J)
    with timed("sensitivities"):
        design = design_columns(sess, cands, noise, P, m, missing, say)
    # a term the session cannot tell is reported so, never weighed (session_scope.py)
    untold = cannot_tell(design.terms, noise, P)
    if noise_first.result is None or not noise_first.result.accepted:
        check_something_to_tell(design.terms, untold)  # (a named noise level is something)
    for row in untold:
        design.terms.pop(row["term"], None)
    evidence = weigh_candidates(
        sess, design, noise, P, folds, m, noise_first.terms, noise_first.result
    )
    with timed("compare"):
        leader = compare_leaders(sess, design, evidence, refine_iterations, blocks, say)
    tried, checked = [], {}
    if leader is not None:
        chosen, theta, sigma, checked = add_second_term(
            sess, design, evidence, leader, refine_iterations, heldout_resimulation, say
        )
        tried = [(chosen, theta, sigma)]
        if len(chosen) > 1:  # the leader alone, should the pair not be named
            tried.append((chosen[:1], leader.theta, leader.sigma))
        # the runner-up, fitted only should the leader not be named either
        tried.append(runner_up(sess, design, evidence, leader.name, refine_iterations, say))
    deviations = nominal_deviations(sess, evidence)
    with timed("heldout"):
        decision = decide(
            sess,
            evidence,
            config,
            design.terms,
            noise_first,
            tried,
            checked,
            refine_iterations,
            heldout_resimulation,
            say,
        )
        if heldout_resimulation:  # a simpler term as good on the held-out blocks is named
            decision = prefer_simpler(
                sess, evidence, config, design.terms, noise_first, decision,
                refine_iterations, say,
            )  # fmt: skip
    chosen, parameters, overrides = decision.chosen, decision.parameters, decision.overrides
    heldout = decision.heldout
    with timed("generic"):
        verdict, note, rival, signature, generic = _judged_and_described(
            sess, evidence, deviations, design.terms, decision, heldout_resimulation, say
        )
    # a term not named (its held-out check got worse, say), or one this session cannot tell
    # from a generic form, updates no configuration
    if rival and not rival["library_better"]:
        overrides = {}
    updated = merge(config, overrides) if chosen and overrides else None
    verdict, note = _unexplained_or_not(
        verdict, note, chosen, signature, generic, evidence.overall(), deviations.rows
    )
    timings = timed.finish(replays=float(sess.replays + 5 + sensor_replicas))
    return Diagnosis(
        n_features=len(sess.keys),
        groups=deviations.group_stats,
        overall=evidence.overall(),
        where=deviations.rows,
        change_points=deviations.change_points,
        candidates=evidence.results,
        chosen=chosen,
        parameters=parameters,
        overrides=overrides,
        updated_config=updated,
        heldout=heldout,
        missing_candidates=missing,
        timings=timings,
        not_considered=_left_out(candidates),
        residuals=_residual_arrays(sess, deviations, noise, folds, heldout if chosen else {}),
        drift={
            "times": sess.drift.times,
            "offsets": sess.drift.offsets,
            "nominal": nominal_drift(config, sess.drift.times),
        },
        verdict=verdict,
        remaining=decision.remaining,
        verdict_note=note,
        excluded=list(sess.exclusions.rows),
        cannot_tell=untold,
        signature=signature,
        generic=generic,
        rival=rival,
    )


def _judged_and_described(sess, evidence, deviations, terms, decision, resimulate, say):
    """(verdict, note, rival, signature, generic fit): the named terms against their generic
    rival (rival.py), and what no library term explains (generic_fit.describe_unexplained),
    the nominal residual's own description when the session cannot tell them apart."""
    rival, signature, generic = _generic_rival(
        sess, evidence, deviations, terms, decision, resimulate, say
    )
    verdict, note = ruling(decision.verdict, rival), decision.note
    if rival and not rival["library_better"]:
        note = "; ".join(filter(None, [note, rival_words(rival, decision.chosen)]))
    else:
        signature, generic = describe_unexplained(
            sess,
            evidence,
            deviations,
            terms,
            decision.chosen,
            decision.parameters,
            decision.heldout,
            say,
        )
    return verdict, note, rival, signature, generic


def _generic_rival(sess, evidence, deviations, terms, decision, resimulate: bool, say):
    """(rival comparison, signature, generic fit) of a set of named library terms (rival.py):
    the nominal residual described and its generic form fitted and re-simulated, compared with
    the named terms on the held-out blocks. ({}, None, {}) when there is nothing to compare:
    nothing named, no held-out demonstration, or a sensor-noise term alone (a noise level is
    judged on the noise statistics, which no generic offset moves)."""
    library = [n for n in decision.chosen if terms[n][0].analytic != "sensor_noise"]
    if decision.verdict not in (NAMED, PARTLY_EXPLAINED) or not resimulate or not library:
        return {}, None, {}
    say("the named terms against the generic form of the nominal residual")
    signature, generic = describe_unexplained(sess, evidence, deviations, terms, [], {}, {}, say)
    if signature is None:
        return {}, None, {}
    rival = compare_rival(evidence, decision.heldout, generic, sess.r_before)
    if set(HEIGHT_SHAPE_TERMS) <= set(library):  # a z nonlinearity imitates the pair (rival.py)
        try:
            quadratic = quadratic_height_fit(sess, evidence, sess.r.copy(), signature, say)
        except ValueError as exc:  # a model the simulator refuses is no rival
            quadratic = {"fitted": False, "reason": str(exc)}
        other = compare_rival(evidence, decision.heldout, quadratic, sess.r_before)
        if other and closest_rival([rival, other]) is other:
            rival, generic = other, quadratic
            signature.sentences.append(model_sentence(quadratic))
    if rival:
        say(
            f"held-out chi2 {rival['chi2_library']:.1f} (library) against "
            f"{rival['chi2_generic']:.1f} (generic {rival['form']}; bound {rival['bound']:.1f})"
        )
    return rival, signature, generic


def _unexplained_or_not(verdict, note, chosen, signature, generic, overall, where_rows):
    """(verdict, note) once what nothing named leaves is weighed: one group beyond its own noise
    although the whole residual is not is still unexplained; an excess without structure is a
    noise model too optimistic; a one-sub-test verdict must hold on the held-out blocks
    (replication.py)."""
    if verdict == NO_MISSING_PHYSICS and signature is not None and signature.signals:
        verdict = NOT_EXPLAINED
    elif verdict == NOT_EXPLAINED and not chosen and not _structured(signature, where_rows):
        verdict = NO_MISSING_PHYSICS
        note = _unstructured_note(overall, note)
    if verdict == NOT_EXPLAINED and not chosen:
        stands, why = heldout_confirms(overall, generic)
        if not stands:
            verdict = NO_MISSING_PHYSICS
            note = "; ".join(filter(None, [note, f"a hint, not confirmed: {why}"]))
    return verdict, note


def _structured(signature, where_rows: list) -> bool:
    """Whether an excess over the noise model has a structure physics would give it: a signal
    the signature describes, or a signal and condition whose mean departs (Bonferroni p < ALPHA
    over the rows of "where"). An excess spread evenly, with no mean and no form anywhere, is a
    noise model too optimistic for the recording (a rougher substrate than the replicas', say),
    not a term the library lacks; calling it missing physics was the false alarm on nulls."""
    if signature is not None and signature.signals:
        return True
    return any(row["p_mean_bonferroni"] < ALPHA for row in where_rows)


def _unstructured_note(overall: dict, note: str) -> str:
    words = (
        f"the residual exceeds the noise model (chi2 {overall['chi2']:.1f} for {overall['dof']} "
        f"dof, variance factor {overall['variance_factor']:.2f}) without structure: no signal "
        f"or condition departs in its mean (Bonferroni p < {ALPHA:g}) and no form in time or "
        "across the sample is described; the noise model is too optimistic for this recording, "
        "not a term missing"
    )
    return f"{note}; {words}" if note else words


class _Timings:
    """Wall time per stage (`with timed("stage"):`), and the total since it was made."""

    def __init__(self):
        self.start = _time.perf_counter()
        self.timings: dict = {}

    @contextlib.contextmanager
    def __call__(self, stage: str):
        t0 = _time.perf_counter()
        yield
        self.timings[stage] = _time.perf_counter() - t0

    def finish(self, **extra) -> dict:
        self.timings["total"] = _time.perf_counter() - self.start
        return {**self.timings, **extra}


def _residual_arrays(sess, deviations, noise, folds: list, heldout: dict) -> dict:
    """The arrays the report plots: the nominal model's residual (and after the nuisance
    fit), its noise sigma, the folds, the residual after the held-out fit."""
    return {
        "table": sess.table,
        "r": sess.r_before,
        "e": deviations.e,
        "sigma": np.sqrt(np.diag(noise.cov)),
        "folds": folds,
        "after": heldout.get("r_after"),
    }


def _left_out(candidates) -> list[str]:
    """Names of the library terms a caller's candidate list leaves out (None: the library)."""
    given = {c.name for c in (library() if candidates is None else candidates)}
    return [c.name for c in library() if c.name not in given]


def run_sim2real(
    recording_path,
    config_path,
    report_dir,
    progress=None,
    missing_data: str = "error",
    effects=None,
    **kw,
) -> Diagnosis:
    """Read a recording (MCAP), diagnose it against the simulator config, write the report and
    the updated config into report_dir. Raises ValueError subclasses with clear messages.
    missing_data="skip" leaves out commands whose measurement is not in the file (a snapshot
    of a recording still being written ends mid-operation); "error" refuses them. `effects`:
    names of library terms to consider (candidates.select), None or empty: all of them."""
    try:
        recording_path = recording_file(Path(recording_path))  # a rosbag2 folder: its MCAP
    except RecordingError as exc:
        raise SessionError(str(exc)) from None
    if not recording_path.is_file():
        raise FileNotFoundError(f"recording {str(recording_path)!r} does not exist")
    candidates = select(effects)  # before the reading: a misspelt effect costs nothing
    config = load_config(config_path) if config_path is not None else load_config()
    with read_operations(recording_path, missing_data=missing_data) as operations:
        try:
            diagnosis = diagnose(
                operations, config, progress=progress, candidates=candidates, **kw
            )
        except NoFeaturesError as exc:
            raise type(exc)(f"recording {str(recording_path)!r}: {exc}") from exc
    write_report(diagnosis, Path(report_dir), config=config, recording=str(recording_path))
    return diagnosis
