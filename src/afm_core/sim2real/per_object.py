"""Whether each particle differs from the model by its own amount, the same in every image.

An effect that is one constant per particle (each particle's apparent height a few % off, its
own way; a particle displaced by a scanner distortion fixed to its place) has no mean over the
particles and no form in time, and the diagnosis' overdispersion factor of its group absorbs it
(line peaks scaled by 350 on a session whose particles are 10 % off): neither "the group
exceeds its noise" nor "every particle changes alike" sees it. The particles' own means do: per
group measured on one particle at a time (scan-line peaks and widths, raster heights, widths
and centroids; a scan line is given to the configured particle nearest its place), generalised
least squares on the group's features, under the full noise model (what it shares between
passes over one place, the substrate's unknown surface, the drift's wander, is not counted
twice) with the nuisance columns, of one offset per particle (seen in at least MIN_IMAGES
operations) against a plane across the particles' places (a scale, a rotation, a drift's
velocity over a frame: the library's terms and the drift model own those). The chi^2 gain is
chi^2(k - 3) for k particles when nothing differs. It is judged against the group's scatter
about its particles' offsets (an F test: a noise model too optimistic by a constant factor
inflates both alike) and also beyond the diagnosis' overdispersion factor of the group (the
positions of a null session's raster particles differ per particle beyond their modelled
noise, not beyond that factor), each at ALPHA over the groups tried.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from afm_core.sim.generic_terms import GenericTerm
from afm_core.sim2real.noise_model import Whitener, gls

# groups measured on one particle each: raster features are keyed by the particle they matched
# (features.py, anchors), a scan line's by the configured particle nearest its place
OBJECT_GROUPS = (
    "line.peak",
    "line.width",
    "raster.height",
    "raster.half_width",
    "line.pos",
    "raster.x",
    "raster.y",
)
MIN_IMAGES = 2  # a particle seen once has no "same in every image"
MIN_OBJECTS = 4  # fewer particles: a plane through their places leaves no pattern
ALPHA = 0.05
# the generic form of a per-particle height offset, and the scale its columns are taken at (a
# proportional term: the column is linear in it, any step near the effect's size gives it)
PER_OBJECT_FORM = "each particle's height scaled by its own factor"
EACH_ITS_OWN = "each particle its own"  # the form across the sample when no form explains them
OBJECT_STEP = 0.05


def particle_tags(table, anchors=None) -> np.ndarray:
    """The particle each feature is keyed by ("" for none): its own key (raster particles),
    else, with `anchors` ((n, 2) configured particle places, m), the anchor nearest the
    feature's place when it is nearer than half the anchors' smallest spacing (so no feature
    between two particles is given to either)."""
    tags = np.array([str(c.get("particle", "")) for c in table.conditions], dtype=object)
    anchors = None if anchors is None else np.asarray(anchors, float).reshape(-1, 2)
    if anchors is None or len(anchors) < 2:
        return tags.astype(str)
    apart = np.hypot(*(anchors[:, None, :] - anchors[None]).transpose(2, 0, 1))
    reach = 0.5 * float(np.min(apart[~np.eye(len(anchors), dtype=bool)]))
    dist = np.hypot(*(table.xy[:, None, :] - anchors[None]).transpose(2, 0, 1))
    near, nearest = dist.argmin(axis=1), dist.min(axis=1)
    untagged = (tags == "") & (nearest < reach)
    tags[untagged] = [str(k) for k in near[untagged]]
    return tags.astype(str)


def object_offsets(table, r, cov, P, anchors=None, factors=None, groups=OBJECT_GROUPS) -> dict:
    """Per particle-keyed group with at least MIN_OBJECTS particles in MIN_IMAGES images each:
    {chi2 (the gain of one offset per particle over one shared), dof, scatter (the group's
    chi^2 per dof about its particles' offsets, >= 1), p (F test, Bonferroni over the groups
    tried), differ (p < ALPHA), objects: {tag: (offset, sigma)} (GLS, SI; sigma scaled by the
    scatter), place: {tag: (x, y)} (the particle's mean place, m)}. r: residual (N, NaN where a
    feature is missing); cov: its noise covariance (N, N); P: the nuisance columns (N, k);
    anchors: the configured particle places (particle_tags); factors: the diagnosis'
    overdispersion per group (a group passes beyond it too)."""
    r = np.asarray(r, float)
    tags = particle_tags(table, anchors)
    ok = np.isfinite(r)
    tried = {}
    for g in groups:
        sel = ok & (table.groups == g) & (tags != "")
        names = [p for p in np.unique(tags[sel]) if (sel & (tags == p)).sum() >= MIN_IMAGES]
        if len(names) >= MIN_OBJECTS:
            tried[g] = names
    out = {}
    for g, names in tried.items():
        row = _one_group(table, r, cov, P, tags, g, names, len(tried))
        if row is None:
            continue
        out[g] = row
        factor = max(1.0, float((factors or {}).get(g, 1.0)), row["scatter"])
        beyond = stats.chi2.sf(row["chi2"] / factor, row["dof"]) * len(tried) < ALPHA
        row["differ"] = row["differ"] and bool(beyond) and _apart(row["objects"], len(tried))
    return out


def _one_group(table, r, cov, P, tags, g: str, names: list, n_groups: int) -> dict | None:
    """The per-particle test of one group (object_offsets): on the group's own features, one
    offset per particle against one shared, scaled by the group's scatter about its particles'
    own offsets (an F test: a noise model too optimistic for the group by a constant factor
    inflates both alike; an effect constant per particle only the first)."""
    idx = np.flatnonzero(np.isfinite(r) & (table.groups == g))
    white = Whitener(np.asarray(cov)[np.ix_(idx, idx)])
    p_here = np.asarray(P)[idx]
    p_here = p_here[:, np.any(p_here != 0, axis=0)]  # the nuisance that acts on the group
    rw, pw = white(r[idx]), white(p_here)
    cols = np.stack([tags[idx] == p for p in names], 1).astype(float)
    place = {
        name: tuple(float(v) for v in table.xy[(table.groups == g) & (tags == name)].mean(0))
        for name in names
    }
    shared = _planes(cols, np.array([place[p] for p in names]), table.op_index[idx])
    base = np.hstack([pw, white(shared)])
    if base.shape[1] + len(names) >= len(idx):
        return None  # more unknowns than features: nothing to judge by
    _, chi2_shared, _ = gls(rw, base)
    each = np.hstack([base, white(cols)])
    _, chi2_each, _ = gls(rw, each)
    gain = max(chi2_shared - chi2_each, 0.0)
    dof = _rank(each) - _rank(base)
    dof_within = len(idx) - _rank(each)
    scatter = max(1.0, chi2_each / dof_within) if dof_within > 0 else math.inf
    p = float(stats.f.sf(gain / dof / scatter, dof, dof_within)) if dof_within * dof > 0 else 1.0
    # each particle's offset, told alone (beside the planes it is defined only up to them)
    k = pw.shape[1]
    coef, _, cov_c = gls(rw, np.hstack([pw, white(cols)]))
    objects = {
        name: (float(coef[k + j]), float(np.sqrt(max(cov_c[k + j, k + j], 0.0) * scatter)))
        for j, name in enumerate(names)
    }
    return {
        "chi2": float(gain),
        "dof": dof,
        "scatter": float(scatter),
        "p": min(1.0, p * n_groups),
        "differ": bool(p * n_groups < ALPHA),
        "objects": objects,
        "place": place,
    }


def differing(offsets: dict) -> list[str]:
    """The groups whose particles differ from each other beyond the noise."""
    return [g for g, row in offsets.items() if row["differ"]]


def _apart(objects: dict, n_groups: int) -> bool:
    """Whether the particles' offsets, each told alone, differ from each other beyond their
    sigmas (chi^2 about their weighted mean, at ALPHA over the groups): what the description
    says must hold on the offsets it quotes (a work session's pushed particles passed the
    plane-based test with five offsets of -230 +- 98 nm each)."""
    values = np.array([v[0] for v in objects.values()])
    sigmas = np.array([v[1] for v in objects.values()])
    if len(values) < 2 or not np.all(np.isfinite(sigmas) & (sigmas > 0)):
        return False
    w = 1 / sigmas**2
    chi2 = float(np.sum(w * (values - np.sum(w * values) / np.sum(w)) ** 2))
    return bool(stats.chi2.sf(chi2, len(values) - 1) * n_groups < ALPHA)


def _planes(cols: np.ndarray, places: np.ndarray, ops: np.ndarray) -> np.ndarray:
    """The columns a plane across the particles' places explains (a scale, a rotation, a
    drift's velocity over a frame: the library's terms and the drift model own those): per
    operation that shows at least MIN_OBJECTS particles (an image: its drift during the frame
    is its own), one plane; the operations showing fewer (a scan line sees one particle) share
    one."""
    xy = (places - places.mean(axis=0)) / max(float(np.ptp(places)), 1e-12)
    affine = np.hstack([np.ones((len(places), 1)), xy])
    seen = cols.any(axis=1)
    mine = cols @ affine  # each feature: 1 and its particle's place
    out, together = [], np.zeros(len(ops), bool)
    for op in np.unique(ops[seen]):
        at = seen & (ops == op)
        if np.count_nonzero(cols[at].any(axis=0)) >= MIN_OBJECTS:
            out.append(mine * at[:, None])
        else:
            together |= at
    if together.any():
        out.append(mine * together[:, None])
    return np.hstack(out)


def _rank(a: np.ndarray) -> int:
    norms = np.linalg.norm(a, axis=0)
    return int(np.linalg.matrix_rank(a[:, norms > 0] / norms[norms > 0]))


def object_rows(objects: dict, words: dict) -> list[dict]:
    """Signature rows (signature._significant_groups' shape) of the groups whose particles
    differ: chi2 and excess of the per-particle offsets, scaled by the group's scatter."""
    rows = []
    for g in differing(objects):
        row = objects[g]
        chi2 = row["chi2"] / row["scatter"]
        name, kind = words.get(g, (g, "other"))
        rows.append(
            {
                "group": g,
                "words": name,
                "kind": kind,
                "n": row["dof"],
                "chi2": chi2,
                "excess": chi2 - row["dof"],
                "structure_p": row["p"],
                "per_object": True,
            }
        )
    return rows


def particles_entry(row: dict) -> dict:
    """signature.Signature.particles' entry of a group whose particles differ: not alike, the
    particle departing most from their common offset (in its sigmas)."""
    tags = list(row["objects"])
    offsets = np.array([row["objects"][t][0] for t in tags])
    sigmas = np.array([row["objects"][t][1] for t in tags])
    w = 1 / np.maximum(sigmas, 1e-300) ** 2
    common = float(np.sum(w * offsets) / np.sum(w))
    most = int(np.argmax(np.abs(offsets - common) / np.maximum(sigmas, 1e-300)))
    return {
        "alike": False,
        "p": row["p"],
        "most": tags[most],
        "common": common,
        "per_object": True,
    }


def object_sentence(group_words: str, row: dict, scale: float, unit: str) -> str:
    """The per-particle finding in words."""
    offsets = [v[0] for v in row["objects"].values()]
    sigma = float(np.median([v[1] for v in row["objects"].values()]))
    return (
        f"In {group_words} each particle differs from the model by its own amount, the same in "
        f"every image: {len(offsets)} particles, offsets from {min(offsets) * scale:+.3g} to "
        f"{max(offsets) * scale:+.3g} {unit} (each +- {sigma * scale:.2g} {unit}), beyond what "
        f"a plane across the sample explains (p = {row['p']:.2g}); an effect of each object, not "
        "of the images of all particles alike."
    )


def object_basis(tags, anchors) -> list[GenericTerm]:
    """One generic term per particle (sim/generic_terms.py's disc_proportional, at unit
    amplitude): the heights within half the particles' smallest spacing of its configured place
    scaled, the others' not. Particles keyed by no configured place give none."""
    anchors = np.asarray(anchors, float).reshape(-1, 2)
    if len(anchors) < 2:
        return []
    apart = np.hypot(*(anchors[:, None, :] - anchors[None]).transpose(2, 0, 1))
    reach = 0.5 * float(np.min(apart[~np.eye(len(anchors), dtype=bool)]))
    return [
        GenericTerm(
            "height",
            "disc_proportional",
            1.0,
            (("x0", float(anchors[k, 0])), ("y0", float(anchors[k, 1])), ("radius", reach)),
        )
        for k in (int(t) for t in tags if str(t).isdigit())
        if k < len(anchors)
    ]
