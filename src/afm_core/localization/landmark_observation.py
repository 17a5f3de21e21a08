"""Landmark observation from one local scan line (book 5.2.3-5.2.4, eq. 5.9-5.15, 7.1).

The tip scans a straight line across a landmark. Where the height profile crosses a
threshold going up (l_ka) and coming down (l_kb), the midpoint of the two crossings is where
the line passes the landmark's centre (eq. 5.10): more robust than the highest sample, whose
position is at the mercy of the noise on a flat top. At that moment t_kp the tip is at the
foot of the perpendicular from the landmark centre m to its true path, so the component of
the tip position along the line's true direction d equals that of m:

    z = u . m  =  u . x(t_kp) + v,       H = u^T          (eq. 5.11-5.13, R_theta and S_x)

u = d for a sphere (a horizontal line measures x, a vertical one y). A tube's cross-section
along any line crossing it is symmetric about the point where the line meets the tube's axis,
so a line across a tube measures the tip's position perpendicular to the axis: u = the axis
normal (sign along d); the position along the axis is not observed.

Threshold (default 0.5 of the landmark's map height above the line's own substrate level):
- the substrate level is the median of the line's first and last 10 % of samples (the line
  starts and ends clear of the particle), so slow z drift and tilt of the line cancel;
- at half height the dilated profile is steepest (a sphere's or tube's equator, where the
  tip's flank touches it): the crossing position is least sensitive to height noise, and the
  tip apex (top) and the tip cone meeting the substrate (bottom corners) are both avoided;
- a sphere of radius r sitting on the substrate is r + sqrt(r^2 - delta^2) high at a lateral
  offset delta from its centre, i.e. above half height for every delta < r: a line anywhere
  across the particle still finds a pair, and a line that misses it by more finds none (lost)
  instead of a biased centre;
- a run that dips between two tops (MERGED_DIP_FRACTION) is two features merged above the
  threshold, whose midpoint is neither's centre: not taken. The other single pairs on the line
  are reported (`alternatives`) so that the localizer can tell whether the gate would take
  one of them too.

Observation noise (eq. 5.15, 7.1): v = v_map + v_region + v_deflection:
- v_map: the landmark's own map covariance projected on u (u^T Sigma_m u);
- v_region: `calibration.scan_region_sigma` (centre found from different chords);
- v_deflection: `line_deflection_sigma_deg` times the largest perpendicular offset of the
  line from the centre, the landmark radius (book: "the maximum d_kp is the radius", ~2 nm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from afm_core.instrument import ScanLineData
from afm_core.localization.calibration.model import Calibration

DEFAULT_THRESHOLD_FRACTION = 0.5
EDGE_FRACTION = 0.1  # of the samples at each end: the line's substrate level
MIN_EDGE_SAMPLES = 3
KINDS = ("sphere", "tube", "rod")
# A run above the threshold that dips by more than this fraction of the landmark's height (and
# MERGED_DIP_NOISE x the line's noise) between two higher parts holds two features: particles
# closer than the tip can separate merge above half height, and the run's midpoint then lies
# between them (two 100 nm spheres 50 nm apart: one 490 nm run, a dip of 86 nm, its midpoint
# 125 nm off the landmark, accepted at 1.7 sigma of a 70 nm prior and the estimate left 130 nm
# off at a 9 nm sigma). A single sphere, tube or rod is unimodal along a line (dips of a few
# noise sigma); two touching equal spheres dip by about 0.2 of their height with a tip apex up
# to half their radius.
MERGED_DIP_FRACTION = 0.1
MERGED_DIP_NOISE = 6.0


def check_covariance(name: str, covariance) -> np.ndarray:
    """A finite, symmetric, positive semi-definite 2x2 matrix, or ValueError naming it."""
    c = np.asarray(covariance, dtype=float)
    if c.shape != (2, 2):
        raise ValueError(f"{name}: need a 2x2 matrix, got shape {c.shape}")
    if not np.isfinite(c).all():
        raise ValueError(f"{name}={c.tolist()}: must be finite")
    if not np.allclose(c, c.T, rtol=1e-9, atol=1e-30):
        raise ValueError(f"{name}={c.tolist()}: must be symmetric")
    smallest = float(np.linalg.eigvalsh(c).min())
    if smallest < -1e-12 * max(float(np.abs(c).max()), 1e-300):
        raise ValueError(
            f"{name}={c.tolist()}: not positive semi-definite (smallest eigenvalue {smallest:.3e})"
        )
    return 0.5 * (c + c.T)


@dataclass
class MapLandmark:
    """A landmark in the task frame, as the localizer uses it (SI units).
    `from_landmark` converts an `afm_core.imaging.landmarks.Landmark`."""

    x: float  # m, centre in the task frame
    y: float
    covariance: np.ndarray  # 2x2 m^2, map error of the centre
    radius: float  # m (sphere radius, tube/rod radius)
    kind: str = "sphere"  # "sphere" | "tube" | "rod"
    height: float = 0.0  # m, apparent height above the substrate; 0: 2 * radius
    orientation: float = 0.0  # rad from +x, axis of a tube/rod
    half_width: float = 0.0  # m, apparent half-width at half height; 0: unknown
    id: int = -1

    def __post_init__(self):
        self.validate()

    def validate(self) -> None:
        for name in ("x", "y", "radius", "height", "orientation", "half_width"):
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise ValueError(f"landmark.{name}={value}: must be finite")
        if not self.radius > 0:
            raise ValueError(f"landmark.radius={self.radius}: must be > 0 m")
        if self.height < 0 or self.half_width < 0:
            raise ValueError("landmark.height and landmark.half_width: must be >= 0 m")
        if self.kind not in KINDS:
            raise ValueError(f"landmark.kind={self.kind!r}: must be one of {KINDS}")
        self.covariance = check_covariance("landmark.covariance", self.covariance)

    @property
    def position(self) -> np.ndarray:
        return np.array([self.x, self.y])

    @property
    def apparent_height(self) -> float:
        return self.height if self.height > 0 else 2.0 * self.radius

    @property
    def elongated(self) -> bool:
        return self.kind in ("tube", "rod")

    @property
    def axis(self) -> np.ndarray:
        return np.array([math.cos(self.orientation), math.sin(self.orientation)])

    @classmethod
    def from_landmark(cls, landmark) -> MapLandmark:
        """From afm_core.imaging.landmarks.Landmark (or anything with the same fields)."""
        return cls(
            x=float(landmark.x),
            y=float(landmark.y),
            covariance=np.array(landmark.covariance, dtype=float),
            radius=float(landmark.radius),
            kind=str(landmark.kind),
            height=float(getattr(landmark, "height", 0.0)),
            orientation=float(getattr(landmark, "orientation", 0.0)),
            half_width=float(getattr(landmark, "half_width", 0.0)),
            id=int(getattr(landmark, "id", -1)),
        )


def as_map_landmark(landmark) -> MapLandmark:
    return landmark if isinstance(landmark, MapLandmark) else MapLandmark.from_landmark(landmark)


def observation_direction(landmark: MapLandmark, line_direction) -> np.ndarray:
    """u: the unit vector along which a line of true direction `line_direction` measures."""
    d = np.asarray(line_direction, dtype=float)
    d = d / np.hypot(*d)
    if not landmark.elongated:
        return d
    normal = np.array([-landmark.axis[1], landmark.axis[0]])
    return normal if normal @ d >= 0 else -normal


def line_variance(landmark: MapLandmark, calibration: Calibration) -> float:
    """The part of eq. 5.15 each line draws afresh: scan-region error + line-deflection error
    (m^2). The map error is the landmark's, shared by every line across it."""
    deflection = math.radians(calibration.line_deflection_sigma_deg) * landmark.radius
    return calibration.scan_region_sigma**2 + deflection**2


def observation_variance(landmark: MapLandmark, direction, calibration: Calibration) -> float:
    """Eq. 5.15: map error along u + scan-region error + line-deflection error (m^2)."""
    u = np.asarray(direction, dtype=float)
    return float(u @ landmark.covariance @ u) + line_variance(landmark, calibration)


@dataclass
class LineObservation:
    """What one local scan line saw. status "ok" or "lost" (reason says why)."""

    status: str
    reason: str = ""
    threshold: float = math.nan  # m, absolute height threshold used
    substrate: float = math.nan  # m, line's substrate level
    crossings: tuple = (
        math.nan,
        math.nan,
    )  # fractional sample indices of the rising / falling crossing
    index: float = math.nan  # fractional sample index of the midpoint (x_kp)
    time: float = math.nan  # s, instrument clock at x_kp
    command: tuple = (math.nan, math.nan)  # m, commanded scanner position at x_kp
    direction: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))  # u (task frame)
    value: float = math.nan  # m, z = u . m
    variance: float = math.nan  # m^2, observation noise (eq. 5.15)
    line_variance: float = math.nan  # m^2, its part without the landmark's map error
    width: float = math.nan  # m, commanded distance between the crossings
    # m, commanded (x, y) of the midpoints of the line's other crossing pairs that could be a
    # landmark of this kind (single, not too wide): the localizer asks whether one of them
    # would pass the gate too
    alternatives: tuple = ()

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def _crossing(h: np.ndarray, threshold: float, i: int) -> float:
    """Fractional index between samples i and i + 1 where h crosses threshold (linear)."""
    a, b = h[i] - threshold, h[i + 1] - threshold
    return i + (a / (a - b) if a != b else 0.5)


def line_noise(height) -> float:
    """Robust sigma of a profile's noise from its sample-to-sample differences (MAD; the
    flanks of a landmark, a minority of the differences, do not count)."""
    steps = np.diff(np.asarray(height, dtype=float))
    return (
        float(np.median(np.abs(steps - np.median(steps))) / (0.6745 * math.sqrt(2)))
        if steps.size
        else 0.0
    )


def line_threshold(height, apparent_height: float, fraction: float) -> tuple[float, float]:
    """(substrate, threshold) of a line across a landmark: the substrate is the median of the
    line's ends (EDGE_FRACTION of it at each end, at least MIN_EDGE_SAMPLES), the threshold that
    plus `fraction` of the landmark's apparent height. Ends that disagree by more than half of
    that fraction of the height (far beyond a line's tilt or z drift) mean that one of them
    lies on another feature, a neighbour the line runs onto, and the lower one is the
    substrate: the median of both put the threshold near the landmark's top and the line
    'missed' a landmark it crossed."""
    h = np.asarray(height, dtype=float)
    edge = max(MIN_EDGE_SAMPLES, int(EDGE_FRACTION * h.size))
    first, last = float(np.median(h[:edge])), float(np.median(h[-edge:]))
    if abs(first - last) > 0.5 * fraction * apparent_height:
        substrate = min(first, last)
    else:
        substrate = float(np.median(np.concatenate([h[:edge], h[-edge:]])))
    return substrate, substrate + fraction * apparent_height


def find_crossings(
    height, threshold: float, expected_index: float | None = None, margin: float | None = None
):
    """Pairs (rising, falling) of threshold crossings as fractional indices; the pair whose
    midpoint is nearest `expected_index` (default: the line's middle) first. Returns
    (pairs, reason) with reason non-empty when there is no complete pair.

    margin: hysteresis (Schmitt trigger) against noise on a flank, where the profile crosses
    the threshold several times and would make an extra, narrow pair that can lie nearer the
    expected index than the landmark's own: a run above the threshold counts only if it
    reaches threshold + margin, and dips that stay above threshold - margin do not split a
    run (its crossings are the outermost ones). Default 3 x `line_noise`, at most half the
    threshold's height above the profile's median."""
    h = np.asarray(height, dtype=float)
    above = h > threshold
    if not above.any():
        return [], "no sample above the threshold: the line missed the landmark"
    if above.all():
        return [], "every sample above the threshold: the line lies on the landmark"
    if margin is None:
        margin = min(3.0 * line_noise(h), 0.5 * max(threshold - float(np.median(h)), 0.0))
    elif not (math.isfinite(margin) and margin >= 0):
        raise ValueError(f"margin={margin}: must be finite and >= 0 (height units of the profile)")
    edges = np.flatnonzero(np.diff(above.astype(np.int8))) + 1
    bounds = np.concatenate([[0], edges, [h.size]])
    runs = [
        [int(i), int(j)] for i, j in zip(bounds[:-1], bounds[1:]) if above[i]
    ]  # [first, end) above
    merged = [runs[0]]
    for run in runs[1:]:
        if h[merged[-1][1] : run[0]].min() >= threshold - margin:
            merged[-1][1] = run[1]
        else:
            merged.append(run)
    reaching = [(i, j) for i, j in merged if h[i:j].max() >= threshold + margin]
    if not reaching:
        return [], (
            f"no run above the threshold reaches it + margin {margin:.3g}: the line missed the "
            "landmark (what rises above the threshold is noise)"
        )
    pairs = [
        (_crossing(h, threshold, i - 1), _crossing(h, threshold, j - 1))
        for i, j in reaching
        if i > 0 and j < h.size
    ]
    if not pairs:
        where = "starts" if above[0] else "ends"  # an edge run above the threshold is not a pair
        return [], f"the line {where} on the landmark: no rising/falling crossing pair"
    centre = 0.5 * (h.size - 1) if expected_index is None else float(expected_index)
    pairs.sort(key=lambda p: abs(0.5 * (p[0] + p[1]) - centre))
    return pairs, ""


def deepest_dip(height, rising: float, falling: float) -> float:
    """The deepest dip between the crossings `rising` and `falling` (fractional indices): how far
    the profile falls below the lower of the highest samples on either side of it (0 for a
    profile that rises to one top and falls)."""
    h = np.asarray(height, dtype=float)
    run = h[int(math.ceil(rising)) : int(math.floor(falling)) + 1]
    if run.size < 3:
        return 0.0
    left = np.maximum.accumulate(run)
    right = np.maximum.accumulate(run[::-1])[::-1]
    return float((np.minimum(left, right) - run).max())


def observe_line(
    line: ScanLineData,
    landmark,
    calibration: Calibration,
    line_direction,
    threshold_fraction: float = DEFAULT_THRESHOLD_FRACTION,
    expected_index: float | None = None,
    max_width: float | None = None,
) -> LineObservation:
    """The landmark observation of one local scan line (eq. 5.9-5.15).

    line_direction: the line's true direction in the task frame (the motion model's
    `line_direction` of the commanded step). expected_index: fractional sample index where the
    landmark is predicted (picks the pair when the line crosses more than one feature).
    max_width: widest acceptable crossing pair (m, commanded distance); default
    4 * (apparent height) + 200 nm, generous for tip dilation (a 20 nm tube images ~50 nm wide)."""
    landmark = as_map_landmark(landmark)
    if not (math.isfinite(threshold_fraction) and 0.0 < threshold_fraction < 1.0):
        raise ValueError(f"threshold_fraction={threshold_fraction}: must be in (0, 1)")
    d = np.asarray(line_direction, dtype=float)
    if d.shape != (2,) or not np.isfinite(d).all() or not np.hypot(*d) > 0:
        raise ValueError(f"line_direction={line_direction}: need a finite non-zero 2-vector")
    u = observation_direction(landmark, d)
    h = np.asarray(line.height, dtype=float)
    n = h.size
    if n < 2 * MIN_EDGE_SAMPLES + 2:
        return LineObservation("lost", f"only {n} samples on the line", direction=u)
    if not line.complete:
        return LineObservation("lost", "the line was not completed (cancelled)", direction=u)
    if not np.isfinite(h).all():
        return LineObservation("lost", "the height profile has non-finite samples", direction=u)
    if landmark.elongated and abs(float(u @ (d / np.hypot(*d)))) < math.cos(math.radians(60.0)):
        return LineObservation(
            "lost",
            "the line runs within 30 deg of the tube's axis: it cannot measure "
            "the position across the tube",
            direction=u,
        )
    substrate, threshold = line_threshold(h, landmark.apparent_height, threshold_fraction)
    pairs, reason = find_crossings(h, threshold, expected_index)
    base = dict(threshold=threshold, substrate=substrate, direction=u)
    if not pairs:
        return LineObservation("lost", reason, **base)
    xs, ys = np.asarray(line.x, dtype=float), np.asarray(line.y, dtype=float)
    samples = np.arange(n)
    if max_width is None:
        max_width = 4.0 * landmark.apparent_height + 200e-9
    merged_limit = max(
        MERGED_DIP_FRACTION * landmark.apparent_height, MERGED_DIP_NOISE * line_noise(h)
    )
    single = [p for p in pairs if deepest_dip(h, *p) <= merged_limit]
    if not single:
        rising, falling = pairs[0]
        return LineObservation(
            "lost",
            f"what the line crossed dips {deepest_dip(h, rising, falling):.3e} m between two "
            f"tops (more than {merged_limit:.3e} m): two features merged above the threshold, "
            "whose midpoint is not the landmark's centre",
            crossings=(rising, falling),
            **base,
        )
    rising, falling = single[0]
    width = float(
        np.hypot(
            np.interp(falling, samples, xs) - np.interp(rising, samples, xs),
            np.interp(falling, samples, ys) - np.interp(rising, samples, ys),
        )
    )
    if width > max_width:
        return LineObservation(
            "lost",
            f"crossing pair {width:.3e} m apart, wider than {max_width:.3e} m: not this landmark",
            crossings=(rising, falling),
            width=width,
            **base,
        )
    alternatives = tuple(
        (
            float(np.interp(0.5 * (a + b), samples, xs)),
            float(np.interp(0.5 * (a + b), samples, ys)),
        )
        for a, b in single[1:]
        if math.hypot(
            np.interp(b, samples, xs) - np.interp(a, samples, xs),
            np.interp(b, samples, ys) - np.interp(a, samples, ys),
        )
        <= max_width
    )
    index = 0.5 * (rising + falling)
    time = float(line.start_time + np.interp(index, samples, np.asarray(line.times, dtype=float)))
    command = (float(np.interp(index, samples, xs)), float(np.interp(index, samples, ys)))
    return LineObservation(
        "ok",
        "",
        threshold=threshold,
        substrate=substrate,
        crossings=(rising, falling),
        index=index,
        time=time,
        command=command,
        direction=u,
        value=float(u @ landmark.position),
        variance=observation_variance(landmark, u, calibration),
        line_variance=line_variance(landmark, calibration),
        width=width,
        alternatives=alternatives,
    )
