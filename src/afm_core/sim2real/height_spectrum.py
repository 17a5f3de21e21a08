"""A periodic signal in time on the height samples, faster than any feature's sampling.

A feature takes a median, an edge or a peak of a whole scan line or image; a height signal
that oscillates many times within a line (mains pickup: 50 Hz on the z sensor) averages out
there and leaves the features within their noise. The samples keep it: every height sample of
a raster and a scan line has a known time (sample_times.raster_samples: the trace in the first
half of the line period), and the residual recorded less the nominal re-simulation, sample by
sample, holds the oscillation on a clock the re-simulation shares.

What a null's residual holds instead: the sensor noise, and the topography the re-simulation
does not reproduce exactly (the drift's few nm of error at every particle's edge). That
topography repeats from one raster line to the next, so it sits at harmonics of the line rate
(and their aliases through the pixel rate, which is a multiple of the line rate). Hence:

- each raster line less the mean of its two neighbours (same places along the fast axis): what
  repeats from line to line drops out; a signal in time whose phase advances by 2 pi f P per
  line period P passes with gain |1 - cos(2 pi f P)| (none at an exact line harmonic, which no
  raster can tell from topography: the scan lines and the other rasters still can);
- each stretch (a line) less its own mean and slope; each operation in units of its robust
  noise (1.4826 MAD) and clipped at CLIP of them, so no single operation's particle edges
  dominate the spectrum;
- a frequency within one resolution (1 / duration) of a harmonic of a raster's line rate does
  not count that raster's samples there.

The spectrum is the periodogram of all samples on one clock (the samples gridded to a fraction
of the shortest sample spacing, one FFT), P(f) = |sum r exp(-2 pi i f t)|^2 / N. In units of
the robust noise P is exponential with mean one where there is only noise; its floor is the
median of P over each FLOOR_HZ band (over ln 2). A peak counts when, in EACH of the two folds of
time blocks (the held-out check's), P / floor exceeds ln(M / alpha), M = the number of
independent frequencies searched (band x span): a Bonferroni over the independent frequencies
at alpha in each fold (the two folds together: a clock-locked signal is in both halves of the
session, a coincidence of one raster's topography is not).

The generic term is the simulator's `time_sine` on the height (sim/generic_terms.py), its
frequency refined and its amplitude and phase fitted by weighted least squares on the samples
(the same filters applied to the sine's columns), on one fold; the held-out check is the other
fold's amplitude at that frequency: chi^2 with 2 dof (2 P / floor of the held-out samples, a
chi^2(2) under noise) before and after the term, re-simulated, is taken away.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import optimize
from scipy.ndimage import maximum_filter1d

from afm_core.sim2real.sample_times import raster_samples

CLIP = 4.0  # robust noise units a sample is clipped at (particle edges, lost lines)
FLOOR_HZ = 1.0  # the band the spectrum's floor is the median over
MIN_SAMPLES = 8  # a stretch shorter than this has no form in time to speak of
MAX_GRID = 1 << 23  # grid points of the FFT (the step grows for long sessions)
BLOCKS = 6  # time blocks, alternately in the two folds
SEARCH = 2  # grid resolutions either side of a candidate the sine's frequency is sought in


def collect_heights(op, into: dict) -> None:
    """Keep a raster's or scan line's height samples in `into[op.index]`: (t, h), each (lines,
    samples along the fast axis in trace order), and the raster's line period (None: a scan
    line)."""
    data = op.data
    if op.kind not in ("raster", "scan_line") or data is None:
        return
    lines = stretches(data)
    if lines is not None:
        into[op.index] = lines


def stretches(data):
    """(t, h, line period or None) of a raster's or scan line's samples, lines as rows in
    trace order; None when it has too few samples."""
    if hasattr(data, "line_start_times"):
        t, _, _ = raster_samples(data)
        h = np.asarray(data.height, float)
        if data.scan_angle_deg != 0.0:
            t, h = t.T, h.T
        period = float(data.line_period)
    else:
        t = (data.start_time + np.asarray(data.times, float))[None, :]
        h = np.asarray(data.height, float)[None, :]
        period = None
    if t.shape != h.shape or t.shape[1] < MIN_SAMPLES:
        return None
    return t, h, period


def prepared(t, r, period, scale=None):
    """(t, r', the operation's robust noise) of one operation's residual r (lines, samples):
    rasters' lines less their neighbours' mean, each line less its mean and slope; `scale`:
    the robust noise to divide by (None: the residual's own)."""
    if period is not None and r.shape[0] >= 3:
        r = r[1:-1] - 0.5 * (r[:-2] + r[2:])
        t = t[1:-1]
    ok = np.isfinite(r).all(axis=1)
    t, r = t[ok], r[ok]
    if not t.size:
        return t.ravel(), r.ravel(), 1.0
    u = t - t.mean(axis=1, keepdims=True)
    r = r - r.mean(axis=1, keepdims=True)
    slope = np.sum(u * r, axis=1, keepdims=True) / np.maximum(
        np.sum(u * u, axis=1, keepdims=True), 1e-300
    )
    r = r - slope * u
    if scale is None:
        scale = 1.4826 * float(np.median(np.abs(r)))
    scale = scale if scale > 0 else 1.0
    return t.ravel(), r.ravel() / scale, scale


class Residual:
    """The session's height residual samples, prepared (module docstring): times, values in
    robust noise units, the operation of each, its line period (None: a scan line)."""

    def __init__(self, recorded: dict, nominal: dict, scales: dict | None = None):
        parts, self.scales, self.periods = [], {}, {}
        for index, (t, h, period) in recorded.items():
            nom = nominal.get(index)
            if nom is None or nom[1].shape != h.shape:
                continue
            if scales is not None and index not in scales:
                continue
            own = None if scales is None else scales[index]
            tt, rr, scale = prepared(t, h - nom[1], period, own)
            if tt.size < MIN_SAMPLES:
                continue
            self.scales[index] = scale
            self.periods[index] = period
            parts.append((tt, rr, np.full(tt.size, index)))
        if parts:
            self.t, self.unclipped, self.op = (np.concatenate(p) for p in zip(*parts))
        else:
            self.t = self.unclipped = self.op = np.zeros(0)
        self.r = np.clip(self.unclipped, -CLIP, CLIP)
        self.t0 = float(self.t.min()) if self.t.size else 0.0
        self.recorded = recorded

    def folds(self) -> np.ndarray:
        """True where a sample's operation starts in an even time block."""
        start = {o: self.t[self.op == o].min() for o in self.scales}
        t0 = min(start.values())
        span = max(max(start.values()) - t0, 1e-9)
        blocks = np.array([min(int((start[o] - t0) / span * BLOCKS), BLOCKS - 1) for o in self.op])
        return blocks % 2 == 0


class Spectrum:
    """The periodogram of residual samples on one grid (module docstring)."""

    def __init__(self, res: Residual):
        self.res = res
        t = res.t
        self.t0 = float(t.min())
        span = float(t.max()) - self.t0
        # the finest sampling along a line (operations never overlap in time on one instrument)
        spacing = min(float(np.min(np.diff(res.recorded[o][0], axis=1))) for o in res.scales)
        self.step = max(spacing / 2, span / (MAX_GRID - 1))
        self.n = 1 << int(math.ceil(math.log2(span / self.step + 2)))
        self.k = np.round((t - self.t0) / self.step).astype(np.int64)
        self.f = np.fft.rfftfreq(self.n, self.step)
        self.span = span
        # from two cycles in the longest line to the samples' Nyquist (a quarter of the grid's
        # rate: the rounding to the grid costs at most pi/4 of phase there)
        longest = max(float(np.max(np.ptp(res.recorded[o][0], axis=1))) for o in res.scales)
        f_lo = 2.0 / max(min(longest, span), 1e-9)
        f_hi = min(0.5 / spacing, 0.25 / self.step)
        self.band = (self.f > f_lo) & (self.f < f_hi)
        self.m = max((f_hi - f_lo) * span, 1.0)

    def _excluded(self, period, duration) -> np.ndarray:
        """Where a raster's line harmonics are (within one resolution of its duration)."""
        if period is None:
            return np.zeros(self.f.size, bool)
        width = 1.0 / max(duration, period)
        phase = self.f * period
        return np.abs(phase - np.round(phase)) < width * period

    def _group(self, o) -> tuple:
        """Operations whose harmonics are excluded alike share one FFT."""
        period = self.res.periods[o]
        if period is None:
            return (None, 0.0)
        duration = float(np.ptp(self.res.t[self.res.op == o]))
        return (period, float(f"{duration:.2g}"))

    def power(self, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(P(f) / floor, floor) of the samples in `mask` (NaN outside the band)."""
        groups: dict = {}
        for o in np.unique(self.res.op[mask]):
            groups.setdefault(self._group(o), []).append(o)
        total = np.zeros(self.f.size, complex)
        count = np.zeros(self.f.size)
        for (period, duration), members in groups.items():
            sel = mask & np.isin(self.res.op, members)
            grid = np.zeros(self.n)
            np.add.at(grid, self.k[sel], self.res.r[sel])
            keep = ~self._excluded(period, duration)
            total += np.where(keep, np.fft.rfft(grid), 0)
            count += keep * sel.sum()
        p = np.abs(total) ** 2 / np.maximum(count, 1)
        floor = _floor(p, self.band, self.f)
        return p / floor, floor

    def excluded_ops(self, frequency: float) -> set:
        """The operations whose line harmonics `frequency` is on."""
        out = set()
        for o in self.res.scales:
            period, duration = self._group(o)
            if period is not None:
                phase = frequency * period
                if abs(phase - round(phase)) < period / max(duration, period):
                    out.add(o)
        return out


def _floor(p, band, f) -> np.ndarray:
    """The median of p over each FLOOR_HZ band of `band`, over ln 2 (an exponential's median):
    the spectrum's own noise level there."""
    out = np.full(p.size, np.nan)
    idx = np.flatnonzero(band)
    width = max(int(round(FLOOR_HZ / max(f[1], 1e-12))), 16)
    for start in range(0, idx.size, width):
        part = idx[start : start + width]
        level = float(np.median(p[part])) / math.log(2)
        out[part] = level if level > 0 else np.nan
    return out


def tail_threshold(z: np.ndarray, m: float, alpha: float) -> float:
    """The level P / floor that one of m independent frequencies exceeds with probability
    alpha, from the spectrum's own tail: above its 99th percentile u the excesses are taken as
    exponential with the scale their median gives (1 for Gaussian noise; a null's residual,
    spiky at particle edges, has a heavier tail), u + scale ln(0.01 m / alpha)."""
    v = z[np.isfinite(z)]
    u = float(np.quantile(v, 0.99))
    excess = v[v > u] - u
    scale = max(float(np.median(excess)) / math.log(2), 1.0) if excess.size else 1.0
    return u + scale * math.log(max(0.01 * m / alpha, 1.0))


def detect(res: Residual, alpha: float) -> dict | None:
    """The strongest frequency that passes tail_threshold in each fold (module docstring);
    None without one."""
    spectrum = Spectrum(res)
    fold = res.folds()
    if fold.all() or not fold.any():
        return None
    found = []
    for mask in (fold, ~fold):
        z, floor = spectrum.power(mask)
        z = np.where(spectrum.band, np.nan_to_num(z), 0.0)
        # a peak between two bins: either neighbour
        level = tail_threshold(z[spectrum.band], spectrum.m, alpha)
        # the tail's scale: the level moves by it per factor e in alpha
        scale = tail_threshold(z[spectrum.band], spectrum.m, alpha / math.e) - level
        found.append((maximum_filter1d(z, 3), level, floor, scale))
    (za, ta, _, sa), (zb, tb, floor_b, sb) = found
    # the strongest, in all the samples, of the frequencies that pass in both folds (gating
    # the lines puts sidelobes at the line rate about a peak, nearly as strong in one fold)
    z_all = maximum_filter1d(np.nan_to_num(spectrum.power(fold | ~fold)[0]), 3)
    both = np.where((za > ta) & (zb > tb), z_all, 0.0)
    k = int(np.argmax(both))
    if both[k] <= 0:
        return None
    return {
        "frequency": float(spectrum.f[k]),
        "candidates": _candidates(spectrum, za, float(spectrum.f[k])),  # the fit fold's
        "z": [float(za[k]), float(zb[k])],
        "thresholds": [ta, tb],
        # the chance of a peak this high in a fold of noise alone (the larger of the two)
        "false_alarm": float(
            min(1.0, alpha * math.exp(-min((za[k] - ta) / sa, (zb[k] - tb) / sb)))
        ),
        "independent_frequencies": spectrum.m,
        "resolution": float(spectrum.f[1]),
        "spectrum": spectrum,
        "train": fold,
        "floor_test": float(floor_b[k]),
    }


def _candidates(spectrum: Spectrum, z: np.ndarray, frequency: float) -> list[float]:
    """The frequencies the sine may be at, given a peak at `frequency` that may be a sidelobe
    the gating of the raster lines puts at a line rate from it: the strongest bin of z within
    one raster resolution (1 / its duration) of the peak and of the peak +- each line rate."""
    res = spectrum.res
    out = []
    for o, period in res.periods.items():
        if period is None:
            continue
        width = 1.0 / max(float(np.ptp(res.t[res.op == o])), period)
        for centre in (frequency - 1 / period, frequency, frequency + 1 / period):
            near = np.flatnonzero(spectrum.band & (np.abs(spectrum.f - centre) <= width))
            if near.size:
                out.append(float(spectrum.f[near[int(np.argmax(z[near]))]]))
    return sorted(set(out)) or [frequency]


def _columns(res: Residual, frequency: float, ops) -> tuple[np.ndarray, np.ndarray]:
    """sin and cos of 2 pi f (t - t0) at every operation's samples, prepared like the
    residual (its scale), stacked in the residual's sample order for the operations `ops`."""
    cols = []
    for o in ops:
        t, _, period = res.recorded[o]
        w = 2 * math.pi * frequency * (t - res.t0)
        pair = [prepared(t, fn(w), period, res.scales[o])[1] for fn in (np.sin, np.cos)]
        cols.append(np.stack(pair, 1))
    return np.concatenate(cols) if cols else np.zeros((0, 2))


def fit_sine(res: Residual, candidates, mask: np.ndarray, resolution: float) -> dict:
    """The sine (frequency refined within SEARCH grid resolutions, amplitude and phase) fitted by
    least squares to the prepared residual samples in `mask`, unclipped: {frequency,
    coefficients (sin, cos; m), amplitude, phase_time t0 of the simulator's time_sine}."""
    ops = [o for o in res.scales if (mask & (res.op == o)).any()]
    sel = np.concatenate([np.flatnonzero(res.op == o) for o in ops])
    y = res.unclipped[sel]

    def gain(f):
        X = _columns(res, f, ops)
        coef, *_ = np.linalg.lstsq(X, y, rcond=None)
        return -float(np.sum((X @ coef) ** 2)), coef

    # about each candidate (_candidates), a grid of half resolutions; then a grid of
    # twentieths about the best, and a bounded search about that one's best
    steps = resolution * np.arange(-SEARCH, SEARCH + 0.5, 0.5)
    grid = np.concatenate([c + steps for c in candidates if c + steps[0] > 0])
    best = float(grid[int(np.argmin([gain(f)[0] for f in grid]))])
    fine = best + resolution * np.linspace(-0.5, 0.5, 21)
    scores = [gain(f)[0] for f in fine]
    best = float(fine[int(np.argmin(scores))])
    found = optimize.minimize_scalar(
        lambda f: gain(f)[0],
        bounds=(best - resolution / 20, best + resolution / 20),
        method="bounded",
        options={"xatol": resolution * 1e-4},
    )
    f = float(found.x) if found.fun <= min(scores) else best
    _, (a, b) = gain(f)
    phase = math.atan2(b, a)  # a sin(w) + b cos(w) = A sin(w + phase)
    return {
        "frequency": f,
        "amplitude": float(math.hypot(a, b)),
        "t0": res.t0 - phase / (2 * math.pi * f),
        "samples": int(y.size),
    }


def heldout_chi2(res: Residual, unclipped_after: np.ndarray, test, frequency, floor, skip):
    """chi^2 (2 dof) of the held-out samples' amplitude at `frequency`, before and after: 2 |sum
    r exp(-2 pi i f t)|^2 / (N floor), the operations whose line harmonics f is on left out."""
    keep = test & ~np.isin(res.op, list(skip))
    phasor = np.exp(-2j * math.pi * frequency * (res.t[keep] - res.t0))
    n = max(int(keep.sum()), 1)

    def chi2(r):
        return float(2 * np.abs(np.sum(r[keep] * phasor)) ** 2 / (n * floor))

    return chi2(res.unclipped), chi2(unclipped_after)
