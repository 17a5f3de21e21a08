"""What the re-simulation cannot reproduce in an ordinary session, left out with a reason.

The reference replays the recorded commands on the model; it reproduces what the commands and
the model's physics decide, with the drift put where the recording saw the particles. Two
things in a session of normal work are decided by neither:

- **A stroke in contact with a particle.** The torsion of a push that meets a particle is the
  particle's contact history: where on the particle the tip met it (a few nm of the tip's
  positioning walk and of the map's error decide that), how it rolled or slid, and when it
  left the tip. The re-simulation meets its particle a few nm elsewhere and pushes it
  elsewhere; the two torsions differ by the particle's contact forces, not by the tip-substrate
  friction the features are there to measure (a null session's pushed strokes gave chi^2 925
  for 24, and were read as a friction patch 6x the model's). The noise model cannot carry it:
  the difference is a function of where each contact began, which no replica of the model's
  noise draws (the replicas run with the recorded drift and no positioning walk). So the
  whole stroke is left out (its torsion segments and its fluctuation).
- **A particle moved by an earlier push.** After a stroke has pushed it, a particle is where
  that push left it, in the recording and in the re-simulation each by its own contact
  history (a push's outcome scatters by several nm, the positions' noise is about 1 nm). Its
  features in later images and scan lines (position, height, width) are left out, wherever
  its path could have taken it: within reach of the stroke, extended by the reach beyond its
  end.

A stroke *meets* a particle when its commanded path comes within the reach of the particle's
last known place: R_p + R_t (the sphere's and the tip's radius: the centres' distance at
contact is at most their sum) plus how far the command can be from where the tip is against
that place: 3 sigma of the persistent positioning walk (offset + slope x the stroke's length
and a micrometre of approach) and 3 sigma of the drift's wander since the place was measured
(the stationary velocity spread times the time since; the model's mean drift moves the place).
The places are where the session's own images saw the particles (an image supersedes the places
inside its area; before any image, the configured spheres) and where its scan lines crossed one
(the closed loop observes its particle so between legs: on a null closed-loop session a
correction stroke beyond reach of every earlier path met the particle where the last
observation had seen it, and its torsion read 54 sigma), and the paths of the strokes that met
one before: a moved particle is somewhere along them or up to the contact distance beyond
their end (the particle leads the tip). The closed loop's later legs start from where its scan
lines saw the particle, beyond its last stroke's end: on a null closed-loop session two such
correction strokes, taken as meeting nothing, read chi^2 609 for 2 in their torsion before the
paths were extended so. Everything is from the commands and the session's own images, so the
same features are left out of the recording and of every re-simulation.

- **The level of a scan line over a moved particle.** A line's absolute level
  (`features_absolute`) is its edges' substrate; where a push left the particle decides
  whether an edge lies on its flank, which moves the level by nm (a closed loop's anchor line
  over a particle pushed before read -5.5 nm against the re-simulation, 17 sigma). The
  both-edges rule catches an edge on a particle, not one on part of a flank. So the level of a
  line that comes within reach of where a pushed particle may be is left out too; lines over
  particles nothing pushed keep theirs.

One more thing is decided by the tip's positioning walk, which the reference leaves out and the
noise model carries only to first order:

- **The shape of a single scan line.** A line scanned once (no forward/back partner over the
  same segment: a localizer's line) crosses its particle at an offset across the line that the
  walk of the moves before it decides (tens of nm after a long move: a raster, a push). Its
  width, peak and flank asymmetry are a chord of the particle at that offset: non-linear in it
  well inside the walk's spread, so the linear geometry term of the noise model cannot carry it
  (replays with the model's walk at the recorded drift scattered a localizer line's width by
  1-35 nm where that term gave 0.5-2 nm). Its position (`line.mid`) is kept: linear in the
  walk, which the noise model has. Lines in pairs (the protocol's) keep their shapes: the
  pair's tracking centres them, where the chord is flat.

Strokes that meet no particle (slides on bare substrate, as in the protocol) keep their
features: they carry the friction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

WALK_SIGMAS = 3.0  # a stroke more than 3 sigma of the walk from a particle does not meet it
DRIFT_SIGMAS = 3.0  # nor one beyond 3 sigma of the drift's wander since its place was seen
APPROACH = 1e-6  # m: the free move before a stroke, whose walk the stroke also carries
PARTICLE_GROUPS = (
    "line.pos",
    "line.mid",
    "line.dir",
    "line.width",
    "line.peak",
    "line.asym",
    "raster.x",
    "raster.y",
    "raster.height",
    "raster.half_width",
)

# the line features that say where a line crossed a particle (features.py: the crossing's
# point on the line)
LINE_PLACE_GROUPS = ("line.pos", "line.mid")

CONTACT_REASON = (
    "torsion of strokes that meet a particle: the particle's contact history (where the tip "
    "met it, how it rolled, when it left), set by a few nm of positioning walk, which the "
    "re-simulation does not reproduce and no noise replica draws"
)
MOVED_REASON = (
    "features of particles moved by an earlier push: where the push left each is its own "
    "contact history in the recording and in the re-simulation (scatter of nm, the features' "
    "noise about 1 nm)"
)

MOVED_LEVEL_REASON = (
    "absolute levels of scan lines within reach of a moved particle: where the push left it "
    "(its own contact history in the recording and in the re-simulation) decides whether an "
    "edge of the line lies on its flank, which moves the line's substrate level by nm"
)

SINGLE_LINE_GROUPS = ("line.width", "line.peak", "line.asym")
SINGLE_LINE_REASON = (
    "width, peak and flank asymmetry of single scan lines: a chord of the particle at an offset "
    "across the line that the positioning walk decides, non-linear in it within the walk's "
    "spread (the noise model carries the walk to first order only)"
)


@dataclass
class Exclusions:
    keys: set = field(default_factory=set)  # feature keys left out
    rows: list = field(default_factory=list)  # {what, count, reason}
    strokes: int = 0  # strokes that met a particle

    def apply(self, features: dict) -> dict:
        """The features by key without the excluded ones."""
        return {k: f for k, f in features.items() if k not in self.keys}


def _segment_distance(p, a, b) -> float:
    """Distance of point p from the segment a-b (m)."""
    ab = b - a
    n2 = float(ab @ ab)
    t = 0.0 if n2 == 0 else float(np.clip((p - a) @ ab / n2, 0.0, 1.0))
    return float(np.hypot(*(a + t * ab - p)))


def _segment_to_segment(a, b, c, d) -> float:
    """Distance between the segments a-b and c-d (m), for segments that do not cross."""
    ab, cd = b - a, d - c
    cross = ab[0] * cd[1] - ab[1] * cd[0]
    if cross != 0:
        s = ((c - a)[0] * cd[1] - (c - a)[1] * cd[0]) / cross
        u = ((c - a)[0] * ab[1] - (c - a)[1] * ab[0]) / cross
        if 0 <= s <= 1 and 0 <= u <= 1:
            return 0.0
    return min(
        _segment_distance(a, c, d),
        _segment_distance(b, c, d),
        _segment_distance(c, a, b),
        _segment_distance(d, a, b),
    )


class _Reach:
    """How close a stroke may come to a particle's known place without meeting it, from the
    model's radii, walk and drift (module docstring)."""

    def __init__(self, config):
        spheres = list(config.sample.spheres)
        radius = max((float(s["radius"]) for s in spheres), default=config.sample.radius_mean)
        self.contact = radius + float(config.tip.apex_radius)
        s, d = config.scanner, config.drift
        self.walk_offset = float(s.positioning_noise_offset)
        self.walk_slope = float(s.positioning_noise_slope)
        # the mean drift moves a place predictably; its wander (3 sigma of the velocity's
        # stationary spread, per axis) is what the stroke cannot know
        self.mean_velocity = np.array([d.mean_velocity_x, d.mean_velocity_y], float)
        self.drift_spread = DRIFT_SIGMAS * math.hypot(d.sigma_velocity_x, d.sigma_velocity_y)

    def predicted(self, place, elapsed: float) -> np.ndarray:
        """Where the model's mean drift has taken a place measured `elapsed` s ago."""
        return np.asarray(place, float) + self.mean_velocity * max(0.0, elapsed)

    def __call__(self, length: float, elapsed: float) -> float:
        walk = WALK_SIGMAS * math.sqrt(self.walk_offset + self.walk_slope * (length + APPROACH))
        return self.contact + walk + self.drift_spread * max(0.0, elapsed)


def _places_by_operation(features: dict) -> dict:
    """op index -> [(x, y, time)] of the particles its raster saw (raster.x features)."""
    places: dict = {}
    for key, f in features.items():
        if f.group == "raster.x":
            places.setdefault(key[0], []).append((f.x, f.y, f.time))
    return places


def ordinary_exclusions(ops, features: dict, config) -> Exclusions:
    """Which of `features` (key -> Feature, the recording's) the re-simulation cannot reproduce
    (module docstring), from the commands `ops` and the session's own images."""
    reach = _Reach(config)
    places_of = _places_by_operation(features)
    by_op: dict = {}
    for key in features:
        by_op.setdefault(key[0], []).append(key)
    t0 = min((op.start_time for op in ops), default=0.0)
    places = [(float(s["x"]), float(s["y"]), t0) for s in config.sample.spheres]
    paths: list = []  # (start, end, time) of strokes that met a particle
    contact_keys, moved_keys, level_keys = set(), set(), set()
    strokes = 0
    for op in ops:
        keys = by_op.get(op.index, [])
        if op.kind == "push":
            a, b = np.asarray(op.start, float), np.asarray(op.end, float)
            if _meets(a, b, op.start_time, places, paths, reach):
                strokes += 1
                contact_keys.update(keys)
                paths.append((a, b, op.start_time))
            continue
        moved_keys.update(
            k
            for k in keys
            if features[k].group in PARTICLE_GROUPS and _near_paths(features[k], paths, reach)
        )
        level_keys.update(
            k
            for k in keys
            if features[k].group in ("line.level", "line.updown")
            and _line_near_paths(op, features[k].time, paths, reach)
        )
        if op.kind == "raster" and op.request is not None:
            # the image shows what is in its area now: older places there are superseded
            places = [p for p in places if not _inside(p, op.request)]
            places += places_of.get(op.index, [])
        # a scan line across a particle saw it where it crossed (a closed loop's observation
        # between legs: its next leg starts from there)
        places += [
            (features[k].x, features[k].y, features[k].time)
            for k in keys
            if features[k].group in LINE_PLACE_GROUPS
        ]
    single_keys = _single_line_shapes(ops, features)
    rows = []
    if contact_keys:
        rows.append({"what": "push torsion", "count": len(contact_keys), "reason": CONTACT_REASON})
    if moved_keys:
        rows.append(
            {"what": "moved particles' features", "count": len(moved_keys), "reason": MOVED_REASON}
        )
    if level_keys:
        rows.append(
            {
                "what": "scan lines' levels over moved particles",
                "count": len(level_keys),
                "reason": MOVED_LEVEL_REASON,
            }
        )
    single_keys -= moved_keys
    if single_keys:
        rows.append(
            {
                "what": "single scan lines' shapes",
                "count": len(single_keys),
                "reason": SINGLE_LINE_REASON,
            }
        )
    return Exclusions(
        keys=contact_keys | moved_keys | level_keys | single_keys, rows=rows, strokes=strokes
    )


def _single_line_shapes(ops, features: dict) -> set:
    """Keys of the shape features of runs of one scan line (no other line over its segment
    right after it)."""
    from afm_core.sim2real.features import _same_segment

    ops = list(ops)
    single = set()
    for i, op in enumerate(ops):
        if op.kind != "scan_line" or (
            i > 0 and ops[i - 1].kind == "scan_line" and _same_segment(ops[i - 1], op)
        ):
            continue
        if i + 1 < len(ops) and ops[i + 1].kind == "scan_line" and _same_segment(op, ops[i + 1]):
            continue
        single.update((op.index, group) for group in SINGLE_LINE_GROUPS)
    return single & set(features)


def _meets(a, b, start_time: float, places: list, paths: list, reach: _Reach) -> bool:
    """Whether the stroke a-b meets a particle at a known place or one moved along an earlier
    stroke that met one."""
    length = float(np.hypot(*(b - a)))
    for x, y, t in places:
        here = reach.predicted((x, y), start_time - t)
        if _segment_distance(here, a, b) <= reach(length, start_time - t):
            return True
    return any(
        _segment_to_segment(a, b, c, _ahead(c, d, reach)) <= reach(length, start_time - t)
        for c, d, t in paths
    )


def _ahead(a, b, reach: _Reach) -> np.ndarray:
    """The end of the stretch a stroke a-b may have left its particle on: the particle leads
    the tip, so its centre is up to the contact distance beyond the stroke's end."""
    length = float(np.hypot(*(b - a)))
    return b + (b - a) / max(length, 1e-30) * reach.contact


def _line_near_paths(op, time: float, paths: list, reach: _Reach) -> bool:
    """Whether a scan line's segment comes within reach of where a pushed particle may be
    (along a stroke that met one, up to the contact distance beyond its end): the tip then
    meets the particle somewhere on the line, its edges included."""
    a, b = np.asarray(op.start, float), np.asarray(op.end, float)
    for c, d, t in paths:
        length = float(np.hypot(*(d - c)))
        if _segment_to_segment(a, b, c, _ahead(c, d, reach)) <= reach(length, time - t):
            return True
    return False


def _inside(place, request) -> bool:
    x0, y0 = float(request.origin_x), float(request.origin_y)
    return x0 <= place[0] <= x0 + float(request.size_x) and y0 <= place[1] <= y0 + float(
        request.size_y
    )


def _near_paths(feature, paths: list, reach: _Reach) -> bool:
    """Whether a particle feature lies where a pushed particle may be: within reach of a stroke
    that met one, extended by the contact distance beyond its end (the particle leads the
    tip)."""
    p = np.array([feature.x, feature.y])
    for a, b, t in paths:
        length = float(np.hypot(*(b - a)))
        if _segment_distance(p, a, _ahead(a, b, reach)) <= reach(length, feature.time - t):
            return True
    return False
