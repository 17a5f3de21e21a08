"""When the configuration does not reproduce the recording (reference.py's ConfigMismatchError:
its images show other numbers of particles, or the particles are not where the recording saw
them), whether a scanner term of the library would: the scanner puts the tip elsewhere than
the model says (a hysteresis loop wider than calibrated, a feed-forward's error, cross-coupling,
rotation, creep), and the images then show other particles than the sample's model at the
commanded positions. Each such term is set to a few values across its range; at each, the
drift trajectory is fitted again (stage A of drift_trajectory.py, with the term's scanner) and
the session re-simulated. A term that passes the check (particles seen and features
reproduced, each at least reference.MIN_MATCHED_FRACTION of the other, better than the
configuration does) is named in the message as the likely cause, with its value; none: the
sample or the area, saying what was tried."""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from afm_core.sim.config import SimConfig
from afm_core.sim2real.candidates import Candidate, available, library
from afm_core.sim2real.drift_trajectory import ScannerMap, drift_trajectory
from afm_core.sim2real.feature_table import NOISE_GROUPS, by_key
from afm_core.sim2real.features import extract_features
from afm_core.sim2real.protocol import deterministic, replay

# where across a bounded term's range its trial values lie (quarters' centres: the range
# covered evenly with four re-simulations)
RANGE_POINTS = (0.125, 0.375, 0.625, 0.875)
# an unbounded term (a rotation in degrees): its trial values in multiples of its
# finite-difference step either side of the model's value
UNBOUNDED_STEPS = (-8.0, -4.0, 4.0, 8.0)


def scanner_terms(config: SimConfig) -> list[Candidate]:
    """The library's terms that move where the scanner puts the tip (geometric, on the scanner
    or its controller), that can act in `config`."""
    terms, _ = available(config, library())
    return [
        c
        for c in terms
        if c.geometric and all(k.startswith(("scanner.", "controller.")) for k in c.keys)
    ]


def trial_values(cand: Candidate, nominal: np.ndarray) -> list[np.ndarray]:
    """A few values of the term across its range (every parameter of a two-parameter term
    together: a symmetric coupling), the model's own left out."""
    out = []
    if cand.lower is not None and cand.upper is not None:
        lower, upper = np.asarray(cand.lower, float), np.asarray(cand.upper, float)
        values = [lower + q * (upper - lower) for q in RANGE_POINTS]
    else:
        values = [nominal + k * np.asarray(cand.steps, float) for k in UNBOUNDED_STEPS]
    for v in values:
        v = cand.clip(v)
        if not np.allclose(v, nominal):
            out.append(v)
    return out


class Agreement(NamedTuple):
    """How a re-simulation agrees with the recording (the configuration check's two counts)."""

    seen_rec: int  # particles the recording's images show
    seen_sim: int  # the simulation's
    seen_ratio: float  # the smaller over the larger
    n_rec: int  # recorded features of the sample (noise statistics are on any sample)
    n_sim: int  # simulated ones
    n_both: int  # reproduced ones
    feature_ratio: float  # the smaller share of the two reproduced
    images: int  # the recording's images

    @property
    def score(self) -> float:
        """The worse of the two agreements."""
        return min(self.seen_ratio, self.feature_ratio)


def agreement(particles_seen: dict, sim_seen: dict, f_rec: dict, f_sim: dict) -> Agreement:
    """The recording (its particles seen per image, its features) against a simulation's."""
    seen_rec, seen_sim = (
        sum(seen.get(k, 0) for k in particles_seen) for seen in (particles_seen, sim_seen)
    )
    on_sample = {k for k, f in f_rec.items() if f.group not in NOISE_GROUPS}
    sim_on_sample = {k for k, f in f_sim.items() if f.group not in NOISE_GROUPS}
    both = on_sample & sim_on_sample
    return Agreement(
        seen_rec,
        seen_sim,
        min(seen_rec, seen_sim) / max(seen_rec, seen_sim, 1),
        len(on_sample),
        len(sim_on_sample),
        len(both),
        min(len(both) / max(len(on_sample), 1), len(both) / max(len(sim_on_sample), 1)),
        len(particles_seen),
    )


def agreement_with(ops, f_rec: dict, particles_seen: dict, config: SimConfig, anchors, t_end):
    """`agreement` of the re-simulation with `config` at the drift trajectory fitted with its
    scanner (stage A)."""
    scanner_map = ScannerMap(ops, f_rec, config, anchors)
    drift = drift_trajectory(
        scanner_map.obs, config, t_end, scanner_map.moves, spans=scanner_map.spans
    )
    seen: dict = {}
    run = replay(ops, deterministic(config), drift=drift)
    f_sim = by_key(extract_features(run.operations, anchors, seen))
    return agreement(particles_seen, seen, f_rec, f_sim)


def likely_scanner_causes(
    ops,
    f_rec: dict,
    particles_seen: dict,
    config: SimConfig,
    anchors,
    t_end: float,
    nominal_score: float,
    fraction: float,
    say: Callable[[str], None] = lambda message: None,
) -> tuple[list, list]:
    """([(term, value array, its agreement, the model's values)] of the scanner terms at which
    the re-simulation reproduces the recording (its score at least `fraction` and above the
    configuration's `nominal_score`), best first; [names of the terms tried])."""
    found, tried = [], []
    for cand in scanner_terms(config):
        tried.append(cand.name)
        say(f"config mismatch: trying {cand.name}")
        nominal = cand.nominal(config)
        best = None
        for value in trial_values(cand, nominal):
            try:
                agree = agreement_with(
                    ops, f_rec, particles_seen, cand.apply(config, value), anchors, t_end
                )
            except (ValueError, RuntimeError, np.linalg.LinAlgError):
                continue  # a value the scanner cannot drive (out of range, say): not a cause
            if (
                agree.score >= fraction
                and agree.score > nominal_score
                and (best is None or agree.score > best[2].score)
            ):
                best = (cand, value, agree, nominal)
        if best is not None:
            found.append(best)
    found.sort(key=lambda f: -f[2].score)
    return found, tried


def cause_words(found: list, tried: list) -> str:
    """The sentence the mismatch message ends with: the scanner terms that would reproduce the
    recording's particles, or that none of those tried did."""
    if not found:
        return (
            f" No scanner term of the library reproduces the recording either (tried, each at "
            f"{len(RANGE_POINTS)} values across its range: {', '.join(tried) or 'none'}). "
            "Check the sample (particle positions, seed) and the scanner area in the config."
        )
    parts = []
    for cand, value, agree, nominal in found:
        shown = ", ".join(
            f"{key} {v:.3g} x the config's"
            if cand.scale
            else f"{key} about {v:.3g} (the config has {n:.3g})"
            for key, v, n in zip(cand.keys, value, nominal)
        )
        parts.append(
            f"{cand.words}: {shown}, whose images show {agree.seen_sim} particles and which "
            f"reproduces {agree.n_both} of the {agree.n_rec} recorded features of the sample"
        )
    effects = ",".join(c.name for c, _, _, _ in found)
    return (
        " Likely cause: the scanner put the tip elsewhere than the model says. Re-simulated with "
        f"each scanner term of the library at {len(RANGE_POINTS)} values across its range "
        f"(tried: {', '.join(tried)}), the re-simulation reproduces the recording with "
        f"{'; or '.join(parts)}. Check the scanner calibration: set that value in the config "
        f"and rerun (--effects {effects} then fits it); if the calibration is right, check the "
        "sample (particle positions, seed) and the scanner area in the config."
    )
