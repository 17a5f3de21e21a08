"""Verify a push: rescan, find the particle, compare with the goal using control points.

Book 7.3.1 step (4): after the push the area is rescanned and the images before and after are
overlaid using indentation pits as control points, so that drift between the two scans is not
mistaken for a manipulation error (Fig. 7.24g: 530 nm along, 20 nm sideways).

verify_push(instrument, request, goal, ...):

1. rescan the area with `request` (raster_scan on the Instrument; use the request of the
   before image, so the scanner's systematic errors are the same in both);
2. control points: pits (found as peaks of the negated height map with extract_landmarks,
   `pit_depth` deep at least) and, with `use_landmarks`, particles that did not move (the
   landmarks of both images except the pushed one). Their reference positions come from
   `before` (a RasterScanData of the same area before the push) or are given as
   `reference_points` (pits, reference frame). Each reference point is matched to the nearest
   feature of the same kind in the after image within `match_radius`, after removing a first
   offset guess (`offset_guess`, default: the median of the nearest-neighbour displacements
   of the pits);
3. offset = the median of (after - before) over the matched control points, then the mean over
   those within `inlier_radius` of it (a landmark that was pushed or bumped is left out); with
   the before image given, a shift c plus the drift's velocity v times each control point's
   elapsed time (from the before image's pass over it to the after image's), fitted when the
   elapsed times span MIN_ELAPSED_SPAN;
3a. when they do not, and the before image is given, the substrate's bands of rows registered
   between the images are added as control points (`afm_core.manipulation.verify_substrate`)
   and the fit is tried again;
3b. when they still do not (one control point, or all on the same rows) and `drift_prior` is given
   (the calibration's drift velocity), v is that and only c is fitted: the offset at the
   particle is then c + v * its elapsed time. One control point taken as the whole offset put
   a 700 nm push on a 1 nm/s drift 55 nm short (the particle's elapsed time 53 s past the
   pit's), with a 3.5 nm sigma;
4. the particle: the after-image landmark nearest to (expected + offset) within
   `particle_match_radius` (expected: where the plan predicted it, default the goal); its
   position minus the offset is the achieved position in the reference frame;
5. error = achieved - goal (reference frame: the before image's, which is the frame the plan
   was made in when it was made from that image); with `start`, also the displacement from
   it and how much later the before image passed over the achieved position than over the
   start (`pass_time`: the before image's own drift stretches the displacement by the drift
   velocity times that; `afm_core.manipulation.verdict` takes it out and states the
   uncertainty).

Without control points the offset is 0 and `drift_corrected` is False.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from afm_core import checks
from afm_core.imaging.landmarks import Landmark, extract_landmarks
from afm_core.imaging.scan_timing import pixel_times
from afm_core.instrument import Instrument, RasterScanData, ScanRequest
from afm_core.manipulation.verify_substrate import substrate_controls


@dataclass
class ControlPoint:
    kind: str  # "pit" | "landmark"
    before: np.ndarray  # (2,) reference frame
    after: np.ndarray  # (2,) after-image frame
    used: bool = True  # inlier of the offset estimate
    elapsed: float = math.nan  # s from the before image's pass over it to the after image's

    @property
    def displacement(self) -> np.ndarray:
        return self.after - self.before


@dataclass
class VerificationResult:
    achieved: np.ndarray  # (2,) particle centre, reference frame
    goal: np.ndarray  # (2,)
    error_vector: np.ndarray  # achieved - goal
    error: float  # |error_vector|, m
    offset: np.ndarray  # (2,) after-image frame minus reference frame (drift etc.)
    control_points: list[ControlPoint] = field(default_factory=list)
    drift_corrected: bool = False
    raw_position: np.ndarray | None = None  # particle centre in the after image's frame
    particle: Landmark | None = None  # the after-image landmark
    offset_spread: float = 0.0  # m, rms of the used control points' displacements about the offset
    after: RasterScanData | None = None
    # (2,) m, the images' frame: achieved - start (None without start)
    displacement: np.ndarray | None = None
    # s: how much later the before image passed over the achieved position than over the
    # start: the drift in that time stretches the displacement (afm_core.manipulation.verdict)
    pass_time: float = math.nan
    # m/s, the drift's velocity fitted to the control points (None: not measured, the images
    # were scanned the same way; `displacement` then still holds the before image's stretch)
    drift_velocity: np.ndarray | None = None
    elapsed: float = math.nan  # s from the before image's pass over the start to the after's
    # m/s, (2,): the drift's velocity was not measured but given (`drift_prior`: too few control
    # points, or too close in time) with this sigma; None: fitted, or not used
    drift_velocity_sigma: np.ndarray | None = None


# the control points' elapsed times must span this much for the drift's velocity to be fitted
# (an after image scanned the other way than the before image: about twice the time between
# the rows of the rescan's corner pits, ~60 s for a 500 nm push)
MIN_ELAPSED_SPAN = 10.0  # s


# control points that cannot have been pushed: the fits start from these
NEVER_PUSHED = ("pit", "substrate")


def _image_args(scan: RasterScanData) -> dict:
    return dict(
        pixel_size_x=scan.pixel_size_x,
        pixel_size_y=scan.pixel_size_y,
        origin_x=scan.origin_x,
        origin_y=scan.origin_y,
    )


def find_pits(scan: RasterScanData, pit_depth: float = 3e-9) -> list[Landmark]:
    """Pits (indentations) of an image: the features of the negated height map (heights above
    the median clipped off) at least `pit_depth` deep (their `height` is the apparent depth)."""
    height = np.asarray(scan.height, float)
    if not np.all(np.isfinite(height)):
        raise ValueError(
            "scan.height: has NaN pixels (an incomplete scan); rescan before verifying"
        )
    # particles would be deep holes of the negated map and upset its substrate fit: clip them
    # to just above the substrate first
    clipped = np.minimum(height, float(np.median(height)) + 0.5 * pit_depth)
    return extract_landmarks(-clipped, min_height=pit_depth, **_image_args(scan))


def find_particles(scan: RasterScanData, min_height: float = 10e-9) -> list[Landmark]:
    height = np.asarray(scan.height, float)
    if not np.all(np.isfinite(height)):
        raise ValueError(
            "scan.height: has NaN pixels (an incomplete scan); rescan before verifying"
        )
    return extract_landmarks(height, min_height=min_height, **_image_args(scan))


def scan_time(scan: RasterScanData, xy) -> float:
    """When `scan` passed over point xy (m, its frame): the pixel's acquisition time."""
    col = (float(xy[0]) - scan.origin_x) / scan.pixel_size_x - 0.5
    row = (float(xy[1]) - scan.origin_y) / scan.pixel_size_y - 0.5
    return float(pixel_times(scan, row, col))


def _xy(lm) -> np.ndarray:
    return np.array([lm.x, lm.y], float)


def _nearest(points: np.ndarray, target: np.ndarray) -> tuple[int, float]:
    if len(points) == 0:
        return -1, math.inf
    d = np.hypot(*(points - target).T)
    k = int(np.argmin(d))
    return k, float(d[k])


def _fit_offset(controls: list[ControlPoint], inlier_radius: float) -> tuple[np.ndarray, float]:
    """The drift offset as the mean displacement of the control points within inlier_radius of
    their median (at least the one nearest to it), and the rms spread about it; marks each
    control point used or not."""
    if not controls:
        return np.zeros(2), 0.0
    disp = np.array([c.displacement for c in controls])
    return _inlier_mean(controls, disp, np.median(disp, axis=0), inlier_radius)


def _inlier_mean(controls, disp, centre, inlier_radius: float) -> tuple[np.ndarray, float]:
    """The mean of the displacements `disp` (one per control point) within inlier_radius of
    `centre` (at least the one nearest to it) and their rms spread about it; marks each
    control point used or not."""
    distance = np.hypot(*(disp - centre).T)
    inliers = distance <= max(inlier_radius, float(distance.min()))
    for control, used in zip(controls, inliers):
        control.used = bool(used)
    mean = disp[inliers].mean(axis=0)
    return mean, float(np.sqrt(np.mean(np.sum((disp[inliers] - mean) ** 2, axis=1))))


def _fit_drift(controls: list[ControlPoint], inlier_radius: float):
    """The offset as c + v * elapsed (the drift's velocity v between and during the images,
    the scanner's shift c between them), least squares per axis over the timed control points
    (pits first: never pushed; then every one within inlier_radius of that fit, at least the
    best two); (c, v, rms residual), or None when their elapsed times span less than
    MIN_ELAPSED_SPAN (both images scanned the same way: v cannot be told from c)."""
    timed = [c for c in controls if math.isfinite(c.elapsed)]
    e = np.array([c.elapsed for c in timed])
    if len(timed) < 2 or np.ptp(e) < MIN_ELAPSED_SPAN:
        return None
    disp = np.array([c.displacement for c in timed])
    design = np.column_stack([np.ones_like(e), e])
    pits = np.array([c.kind in NEVER_PUSHED for c in timed])
    first = pits if pits.sum() >= 2 and np.ptp(e[pits]) >= MIN_ELAPSED_SPAN else pits | True
    coef = np.linalg.lstsq(design[first], disp[first], rcond=None)[0]
    residual = np.hypot(*(disp - design @ coef).T)
    used = residual <= max(inlier_radius, float(np.sort(residual)[1]))
    if np.ptp(e[used]) < MIN_ELAPSED_SPAN:
        return None
    coef = np.linalg.lstsq(design[used], disp[used], rcond=None)[0]
    for control in controls:
        control.used = False
    for control, keep in zip(timed, used):
        control.used = bool(keep)
    rest = disp[used] - design[used] @ coef
    return coef[0], coef[1], float(np.sqrt(np.mean(np.sum(rest**2, axis=1))))


def _fit_shift(controls: list[ControlPoint], inlier_radius: float, velocity: np.ndarray):
    """The offset as c + velocity * elapsed with the velocity given (the calibration's drift,
    when the control points' elapsed times cannot measure it): c as `_fit_offset` fits the
    offset, over the timed control points' displacements less velocity * elapsed, about the
    pits' median when there are pits (never pushed); (c, rms spread), marks each used or not."""
    timed = [c for c in controls if math.isfinite(c.elapsed)]
    for control in controls:
        control.used = False
    disp = np.array([c.displacement - velocity * c.elapsed for c in timed])
    pits = np.array([c.kind in NEVER_PUSHED for c in timed])
    centre = np.median(disp[pits] if pits.any() else disp, axis=0)
    return _inlier_mean(timed, disp, centre, inlier_radius)


def _predictor(controls, inlier_radius, prior, before, after):
    """The offset expected at a point of the before image from the control points alone (their
    shift, plus the prior's velocity times the point's elapsed time when there is a prior):
    where `substrate_controls` looks."""
    if prior is None or not any(math.isfinite(c.elapsed) for c in controls):
        offset, _ = _fit_offset(controls, inlier_radius)
        return lambda _xy: offset
    shift, _ = _fit_shift(controls, inlier_radius, prior[0])

    def predicted(xy):
        return shift + prior[0] * (scan_time(after, xy + shift) - scan_time(before, xy))

    return predicted


def _references(before, reference_points, use_landmarks, start, p_radius, pit_depth, min_height):
    """The reference frame's control points: (pits, static particles), from `reference_points`
    (pits only) or the before image (its particles but the pushed one, within p_radius of
    `start`: the particle's own size, not how far the push may have taken it)."""
    if reference_points is not None:
        pits = [checks.point(f"reference_points[{i}]", p) for i, p in enumerate(reference_points)]
        return pits, []
    if before is None:
        return [], []
    pits, landmarks = [_xy(p) for p in find_pits(before, pit_depth)], []
    if use_landmarks:
        st = None if start is None else checks.point("start", start)
        for lm in find_particles(before, min_height):
            xy = _xy(lm)
            if st is not None and np.hypot(*(xy - st)) < p_radius:
                continue  # the pushed particle
            landmarks.append(xy)
    return pits, landmarks


def _first_guess(offset_guess, ref_pits, pa) -> np.ndarray:
    """The first offset guess: given, or the median nearest-neighbour displacement of the
    pits."""
    if offset_guess is not None:
        return checks.point("offset_guess", offset_guess)
    if ref_pits and len(pa):
        return np.median(np.array([pa[_nearest(pa, r)[0]] - r for r in ref_pits]), axis=0)
    return np.zeros(2)


def _matched_controls(references, seen, guess, expected, match_radius, images):
    """The control points: each reference pit and static particle (`references`) matched to
    the nearest pit or particle of the after image (`seen`: their positions) within
    match_radius of where the first guess puts it, each taken once; the after image's particle
    nearest the expected position is the pushed one, never a control point. images: (before,
    after, timed): with timed, each point's elapsed time between the two images."""
    (ref_pits, ref_landmarks), (pa, la) = references, seen
    before, after, timed = images

    def control(kind: str, reference: np.ndarray, found: np.ndarray) -> ControlPoint:
        elapsed = scan_time(after, found) - scan_time(before, reference) if timed else math.nan
        return ControlPoint(kind, reference, found.copy(), elapsed=elapsed)

    controls: list[ControlPoint] = []
    k_particle, _ = _nearest(la, expected + guess)
    for kind, refs, points, taken in (
        ("pit", ref_pits, pa, set()),
        ("landmark", ref_landmarks, la, {k_particle} if k_particle >= 0 else set()),
    ):
        for r in refs:
            k, d = _nearest(points, r + guess)
            if d <= match_radius and k not in taken:
                taken.add(k)
                controls.append(control(kind, r, points[k]))
    return controls


def _checked_prior(drift_prior):
    """drift_prior as (mean, sigma) arrays of 2, or None; ValueError when not finite or a sigma
    is negative."""
    if drift_prior is None:
        return None
    prior = tuple(np.asarray(v, float).reshape(2) for v in drift_prior)
    if not all(np.all(np.isfinite(v)) for v in prior) or np.any(prior[1] < 0):
        raise ValueError(f"drift_prior={drift_prior!r}: need finite (mean, sigma >= 0) m/s")
    return prior


def _offset_model(controls, drift, prior, inlier_radius, images, expected):
    """(offset at the expected position, spread, shift, velocity, velocity's sigma): the fitted
    drift, else the prior's velocity with a fitted shift, else one shift (velocity None)."""
    before, after = images
    if drift is None and prior is not None and any(math.isfinite(c.elapsed) for c in controls):
        # too few control points, or too close in time, to measure the drift's velocity: the
        # calibration's, with its sigma (the verdict's), else the offset at the particle is off
        # by the velocity times the elapsed time between the control points and the particle
        velocity, velocity_sigma = prior
        shift, spread = _fit_shift(controls, inlier_radius, velocity)
    elif drift is None:
        offset, spread = _fit_offset(controls, inlier_radius)
        return offset, spread, None, None, None
    else:
        (shift, velocity, spread), velocity_sigma = drift, None
    # the offset where the particle is expected: its elapsed time there
    elapsed = scan_time(after, expected + shift) - scan_time(before, expected)
    return shift + velocity * elapsed, spread, shift, velocity, velocity_sigma


def verify_push(
    instrument: Instrument,
    request: ScanRequest,
    goal,
    *,
    expected=None,
    start=None,
    before: RasterScanData | None = None,
    reference_points: Sequence | None = None,
    use_landmarks: bool = True,
    particle_radius: float = 100e-9,
    pit_depth: float = 3e-9,
    min_height: float = 10e-9,
    match_radius: float = 60e-9,
    inlier_radius: float = 10e-9,
    particle_match_radius: float | None = None,
    offset_guess=None,
    after: RasterScanData | None = None,
    drift_prior=None,
) -> VerificationResult:
    """Rescan and verify (module docstring). start: the particle's position before the push in
    the reference frame (leaves the pushed particle out of the landmark control points; default:
    none left out except the one matched as the particle). after: an already taken after-scan
    (then nothing is scanned). drift_prior: (mean, sigma) of the drift's velocity (m/s, (2,)
    each, the images' frame: the calibration's), taken when the control points cannot measure
    it (step 3b of the module docstring); None: the offset is then one shift."""
    g = checks.point("goal", goal)
    exp = g if expected is None else checks.point("expected", expected)
    checks.positive("particle_radius", particle_radius, "m")
    for name, value in (
        ("match_radius", match_radius),
        ("inlier_radius", inlier_radius),
        ("pit_depth", pit_depth),
    ):
        checks.positive(name, value, "m")
    p_radius = (
        2 * particle_radius + 100e-9 if particle_match_radius is None else particle_match_radius
    )
    prior = _checked_prior(drift_prior)
    if after is None:
        after = instrument.raster_scan(request)
    if not after.complete:
        raise ValueError("after scan: incomplete (cancelled); cannot verify")
    pits_after = find_pits(after, pit_depth)
    particles_after = find_particles(after, min_height)
    pa = np.array([_xy(p) for p in pits_after]).reshape(-1, 2)
    la = np.array([_xy(p) for p in particles_after]).reshape(-1, 2)

    # the pushed particle in the before image: within its own size of the start (p_radius can be
    # the whole push's reach, which left out static particles that are control points)
    own = 2 * particle_radius + 100e-9
    ref_pits, ref_landmarks = _references(
        before, reference_points, use_landmarks, start, own, pit_depth, min_height
    )
    guess = _first_guess(offset_guess, ref_pits, pa)
    timed = before is not None and reference_points is None
    controls = _matched_controls(
        (ref_pits, ref_landmarks), (pa, la), guess, exp, match_radius, (before, after, timed)
    )
    drift = _fit_drift(controls, inlier_radius)
    if drift is None and controls and timed:
        # the pits and static particles cannot measure the drift's velocity: the substrate's
        # bands can (afm_core.manipulation.verify_substrate)
        predicted = _predictor(controls, inlier_radius, prior, before, after)
        bands = substrate_controls(
            before,
            after,
            np.array([_xy(p) for p in find_particles(before, min_height)]),
            la,
            predicted,
            2 * particle_radius + 50e-9,
        )
        for centre, seen in bands:
            elapsed = scan_time(after, seen) - scan_time(before, centre)
            controls.append(ControlPoint("substrate", centre, seen, elapsed=elapsed))
        drift = _fit_drift(controls, inlier_radius) if bands else None
    offset, spread, shift, velocity, velocity_sigma = _offset_model(
        controls, drift, prior, inlier_radius, (before, after), exp
    )

    k, d = _nearest(la, exp + offset)
    if k < 0 or d > p_radius:
        raise ValueError(
            f"particle: no landmark within particle_match_radius={p_radius:.4e} m of the expected "
            f"position ({exp[0]:.6e}, {exp[1]:.6e}) m (+ offset ({offset[0]:.3e}, "
            f"{offset[1]:.3e}) m) in the after scan"
        )
    raw = la[k].copy()
    if velocity is not None:
        offset = shift + velocity * (scan_time(after, raw) - scan_time(before, raw - shift))
    achieved = raw - offset
    err = achieved - g
    displacement, pass_time, elapsed = None, math.nan, math.nan
    if start is not None:
        st = checks.point("start", start)
        displacement = achieved - st
        if before is not None:
            pass_time = scan_time(before, achieved) - scan_time(before, st)
            elapsed = scan_time(after, raw) - scan_time(before, st)
        if velocity is not None:
            # the before image's own drift between the start's and the achieved rows
            displacement = displacement - velocity * pass_time
    return VerificationResult(
        achieved=achieved,
        goal=g,
        error_vector=err,
        error=float(np.hypot(*err)),
        offset=offset,
        control_points=controls,
        drift_corrected=any(c.used for c in controls),
        raw_position=raw,
        particle=particles_after[k],
        offset_spread=spread,
        after=after,
        displacement=displacement,
        pass_time=pass_time,
        drift_velocity=velocity,
        elapsed=elapsed,
        drift_velocity_sigma=velocity_sigma,
    )
