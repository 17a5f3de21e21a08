"""Scoring the suite's families against issue 29's targets, one family at a time.

Reads what a `Diagnosis` has today and what it may gain (`verdict`, `signature`, `generic`)
through getattr with fallbacks, so the same code scores the diagnosis before and after those
land:

- verdict: `Diagnosis.verdict` when present, else derived as today's summary words it (a
  named term; "no candidate in the library explains" when the overall p < UNEXPLAINED_P; "no
  missing physics"); classed as named / partly explained / not explained / no missing physics /
  cannot tell (a session too thin to diagnose) / refused (run_sim2real raised);
- signature: `Diagnosis.signature` judged by its fields when it has them (kind, form in time
  and across the sample, particles, relations: sim2real_injections.Signature.accepts), else by
  its words (Signature.keywords); no such attribute: "no describer";
- generic: the share of the held-out excess a generic fit removed, from `Diagnosis.generic`
  (its held-out check's excess_reduction), when the diagnosis has generic fits.

Rates carry their 95 % Clopper-Pearson interval: 0 of 6 false alarms is still compatible with
a true rate of 46 %.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

NAMED, PARTLY, UNEXPLAINED, NONE, CANNOT_TELL, REFUSED = (
    "named",
    "partly explained",
    "not explained by the library",
    "no missing physics",
    "session cannot tell",
    "refused",
)
MISSING_PHYSICS = (NAMED, PARTLY, UNEXPLAINED)  # the verdicts that claim physics is missing
GENERIC_TARGET = 0.5  # issue 29: a generic fit removes >= 50 % of the held-out excess


def verdict_of(diagnosis) -> tuple[str, str]:
    """(class, the verdict's own words)."""
    from afm_core.sim2real.results import UNEXPLAINED_P

    words = getattr(diagnosis, "verdict", None)
    chosen = list(diagnosis.chosen)
    if words is None:
        if chosen:
            return NAMED, "named: " + ", ".join(chosen)
        if diagnosis.overall.get("p", 1.0) < UNEXPLAINED_P:
            return UNEXPLAINED, "no candidate in the library explains the residual"
        return NONE, "no missing physics"
    text = str(getattr(words, "kind", words)).lower()
    if "partly" in text or "partial" in text:
        return PARTLY, str(words)
    if "not explained" in text or "no candidate" in text or "unexplained" in text:
        return UNEXPLAINED, str(words)
    if "too little" in text or "cannot tell" in text or "protocol" in text:
        return CANNOT_TELL, str(words)
    if "no missing" in text or "consistent" in text:
        return NONE, str(words)
    return (NAMED if chosen else NONE), str(words)


def _text(value) -> str:
    if value is None:
        return ""
    if dataclasses.is_dataclass(value):
        return " ".join(_text(v) for v in dataclasses.asdict(value).values())
    if isinstance(value, dict):
        return " ".join(f"{k} {_text(v)}" for k, v in value.items())
    if isinstance(value, (list, tuple)):
        return " ".join(_text(v) for v in value)
    return str(value)


def _structured(signature, accepts) -> bool | None:
    """Whether a structured signature (kind, time, space, particles, relations) matches one of
    the truth's alternatives; None when it has no `kind` to judge by."""
    kind = getattr(signature, "kind", None)
    if not isinstance(kind, str) or not accepts:
        return None
    time_form = (getattr(signature, "time", None) or {}).get("form")
    space_form = (getattr(signature, "space", None) or {}).get("form")
    particles = getattr(signature, "particles", None) or {}
    relations = _text(getattr(signature, "relations", None)).lower()
    for alt in accepts:
        if kind not in alt["kind"]:
            continue
        if "time" in alt and time_form not in alt["time"]:
            continue
        if "space" in alt and space_form not in alt["space"]:
            continue
        if alt.get("particles_differ") and not any(
            isinstance(g, dict) and g.get("alike") is False for g in particles.values()
        ):
            continue
        if "relation" in alt and alt["relation"] not in relations:
            continue
        return True
    return False


def said(signature) -> str:
    """What a signature says: its sentences (`text()`), else its fields' text."""
    text = getattr(signature, "text", None)
    return str(text()) if callable(text) else _text(signature)


def signature_of(diagnosis, truth) -> dict:
    """{described: True/False, None when the diagnosis has no describer; signature: what it
    said}. `truth`: sim2real_injections.Signature. A structured signature is judged by its
    fields (`truth.accepts`), else its words (`truth.keywords`): the words alone would match
    the names of the forms a describer tried and rejected."""
    if not hasattr(diagnosis, "signature"):
        return {"described": None, "signature": "no describer"}
    signature = diagnosis.signature
    if signature is None:
        return {"described": False, "signature": "nothing described"}
    structured = _structured(signature, truth.accepts)
    text = said(signature)
    if structured is None:
        lower = text.lower()
        structured = all(any(word in lower for word in group) for group in truth.keywords)
    return {"described": bool(structured), "signature": text[:400]}


def generic_share(diagnosis) -> float | None:
    """The generic fit's share of the held-out excess removed; None without generic fits, NaN
    when none was fitted on this recording."""
    if not hasattr(diagnosis, "generic"):
        return None
    generic = diagnosis.generic
    if not generic:
        return math.nan
    heldout = (
        generic.get("heldout") if isinstance(generic, dict) else getattr(generic, "heldout", None)
    )
    for holder in (heldout, generic):
        for key in ("excess_reduction", "heldout_reduction", "share"):
            value = holder.get(key) if isinstance(holder, dict) else getattr(holder, key, None)
            if value is not None:
                return float(value)
    return math.nan


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    from scipy.stats import beta

    if n == 0:
        return math.nan, math.nan
    a = (1 - level) / 2
    lo = 0.0 if k == 0 else float(beta.ppf(a, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - a, k + 1, n - k))
    return lo, hi


def rate(k: int, n: int) -> dict:
    lo, hi = clopper_pearson(k, n)
    return {"k": k, "n": n, "rate": k / n if n else math.nan, "ci95": [lo, hi]}


def _median(values) -> float:
    values = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.median(values)) if values else math.nan


def summarize_family(rows: list[dict]) -> dict:
    """The family's figures (each family has one kind of truth: null, library term or
    out-of-library effect)."""
    done = [r for r in rows if r["verdict"] not in (REFUSED, CANNOT_TELL) and "error" not in r]
    out = {
        "cases": len(rows),
        "diagnosed": len(done),
        "refused": sum(r["verdict"] == REFUSED and "error" not in r for r in rows),
        "too_little": sum(r["verdict"] == CANNOT_TELL for r in rows),
        "crashed": sum("error" in r for r in rows),
        "cpu_seconds_median": _median(r.get("cpu_seconds") for r in rows),
        "cpu_seconds_max": max((r.get("cpu_seconds", 0.0) for r in rows), default=math.nan),
        "wall_seconds_median": _median(r.get("seconds") for r in rows),
        "peak_rss_mib_max": max((r.get("peak_rss_mib", 0.0) for r in rows), default=math.nan),
    }
    kinds = {r["kind"] for r in rows}
    if kinds == {"null"}:
        out["false_named"] = rate(sum(bool(r["chosen"]) for r in rows), len(rows))
        out["false_missing_physics"] = rate(
            sum(r["verdict"] in MISSING_PHYSICS for r in rows), len(rows)
        )
        out["config_written"] = sum(bool(r.get("config_written")) for r in rows)
    elif kinds == {"library"}:
        right = [r for r in rows if r["correct"]]
        out["top1"] = rate(len(right), len(rows))
        out["named_alone"] = rate(sum(r.get("alone", False) for r in right), len(right))
        out["parameter_error_median"] = _median(r.get("parameter_error") for r in right)
        out["heldout_reduction_median"] = _median(r.get("heldout_reduction") for r in right)
    elif kinds == {"out_of_library"}:
        confident = sum(r["verdict"] == NAMED and bool(r["chosen"]) for r in rows)
        out["confident_library_name"] = rate(confident, len(rows))
        out["not_explained_verdict"] = rate(
            sum(r["verdict"] in (UNEXPLAINED, PARTLY) for r in rows), len(rows)
        )
        described = [r for r in rows if r.get("described") is not None]
        out["describer"] = bool(described)
        out["right_signature"] = (
            rate(sum(bool(r["described"]) for r in described), len(rows)) if described else None
        )
        # a recording without a generic fit counts as one that removed nothing
        shares = [r.get("generic_share") for r in rows]
        capable = any(s is not None for s in shares)
        finite = [s for s in shares if s is not None and math.isfinite(s)]
        out["generic_fit"] = capable
        out["generic_share_median"] = _median(finite)
        out["generic_removes_half"] = (
            rate(sum(s >= GENERIC_TARGET for s in finite), len(rows)) if capable else None
        )
    return out
