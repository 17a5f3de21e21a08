"""Offline evaluation of recorded sessions (no ROS): what the images show against truth."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
from scipy import ndimage


@dataclass
class ParticleView:
    """One particle as a raster image shows it."""

    x: float  # m, centroid in the scanner frame
    y: float
    height: float  # m, peak height above the substrate level
    apparent_radius: float  # m, radius of the disk with the area above half height


def substrate_level(height: np.ndarray) -> float:
    """The median is the substrate when particles cover less than half the image."""
    return float(np.median(height))


def find_particles(
    height: np.ndarray,
    pixel_size_x: float,
    pixel_size_y: float,
    origin_x: float,
    origin_y: float,
    min_height: float = 20e-9,
) -> list[ParticleView]:
    """Particles as connected regions above half their own peak height."""
    level = substrate_level(height)
    relief = height - level
    labels, count = ndimage.label(relief > min_height)
    views = []
    for index in range(1, count + 1):
        region = labels == index
        peak = float(relief[region].max())
        half = region & (relief > peak / 2)
        rows, cols = np.nonzero(half)
        area = half.sum() * pixel_size_x * pixel_size_y
        views.append(
            ParticleView(
                x=origin_x + (cols.mean() + 0.5) * pixel_size_x,
                y=origin_y + (rows.mean() + 0.5) * pixel_size_y,
                height=peak,
                apparent_radius=float(np.sqrt(area / np.pi)),
            )
        )
    return views


def match_to_truth(
    found: list[ParticleView], truth_xy: np.ndarray, max_distance: float
) -> list[tuple]:
    """Pair each true particle with the nearest found one within max_distance:
    (truth index, view, distance)."""
    pairs = []
    for i, (tx, ty) in enumerate(np.asarray(truth_xy).reshape(-1, 2)):
        if not found:
            break
        distances = [np.hypot(v.x - tx, v.y - ty) for v in found]
        best = int(np.argmin(distances))
        if distances[best] <= max_distance:
            pairs.append((i, found[best], distances[best]))
    return pairs


# m: images are in commanded scanner coordinates, which hysteresis residue, creep, coupling,
# line deflection and drift put tens of nm off the truth; a particle this close is the same one
MATCH_DISTANCE = 300e-9


def truth_index_at(truth: dict, t: float) -> int:
    """Index of the last ground truth logged before t (the one a scan logged at t saw);
    truth: a recording's /afm/ground_truth arrays (RecordingReader.arrays)."""
    return max(0, int(np.searchsorted(truth["log_time"], t, side="right")) - 1)


# ObjectState.PIT: an indentation the nano-hand made, not a particle
PIT = 3


def truth_xy(truth: dict, index: int, particles: bool = False) -> np.ndarray:
    """(n, 2) m: the true object centres of the index-th ground truth; `particles`: without
    the pits."""
    return np.array(
        [
            [o["position.x"], o["position.y"]]
            for o in truth["objects"][index]
            if not (particles and int(o["kind"]) == PIT)
        ]
    ).reshape(-1, 2)


def scan_against_truth(
    height: np.ndarray, pixel_size, origin, true_xy: np.ndarray, max_distance=MATCH_DISTANCE
) -> dict:
    """One raster image against the true centres at its time: particles found and matched,
    the matched centres' RMS error (m), their mean peak height and apparent radius (m); NaN
    where nothing matched."""
    found = find_particles(height, pixel_size[0], pixel_size[1], origin[0], origin[1])
    pairs = match_to_truth(found, true_xy, max_distance=max_distance)

    def mean(values):
        return float(np.mean(values)) if pairs else float("nan")

    return {
        "found": len(found),
        "matched": len(pairs),
        "centre_error_rms": float(np.sqrt(mean([d**2 for _, _, d in pairs]))),
        "peak_height_mean": mean([v.height for _, v, _ in pairs]),
        "apparent_radius_mean": mean([v.apparent_radius for _, v, _ in pairs]),
    }


def affine_fit(true_xy, mapped_xy) -> np.ndarray:
    """(2, 3) [A | b] with mapped = A true + b, least squares over the point pairs (m).
    ValueError when the shapes differ or fewer than 3 non-collinear points are given."""
    true_xy = np.asarray(true_xy, float).reshape(-1, 2)
    mapped_xy = np.asarray(mapped_xy, float).reshape(-1, 2)
    if true_xy.shape != mapped_xy.shape:
        raise ValueError(f"true_xy {true_xy.shape} and mapped_xy {mapped_xy.shape}: must pair up")
    centred = true_xy - true_xy.mean(axis=0)
    # collinear points leave the affine undetermined across their line
    if len(true_xy) < 3 or np.linalg.matrix_rank(centred, tol=1e-3 * np.abs(centred).max()) < 2:
        raise ValueError(f"true_xy: need at least 3 non-collinear points, got {len(true_xy)}")
    design = np.hstack([true_xy, np.ones((len(true_xy), 1))])
    solution, *_ = np.linalg.lstsq(design, mapped_xy, rcond=None)
    return solution.T


def in_frame(points, frame: np.ndarray) -> np.ndarray:
    """(n, 2) positions (m) through a (2, 3) affine frame [A | b]: p A^T + b."""
    frame = np.asarray(frame, float)
    return np.asarray(points, float).reshape(-1, 2) @ frame[:, :2].T + frame[:, 2]


def anchor_frame(truth: dict, image_frame: np.ndarray) -> np.ndarray:
    """(2, 3) [A | b]: metric truth into the commanded frame about where the session started (at
    rest there, commanded = true), scaled by `image_frame` (image_frame_matrix). The fallback
    of `map_frame` for a session without a landmark map."""
    inverse = np.linalg.inv(image_frame)
    start_metric = np.array([truth["tip_position.x"][0], truth["tip_position.y"][0]])
    start_commanded = np.array(
        [truth["commanded_position.x"][0], truth["commanded_position.y"][0]]
    )
    return np.hstack([inverse, (start_commanded - inverse @ start_metric)[:, None]])


def map_frame(truth: dict, landmarks: dict, image_frame: np.ndarray) -> np.ndarray | None:
    """(2, 3) [A | b]: the first landmark map's own frame, the affine that takes the true
    particle centres at its time to their mapped positions, or None when fewer than 3
    landmarks pair with a true particle. `landmarks`: a recording's /afm/landmarks arrays, of
    which the first map is taken, before a push moved anything. A landmark pairs with the true
    centre nearest where `anchor_frame` puts it, within MATCH_DISTANCE (that frame is off by
    tens of nm, particles are hundreds apart). The localizer's task frame is the map's: a pose
    is where the map puts the tip, and the truth of that is where the map would put the true
    tip (docs/localization.md, "Judging the localizer against the truth")."""
    if not len(landmarks.get("landmarks", [])) or not len(landmarks["landmarks"][0]):
        return None
    mapped = np.array([[m["position.x"], m["position.y"]] for m in landmarks["landmarks"][0]])
    # the truth as the map was published (nothing moves a particle while it is imaged)
    true_xy = truth_xy(truth, truth_index_at(truth, landmarks["log_time"][0]), particles=True)
    guess = anchor_frame(truth, image_frame)
    seen = in_frame(true_xy, guess)
    pairs = []
    for k, position in enumerate(mapped):
        distance = np.hypot(*(seen - position).T) if len(seen) else np.array([np.inf])
        if distance.min() <= MATCH_DISTANCE:
            pairs.append((int(np.argmin(distance)), k))
    if len({j for j, _ in pairs}) < 3:
        return None
    try:
        return affine_fit(true_xy[[j for j, _ in pairs]], mapped[[k for _, k in pairs]])
    except ValueError:
        return None


def truth_frame(truth: dict, landmarks: dict, image_frame: np.ndarray) -> tuple[np.ndarray, str]:
    """(frame, basis): `map_frame` ("first landmark map"), or without one `anchor_frame`
    ("session start")."""
    frame = map_frame(truth, landmarks, image_frame)
    if frame is not None:
        return frame, "first landmark map"
    return anchor_frame(truth, image_frame), "session start"


def tip_against_truth(poses: dict, truth: dict, frame: np.ndarray) -> dict:
    """The localizer's tip estimates (/afm/tip_pose arrays) against the true tip
    (/afm/ground_truth arrays): error RMS (m), mean NEES (2 dof: 2 when consistent), the pairs
    compared with their times (s from the first), errors (estimate minus truth) and sigmas, the
    final sigma (m). frame: (2, 3) [A | b], the metric truth into the frame the estimate is in
    (`map_frame`, or `anchor_frame` without a map)."""
    means = np.stack([poses["pose.pose.position.x"], poses["pose.pose.position.y"]], axis=1)
    cov = np.asarray(poses["pose.covariance"])[:, [0, 1, 6, 7]].reshape(-1, 2, 2)
    metric = np.stack([truth["tip_position.x"], truth["tip_position.y"]], axis=1)
    frame = np.asarray(frame, float)
    true_tip = in_frame(metric, frame)
    # the localizer publishes its estimate as each command ends, the driver its truth: compare
    # the pairs with the same stamp (error and NEES). Recordings made before 2026-11-27 hold
    # poses for times past the last command heard (the tip still where the move began), then
    # the same stamp again once the command came: take the last pose published with each stamp.
    # (a stamp summed from a start and a duration in float seconds since 1970 is good to
    # ~0.3 us)
    origin = int(truth["header.stamp.sec"][0])
    stamps = (poses["header.stamp.sec"] - origin) + poses["header.stamp.nanosec"] * 1e-9
    truth_stamps = (truth["header.stamp.sec"] - origin) + truth["header.stamp.nanosec"] * 1e-9
    same = np.abs(stamps[None, :] - truth_stamps[:, None]) < 5e-6
    ok = same.any(axis=1)
    k = len(stamps) - 1 - np.argmax(same[:, ::-1], axis=1)  # the last published with that stamp
    errors = true_tip[ok] - means[k[ok]]
    nees = [float(e @ np.linalg.solve(c, e)) for e, c in zip(errors, cov[k[ok]])]
    compared_cov = cov[k[ok]]
    return {
        "times": truth_stamps[ok] - (truth_stamps[ok][0] if ok.any() else 0.0),
        "errors": -errors,  # estimate minus truth, per pair compared
        "sigmas": np.sqrt(np.stack([compared_cov[:, 0, 0], compared_cov[:, 1, 1]], axis=1)),
        "means": means,
        "covariances": cov,
        "true_tip": true_tip,
        "error_rms": float(np.sqrt(np.mean(np.sum(errors**2, axis=1))))
        if len(errors)
        else float("nan"),
        "mean_nees": float(np.mean(nees)) if nees else float("nan"),
        "compared": int(len(errors)),
        "final_sigma": np.sqrt(np.diag(cov[-1])).tolist(),
        "frame": frame.tolist(),
    }


def compare_payloads(messages_a, messages_b) -> dict:
    """Two streams of (topic, bytes): per topic, counts and whether the payloads are identical
    in order. Keeps digests, not payloads, so recordings of any size stream through."""

    def by_topic(stream):
        out: dict[str, list[bytes]] = {}
        for topic, data in stream:
            out.setdefault(topic, []).append(hashlib.sha256(data).digest())
        return out

    a, b = by_topic(messages_a), by_topic(messages_b)
    return {
        topic: {
            "count_a": len(a.get(topic, [])),
            "count_b": len(b.get(topic, [])),
            "identical": a.get(topic) == b.get(topic),
        }
        for topic in sorted(set(a) | set(b))
    }


APPROACH_BEYOND = np.array([2e-6, 2e-6])  # m: an image's approach overshoot (one ~2 um image)


def image_frame_matrix(config=None, step: float = 1e-6, at=None) -> np.ndarray:
    """Evaluation only (simulator truth): true displacement per commanded displacement for a
    short move about the scanner centre (or about `at`, m, reached by a move from the centre
    and approached from beyond, within the config's `limits` range, as the driver approaches
    images: the scanner's gain depends on
    its hysteresis branch, which this makes the images' own), on a noise-, drift- and
    creep-free copy of the simulated instrument. Images and calibrated maps are in commanded
    coordinates (the frame the calibration experiments measure in); the simulator's truth is
    metric. With the default
    scanner the two differ by ~6 % in scale (the residual hysteresis of short sweeps), so true
    displacements are brought into the image frame with the inverse of this matrix before they
    are compared with what the graph planned or estimated."""
    from afm_core.sim.config import load_config, merge
    from afm_core.sim.instrument import SimulatedAfm

    config = load_config() if config is None else config
    quiet = merge(
        config,
        {
            "drift": {"enabled": False},
            "sample": {"spheres": [], "rods": [], "electrodes": [], "random_spheres": 0},
            "scanner": {"creep_enabled": False, "positioning_noise_enabled": False},
        },
    )
    columns = []
    for d in (np.array([step, 0.0]), np.array([0.0, step])):
        sim = SimulatedAfm(quiet)
        if at is not None:
            # from beyond, as the driver approaches every image (imaging.raster_approach): the
            # step then sweeps the reversed hysteresis branch the images are taken on
            limits = sim.limits  # the config's range, not the default instrument's
            beyond = np.minimum(
                np.asarray(at, dtype=float) + APPROACH_BEYOND, (limits.range_x, limits.range_y)
            )
            sim.move_tip(float(beyond[0]), float(beyond[1]), 1e-5)
            sim.move_tip(float(at[0]), float(at[1]), 1e-5)
        before = np.array(sim.truth()["tip_position"])
        x, y = np.array(sim.commanded_position()) + d
        sim.move_tip(x, y, 1e-5)
        columns.append((np.array(sim.truth()["tip_position"]) - before) / step)
    return np.array(columns).T


def images_frame_matrix(config, scan, at, step: float = 530e-9) -> np.ndarray:
    """Evaluation only (simulator truth): true displacement per image displacement of raster
    `scan` (a ScanRequest), the scanner's creep on and no drift: a sphere (r = 100 nm) at `at`
    (m) and `step` away along -x and along -y, each imaged on a fresh simulator. The images'
    own gain: `image_frame_matrix` is a creep-free short move, and the images' gain with creep
    differs from it (on the default simulator, maps 2.4 um at 4 Hz: 2 % in x, 0.7 % in y)."""
    from afm_core.imaging.landmarks import scan_landmarks
    from afm_core.sim.config import merge
    from afm_core.sim.instrument import SimulatedAfm

    quiet = merge(config, {"drift": {"enabled": False}})

    def centre(x: float, y: float) -> np.ndarray:
        sample = {"spheres": [{"x": x, "y": y, "radius": 100e-9}], "rods": [], "electrodes": []}
        image = SimulatedAfm(merge(quiet, {"sample": sample})).raster_scan(scan)
        found = scan_landmarks(image)
        if len(found) != 1:
            raise ValueError(f"at={tuple(at)}: the scan shows {len(found)} spheres, not 1")
        return np.array([found[0].x, found[0].y])

    x0, y0 = float(at[0]), float(at[1])
    here = centre(x0, y0)
    seen = np.array([centre(x0 - step, y0) - here, centre(x0, y0 - step) - here]).T
    return -step * np.linalg.inv(seen)


@dataclass
class PushImageFrames:
    """Where the nano-hand's before and after rescans lie in the task frame: add
    `before_shift` (after_shift) to a position in the before (after) image, m."""

    before_shift: np.ndarray  # (2,)
    after_shift: np.ndarray | None  # (2,), None without an after image
    control_points: int  # matched control points behind the after image's drift offset


def push_image_frames(
    before, after, start, goal, particle_radius: float = 100e-9
) -> PushImageFrames:
    """The task-frame placement of a push's rescans, as the nano-hand ties them to the map
    (`PushProcedure`'s verification): the before image by the pushed particle, seen in it near
    its mapped `start` (task frame), the after image also by the drift offset the control
    points (pits, particles that did not move) give between the two (`verify_push`, with the
    particle looked for within its reach of `goal`). `before` and `after` are
    `RasterScanData` (after may be None). ValueError if the before image shows no particle or
    the after image not the pushed one. The scanner matrix's correction of the particle's own
    displacement (about 1 % of it) is left out: a few nm over a 300 nm push."""
    from afm_core.manipulation.push_steps import nearest_particle
    from afm_core.manipulation.verify import verify_push

    start, goal = np.asarray(start, float), np.asarray(goal, float)
    seen = nearest_particle(before, start)
    if seen is None:
        raise ValueError("before image: no particle near the push's start")
    before_shift = start - seen
    if after is None:
        return PushImageFrames(before_shift, None, 0)
    result = verify_push(
        None,
        None,
        goal - before_shift,
        after=after,
        start=seen,
        before=before,
        particle_radius=particle_radius,
        # where the nano-hand looks for it: anywhere the push could have taken it
        particle_match_radius=float(np.hypot(*(goal - start))) + 2 * particle_radius + 100e-9,
    )
    used = sum(1 for c in result.control_points if c.used)
    return PushImageFrames(before_shift, before_shift - result.offset, used)


def pattern_against_truth(starts, goals, true_before, true_after) -> dict:
    """An assembled pattern against the simulator's truth: each particle is the true one
    nearest its mapped start in `true_before`; its true displacement (`true_after` minus
    `true_before`, both (m, 2) m in the maps' frame, rows the same objects) from its mapped
    start gives its true end, scored against its goal. Returns per particle the true index, end
    and error (m), and the pattern's RMS error, the RMS left once the pattern's common offset is
    removed (its shape alone), and the shares within 10 and 20 nm."""
    starts, goals = np.asarray(starts, float), np.asarray(goals, float)
    before, after = np.asarray(true_before, float), np.asarray(true_after, float)
    if starts.shape != goals.shape or starts.ndim != 2 or starts.shape[1] != 2:
        raise ValueError(f"starts {starts.shape} and goals {goals.shape}: must both be (n, 2) m")
    if before.shape != after.shape or len(before) < len(starts):
        raise ValueError(
            f"true_before {before.shape} and true_after {after.shape}: must be (m, 2) m with "
            f"m >= {len(starts)}, the same objects in the same rows"
        )
    index = [int(np.argmin(np.hypot(*(before - s).T))) for s in starts]
    ends = starts + after[index] - before[index]
    offsets = ends - goals
    errors = np.hypot(*offsets.T)
    shape = offsets - offsets.mean(axis=0)
    return {
        "true_index": index,
        "true_end": ends.tolist(),
        "errors": errors.tolist(),
        "rms": float(np.sqrt(np.mean(errors**2))),
        "shape_rms": float(np.sqrt(np.mean(np.sum(shape**2, axis=1)))),
        "within_20nm": float(np.mean(errors <= 20e-9)),
        "within_10nm": float(np.mean(errors <= 10e-9)),
    }


def maps_frame_matrix(config, scans, approach_overshoot: float = 0.0) -> np.ndarray:
    """Evaluation only (simulator truth): true displacement per map displacement of a map
    imaged as `scans` (ScanRequests of one area: one image as it is, or a 0 and a 90 deg image
    corrected for drift as the imaging node corrects a pair, `compensate_pair`), the frame a
    push planned on that map is judged in (docs/manipulation.md, "The truth's frame"). The map
    is imaged on a copy of `config` whose sample is a 3 x 3 lattice of spheres over the area
    (r = 100 nm, or a fifth of the pitch); the result is the inverse of the affine that takes
    their true centres to their landmarks. Drift, creep and noise draw from streams that do not
    depend on the sample, so a session's own config (seed included) gives that session's map
    frame, drift and all; with drift off, the frame of a drift-free map. The images are taken
    from the tip's rest at the range centre, each approached from `approach_overshoot` image
    sizes beyond its start (the driver's raster approach; 0: the simulator's own approach).

    It differs from `image_frame_matrix` (a creep-free step) where creep is on: a scan line is
    traced faster than the creep follows, so a map's fast axis images short by about the creep
    fractions (2 % on the default simulator), its slow axis by what the creep follows in the
    image's time, and a 0/90 pair's drift correction takes the two images' difference for drift
    and leaves the pair at the fast axis's gain on both axes. ValueError when a scan is not
    0 or 90 deg, a pair is not one 0 and one 90 deg image of the same area, the area is under
    1 um, or not all 9 spheres are found."""
    from afm_core.imaging.drift_compensation import compensate_pair
    from afm_core.imaging.landmarks import extract_landmarks
    from afm_core.imaging.raster_approach import approach_point
    from afm_core.sim.config import merge
    from afm_core.sim.instrument import SimulatedAfm

    scans = list(scans)
    first = scans[0] if scans else None
    if len(scans) == 2 and {s.scan_angle_deg for s in scans} != {0.0, 90.0}:
        raise ValueError("scans: a pair must be one 0 deg and one 90 deg image")
    if len(scans) not in (1, 2) or any(
        (s.origin_x, s.origin_y, s.size_x, s.size_y)
        != (first.origin_x, first.origin_y) + (first.size_x, first.size_y)
        for s in scans
    ):
        raise ValueError(f"scans: need 1 image or a 0/90 pair of one area, got {len(scans)}")
    if min(first.size_x, first.size_y) < 1e-6:
        raise ValueError(f"scans: area {first.size_x} x {first.size_y} m, must be >= 1 um")
    pitch = np.array([first.size_x, first.size_y]) / 3.6  # the lattice keeps 0.8 pitch clear
    centre = np.array([first.origin_x + first.size_x / 2, first.origin_y + first.size_y / 2])
    radius = min(100e-9, float(pitch.min()) / 5)
    true_xy = np.array([centre + pitch * (i, j) for i in (-1, 0, 1) for j in (-1, 0, 1)])
    sample = {
        "spheres": [{"x": x, "y": y, "radius": radius} for x, y in true_xy],
        "rods": [],
        "electrodes": [],
        "random_spheres": 0,
    }
    sim = SimulatedAfm(merge(config, {"sample": sample}))
    images = {}
    for scan in scans:
        if approach_overshoot > 0:
            beyond = approach_point(scan, approach_overshoot, sim.limits)
            sim.move_tip(*beyond, sim.limits.max_speed / 10)
        images[scan.scan_angle_deg] = sim.raster_scan(scan)
    image = images[first.scan_angle_deg] if len(scans) == 1 else images[0.0]
    height = (
        image.height if len(scans) == 1 else compensate_pair(images[0.0], images[90.0]).corrected
    )
    marks = extract_landmarks(
        np.asarray(height, float),
        image.pixel_size_x,
        image.pixel_size_y,
        image.origin_x,
        image.origin_y,
    )
    mapped = np.array([[m.x, m.y] for m in marks]).reshape(-1, 2)
    # map and truth differ by a few % about the range centre: tens of nm, the pitch is 280+
    pairs = [(int(np.argmin(np.hypot(*(true_xy - p).T))), k) for k, p in enumerate(mapped)]
    if len(marks) != 9 or len({j for j, _ in pairs}) != 9:
        raise ValueError(f"maps_frame_matrix: the map shows {len(marks)} of the 9 spheres")
    fit = affine_fit(true_xy[[j for j, _ in pairs]], mapped[[k for _, k in pairs]])
    return np.linalg.inv(fit[:, :2])


def rod_pose_against_truth(true_before, true_after, move, turn: float, frame) -> dict:
    """A rod's or tube's push scored against the simulator's truth in the maps' frame: the
    true start and end poses (`true_before`, `true_after`: (x, y, axis angle), m and rad, the
    simulator's metres) against the goal's displacement `move` (m, maps' frame) and `turn`
    (rad) from the map's pose (the map's own error is common to the start and the goal). True
    displacements and axis directions go through the inverse of `frame` (true per map
    displacement: `maps_frame_matrix`, the map's own, or `image_frame_matrix`). Returns the
    position error (m) and the axis angle error (rad, folded into a half turn: an axis has no
    head), and the true
    displacement and turn in the maps' frame."""
    frame = np.asarray(frame, float)
    if frame.shape != (2, 2):
        raise ValueError(f"frame {frame.shape}: must be a 2x2 matrix")
    before, after = np.asarray(true_before, float), np.asarray(true_after, float)
    if before.shape != (3,) or after.shape != (3,):
        raise ValueError(
            f"true_before {before.shape} and true_after {after.shape}: must be (x, y, angle)"
        )
    moved = np.linalg.solve(frame, after[:2] - before[:2])

    def maps_angle(angle: float) -> float:
        d = np.linalg.solve(frame, [np.cos(angle), np.sin(angle)])
        return float(np.arctan2(d[1], d[0]))

    turned = fold_half_turn(maps_angle(after[2]) - maps_angle(before[2]))
    return {
        "error": float(np.hypot(*(moved - np.asarray(move, float)))),
        "angle_error": abs(fold_half_turn(turned - turn)),
        "moved": moved.tolist(),
        "turned": turned,
    }


def fold_half_turn(angle: float) -> float:
    """An axis angle difference folded into [-pi/2, pi/2)."""
    return float((angle + np.pi / 2) % np.pi - np.pi / 2)
