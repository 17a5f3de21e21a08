"""The friction-region candidate, whose form comes from the data: friction changed in one
patch of the sample. regions.py finds the rectangle from the slides' torsion; its four edges
count as parameters (p = 5), the held-out check searches the patch again on the training blocks
alone, and the factor's sigma is widened to its spread over searches with one time block left
out (the edges are found in the same torsion)."""

from __future__ import annotations

import math

import numpy as np

from afm_core.sim.config import SimConfig
from afm_core.sim2real import regions
from afm_core.sim2real.candidates import FrictionRegion, has_key
from afm_core.sim2real.feature_table import Table
from afm_core.sim2real.features import SEGMENT
from afm_core.sim2real.noise_model import NoiseModel, Whitener, gls

# smallest change of a friction region's factor its design column is taken over
REGION_MIN_STEP = 0.05


def friction_region(
    design: dict,
    config: SimConfig,
    table: Table,
    r: np.ndarray,
    d_rec: np.ndarray,
    noise: NoiseModel,
):
    """The friction-region candidate at the rectangle where the slides' torsion residual
    follows the friction's effect best (sim2real.regions: searched between segment centres,
    then its edges moved continuously), or None; and the function the held-out check uses to
    search the region again on the training blocks alone (training mask -> column or None),
    with the linear column effect x overlap (the torsion is linear in mu: the global
    friction's sensitivity gives the effect)."""
    if "friction" not in design or not has_key(config, "contact.friction_regions"):
        return None, lambda train: None
    _, mu, friction_cols = design["friction"]
    torsion = table.groups == "push.torsion"
    effect = np.where(torsion, mu[0] * friction_cols[:, 0], 0.0)  # d torsion / d (region's scale)
    points = regions.sample_points(table.xy, d_rec)
    axes = [c.get("axis", "x") for c in table.conditions]
    lengths = np.array([c.get("segment_length", SEGMENT) for c in table.conditions])

    def search(mask):
        sel = np.flatnonzero(torsion & mask)
        found = regions.best_region(
            points[sel],
            effect[sel],
            r[sel],
            noise.cov[np.ix_(sel, sel)],
            slides=table.op_index[sel],
        )
        if found is None:
            return None
        return regions.refine_region(
            points[sel],
            [axes[i] for i in sel],
            lengths[sel],
            effect[sel],
            r[sel],
            noise.cov[np.ix_(sel, sel)],
            found[0],
        )

    def fold_column(train):
        found = search(train)
        return (
            None
            if found is None
            else (effect * regions.overlap(points, axes, lengths, found[0]))[:, None]
        )

    found = search(np.ones(len(r), bool))
    if found is None:
        return None, fold_column
    bounds, _, change = found
    # the design column is the secant to the factor the torsion says (regions' doc)
    step = change if abs(change) >= REGION_MIN_STEP else math.copysign(REGION_MIN_STEP, change)
    return FrictionRegion.at(bounds, step=max(step, -0.95)), fold_column


def region_jackknife_sigma(
    region_columns, r: np.ndarray, P: np.ndarray, cov: np.ndarray, blocks: np.ndarray
):
    """The friction patch's factor's spread over the session with one time block left out at a
    time, the patch searched again each time (the delete-one jackknife). The factor's own
    sigma takes the patch's edges as known, but they are found in the same torsion: an edge a
    few tens of nm off over 250 nm segments shifts the factor more than the torsion's noise
    does (0.4225 +- 0.0006 against 0.413). Zero when fewer than three searches find a patch."""
    estimates = []
    for block in np.unique(blocks):
        train = blocks != block
        column = region_columns(train)
        if column is None:
            continue
        white = Whitener(cov[np.ix_(train, train)])
        coef, _, _ = gls(white(r[train]), white(np.hstack([P[train], column[train]])))
        estimates.append(float(coef[-1]))
    if len(estimates) < 3:
        return np.zeros(1)
    return np.array([math.sqrt(len(estimates) - 1) * float(np.std(estimates))])


def with_region(first: np.ndarray, region: np.ndarray | None) -> np.ndarray:
    """The first term's columns and the region's (none found on these training blocks: a
    zero column, so the fold counts as predicting nothing more)."""
    return np.hstack([first, np.zeros((len(first), 1)) if region is None else region])
