"""What a session can inform: the terms it cannot tell, and sessions too small to diagnose.

A session of normal work measures what the work needed, not what the diagnosis would like: a
term may act on none of its features (no slide on bare substrate leaves the friction unseen
once the pushes' torsion is left out, exclusions.py), or act only as the drift offset does
(the nuisance takes it). Such a term is reported as "this session cannot tell", never weighed
as evidence of anything:

- its design column is zero on the session's features, or repeats the nuisance columns (the
  drift offset per axis) after whitening (GLS leaves it out, `noise_model.gls`); or
- its Fisher sigma (the GLS covariance of the term fitted with the nuisance, at the noise
  model) exceeds the term's physical range: the width of [lower, upper] where both bounds
  exist, the distance from the model's value to the one bound it has otherwise (the session
  cannot tell the value from that bound). A term without bounds, or whose model sits at its one
  bound (no wear), is judged by the first rule only.

A session is too small to diagnose at all when it has fewer features than the smallest term
needs to be tested with a held-out check (`MIN_FEATURES`), or when no term of the library can
be told by it. Then the diagnosis says so and suggests the diagnostic protocol instead of a
verdict (`TooLittleError`).
"""

from __future__ import annotations

import numpy as np

from afm_core.sim2real.noise_model import Whitener, gls
from afm_core.sim2real.reference import NoFeaturesError

# the fewest non-noise features a diagnosis runs on: the nuisance takes 2 (a drift offset per
# axis), a one-parameter term 1, and each of the two held-out folds needs at least as many
# features as the fit has parameters plus one to leave a residual: 2 x (2 + 1 + 1)
MIN_FEATURES = 8
PROTOCOL_HINT = (
    "record the diagnostic protocol (afm_core.sim2real.protocol.run_protocol on the "
    "instrument, through RecordingInstrument) for a session that informs every term"
)


class TooLittleError(NoFeaturesError):
    """The session holds too little to diagnose at all (it says what, and suggests the
    protocol)."""


def check_enough_features(sess) -> None:
    """TooLittleError when the session has fewer than MIN_FEATURES features that are not noise
    statistics."""
    informative = int(np.sum(~sess.noisy))
    if informative < MIN_FEATURES:
        excluded = sum(row["count"] for row in getattr(sess.exclusions, "rows", []))
        left = f" ({excluded} more left out: {_whats(sess)})" if excluded else ""
        raise TooLittleError(
            f"too little to diagnose: the session gives {informative} features of the sample "
            f"besides noise statistics{left}, and a diagnosis needs at least {MIN_FEATURES} "
            f"(a drift offset per axis, one term, a held-out check); {PROTOCOL_HINT}"
        )


def _whats(sess) -> str:
    return "; ".join(row["what"] for row in sess.exclusions.rows)


def _physical_range(cand, theta0: np.ndarray) -> np.ndarray:
    """Per parameter: the width of its bounds, or the distance to its one bound (inf: none)."""
    size = len(theta0)
    lower = cand.lower if cand.lower is not None else [None] * size
    upper = cand.upper if cand.upper is not None else [None] * size
    out = np.full(size, np.inf)
    for j in range(size):
        lo, hi = lower[j], upper[j]
        if lo is not None and hi is not None:
            out[j] = float(hi) - float(lo)
        elif lo is not None or hi is not None:
            distance = abs(float(theta0[j]) - float(lo if lo is not None else hi))
            # a model at its one bound (no wear) leaves the other side open: no range to judge
            out[j] = distance if distance > 0 else np.inf
    return out


def cannot_tell(design: dict, noise, P: np.ndarray) -> list:
    """[{term, reason}] of the terms in `design` (name -> (candidate, nominal, columns)) this
    session cannot tell (module docstring)."""
    white = Whitener(noise.cov)
    pw = white(P) if P.size else np.zeros((noise.cov.shape[0], 0))
    rw = np.zeros(noise.cov.shape[0])
    out = []
    for name, (cand, theta0, cols) in design.items():
        cols = np.nan_to_num(np.asarray(cols, float).reshape(len(rw), -1))
        if not np.any(cols):
            out.append({"term": name, "reason": "it changes none of this session's features"})
            continue
        _, _, cov = gls(rw, np.hstack([pw, white(cols)]))
        variance = np.diag(cov)[pw.shape[1] :]
        if not np.all(np.isfinite(variance)):
            out.append(
                {
                    "term": name,
                    "reason": "on this session's features it acts only as the drift offset does",
                }
            )
            continue
        sigma = np.sqrt(variance)
        reach = _physical_range(cand, np.asarray(theta0, float))
        wide = sigma > reach
        if wide.any():
            j = int(np.argmax(wide))
            unit = cand.units[j] if j < len(cand.units) else ""
            out.append(
                {
                    "term": name,
                    "reason": (
                        f"its uncertainty on this session ({cand.keys[j]}: sigma "
                        f"{sigma[j]:.3g} {unit}) exceeds its physical range ({reach[j]:.3g} "
                        f"{unit})"
                    ),
                }
            )
    return out


def check_something_to_tell(design: dict, untold: list) -> None:
    """TooLittleError when the session can tell no term of those considered."""
    if design and len({row["term"] for row in untold}) >= len(design):
        raise TooLittleError(
            "too little to diagnose: this session cannot tell any of the "
            f"{len(design)} terms considered (none acts on its features beyond the drift "
            f"offset and the noise); {PROTOCOL_HINT}"
        )


def scope_section(diagnosis) -> list[str]:
    """The report's lines on what this session could not inform: the features left out (and
    why) and the terms it cannot tell; none when there is neither."""
    excluded = getattr(diagnosis, "excluded", []) or []
    untold = getattr(diagnosis, "cannot_tell", []) or []
    if not excluded and not untold:
        return []
    lines = ["## What this session cannot inform", ""]
    if excluded:
        lines += [
            "Left out (the re-simulation cannot reproduce them):",
            "",
            "| features | count | why |",
            "|---|---|---|",
        ]
        lines += [f"| {row['what']} | {row['count']} | {row['reason']} |" for row in excluded]
        lines.append("")
    if untold:
        lines += ["This session cannot tell:", ""]
        lines += [f"- `{row['term']}`: {row['reason']}" for row in untold]
        lines.append("")
    return lines
