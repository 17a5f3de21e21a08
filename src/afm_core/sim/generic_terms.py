"""Generic simulator terms: an additive offset on one measured signal, shaped by a small basis.

A diagnosis that finds physics no library term has describes its residual (which signal, its
form in time, across the sample, along the scan) and fits the simplest generic model of that
form. The simulator takes such a model from its configuration (`generic_terms: [...]`, default
none), so the fitted description can be re-simulated and kept, without pretending it is a
named physical effect. Each entry:

    {signal: height | torsion | x_position | y_position | lateral, form: <form>,
     amplitude: <SI>, ...form parameters}

`height` adds to every measured height (rasters and scan lines; m), `torsion` to the push
traces' lateral torsion (rad); `x_position` and `y_position` displace the scanner's true x or
y (m) as a function of where it truly is (a commanded-to-true map the library's scanner terms
do not have: a sensitivity that ripples or changes across the range), so every measurement
taken there, heights and torsion alike, is taken at the displaced place. The lateral signals
take the forms across the sample only (LATERAL_FORMS): a displacement in time is the drift's.
Forms, with t the instrument clock (s) and x, y the scanner's true position (m):

- constant: amplitude
- time_linear: amplitude * (t - t0)                    (amplitude per s; t0 default 0)
- time_step: amplitude * (t >= t0)
- time_sine: amplitude * sin(2 pi (t - t0) / period)   (t0 as a phase)
- time_legendre: amplitude * P_degree(2 (t - t0) / (t1 - t0) - 1), the Legendre polynomial of
  that degree (1 to MAX_DEGREE) over the span [t0, t1]: a smooth change in time (a settling,
  a slow bend) as a sum of degrees, each bounded by |amplitude| on the span
- x_linear, y_linear: amplitude * (x - x0) or (y - y0) (amplitude per m; x0, y0 default 0)
- x_sine, y_sine: amplitude * sin(2 pi (x - x0) / period)
- scan_direction: +amplitude / 2 on a local scan line scanned along +x (+y for a line closer
  to y), -amplitude / 2 on one scanned back (height signal only): a z offset by scan
  direction, forward less backward = amplitude (feedback lag, a tilted tip). It acts on one
  line of samples (1-D t, x, y, its direction from its ends); an image's rows (2-D) record
  their trace only, where an offset by direction is one constant: 0 there
- height_proportional: amplitude * (true height about the substrate)  (height signal only)
- height_squared: amplitude * (true height about the substrate)^2  (height signal only;
  amplitude per m): a z sensor whose sensitivity changes along its range (a nonlinear piezo),
  which the library's one z gain cannot take
- deflection_proportional: amplitude * (the vertical deflection measured at the same moment)
  (torsion signal only; amplitude in rad per m): one signal leaking into another, as a
  residual that tracks a signal recorded alongside it
- disc_proportional: amplitude * (true height about the substrate) where the scanner is within
  radius of (x0, y0), else 0: one object's apparent height scaled, the others' not (height
  signal only; one term per object describes "each particle differs by its own amount")

`lateral` is the noise family's one signal: where each scan line is read along its fast axis.

- line_jitter: each scan line (an image's rows and every local scan line) read at a random
  offset along its own direction, normal with sd amplitude (m), independent from line to line:
  a line reads h(s + d). It is no additive offset (`offset` gives none); the simulator draws
  it from its sensor-noise generator's seed, so replicas with other noise seeds draw others.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# "lateral": the lines' own random offsets along their fast axis (line_jitter, noise-like);
# x_position / y_position: the scanner's true x or y displaced as a function of its place
SIGNALS = ("height", "torsion", "x_position", "y_position", "lateral")
LATERAL_SIGNALS = ("x_position", "y_position")
LATERAL_FORMS = ("x_linear", "y_linear", "x_sine", "y_sine")
FORMS = {
    # form -> its parameters besides amplitude (defaults None: required)
    "constant": {},
    "time_linear": {"t0": 0.0},
    "time_step": {"t0": None},
    "time_sine": {"period": None, "t0": 0.0},
    "time_legendre": {"degree": None, "t0": None, "t1": None},
    "x_linear": {"x0": 0.0},
    "y_linear": {"y0": 0.0},
    "x_sine": {"period": None, "x0": 0.0},
    "y_sine": {"period": None, "y0": 0.0},
    "scan_direction": {},
    "height_proportional": {},
    "height_squared": {},
    "deflection_proportional": {},
    "disc_proportional": {"x0": None, "y0": None, "radius": None},
    "line_jitter": {},
}
# the proportional forms: form -> the one signal they act on
PROPORTIONAL = {
    "height_proportional": "height",
    "height_squared": "height",
    "deflection_proportional": "torsion",
    "disc_proportional": "height",
}
SIGNAL_ONLY = {"scan_direction": "height"}  # forms on one signal that scale no signal
MAX_OFFSET = 1e-5  # m or rad: a generic term larger than the z range describes no instrument
MAX_STRAIN = 0.1  # x_position/y_position linear in x or y: a 10 % gain error is no ripple
MAX_DEGREE = 5  # time_legendre: a smooth change, not a fit of every wiggle


@dataclass(frozen=True)
class GenericTerm:
    signal: str
    form: str
    amplitude: float
    params: tuple = ()  # ((name, value), ...) in FORMS[form]'s order

    def param(self, name: str) -> float:
        return dict(self.params)[name]

    def offset(self, t, x, y, measured=None) -> np.ndarray:
        """The term's additive offset at times t (s) and scanner positions x, y (m);
        `measured`: the signal a proportional form scales there (the true height for
        height_proportional, the measured vertical deflection for deflection_proportional)."""
        t, x, y = (np.asarray(a, float) for a in (t, x, y))
        a, form = self.amplitude, self.form
        shape = np.broadcast(t, x, y).shape
        if form == "constant":
            return np.full(shape, a)
        if form == "line_jitter":  # where a line is read, not what is added to it
            return np.zeros(shape)
        if form == "scan_direction":
            return np.full(shape, 0.5 * a * _line_sign(x, y))
        if form == "time_linear":
            return np.broadcast_to(a * (t - self.param("t0")), shape).copy()
        if form == "time_step":
            return np.broadcast_to(a * (t >= self.param("t0")), shape).astype(float)
        if form == "time_legendre":
            t0, t1 = self.param("t0"), self.param("t1")
            u = 2.0 * (t - t0) / (t1 - t0) - 1.0
            value = np.polynomial.legendre.legval(u, [0.0] * int(self.param("degree")) + [a])
            return np.broadcast_to(value, shape).copy()
        if form == "time_sine":
            phase = 2 * math.pi * (t - self.param("t0")) / self.param("period")
            return np.broadcast_to(a * np.sin(phase), shape).copy()
        if form in ("x_linear", "y_linear"):
            coord, origin = (x, "x0") if form[0] == "x" else (y, "y0")
            return np.broadcast_to(a * (coord - self.param(origin)), shape).copy()
        if form in ("x_sine", "y_sine"):
            coord, origin = (x, "x0") if form[0] == "x" else (y, "y0")
            phase = 2 * math.pi * (coord - self.param(origin)) / self.param("period")
            return np.broadcast_to(a * np.sin(phase), shape).copy()
        # the proportional forms
        if measured is None:
            return np.zeros(shape)
        if form == "disc_proportional":
            scaled = a * np.broadcast_to(np.asarray(measured, float), shape)
            x0, y0 = self.param("x0"), self.param("y0")
            return np.where(np.hypot(x - x0, y - y0) <= self.param("radius"), scaled, 0.0)
        if form == "height_squared":
            return a * np.asarray(measured, float) ** 2
        return a * np.asarray(measured, float)

    def as_dict(self) -> dict:
        return {"signal": self.signal, "form": self.form, "amplitude": self.amplitude} | dict(
            self.params
        )


def _line_sign(x: np.ndarray, y: np.ndarray) -> float:
    """+1 for one line of samples (1-D) scanned along +x (+y if it runs closer to y), -1 back;
    0 for an image's rows (2-D) or a line that does not move."""
    if x.ndim != 1 or y.ndim != 1 or x.size < 2 or y.size < 2:
        return 0.0
    dx, dy = float(x[-1] - x[0]), float(y[-1] - y[0])
    return float(np.sign(dx if abs(dx) >= abs(dy) else dy))


def parse_generic_terms(entries) -> list[GenericTerm]:
    """GenericTerms from the configuration's `generic_terms` list; errors name the entry, the
    field and the limit."""
    if entries is None:
        return []
    if not isinstance(entries, (list, tuple)):
        raise ValueError(f"generic_terms={entries!r}: expected a list of mappings")
    return [_parse_one(k, entry) for k, entry in enumerate(entries)]


def _number(where: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{where}={value!r}: expected a finite number (SI units)")
    return float(value)


def _parse_one(k: int, entry) -> GenericTerm:
    if isinstance(entry, GenericTerm):
        return entry
    where = f"generic_terms[{k}]"
    if not isinstance(entry, dict):
        raise ValueError(f"{where}={entry!r}: expected a mapping")
    signal, form = entry.get("signal"), entry.get("form")
    if signal not in SIGNALS:
        raise ValueError(f"{where}.signal={signal!r}: must be one of {list(SIGNALS)}")
    if form not in FORMS:
        raise ValueError(f"{where}.form={form!r}: must be one of {sorted(FORMS)}")
    if (signal == "lateral") != (form == "line_jitter"):
        raise ValueError(
            f"{where}.form={form}: line_jitter, and only it, acts on the lateral signal"
        )
    only = PROPORTIONAL.get(form, SIGNAL_ONLY.get(form))
    if only is not None and signal != only:
        raise ValueError(f"{where}.form={form}: only on the {only} signal")
    if signal in LATERAL_SIGNALS and form not in LATERAL_FORMS:
        raise ValueError(
            f"{where}.form={form}: the {signal} signal takes only {list(LATERAL_FORMS)}"
        )
    known = {"signal", "form", "amplitude", "description"} | set(FORMS[form])
    unknown = sorted(set(entry) - known)
    if unknown:
        raise ValueError(
            f"{where}: unknown key(s) {unknown} for form {form}; known: {sorted(known)}"
        )
    amplitude = _number(f"{where}.amplitude", entry.get("amplitude", 0.0))
    params = []
    for name, default in FORMS[form].items():
        if name not in entry and default is None:
            raise ValueError(f"{where}.{name}: required by form {form}")
        value = _number(f"{where}.{name}", entry.get(name, default))
        if name in ("period", "radius") and value <= 0:
            raise ValueError(f"{where}.{name}={value}: must be > 0")
        if name == "degree" and (value != int(value) or not 1 <= value <= MAX_DEGREE):
            raise ValueError(f"{where}.degree={value}: must be an integer from 1 to {MAX_DEGREE}")
        params.append((name, value))
    if form == "time_legendre" and dict(params)["t1"] <= dict(params)["t0"]:
        raise ValueError(f"{where}.t1={dict(params)['t1']}: must be > t0={dict(params)['t0']}")
    term = GenericTerm(signal, form, amplitude, tuple(params))
    bounded = ("constant", "time_step", "time_sine", "time_legendre", "x_sine", "y_sine")
    bounded += ("scan_direction",)
    if form == "line_jitter" and not 0.0 <= amplitude <= MAX_OFFSET:
        raise ValueError(f"{where}.amplitude={amplitude}: an sd in m, from 0 to {MAX_OFFSET}")
    if form in bounded and abs(amplitude) > MAX_OFFSET:
        raise ValueError(f"{where}.amplitude={amplitude}: |amplitude| must be <= {MAX_OFFSET}")
    if signal in LATERAL_SIGNALS and form.endswith("_linear") and abs(amplitude) > MAX_STRAIN:
        raise ValueError(f"{where}.amplitude={amplitude}: |amplitude| must be <= {MAX_STRAIN}")
    return term


def total_offset(terms, signal: str, t, x, y, measured=None):
    """The sum of the terms on `signal` at (t, x, y) (`measured`: GenericTerm.offset's); None
    when none acts on it."""
    acting = [term for term in terms if term.signal == signal]
    if not acting:
        return None
    return sum(term.offset(t, x, y, measured) for term in acting)


def line_jitter_sd(terms) -> float:
    """The sd (m) of the per-line lateral offset the line_jitter terms give together (they add
    in quadrature); 0 without one."""
    return math.sqrt(sum(t.amplitude**2 for t in terms if t.form == "line_jitter"))
