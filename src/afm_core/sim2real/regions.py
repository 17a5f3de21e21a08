"""Friction that changes in one region of the sample: where, from the contact slides' torsion.

A contaminated patch, a terrace of another material or a worn spot makes the tip-substrate
friction differ in one part of the sample only. The slides' mean torsion per segment
(features.py, `push.torsion`) then deviates from the model inside that part and nowhere else.

The region is an axis-aligned rectangle of the sample (afm_task frame, the frame the
simulator's `contact.friction_regions` use): a segment's commanded centre minus the drift
offset of the recording's trajectory at its time (the drift trajectory puts the recorded
particles where the recording saw them, so the same offset takes a commanded point to the
sample). Inside, the tip-substrate friction is scaled by s; a segment's torsion changes by
(s - 1) mu dtau/dmu times the fraction of it inside (the torsion is linear in mu: the global
friction candidate's sensitivity gives dtau/dmu per segment).

`best_region` searches every rectangle whose edges fall between neighbouring segment
centres (each side at least `min_inside` / `min_outside` segments, so it is neither empty
nor the global friction) for the largest generalised-least-squares chi^2 improvement of that
one column; `refine_region` then moves the edges continuously (an edge inside a segment
makes a partial step). The diagnosis re-simulates the candidate at those edges for its
design column, as the secant from the model to the factor this linear fit gives: a slide
across an edge also fluctuates more whichever way the friction changed, which a tangent
column cannot tell apart from the mirror factor 1 + |s - 1|. It counts the four edges as
parameters (complexity) and checks the choice on held-out blocks by searching on the
training blocks only.
"""

from __future__ import annotations

import numpy as np
from scipy import linalg, optimize

MERGE = 50e-9  # m: segment centres closer than this along an axis share an edge position


def sample_points(commanded_xy: np.ndarray, drift_offset: np.ndarray) -> np.ndarray:
    """Sample-frame positions (N, 2) of commanded points at the drift offsets of their times."""
    return np.asarray(commanded_xy, float) - np.asarray(drift_offset, float)


def _edges(values: np.ndarray) -> np.ndarray:
    """Edge positions between neighbouring (merged) coordinates, plus one beyond each end."""
    v = np.sort(np.asarray(values, float))
    clusters = [[v[0]]]
    for x in v[1:]:
        if x - clusters[-1][-1] <= MERGE:
            clusters[-1].append(x)
        else:
            clusters.append([x])
    centres = np.array([np.mean(c) for c in clusters])
    if centres.size == 1:
        return np.array([centres[0] - MERGE, centres[0] + MERGE])
    gaps = np.diff(centres)
    inner = centres[:-1] + 0.5 * gaps
    return np.concatenate([[centres[0] - 0.5 * gaps[0]], inner, [centres[-1] + 0.5 * gaps[-1]]])


def best_region(
    points: np.ndarray,
    effect: np.ndarray,
    residual: np.ndarray,
    cov: np.ndarray,
    slides=None,
    min_inside: int = 3,
    min_outside: int = 3,
    min_slides: int = 2,
):
    """The rectangle R maximising the GLS chi^2 improvement of the column effect * [point in R]
    on `residual` with covariance `cov` (all restricted to the segments). `slides`: which
    slide (operation) each segment belongs to; a patch of the sample is crossed by at least
    `min_slides` of them (a few segments of one slide, or of one push against a particle, are
    not a place on the sample). Returns (bounds (x0, y0, x1, y1), chi^2 improvement, inside
    mask) or None when no rectangle qualifies."""
    points = np.asarray(points, float)
    effect = np.asarray(effect, float)
    residual = np.asarray(residual, float)
    usable = (
        np.isfinite(effect)
        & (effect != 0)
        & np.isfinite(residual)
        & np.all(np.isfinite(points), axis=1)
    )
    if usable.sum() < min_inside + min_outside:
        return None
    idx = np.flatnonzero(usable)
    p, a, e = points[idx], effect[idx], residual[idx]
    slide_ids = np.unique(
        np.arange(len(points)) if slides is None else np.asarray(slides), return_inverse=True
    )[1]
    member = np.eye(slide_ids.max() + 1)[slide_ids[idx]]  # segment x slide
    factor = linalg.cho_factor(np.asarray(cov, float)[np.ix_(idx, idx)], lower=True)
    g = a * linalg.cho_solve(factor, e)  # c . g = a_c^T C^-1 e
    A = a[:, None] * linalg.cho_solve(factor, np.diag(a))  # c^T A c = a_c^T C^-1 a_c
    ex, ey = _edges(p[:, 0]), _edges(p[:, 1])
    # every y interval at once: rows = intervals, columns = segments
    lo, hi = np.triu_indices(ey.size, 1)
    in_y = (p[None, :, 1] > ey[lo, None]) & (p[None, :, 1] < ey[hi, None])
    best = None
    for i in range(ex.size - 1):
        for j in range(i + 1, ex.size):
            in_x = (p[:, 0] > ex[i]) & (p[:, 0] < ex[j])
            if in_x.sum() < min_inside:
                continue
            inside = in_x[None, :] & in_y
            count = inside.sum(axis=1)
            crossing = ((inside.astype(float) @ member) > 0).sum(axis=1)
            ok = (
                (count >= min_inside)
                & (idx.size - count >= min_outside)
                & (crossing >= min_slides)
            )
            if not ok.any():
                continue
            c = inside[ok].astype(float)
            num = c @ g
            den = np.einsum("ki,ij,kj->k", c, A, c)
            gain = np.where(den > 0, num**2 / np.maximum(den, 1e-300), 0.0)
            k = int(np.argmax(gain))
            if best is None or gain[k] > best[1]:
                rows = np.flatnonzero(ok)
                best = (
                    (float(ex[i]), float(ey[lo[rows[k]]]), float(ex[j]), float(ey[hi[rows[k]]])),
                    float(gain[k]),
                    c[k].astype(bool),
                )
    if best is None:
        return None
    mask = np.zeros(points.shape[0], bool)
    mask[idx[best[2]]] = True
    return best[0], best[1], mask


def overlap(points: np.ndarray, axes, lengths: np.ndarray, bounds) -> np.ndarray:
    """Fraction of each segment (centre `points`, along `axes` "x"/"y", `lengths` m) inside the
    rectangle `bounds` (x0, y0, x1, y1): a patch edge that cuts a segment changes its mean
    torsion by that fraction of the full step."""
    x0, y0, x1, y1 = bounds
    points = np.asarray(points, float)
    along_x = np.asarray([a == "x" for a in axes])
    half = 0.5 * np.asarray(lengths, float)
    centre_along = np.where(along_x, points[:, 0], points[:, 1])
    across = np.where(along_x, points[:, 1], points[:, 0])
    lo, hi = np.where(along_x, x0, y0), np.where(along_x, x1, y1)
    lo_across, hi_across = np.where(along_x, y0, x0), np.where(along_x, y1, x1)
    covered = np.clip(
        np.minimum(hi, centre_along + half) - np.maximum(lo, centre_along - half), 0.0, None
    )
    return np.where(
        (across > lo_across) & (across < hi_across), covered / np.maximum(2 * half, 1e-30), 0.0
    )


def refine_region(
    points: np.ndarray,
    axes,
    lengths: np.ndarray,
    effect: np.ndarray,
    residual: np.ndarray,
    cov: np.ndarray,
    bounds,
):
    """The rectangle's edges moved continuously from `bounds` (best_region's, between segment
    centres) to where the GLS gain of the column effect x overlap is largest: an edge inside a
    segment makes that segment's torsion a partial step. Returns (bounds, gain, coefficient of
    the column: the factor's change s - 1 when `effect` is the torsion change per unit s)."""
    a = np.asarray(effect, float)
    factor = linalg.cho_factor(np.asarray(cov, float), lower=True)
    g = linalg.cho_solve(factor, np.asarray(residual, float))
    scale = 1e-6  # optimise in um: a well-scaled simplex

    def fit(edges_um):
        """(GLS gain, coefficient) of the column at these edges."""
        x0, y0, x1, y1 = np.asarray(edges_um) * scale
        if not (x1 > x0 and y1 > y0):
            return 0.0, 0.0
        column = a * overlap(points, axes, lengths, (x0, y0, x1, y1))
        den = float(column @ linalg.cho_solve(factor, column))
        num = float(column @ g)
        return (num**2 / den, num / den) if den > 0 else (0.0, 0.0)

    start = np.asarray(bounds, float) / scale
    result = optimize.minimize(
        lambda e: -fit(e)[0],
        start,
        method="Nelder-Mead",
        options={
            "xatol": 1e-3,
            "fatol": 1e-6,
            "initial_simplex": start + np.vstack([np.zeros(4), 0.1 * np.eye(4)]),
        },
    )
    best = result.x if -result.fun >= fit(start)[0] else start
    gain, coefficient = fit(best)
    return tuple(float(v) * scale for v in best), gain, coefficient


def inside(points: np.ndarray, bounds) -> np.ndarray:
    x0, y0, x1, y1 = bounds
    points = np.asarray(points, float)
    return (points[:, 0] > x0) & (points[:, 0] < x1) & (points[:, 1] > y0) & (points[:, 1] < y1)
