"""Sim-to-real diagnosis: where a recording deviates from the nominal simulation, which physics
is missing, its fitted parameters, and the improvement on held-out operations.

The stages, in the order `diagnose` runs them (all SI; each module's docstring says its method):

1. Features of every operation (features.py), recorded and re-simulated, compared key by key
   (feature_table.py).
2. The reference at the recorded geometry (reference.py): the drift trajectory that puts the
   particles where the recording saw them (drift_trajectory.py), the deterministic
   re-simulation with it, each feature's drift sensitivity J, the sensor-noise replicas.
3. Sensor noise first (noise_term.py): the noise terms tested on the noise statistics alone;
   a named noise level redraws the replicas. Then the noise model and GLS (noise_model.py).
4. Candidates (candidates.py: config keys): design columns by re-simulation
   (design_columns.py; the friction patch from the data: region_candidate.py), the evidence
   of each alone (evidence.py: Bonferroni, BIC, held-out blocks), the leaders compared
   re-simulated at their refined values (refinement.py), a second term on top of the first
   (second_term.py).
5. Where the nominal model deviates, by condition (deviations.py); the chosen terms' values,
   sigmas and the updated configuration.
6. Held-out demonstration (heldout.py): fit on one fold only, re-simulate the whole session
   with that fit, residuals on the other fold before and after.
7. What no library term explains (generic_fit.py): its signature (signature.py) and a generic
   simulator term of that form, fitted and checked on held-out blocks the same way.
"""

from __future__ import annotations

import contextlib
import time as _time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from afm_core.sim.config import SimConfig, load_config, merge
from afm_core.sim2real.candidates import available, library, merge_overrides, select
from afm_core.sim2real.design_columns import design_columns
from afm_core.sim2real.deviations import nominal_deviations
from afm_core.sim2real.drift_trajectory import nominal_drift
from afm_core.sim2real.evidence import weigh_candidates
from afm_core.sim2real.generic_fit import describe_unexplained
from afm_core.sim2real.heldout import fold_blocks, heldout_demonstration
from afm_core.sim2real.noise_model import nuisance_columns, session_noise_model
from afm_core.sim2real.noise_term import NoiseFirst, sensor_noise_first
from afm_core.sim2real.reference import NoFeaturesError, build_reference
from afm_core.sim2real.refinement import compare_leaders
from afm_core.sim2real.report import write_report
from afm_core.sim2real.results import Diagnosis
from afm_core.sim2real.second_term import add_second_term
from afm_core.sim2real.session_reader import read_operations


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
    evidence = weigh_candidates(
        sess, design, noise, P, folds, m, noise_first.terms, noise_first.result
    )
    with timed("compare"):
        leader = compare_leaders(sess, design, evidence, refine_iterations, blocks, say)
    chosen, theta, sigma, checked = [], None, None, {}
    if leader is not None:
        chosen, theta, sigma, checked = add_second_term(
            sess, design, evidence, leader, refine_iterations, heldout_resimulation, say
        )
    deviations = nominal_deviations(sess, evidence)
    with timed("fit"):
        chosen, parameters, overrides = _fitted_terms(
            config, design.terms, chosen, theta, sigma, noise_first
        )
        updated = merge(config, overrides) if chosen else None
    with timed("heldout"):
        heldout = heldout_demonstration(
            sess,
            evidence,
            design.terms,
            chosen,
            parameters,
            checked,
            refine_iterations,
            heldout_resimulation,
            say,
        )
    with timed("generic"):
        signature, generic = describe_unexplained(
            sess, evidence, deviations, design.terms, chosen, parameters, heldout, say
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
        residuals=_residual_arrays(sess, deviations, noise, folds, heldout),
        drift={
            "times": sess.drift.times,
            "offsets": sess.drift.offsets,
            "nominal": nominal_drift(config, sess.drift.times),
        },
        signature=signature,
        generic=generic,
    )


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


def _fitted_terms(config, design: dict, chosen: list, theta, sigma, noise_first: NoiseFirst):
    """(the chosen terms' names, the noise term's first; key -> {value, sigma, nominal,
    candidate}; the nested config overrides of their values). The noise term's design joins
    `design`."""
    parameters, overrides = {}, {}
    offset = 0
    for name in chosen:
        cand, theta0, _ = design[name]
        part = theta[offset : offset + cand.size]
        overrides = merge_overrides(overrides, cand.overrides(config, part))
        for j, key in enumerate(cand.keys):
            parameters[key] = {
                "value": float(theta[offset + j]),
                "sigma": float(sigma[offset + j]),
                "nominal": float(theta0[j]),
                "candidate": name,
            }
        offset += cand.size
    noise_result = noise_first.result
    if noise_result is not None and noise_result.accepted:
        cand, theta0, _ = noise_first.design
        design[cand.name] = noise_first.design
        chosen = [cand.name] + chosen
        overrides = merge_overrides(cand.overrides(config, noise_result.estimate), overrides)
        for j, key in enumerate(cand.keys):
            parameters[key] = {
                "value": float(noise_result.estimate[j]),
                "sigma": float(noise_result.sigma[j]),
                "nominal": float(theta0[j]),
                "candidate": cand.name,
            }
    return chosen, parameters, overrides


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
    recording_path = Path(recording_path)
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
            raise NoFeaturesError(f"recording {str(recording_path)!r}: {exc}") from exc
    write_report(diagnosis, Path(report_dir), config=config, recording=str(recording_path))
    return diagnosis
