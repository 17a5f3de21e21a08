"""The words of a residual's signature (signature.py): what each feature group is to a
microscopist, the units a signal's sizes are told in, and the plain sentences."""

from __future__ import annotations

import math

WORDS = {
    "line.pos": ("scan-line crossing positions", "lateral"),
    "line.mid": ("single scan-line crossing positions", "lateral"),
    "line.dir": ("forward/backward shift of scan lines", "lateral"),
    "line.width": ("particle widths in scan lines", "z"),
    "line.peak": ("particle heights in scan lines", "z"),
    "line.asym": ("flank asymmetry in scan lines", "z"),
    "line.level": ("absolute substrate level of scan lines", "z"),
    "line.updown": (
        "z offset by scan direction (substrate level of forward less backward scan lines)",
        "z",
    ),
    "raster.x": ("raster centroids (x)", "lateral"),
    "raster.y": ("raster centroids (y)", "lateral"),
    "raster.height": ("particle heights in images", "z"),
    "raster.half_width": ("particle widths in images", "z"),
    "raster.level": ("absolute substrate level of images", "z"),
    "raster.bow_xx": ("substrate curvature (xx)", "z"),
    "raster.bow_yy": ("substrate curvature (yy)", "z"),
    "raster.bow_xy": ("substrate curvature (xy)", "z"),
    "raster.streak": ("line-offset noise", "noise"),
    "raster.pixel_noise": ("pixel noise", "noise"),
    "raster.line_shift": ("each image line's own shift along the fast axis", "noise"),
    "push.torsion": ("torsion while sliding", "torsion"),
    "push.fluct": ("torsion fluctuation while sliding", "torsion"),
}
UNITS = {"z": (1e9, "nm"), "lateral": (1e9, "nm"), "torsion": (1e3, "mrad"), "noise": (1e9, "nm")}


def sentences(sig, alpha: float) -> list[str]:
    """Plain sentences of a signature.Signature (`alpha`: its statements' false-alarm rate)."""
    scale, unit = UNITS.get(sig.kind, (1.0, "SI"))
    lead = sig.signals[0]
    where = ", ".join(
        f"{row['words']} ({row['share']:.0%} of the excess)" for row in sig.signals[:4]
    )
    out = [
        f"The unexplained residual is a {sig.kind} signal; it lives in {where}.",
        f"Its size: {sig.size['rms'] * scale:.3g} {unit} rms, {sig.size['rms_sigma']:.3g} times "
        f"the noise sigma ({sig.size['noise_sigma'] * scale:.3g} {unit}) in "
        f"{', '.join(sig.groups)}.",
    ]
    if lead["kind"] == "z" and not set(sig.groups) & {"line.level", "raster.level"}:
        out.append("The absolute substrate level does not move beyond its noise.")
    for cond in sig.conditions:
        out.append(
            f"Beyond its form it depends on the {cond['condition']} (most at {cond['most']}: "
            f"{cond['departure'] * scale:+.3g} {unit}; p = {cond['p']:.2g})."
        )
    forms = [
        _time_sentence(sig.time, scale, unit) if sig.time else "",
        _space_sentence(sig.space, scale, unit, alpha) if sig.space else "",
    ]
    out += forms if sig.primary == "time" else forms[::-1]
    if sig.time:
        out.append(
            f"After its form {sig.size['left_rms_sigma']:.3g} times the noise sigma is left."
        )
    if sig.along_scan and sig.along_scan["p"] < alpha:
        out.append(
            f"Along the scan it changes by {sig.along_scan['slope'] * scale * 1e-6:.3g} {unit} "
            "per um of fast-axis position."
        )
    for rel in sig.relations:
        sign = "rises" if rel["r"] > 0 else "falls"
        if rel.get("samples"):  # signal_relations.py: sample by sample, with its slope
            out.append(
                f"Sample by sample it {sign} with {rel['covariate']}: proportional to it, "
                f"{rel['coefficient']:.3g} {rel['units']} (rank correlation {rel['r']:.2f} over "
                f"{rel['n']} samples, p = {rel['p']:.2g})."
            )
            continue
        out.append(f"It {sign} with {rel['covariate']} (rank correlation {rel['r']:.2f}).")
    for g, part in sig.particles.items():
        out.append(
            f"In {WORDS[g][0]} every particle changes alike."
            if part["alike"]
            else f"In {WORDS[g][0]} the particles change differently (most: particle "
            f"{part['most']}, p = {part['p']:.2g})."
        )
    return out


def _time_sentence(time: dict, scale: float, unit: str) -> str:
    form, p = time["form"], time["params"]
    if not time.get("primary"):
        return _time_sentence(dict(time, primary=True), scale, unit).replace(
            "In time", "Beyond that, in time", 1
        )
    if form == "none":
        return "In time it has no systematic form."
    if form == "constant":
        return f"In time it is a constant offset of {p['offset'] * scale:.3g} {unit}."
    if form == "linear trend":
        return f"In time it is a linear trend of {p['slope'] * scale * 60:.3g} {unit} per minute."
    if form == "step":
        return f"In time it is a step of {p['size'] * scale:.3g} {unit} at t = {p['time']:.0f} s."
    if form == "smooth":
        return (
            f"In time it changes smoothly (a polynomial of degree {p['degree']}): by "
            f"{p['change'] * scale:.3g} {unit} from t = {p['t0']:.0f} s to {p['t1']:.0f} s."
        )
    if form == "periodic":
        return (
            f"In time it is periodic: {p['amplitude'] * scale:.3g} {unit} amplitude, period "
            f"{p['period']:.3g} s."
        )
    return (
        f"In time it wanders as a random walk ({math.sqrt(p['step_variance_per_s']) * scale:.3g} "
        f"{unit} per sqrt(s))."
    )


def _space_sentence(space: dict, scale: float, unit: str, alpha: float) -> str:
    form, p = space["form"], space["params"]
    lead = "Across the sample" + (
        " (better than any form in time)" if space.get("primary") else ", beyond that,"
    )
    if form == "uniform":
        text = f"{lead} it shows no gradient"
    elif form == "each particle its own":
        text = f"{lead} no form through the particles' places explains their offsets"
    elif form.startswith("linear"):
        grads = ", ".join(f"{g * scale * 1e-6:.3g} {unit}/um" for g in p["gradient"])
        text = f"{lead} it is {form} ({grads})"
    else:
        text = (
            f"{lead} it is {form}: {p['amplitude'] * scale:.3g} {unit} amplitude, period "
            f"{p['period'] * 1e6:.3g} um"
        )
    loc = space["localized"]
    if loc["p"] < alpha and loc["where"] is not None:
        x, y = loc["where"]
        text += (
            f"; beyond its form it departs most near ({x * 1e6:.2f}, {y * 1e6:.2f}) um "
            f"({loc['mean_there'] * scale:+.3g} {unit} there)"
        )
    return text + "."
