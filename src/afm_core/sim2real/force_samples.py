"""A recorded push's or indent's force trace as first differences of torsion and deflection,
kept while the recording streams past (reference._read never holds the whole recording), for
the sample-level relation of signal_relations.py. Apart from it so the reference session can
collect them without importing the signature's machinery (an import cycle otherwise)."""

from __future__ import annotations

import numpy as np

from afm_core.sim2real.height_spectrum import collect_heights


def force_differences(op) -> dict:
    """{op.index: (first differences of the torsion, of the deflection)} of a push or indent
    with a force trace, else {}: what the sample-level relation needs of a recorded trace (the
    recording is read once and not held: reference._read)."""
    data = op.data
    if op.kind not in ("push", "indent") or data is None:
        return {}
    if not hasattr(data, "lateral_torsion") or not hasattr(data, "vertical_deflection"):
        return {}
    torsion = np.asarray(data.lateral_torsion, float)
    deflection = np.asarray(data.vertical_deflection, float)
    if torsion.size != deflection.size or torsion.size < 3:
        return {}
    return {op.index: (np.diff(torsion), np.diff(deflection))}


def collecting(ops, into: dict, heights: dict | None = None):
    """The operations `ops`, one by one, each push's force_differences kept in `into` (and, given
    `heights`, each raster's and scan line's height samples: height_spectrum.collect_heights)."""
    for op in ops:
        into.update(force_differences(op))
        if heights is not None:
            collect_heights(op, heights)
        yield op
