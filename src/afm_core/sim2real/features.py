"""Features of a session's operations, in SI units, each with the conditions it was taken under.

Per operation (recorded or simulated) the same keyed scalars, so a recorded and a simulated
session are compared key by key. What a feature is depends only on the commands (which lines
form a pair, which raster is large), never on what was measured, so keys mean the same in
every session made of the same commands; a feature is absent where its measurement failed.

- Scan lines across a particle. Per line: the midpoint of the half-height crossings (position
  along the line's axis, m), the distance between them (width), the 20-80 % widths of the two
  flanks and the peak height above the line's substrate (thresholds relative to the line's own
  peak, so a z gain moves only the peak). Consecutive lines over the same segment with no other
  command between them form a *run* (the tip never left the segment: no positioning noise
  between them); consecutive forward/backward lines in a run form *pairs*:
    - `line.pos`: the pair's mean position (direction-dependent shifts cancel), a position
      feature measured along the axis u; an unpaired line gives `line.mid` instead;
    - `line.dir`: half the shift that best aligns the forward and the backward height profile
      (positive: the particle appears further along the scan direction, as with a sensor
      latency; the whole profile counts, and shape changes both lines share cancel);
    - per run: `line.width`, `line.peak` (means over its lines) and `line.asym` (mean of the
      +u-side flank width minus the -u-side one: a tip with one blunter flank).
- Rasters (`raster.*`): per particle (extract_landmarks; pixels <= 60 nm) its centroid x and y
  (position features), and with pixels <= 20 nm its apparent height and half-width. With
  `anchors` (the configured sphere positions) every particle is keyed by the anchor it matches
  after the best common translation, so several particles of one image are compared one by
  one; without, only the particle nearest the image centre. Large images (>= 10 um) give the
  curvature of the substrate background (`raster.bow_xx`, `bow_yy`: second derivative, 1/m;
  `bow_xy`). Images with >= 64 lines give, per block of 48 lines, the line-offset noise
  (`raster.streak`, m: the streaks coloured z noise draws; white noise averages out over a
  whole line) and the pixel-to-pixel noise along the lines (`raster.pixel_noise`, m: white z
  noise, on top of the substrate's roughness at the pixel scale, which the model's own sample
  gives it too).
- Contact slides / pushes (`push.*`): the mean lateral torsion over each 250 nm segment of the
  path (friction and where it changes; the segment's commanded centre is its place) and the
  rms of the detrended torsion per push (stick-slip).

Conditions per feature: time (s), position (m), measured direction u (position features),
scan direction sign, dwell since the last free move, that move's distance and direction,
contact distance slid before, the particle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import binary_dilation
from scipy.stats import median_abs_deviation

from afm_core.localization.landmark_observation import find_crossings
from afm_core.sim2real.features_absolute import AbsoluteLevels
from afm_core.sim2real.line_shift import LINE_SHIFT_GROUP, line_shift_noise

POSITION_GROUPS = ("line.pos", "line.mid", "raster.x", "raster.y")
EDGE_FRACTION = 0.1
MIN_PEAK = 20e-9  # m, a line whose peak is lower saw no particle
MAX_LANDMARK_PIXEL = 60e-9  # m, coarser images give no particle features
MAX_SHAPE_PIXEL = 20e-9  # m, coarser images give positions only (a particle's apparent height and
#   width depend on where the pixel grid falls on it)
BOW_MIN_SIZE = 10e-6  # m, images at least this large give the background curvature
SEGMENT = 250e-9  # m of path per torsion feature
MATCH_RADIUS = 200e-9  # m, a landmark belongs to an anchor this close (after translation)
SAME_POINT = 1e-12  # m
CENTRE_LEVEL = 5e-9  # m above the substrate: a raster particle's centre weighs what rises above
STREAK_MIN_LINES = 64  # images with fewer lines (or pixels per line) give no line-offset noise
STREAK_BLOCK = 48  # lines per line-offset noise feature
PARTICLE_LEVEL = (
    5e-9  # m above a line's median: a particle, not substrate (pixel noise leaves it out)
)
PARTICLE_MARGIN = 3  # pixels either side of a particle also left out (the foot of its flanks)


@dataclass
class Feature:
    key: tuple  # (operation index, name): the same in recorded and simulated sessions
    group: str
    value: float
    time: float  # s, instrument clock
    x: float  # m, where on the sample (commanded)
    y: float
    u: tuple = (0.0, 0.0)  # measured direction (position features), else (0, 0)
    conditions: dict = field(default_factory=dict)


def _profile_features(h: np.ndarray, s: np.ndarray):
    """Crossing features of one height profile h along arc length s (m); None if no particle."""
    n = h.size
    edge = max(3, int(EDGE_FRACTION * n))
    substrate = float(np.median(np.concatenate([h[:edge], h[-edge:]])))
    smooth = np.convolve(h - substrate, np.ones(5) / 5, mode="same")
    peak = float(np.max(smooth[2:-2])) if n > 6 else float(np.max(h - substrate))
    if not peak > MIN_PEAK:
        return None
    out = {"peak": peak}
    levels = {}
    for fraction in (0.2, 0.5, 0.8):
        pairs, _ = find_crossings(h, substrate + fraction * peak)
        if not pairs:
            return None
        levels[fraction] = pairs[0]
    idx = np.arange(n)
    at = lambda i: float(np.interp(i, idx, s))  # noqa: E731
    rise, fall = levels[0.5]
    out["mid"] = 0.5 * (at(rise) + at(fall))
    out["width"] = at(fall) - at(rise)
    out["lead"] = at(levels[0.8][0]) - at(levels[0.2][0])
    out["trail"] = at(levels[0.2][1]) - at(levels[0.8][1])
    out["mid_index"] = 0.5 * (rise + fall)
    return out


def _quad_background(height: np.ndarray, px: float, py: float):
    """Background curvature of an image's substrate: (d2h/dx2, d2h/dy2, d2h/dxdy) in 1/m, from a
    full quadratic fitted to the pixels that are not on a particle (more than 3 nm above the
    fitted background, iterated twice)."""
    h = np.asarray(height, float)
    ny, nx = h.shape
    yy, xx = np.mgrid[0:ny, 0:nx]
    x = ((xx - (nx - 1) / 2) * px).ravel()
    y = ((yy - (ny - 1) / 2) * py).ravel()
    values = h.ravel()
    scale = np.array([1, 1e6, 1e6, 1e12, 1e12, 1e12])
    A = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], 1) * scale
    mask = np.isfinite(values)
    mask &= values < np.nanmedian(values) + 3e-9
    coef = None
    for _ in range(3):
        if mask.sum() < 20:
            return None
        coef, *_ = np.linalg.lstsq(A[mask], values[mask], rcond=None)
        mask = np.isfinite(values) & (values - A @ coef < 3e-9)
    coef = coef * scale
    return {"xx": 2 * coef[3], "yy": 2 * coef[5], "xy": coef[4]}


def line_profile(data):
    """(direction u, profile features or None, crossing time, crossing position (x, y)) of a
    scan line's data; None when the line is too short, flat in position or not finite."""
    x, y, h = (np.asarray(a, float) for a in (data.x, data.y, data.height))
    if h.size < 10 or not np.isfinite(h).all():
        return None
    d = np.array([x[-1] - x[0], y[-1] - y[0]])
    length = float(np.hypot(*d))
    if length == 0:
        return None
    u = d / length
    f = _profile_features(h, (x - x[0]) * u[0] + (y - y[0]) * u[1])
    if f is None:
        return u, None, math.nan, (math.nan, math.nan)
    t = float(
        data.start_time
        + np.interp(f["mid_index"], np.arange(h.size), np.asarray(data.times, float))
    )
    return u, f, t, (x[0] + f["mid"] * u[0], y[0] + f["mid"] * u[1])


def _same_segment(a, b) -> bool:
    """Two scan lines over the same segment (either direction)."""
    ra, rb = a.request, b.request
    pa = (
        np.array([ra.start_x, ra.start_y, ra.end_x, ra.end_y])
        if ra is not None
        else np.array([*a.start, *a.end], float)
    )
    pb = (
        np.array([rb.start_x, rb.start_y, rb.end_x, rb.end_y])
        if rb is not None
        else np.array([*b.start, *b.end], float)
    )
    return bool(
        np.all(np.abs(pa - pb) <= SAME_POINT)
        or np.all(np.abs(pa - pb[[2, 3, 0, 1]]) <= SAME_POINT)
    )


class FeatureExtractor:
    """Features of operations fed one at a time in command order (`add`), so a recording's
    measurements need not be held: only a run of scan lines over one segment waits until the
    run ends. `finish()` returns every feature (see the module docstring). anchors: (n, 2)
    sample-frame particle positions (the configured spheres) to key raster particles by."""

    def __init__(self, anchors=None):
        self.anchors = anchors
        self.features: list[Feature] = []
        self._last_move_end_time = 0.0
        self._last_move = (0.0, 0.0, 0.0)  # distance, direction x, y
        self._slid = 0.0
        self._run: list = []
        self._run_common: dict = {}
        self.particles_seen: dict = {}  # raster's op index -> how many particles it shows
        self.levels = AbsoluteLevels(Feature, EDGE_FRACTION, STREAK_BLOCK, STREAK_MIN_LINES)

    def add(self, op) -> None:
        if op.kind == "scan_line" and self._run and _same_segment(self._run[0], op):
            self._run.append(op)
            return
        self._flush()
        kind = op.kind
        start, end = np.asarray(op.start, float), np.asarray(op.end, float)
        if kind in ("move", "push", "indent"):
            d = float(np.hypot(*(end - start)))
            if d > 0:
                self._last_move = (d, *((end - start) / d))
            if kind == "push" and op.data is not None:
                self.features += _push_features(op, self._slid)
                self._slid += float(np.hypot(*(end - start)))
            self._last_move_end_time = op.start_time + (
                op.duration if np.isfinite(op.duration) else 0.0
            )
            return
        common = {
            "dwell": max(0.0, op.start_time - self._last_move_end_time),
            "move_distance": self._last_move[0],
            "move_dx": self._last_move[1],
            "move_dy": self._last_move[2],
            "contact_slid": self._slid,
        }
        if kind == "scan_line":
            self._run, self._run_common = [op], common
        elif kind == "raster" and op.data is not None:
            self.features += _raster_features(op, common, self.anchors, self.particles_seen)
            self.features += self.levels.raster(op, common)

    def _flush(self) -> None:
        if self._run:
            self.features += _run_features(self._run, self._run_common)
            self.features += self.levels.run(self._run, self._run_common)
            self._run = []

    def finish(self) -> list[Feature]:
        self._flush()
        return self.features


def extract_features(
    operations, anchors=None, particles_seen: dict | None = None
) -> list[Feature]:
    """Features of every operation (see the module docstring and FeatureExtractor);
    particles_seen, if given, gets FeatureExtractor.particles_seen."""
    extractor = FeatureExtractor(anchors)
    for op in operations:
        extractor.add(op)
    features = extractor.finish()
    if particles_seen is not None:
        particles_seen.update(extractor.particles_seen)
    return features


def _run_features(run, common) -> list[Feature]:
    """Features of a run of scan lines over one segment: pairs' positions and direction
    shifts, unpaired lines' midpoints, and the run's mean shape (when every line saw the
    particle)."""
    profiles = [(op, line_profile(op.data)) if op.data is not None else (op, None) for op in run]
    if profiles[0][1] is None:
        return []
    u0 = profiles[0][1][0]
    axis_u = np.abs(u0)  # positions are measured along +axis
    axis = "x" if abs(u0[0]) >= abs(u0[1]) else "y"
    first = run[0]
    speed = float(first.speed) if first.speed == first.speed else math.nan

    def cond(sign, extra=None):
        c = dict(common, axis=axis, scan_sign=float(sign), speed=speed)
        if extra:
            c.update(extra)
        return c

    lines = [_line_measurement(op, prof, axis_u) for op, prof in profiles]
    out, paired = _pair_features(run, lines, axis_u, cond)
    out += _unpaired_features(run, lines, paired, axis_u, cond)
    if all(line is not None for line in lines):
        out += _run_shape_features(first.index, lines, cond)
    return out


def _line_measurement(op, prof, axis_u) -> dict | None:
    """What one line of a run measured along the run's axis; None if it saw no particle."""
    if prof is None or prof[1] is None:
        return None
    u, f, t, (px, py) = prof
    sign = float(np.sign(u @ axis_u)) or 1.0
    data = op.data
    coord = np.asarray(data.x, float) * axis_u[0] + np.asarray(data.y, float) * axis_u[1]
    return {
        "op": op,
        "sign": sign,
        "pos": float(axis_u @ np.array([px, py])),
        "t": t,
        "px": px,
        "py": py,
        "width": f["width"],
        "peak": f["peak"],
        "asym": sign * (f["trail"] - f["lead"]),
        "coord": coord,
        "height": np.asarray(data.height, float),
    }


def _pair_features(run, lines, axis_u, cond) -> tuple[list[Feature], set]:
    """`line.pos` and `line.dir` of the run's pairs: consecutive opposite lines, greedily from
    the run's start (by command only, so a pair is one whether or not its lines saw the
    particle). Returns (features, indices of the paired lines)."""
    out = []
    paired = set()
    signs = [
        float(np.sign(np.asarray([op.end[0] - op.start[0], op.end[1] - op.start[1]]) @ axis_u))
        or 1.0
        for op in run
    ]
    k = 0
    while k + 1 < len(run):
        if signs[k] == signs[k + 1]:
            k += 1
            continue
        paired.update((k, k + 1))
        a, b = lines[k], lines[k + 1]
        if a is not None and b is not None:
            plus, minus = (a, b) if a["sign"] > 0 else (b, a)
            t = 0.5 * (a["t"] + b["t"])
            px, py = 0.5 * (a["px"] + b["px"]), 0.5 * (a["py"] + b["py"])
            key_op = run[k].index
            out.append(
                Feature(
                    (key_op, "line.pos"),
                    "line.pos",
                    0.5 * (a["pos"] + b["pos"]),
                    t,
                    px,
                    py,
                    tuple(float(v) for v in axis_u),
                    cond(0.0, {"pair": True}),
                )
            )
            shift = _profile_shift(plus, minus)
            if shift is not None:
                out.append(
                    Feature(
                        (key_op, "line.dir"),
                        "line.dir",
                        0.5 * shift,
                        t,
                        px,
                        py,
                        (0.0, 0.0),
                        cond(0.0, {"pair": True}),
                    )
                )
        k += 2
    return out, paired


def _unpaired_features(run, lines, paired, axis_u, cond) -> list[Feature]:
    """`line.mid` of every line that saw the particle and has no partner."""
    return [
        Feature(
            (run[k].index, "line.mid"),
            "line.mid",
            line["pos"],
            line["t"],
            line["px"],
            line["py"],
            tuple(float(v) for v in axis_u),
            cond(line["sign"]),
        )
        for k, line in enumerate(lines)
        if k not in paired and line is not None
    ]


def _run_shape_features(key_op, lines, cond) -> list[Feature]:
    """`line.width`, `line.peak`, `line.asym`: means over the run's lines."""
    t = float(np.mean([line["t"] for line in lines]))
    px, py = (
        float(np.mean([line["px"] for line in lines])),
        float(np.mean([line["py"] for line in lines])),
    )
    return [
        Feature(
            (key_op, f"line.{name}"),
            f"line.{name}",
            float(np.mean([line[name] for line in lines])),
            t,
            px,
            py,
            (0.0, 0.0),
            cond(0.0, {"lines": len(lines)}),
        )
        for name in ("width", "peak", "asym")
    ]


def _profile_shift(plus: dict, minus: dict, reach: float = 30e-9, step: float = 0.5e-9):
    """How far (m, along +u) the particle appears further in the line scanned along +u than in
    the one scanned back: the shift that best aligns the two height profiles over the particle
    (least squares, parabolic refinement), so the whole profile counts and a change of the
    particle's shape that both lines share (tip, geometry) does not. Searched within `reach`
    of the shift between the two lines' half-height midpoints (a lag of 25 ms shifts the lines
    by more than any fixed window around zero)."""

    def prepared(line):
        c, h = line["coord"], line["height"]
        order = np.argsort(c)
        c, h = c[order], h[order]
        edge = max(3, int(EDGE_FRACTION * h.size))
        return c, h - float(np.median(np.concatenate([h[:edge], h[-edge:]])))

    cp, hp = prepared(plus)
    cm, hm = prepared(minus)
    peak = float(np.max(hp))
    use = hp > 0.2 * peak
    if use.sum() < 5:
        return None
    shifts = (plus["pos"] - minus["pos"]) + np.arange(-reach, reach + step / 2, step)
    sse = np.array([np.sum((hp[use] - np.interp(cp[use] - tau, cm, hm)) ** 2) for tau in shifts])
    k = int(np.argmin(sse))
    if k == 0 or k == shifts.size - 1:
        return None
    a, b, c = sse[k - 1], sse[k], sse[k + 1]
    curvature = a - 2 * b + c
    offset = 0.5 * (a - c) / curvature if curvature > 0 else 0.0
    return float(shifts[k] + offset * step)


def match_anchors(points: np.ndarray, anchors: np.ndarray, radius: float = MATCH_RADIUS) -> dict:
    """{point index: anchor index} after the common translation that matches the most points
    (ties: the smallest mean distance); each anchor at most once."""
    points, anchors = (
        np.asarray(points, float).reshape(-1, 2),
        np.asarray(anchors, float).reshape(-1, 2),
    )
    if not len(points) or not len(anchors):
        return {}
    best, best_score = {}, (0, 0.0)
    for p in points:
        for a in anchors:
            shift = p - a
            d = np.hypot(*(points[:, None, :] - anchors[None, :, :] - shift).transpose(2, 0, 1))
            match = {}
            used = set()
            for i in np.argsort(d.min(axis=1)):
                j = int(np.argmin(d[i]))
                if d[i, j] <= radius and j not in used:
                    match[int(i)] = j
                    used.add(j)
            score = (
                len(match),
                -float(np.mean([d[i, j] for i, j in match.items()])) if match else 0.0,
            )
            if score > best_score:
                best, best_score = match, score
    return best


def _raster_features(
    op, common, anchors=None, particles_seen: dict | None = None
) -> list[Feature]:
    from afm_core.imaging.landmarks import extract_landmarks

    data = op.data
    h = np.asarray(data.height, float)
    if not np.isfinite(h).all():
        return []
    cond = dict(common, angle=float(data.scan_angle_deg), up=bool(data.slow_scan_up))
    t = float(data.start_time + 0.5 * data.line_period * len(data.line_start_times))
    out = []
    size_x, size_y = h.shape[1] * data.pixel_size_x, h.shape[0] * data.pixel_size_y
    cx = data.origin_x + 0.5 * size_x
    cy = data.origin_y + 0.5 * size_y
    if max(data.pixel_size_x, data.pixel_size_y) <= MAX_LANDMARK_PIXEL:
        try:
            marks = extract_landmarks(
                h,
                data.pixel_size_x,
                data.pixel_size_y,
                data.origin_x,
                data.origin_y,
                min_height=20e-9,
            )
        except ValueError:
            marks = []
        if particles_seen is not None:
            particles_seen[op.index] = len(marks)
        if anchors is not None and len(anchors) > 1 and len(marks) > 1:
            # (one particle alone matches any anchor under some translation: keyed as the central
            # one)
            match = match_anchors(np.array([(m.x, m.y) for m in marks]), anchors)
            chosen = [
                (f"{j}", marks[i]) for i, j in sorted(match.items(), key=lambda item: item[1])
            ]
        elif marks:
            # the particle nearest the image centre: the one the image was centred on
            chosen = [("", min(marks, key=lambda lm: math.hypot(lm.x - cx, lm.y - cy)))]
        else:
            chosen = []
        level = np.median(h)
        for tag, m in chosen:
            mx, my = _weighted_centre(h, data, m, level)
            # the time the scan passed the particle
            row = (
                (m.y - data.origin_y) / data.pixel_size_y
                if data.scan_angle_deg == 0.0
                else (m.x - data.origin_x) / data.pixel_size_x
            )
            starts = np.asarray(data.line_start_times, float)
            line = int(np.clip(round(row - 0.5), 0, len(starts) - 1))
            tm = float(
                data.start_time
                + (starts[line] if np.isfinite(starts[line]) else 0.0)
                + 0.25 * data.line_period
            )
            names = [("x", mx, (1.0, 0.0)), ("y", my, (0.0, 1.0))]
            if max(data.pixel_size_x, data.pixel_size_y) <= MAX_SHAPE_PIXEL:
                names += [
                    ("height", m.height, (0.0, 0.0)),
                    ("half_width", m.half_width, (0.0, 0.0)),
                ]
            for name, value, u in names:
                out.append(
                    Feature(
                        (op.index, f"raster.{name}{tag}"),
                        f"raster.{name}",
                        float(value),
                        tm,
                        float(m.x),
                        float(m.y),
                        u,
                        dict(cond, particle=tag),
                    )
                )
    out += _streak_features(op, h, cond)
    if min(size_x, size_y) >= BOW_MIN_SIZE:
        quad = _quad_background(h, data.pixel_size_x, data.pixel_size_y)
        if quad is not None:
            for name, value in quad.items():
                out.append(
                    Feature(
                        (op.index, f"raster.bow_{name}"),
                        f"raster.bow_{name}",
                        float(value),
                        t,
                        cx,
                        cy,
                        (0.0, 0.0),
                        dict(
                            cond,
                            image=(h.shape[0], h.shape[1], data.pixel_size_x, data.pixel_size_y),
                        ),
                    )
                )
    return out


def line_offset_noise(offsets: np.ndarray) -> float:
    """Robust standard deviation (m) of the line-to-line changes of consecutive lines' offsets,
    after a quadratic along the slow axis is taken out (sample tilt, bow and the slow wander
    of the whole image are not streaks), divided by sqrt(2): the noise of one line's offset."""
    offsets = np.asarray(offsets, float)
    index = np.arange(offsets.size)
    steps = np.diff(offsets - np.polyval(np.polyfit(index, offsets, 2), index))
    return float(median_abs_deviation(steps, scale="normal") / math.sqrt(2))


def pixel_noise(lines: np.ndarray, offsets: np.ndarray) -> float:
    """Robust standard deviation (m) of the changes from pixel to pixel along the lines (rows)
    on the bare substrate, divided by sqrt(2): the noise of one pixel if it is white. Pixels
    raised PARTICLE_LEVEL above their line's offset (`offsets`: each line's median height) and
    PARTICLE_MARGIN pixels either side are left out: a particle's flanks are few, but a blunter
    tip widens them, and even a per cent more large steps moves the spread by more than its
    noise."""
    steps = np.diff(lines, axis=1)
    raised = lines - np.asarray(offsets)[:, None] > PARTICLE_LEVEL
    raised = binary_dilation(raised, structure=np.ones((1, 2 * PARTICLE_MARGIN + 1), bool))
    bare = ~raised[:, 1:] & ~raised[:, :-1]
    if bare.sum() >= 0.5 * bare.size:
        steps = steps[bare]
    return float(median_abs_deviation(steps, axis=None, scale="normal") / math.sqrt(2))


def raster_noise_statistics(op) -> list[Feature]:
    """The noise statistics (`raster.streak`, `raster.pixel_noise`) of one raster, without the
    particles and the background its other features need (conditions left empty)."""
    h = np.asarray(op.data.height, float)
    return _streak_features(op, h, {}) if np.isfinite(h).all() else []


def _streak_features(op, h: np.ndarray, cond: dict) -> list[Feature]:
    """Noise statistics per block of STREAK_BLOCK consecutive lines of an image with at least
    STREAK_MIN_LINES lines. `raster.streak`: how much each line's offset (its median height:
    particles and roughness average out) jumps from line to line; white sensor noise adds little
    to a median of a whole line, low-frequency (1/f, coloured) z noise shifts whole lines and
    makes the streaks an image shows. `raster.pixel_noise`: how much the height jumps from
    pixel to pixel along a line; white noise makes it, 1/f noise has little power that fast."""
    data = op.data
    lines = h if data.scan_angle_deg == 0.0 else h.T  # rows: one scan line each
    if lines.shape[0] < STREAK_MIN_LINES or lines.shape[1] < STREAK_MIN_LINES:
        return []
    offsets = np.median(lines, axis=1)
    starts = np.asarray(data.line_start_times, float)
    out = []
    for b, block in enumerate(
        np.array_split(np.arange(lines.shape[0]), lines.shape[0] // STREAK_BLOCK)
    ):
        # where: the block's middle across the lines, the lines' middle along them
        across, along = (block[0] + block[-1] + 1) / 2, lines.shape[1] / 2
        col, row = (along, across) if data.scan_angle_deg == 0.0 else (across, along)
        x, y = data.origin_x + col * data.pixel_size_x, data.origin_y + row * data.pixel_size_y
        t = (
            float(data.start_time + np.nanmean(starts[block]) + 0.5 * data.line_period)
            if np.isfinite(starts[block]).any()
            else float(data.start_time)
        )
        where = dict(cond, lines=int(block.size), line_period=float(data.line_period))
        for group, value in (
            ("raster.streak", line_offset_noise(offsets[block])),
            ("raster.pixel_noise", pixel_noise(lines[block], offsets[block])),
        ):
            out.append(
                Feature(
                    (op.index, f"{group}{b}"),
                    group,
                    value,
                    t,
                    float(x),
                    float(y),
                    (0.0, 0.0),
                    where,
                )
            )
    # one per image: the lines crossing a particle are too few per block
    shift, crossings = line_shift_noise(
        lines, data.pixel_size_x if data.scan_angle_deg == 0.0 else data.pixel_size_y
    )
    if math.isfinite(shift):
        t_mid = float(data.start_time + 0.5 * data.line_period * lines.shape[0])
        x = data.origin_x + 0.5 * h.shape[1] * data.pixel_size_x
        y = data.origin_y + 0.5 * h.shape[0] * data.pixel_size_y
        where = dict(cond, lines=int(lines.shape[0]), crossings=crossings, statistic=shift)
        out.append(
            Feature(
                (op.index, LINE_SHIFT_GROUP),
                LINE_SHIFT_GROUP,
                shift,
                t_mid,
                float(x),
                float(y),
                (0.0, 0.0),
                where,
            )
        )
    return out


def _weighted_centre(h: np.ndarray, data, mark, level: float) -> tuple[float, float]:
    """A particle's centre as the centroid of its height above the substrate (+ CENTRE_LEVEL),
    weighted by the excess, over a window reaching well beyond its foot: it moves smoothly with
    the particle (a centroid of thresholded pixels jumps by fractions of a pixel whenever one
    crosses a threshold)."""
    px, py = data.pixel_size_x, data.pixel_size_y
    col = (mark.x - data.origin_x) / px - 0.5
    row = (mark.y - data.origin_y) / py - 0.5
    reach = 2.5 * max(mark.half_width, 2 * max(px, py)) + 2 * max(px, py)
    r0, r1 = (
        int(max(0, math.floor(row - reach / py))),
        int(min(h.shape[0], math.ceil(row + reach / py) + 1)),
    )
    c0, c1 = (
        int(max(0, math.floor(col - reach / px))),
        int(min(h.shape[1], math.ceil(col + reach / px) + 1)),
    )
    window = h[r0:r1, c0:c1]
    w = np.clip(window - (level + CENTRE_LEVEL), 0.0, None)
    if not window.size or w.sum() <= 0:
        return float(mark.x), float(mark.y)
    rows, cols = np.mgrid[r0:r1, c0:c1]
    return (
        float(data.origin_x + (np.sum(w * cols) / w.sum() + 0.5) * px),
        float(data.origin_y + (np.sum(w * rows) / w.sum() + 0.5) * py),
    )


def _step_noise(values: np.ndarray) -> float:
    """Robust sd of the sample-to-sample changes over sqrt(2): the white noise of a trace,
    which its slow course and a few jumps (slips, contacts) do not reach."""
    return float(median_abs_deviation(np.diff(values), scale="normal") / math.sqrt(2))


def _push_features(op, slid_before) -> list[Feature]:
    data = op.data
    torsion = np.asarray(data.lateral_torsion, float)
    if torsion.size < 20:
        return []
    cx, cy = np.asarray(data.commanded_x, float), np.asarray(data.commanded_y, float)
    times = np.asarray(data.times, float)
    step = np.hypot(np.diff(cx), np.diff(cy))
    moving = np.concatenate([[False], step > 0])
    if moving.sum() < 20:
        return []
    travelled = np.concatenate([[0.0], np.cumsum(step)])
    length = float(travelled[-1])
    direction = np.array([cx[-1] - cx[0], cy[-1] - cy[0]]) / max(length, 1e-30)
    tm, xm, ym, tor, sm = times[moving], cx[moving], cy[moving], torsion[moving], travelled[moving]
    t = float(data.start_time + np.mean(tm))
    axis = "x" if abs(direction[0]) >= abs(direction[1]) else "y"
    cond = {
        "contact_slid": slid_before,
        "push_phase": "sliding",
        "axis": axis,
        "scan_sign": float(np.sign(direction[0] if axis == "x" else direction[1])),
    }
    out = []
    trend = np.polyval(np.polyfit(np.arange(tor.size), tor, 1), np.arange(tor.size))
    out.append(
        Feature(
            (op.index, "push.fluct"),
            "push.fluct",
            float(np.std(tor - trend)),
            t,
            float(np.mean(xm)),
            float(np.mean(ym)),
            (0.0, 0.0),
            # how well an rms of these samples is known (noise_floor.py): their count and the
            # trace's own sample-to-sample noise
            dict(cond, samples=int(tor.size), step_noise=_step_noise(tor)),
        )
    )
    n_seg = max(1, int(round(length / SEGMENT)))
    edges = np.linspace(0.0, length, n_seg + 1)
    segment = np.clip(np.searchsorted(edges, sm, side="right") - 1, 0, n_seg - 1)
    for q in range(n_seg):
        part = segment == q
        if part.sum() < 3:
            continue
        out.append(
            Feature(
                (op.index, f"push.torsion{q}"),
                "push.torsion",
                float(np.mean(tor[part])),
                float(data.start_time + np.mean(tm[part])),
                float(np.mean(xm[part])),
                float(np.mean(ym[part])),
                (0.0, 0.0),
                dict(
                    cond,
                    segment=q,
                    segment_length=float(edges[q + 1] - edges[q]),
                    contact_slid=slid_before + float(edges[q]),
                ),
            )
        )
    return out
