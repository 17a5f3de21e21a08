"""Where the recording deviates from the nominal model: the residual after the nuisance fit,
by feature group and by condition (axis, scan direction, dwell, last move, sliding, raster
angle, particle, time, position), as mean and chi^2 against the noise model with Bonferroni
p values, and CUSUM change points in time per group."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy import stats

from afm_core.sim2real.evidence import Evidence
from afm_core.sim2real.feature_table import Table
from afm_core.sim2real.noise_model import gls
from afm_core.sim2real.reference import ReferenceSession


def _bins(table: Table):
    """(label, mask) of condition bins per group."""
    out = []
    conds = table.conditions
    for group in np.unique(table.groups):
        g = table.groups == group
        out.append((f"{group}", g))

        def add(label, values, edges=None):
            values = np.array(values, dtype=object)
            if edges is not None:
                numeric = np.array([float(v) if v is not None else np.nan for v in values])
                for lo, hi in zip(edges[:-1], edges[1:]):
                    sel = g & (numeric >= lo) & (numeric < hi)
                    if sel.sum() >= 3:
                        out.append((f"{group} | {label} in [{lo:g}, {hi:g})", sel))
            else:
                for v in sorted({str(x) for x in values[g]}):
                    sel = g & (values.astype(str) == v)
                    if 3 <= sel.sum() < g.sum():
                        out.append((f"{group} | {label} = {v}", sel))

        add("axis", [c.get("axis") for c in conds])
        add("scan direction", [c.get("scan_sign") for c in conds])
        add("dwell after move (s)", [c.get("dwell", np.nan) for c in conds], [0, 1, 5, 20, np.inf])
        add(
            "last move (um)",
            [c.get("move_distance", np.nan) * 1e6 for c in conds],
            [0, 1, 2, np.inf],
        )
        add(
            "contact slid before (um)",
            [c.get("contact_slid", np.nan) * 1e6 for c in conds],
            [0, 0.5, 4, 8, np.inf],
        )
        add("raster angle", [c.get("angle") for c in conds])
        add("frame up", [c.get("up") for c in conds])
        add("particle", [c.get("particle") for c in conds])
        add(
            "time (s)",
            table.time,
            np.round(np.quantile(table.time[g], [0, 0.25, 0.5, 0.75, 1]) + [0, 0, 0, 0, 1e-6], 1)
            if g.any()
            else None,
        )
        add(
            "x (um)",
            table.xy[:, 0] * 1e6,
            np.round(np.quantile(table.xy[g, 0] * 1e6, [0, 0.33, 0.67, 1]) + [0, 0, 0, 1e-9], 3)
            if g.any()
            else None,
        )
        add(
            "y (um)",
            table.xy[:, 1] * 1e6,
            np.round(np.quantile(table.xy[g, 1] * 1e6, [0, 0.33, 0.67, 1]) + [0, 0, 0, 1e-9], 3)
            if g.any()
            else None,
        )
    return out


def where_by_condition(table: Table, e: np.ndarray, cov: np.ndarray, variance_factor: float = 1.0):
    bins = _bins(table)
    rows = []
    group_stats = {}
    for label, sel in bins:
        idx = np.flatnonzero(sel)
        c = cov[np.ix_(idx, idx)] * variance_factor
        mean = float(e[idx].mean())
        sd = float(math.sqrt(max(np.ones(idx.size) @ c @ np.ones(idx.size), 1e-300)) / idx.size)
        try:
            chi2 = float(e[idx] @ np.linalg.solve(c, e[idx]))
        except np.linalg.LinAlgError:
            chi2 = float("nan")
        row = {
            "where": label,
            "n": int(idx.size),
            "mean": mean,
            "sd": sd,
            "z": mean / sd,
            "chi2": chi2,
            "p_chi2": float(stats.chi2.sf(chi2, idx.size)),
            "p_mean": float(2 * stats.norm.sf(abs(mean / sd))),
        }
        rows.append(row)
        if "|" not in label:
            group_stats[label] = {
                "n": int(idx.size),
                "chi2": chi2,
                "dof": int(idx.size),
                "p": row["p_chi2"],
                "rms_residual": float(np.sqrt(np.mean(e[idx] ** 2))),
                "noise_sigma": float(np.sqrt(np.mean(np.diag(c)))),
            }
    m = max(1, len(rows))
    for row in rows:
        row["p_mean_bonferroni"] = min(1.0, row["p_mean"] * m)
        row["p_chi2_bonferroni"] = min(1.0, row["p_chi2"] * m)
    rows.sort(key=lambda row: min(row["p_mean"], row["p_chi2"]))
    change = []
    for group in np.unique(table.groups):
        idx = np.flatnonzero(table.groups == group)
        if idx.size < 8:
            continue
        idx = idx[np.argsort(table.time[idx])]
        z = e[idx] / np.sqrt(np.diag(cov)[idx])
        z = z - z.mean()
        cusum = np.cumsum(z) / math.sqrt(idx.size)
        k = int(np.argmax(np.abs(cusum[:-1])))
        stat = float(abs(cusum[k]))
        # Kolmogorov limit of the Brownian bridge maximum
        p = float(
            min(
                1.0,
                2
                * sum((-1) ** (j - 1) * math.exp(-2 * j * j * stat * stat) for j in range(1, 50)),
            )
        )
        change.append(
            {
                "group": group,
                "time": float(table.time[idx[k]]),
                "statistic": stat,
                "p": p,
                "mean_before": float(e[idx[: k + 1]].mean()),
                "mean_after": float(e[idx[k + 1 :]].mean()),
            }
        )
    change.sort(key=lambda c: c["p"])
    return rows, change, group_stats


class Deviations(NamedTuple):
    rows: list  # deviations by condition, most significant first
    change_points: list
    group_stats: dict  # group -> {n, chi2, dof, p, rms_residual, noise_sigma}
    e: np.ndarray  # the nominal model's residual after the nuisance fit


def nominal_deviations(sess: ReferenceSession, evidence: Evidence) -> Deviations:
    """Where the nominal model's residual deviates, after the nuisance fit, by condition."""
    r_seen = sess.r_before
    coef_p, _, _ = gls(evidence.weighting.white(r_seen), evidence.pw)
    e = r_seen - evidence.P @ coef_p
    rows, change_points, group_stats = where_by_condition(
        sess.table, e, evidence.weighting.noise.cov, variance_factor=1.0
    )
    return Deviations(rows, change_points, group_stats, e)
