"""Scoring the suite's families against issue 29's targets, one family at a time.

Reads what a `Diagnosis` has today and what it may gain (`verdict`, `signature`, `generic`)
through getattr with fallbacks, so the same code scores the diagnosis before and after those
land:

- verdict: `Diagnosis.verdict` when present, else derived as today's summary words it (a
  named term; "no candidate in the library explains" when the overall p < UNEXPLAINED_P; "no
  missing physics"); classed as named / partly explained / not explained / no missing physics /
  cannot tell (a session too thin to diagnose) / refused (run_sim2real raised);
- signature: `Diagnosis.signature` read as text (its fields, or str), matched against the
  injected effect's accepted words (sim2real_injections.Signature.keywords); absent: "no
  describer";
- generic: the share of the held-out excess a generic fit removed, from `Diagnosis.generic`
  (an attribute or key excess_reduction / heldout_reduction / share), when present.

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


def signature_of(diagnosis, keywords) -> dict:
    """{described: bool | None (no describer), text}."""
    signature = getattr(diagnosis, "signature", None)
    if signature is None:
        return {"described": None, "signature": "no describer"}
    text = _text(signature).lower()
    match = all(any(word in text for word in group) for group in keywords)
    return {"described": bool(match), "signature": _text(signature)[:400]}


def generic_share(diagnosis) -> float:
    generic = getattr(diagnosis, "generic", None)
    if generic is None:
        return math.nan
    for key in ("excess_reduction", "heldout_reduction", "share"):
        value = generic.get(key) if isinstance(generic, dict) else getattr(generic, key, None)
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
    done = [r for r in rows if r["verdict"] != REFUSED and "error" not in r]
    out = {
        "cases": len(rows),
        "diagnosed": len(done),
        "refused": sum(r["verdict"] == REFUSED for r in rows),
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
        shares = [r.get("generic_share", math.nan) for r in rows]
        finite = [s for s in shares if math.isfinite(s)]
        out["generic_fit"] = bool(finite)
        out["generic_share_median"] = _median(finite)
        out["generic_removes_half"] = (
            rate(sum(s >= GENERIC_TARGET for s in finite), len(rows)) if finite else None
        )
    return out
