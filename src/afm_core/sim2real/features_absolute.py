"""Absolute substrate levels: what moves the whole z signal, which relative features cannot see.

Every other height feature is taken relative to its own line's or image's substrate (a peak
above the line's edges, a particle above the image's median), so an offset of the whole z
signal (a cantilever bending slowly with temperature, a pickup on the z sensor) leaves them
alone. These features keep it:

- `line.level`: per run of scan lines over one segment, the mean over its lines of each
  line's substrate (the median of its first and last EDGE_FRACTION of samples, as the crossing
  features take it), over the lines whose two edges are both on the substrate
  (`edges_on_substrate`): where one edge lies on a particle, the two edges' median falls
  between substrate and particle top, where a nm of the tip's positioning walk along the line
  (which the re-simulation does not reproduce) moves it by nm -- no substrate level at all (the
  protocol suite's null-4 read 3 such lines as +4.8, +2.0, +0.8 nm of level, chi^2 577 for
  56, a false 'not explained by the library');
- `raster.level`: per block of lines of an image as the line-offset noise takes them (else per
  image), the median height of its pixels (particles are few).

- `line.updown`: per run with lines in both directions (on the substrate, as above), the mean
  level of its lines scanned along +axis (+x, or +y for a run along y) less that of the lines
  scanned back: a z offset by scan direction (feedback lag, a tilted tip), which the run's
  mean level and every height relative to a line's edges cancel. Both directions cover one
  stretch, so the substrate's roughness cancels too; not relative to the first level.

The levels are relative to the session's first level (the first run's or image's, whichever
came first), so the z sensor's arbitrary zero cancels; that first level is not a feature
itself. Their noise: the sensor noise through the replicas like every feature, plus the
substrate's roughness averaged over the measured stretch (`level_variance`): the recording's
sample and the model's are two realizations, and the tip's random positioning puts the lines
on other stretches (not `line.updown`'s: its two directions share theirs).
"""

from __future__ import annotations

import math

import numpy as np

LEVEL_GROUPS = ("line.level", "raster.level")
UPDOWN_GROUP = "line.updown"  # forward less backward level of a run (not relative)
# Two edges on the same substrate differ by their medians' scatter, which is at most one
# sample's spread (the roughness correlates an edge's samples, so the median may average
# nothing away); each edge's spread is its own robust (MAD) standard deviation, which carries
# the roughness, the sensor's noise and any slope within the edge. Beyond 3.29 of those sigmas
# (a two-sided 0.1 % false-exclusion rate for Gaussian scatter, and far less as the edges do
# average) the edges are not on one level: one lies on a particle (tens to hundreds of nm).
EDGE_AGREEMENT_SIGMAS = 3.29
MAD_TO_SIGMA = 1.4826  # the MAD of Gaussian samples times this is their standard deviation


def edges_on_substrate(height, edge: int) -> bool:
    """Whether a scan line's first and last `edge` samples lie on one level (both on the
    substrate), from the line's own data: their medians agree within EDGE_AGREEMENT_SIGMAS of
    the two edges' own robust spreads."""
    h = np.asarray(height, float)
    if edge < 1 or 2 * edge > h.size:
        raise ValueError(f"edge: {edge} samples must be >= 1 and at most half of {h.size}")
    first, last = h[:edge], h[-edge:]
    m1, m2 = float(np.median(first)), float(np.median(last))
    s1 = MAD_TO_SIGMA * float(np.median(np.abs(first - m1)))
    s2 = MAD_TO_SIGMA * float(np.median(np.abs(last - m2)))
    return abs(m1 - m2) <= EDGE_AGREEMENT_SIGMAS * math.hypot(s1, s2)


class AbsoluteLevels:
    """The level features of a session fed in command order (one per FeatureExtractor, which
    hands over its Feature type and its constants: features.py imports this module)."""

    def __init__(self, feature_type, edge_fraction: float, block: int, min_lines: int):
        self.feature_type, self.edge_fraction = feature_type, edge_fraction
        self.block, self.min_lines = block, min_lines
        self.reference: tuple | None = None  # (level m, roughness support: ("length"|"area", m^k))

    def _relative(self, level: float, support: tuple):
        if self.reference is None:
            self.reference = (level, support)
            return None
        return level - self.reference[0]

    def run(self, run, common: dict) -> list:
        """`line.level` of a run of scan lines over one segment (ops with data)."""
        levels, times, xs, ys, length, signs = [], [], [], [], 0.0, []
        first = run[0]
        d = np.array([first.end[0] - first.start[0], first.end[1] - first.start[1]], float)
        k_axis = 0 if abs(d[0]) >= abs(d[1]) else 1
        for op in run:
            data = op.data
            if data is None:
                continue
            h = np.asarray(data.height, float)
            if h.size < 10 or not np.isfinite(h).all():
                continue
            edge = max(3, int(self.edge_fraction * h.size))
            if not edges_on_substrate(h, edge):
                continue
            levels.append(float(np.median(np.concatenate([h[:edge], h[-edge:]]))))
            signs.append(float(np.sign(op.end[k_axis] - op.start[k_axis])))
            t = np.asarray(data.times, float)
            times.append(float(data.start_time + 0.5 * (t[0] + t[-1])))
            x, y = np.asarray(data.x, float), np.asarray(data.y, float)
            xs.append(0.5 * (x[0] + x[-1]))
            ys.append(0.5 * (y[0] + y[-1]))
            length += 2 * edge / h.size * float(np.hypot(x[-1] - x[0], y[-1] - y[0]))
        if not levels:
            return []
        axis = "xy"[k_axis]
        where = (float(np.mean(times)), float(np.mean(xs)), float(np.mean(ys)), (0.0, 0.0))
        out = self._updown(first.index, np.array(levels), np.array(signs), where, common, axis)
        support = ("length", length)
        value = self._relative(float(np.mean(levels)), support)
        if value is None:
            return out
        cond = dict(common, axis=axis, lines=len(levels), substrate=support)
        cond["reference_substrate"] = self.reference[1]
        level = self.feature_type((first.index, "line.level"), "line.level", value, *where, cond)
        return [level, *out]

    def _updown(self, index, levels, signs, where, common: dict, axis: str) -> list:
        """`line.updown` of a run (its lines' levels and scan signs along its axis): none
        unless both directions have a line on the substrate."""
        forward, backward = levels[signs > 0], levels[signs < 0]
        if not forward.size or not backward.size:
            return []
        value = float(np.mean(forward) - np.mean(backward))
        cond = dict(common, axis=axis, lines=int(forward.size + backward.size))
        return [self.feature_type((index, UPDOWN_GROUP), UPDOWN_GROUP, value, *where, cond)]

    def raster(self, op, common: dict) -> list:
        """`raster.level` per block of lines of a raster (op with data)."""
        data = op.data
        h = np.asarray(data.height, float)
        if not np.isfinite(h).all():
            return []
        lines = h if data.scan_angle_deg == 0.0 else h.T  # rows: one scan line each
        n = lines.shape[0]
        parts = (
            np.array_split(np.arange(n), n // self.block)
            if n >= self.min_lines and lines.shape[1] >= self.min_lines
            else [np.arange(n)]
        )
        starts = np.asarray(data.line_start_times, float)
        cond = dict(common, angle=float(data.scan_angle_deg), up=bool(data.slow_scan_up))
        pixel_area = data.pixel_size_x * data.pixel_size_y
        out = []
        for b, block in enumerate(parts):
            support = ("area", block.size * lines.shape[1] * pixel_area)
            value = self._relative(float(np.median(lines[block])), support)
            if value is None:
                continue
            across, along = (block[0] + block[-1] + 1) / 2, lines.shape[1] / 2
            col, row = (along, across) if data.scan_angle_deg == 0.0 else (across, along)
            x = data.origin_x + col * data.pixel_size_x
            y = data.origin_y + row * data.pixel_size_y
            t = (
                float(data.start_time + np.nanmean(starts[block]) + 0.5 * data.line_period)
                if np.isfinite(starts[block]).any()
                else float(data.start_time)
            )
            where = dict(cond, lines=int(block.size), substrate=support)
            where["reference_substrate"] = self.reference[1]
            out.append(
                self.feature_type(
                    (op.index, f"raster.level{b}"),
                    "raster.level",
                    value,
                    t,
                    float(x),
                    float(y),
                    (0.0, 0.0),
                    where,
                )
            )
        return out


def _roughness_mean_variance(support, sigma: float, correlation: float) -> float:
    """Variance of the roughness (rms sigma, Gaussian correlation length `correlation`)
    averaged over a stretch of the given length or an area: sigma^2 times the share of one
    correlation cell in it (at most 1)."""
    if support is None:
        return 0.0
    kind, size = support
    if size <= 0:
        return sigma**2
    cell = math.sqrt(math.pi) * correlation if kind == "length" else math.pi * correlation**2
    return sigma**2 * min(1.0, cell / size)


def level_variance(table, config) -> np.ndarray:
    """Per feature (N): the roughness part of a level feature's variance (0 elsewhere): its own
    stretch and the reference level's, each in two realizations (the recording's sample and the
    model's)."""
    out = np.zeros(len(table.keys))
    sigma, corr = config.sample.roughness_sigma, config.sample.roughness_correlation
    for i, (group, cond) in enumerate(zip(table.groups, table.conditions)):
        if group in LEVEL_GROUPS:
            own = _roughness_mean_variance(cond.get("substrate"), sigma, corr)
            ref = _roughness_mean_variance(cond.get("reference_substrate"), sigma, corr)
            out[i] = 2.0 * (own + ref)
    return out
