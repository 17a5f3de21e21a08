"""The images' lateral scale on a reference of known pitch (a calibration grating): what the
calibration's own experiments cannot see, because every image they measure in shares it.

The reference is a square lattice of particles or pillars of known pitch P (TGQ/TGX-like
standards; on the simulator a lattice of spheres in the sample config), its rows along the
sample's x. It is imaged like the maps (2.4 um, 256 px, 4 Hz, approached from beyond its first
sample as the driver does, `raster_approach`), since the images' gain depends on the scan and
the approach. The particles are found as the maps' landmarks are (`extract_landmarks`), the
lattice positions = origin + i a + j b are fitted by least squares (integer indices from the
nominal pitch, refined once from the fit), and the image -> metres matrix is P [a b]^-1.

Each pass's slow axis is stretched or shrunk by the drift while it runs (about 0.1 nm/s over a
64 s image: 0.3 %); the reference is imaged slow axis up and down and the two passes' lattice
vectors averaged, which cancels a constant drift. The fits' uncertainties (residual scatter of
the particle centres, propagated: `fit_sigma`) do not see the drift, which stretches a whole
pass: on the simulator they were 0.002-0.003 % where the pair's mean was 0.04-0.09 % off the
truth. The stated uncertainties (`scale_sigma`, `matrix_sigma`) therefore add the standard
error of the passes' mean (|up - down| / 2 for a pair), which bounds what the averaging leaves
of the drift. The matrix's rotation part assumes the grating's rows along the sample's x (its
mounting angle is not measured); `scale` = sqrt(det) does not depend on it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from afm_core import checks
from afm_core.imaging.landmarks import scan_landmarks
from afm_core.imaging.raster_approach import RASTER_APPROACH_OVERSHOOT, approach_point
from afm_core.instrument import ScanRequest
from afm_core.localization.calibration.experiment import range_centre, wait

MIN_PARTICLES = 9  # per image: a 3 x 3 patch of the lattice, 3 parameters per coordinate
PITCH_TOLERANCE = (
    0.2  # a fitted lattice vector this far (relative) from the nominal pitch: refused
)
OFF_LATTICE = 0.25  # of a pitch: a particle farther from its lattice site is not the lattice's
# The maps' scan (bench_push_closed_loop, the driver's default map): the reference is imaged
# the same way, because the images' gain depends on the scan's size and speed.
MAP_SIZE = 2.4e-6  # m
MAP_PIXELS = 256
MAP_LINE_RATE = 4.0  # Hz


@dataclass(frozen=True)
class LatticeFit:
    """One image's lattice: `vectors` columns a, b (m of the image frame), row-major
    covariance of (a_x, b_x, a_y, b_y), and the particles it used."""

    vectors: np.ndarray  # 2x2
    covariance: np.ndarray  # 4x4, m^2
    residual_rms: float  # m, per coordinate
    particles: int


@dataclass(frozen=True)
class LateralScale:
    """The images' scale against a reference of known pitch."""

    matrix: np.ndarray  # 2x2: metres (sample, grating's rows along x) per unit of the images
    matrix_sigma: np.ndarray  # 2x2, 1 sigma of each element: fits and passes' spread
    scale: float  # sqrt(det(matrix)): Calibration.lateral_scale, m per unit of the maps' frame
    scale_sigma: float  # 1 sigma: the fits' and the standard error of the passes' mean
    fit_sigma: float  # 1 sigma of scale from the fits' residuals alone
    pitch: float  # m, the reference's nominal pitch
    particles: int  # lattice sites used, both passes
    residual_rms: float  # m, particle centres about the fitted lattice, both passes
    pass_scales: tuple  # sqrt(det) of each pass alone (slow axis up, down): the drift's share


def fit_lattice(points, pitch: float) -> LatticeFit:
    """Least-squares square lattice through `points` (n x 2, m, image frame) of nominal
    `pitch` (m). ValueError when fewer than MIN_PARTICLES are given or lie on the lattice, or
    when the lattice's vectors are more than PITCH_TOLERANCE from the pitch."""
    pitch = checks.positive("pitch", pitch, "m")
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(pts) < MIN_PARTICLES:
        raise ValueError(
            f"particles found={len(pts)}: need at least {MIN_PARTICLES} (a 3 x 3 patch of the "
            "reference lattice) in the image"
        )
    vectors = _neighbour_vectors(pts, pitch)
    centre = pts[np.argmin(np.hypot(*(pts - pts.mean(axis=0)).T))]
    origin = centre
    # twice: indices from the neighbours' vectors, then from the first fit's (a few pitches
    # out a 1 % error of the first guess would otherwise shift an index)
    for _ in range(2):
        ij = np.rint(np.linalg.solve(vectors, (pts - origin).T).T)
        site = origin + ij @ vectors.T
        keep = np.hypot(*(pts - site).T) < OFF_LATTICE * pitch
        if keep.sum() < MIN_PARTICLES:
            raise ValueError(
                f"particles found={int(keep.sum())} on the lattice of pitch={pitch:.4g} m: need "
                f"at least {MIN_PARTICLES}"
            )
        design = np.column_stack([np.ones(keep.sum()), ij[keep]])
        coef, *_ = np.linalg.lstsq(design, pts[keep], rcond=None)  # rows: origin, a, b
        origin, vectors = coef[0], coef[1:].T
    residual = pts[keep] - design @ coef
    dof = max(len(design) - 3, 1)
    inverse = np.linalg.inv(design.T @ design)[1:, 1:]
    covariance = np.zeros((4, 4))
    for row in (0, 1):
        variance = float(residual[:, row] @ residual[:, row]) / dof
        covariance[2 * row : 2 * row + 2, 2 * row : 2 * row + 2] = variance * inverse
    _check_pitch(vectors, pitch)
    return LatticeFit(
        vectors=vectors,
        covariance=covariance,
        residual_rms=float(np.sqrt(np.mean(residual**2))),
        particles=int(keep.sum()),
    )


def _neighbour_vectors(pts: np.ndarray, pitch: float) -> np.ndarray:
    """First guess of the lattice vectors (columns): the median displacement to the neighbours
    within PITCH_TOLERANCE of the pitch, along x and along y."""
    d = (pts[None, :, :] - pts[:, None, :]).reshape(-1, 2)
    length = np.hypot(*d.T)
    near = d[np.abs(length / pitch - 1.0) <= PITCH_TOLERANCE]
    along_x = near[near[:, 0] > np.abs(near[:, 1])]
    along_y = near[near[:, 1] > np.abs(near[:, 0])]
    if len(along_x) < 2 or len(along_y) < 2:
        raise ValueError(
            f"pitch={pitch:.4g} m: the particles found have no neighbours along x and y within "
            f"{PITCH_TOLERANCE * 100:.0f} % of it; is it the reference's pitch?"
        )
    return np.column_stack([np.median(along_x, axis=0), np.median(along_y, axis=0)])


def _check_pitch(vectors: np.ndarray, pitch: float) -> None:
    for name, vector in zip(("a (along x)", "b (along y)"), vectors.T):
        ratio = float(np.hypot(*vector)) / pitch
        if abs(ratio - 1.0) > PITCH_TOLERANCE:
            raise ValueError(
                f"lattice vector {name}: {ratio * pitch:.4g} m in the image, {ratio:.3f} x the "
                f"nominal pitch={pitch:.4g} m; more than {PITCH_TOLERANCE * 100:.0f} % apart"
            )


def lateral_scale_from_fits(fits, pitch: float) -> LateralScale:
    """The scale from one or more passes' lattice fits (their vectors averaged)."""
    pitch = checks.positive("pitch", pitch, "m")
    if not fits:
        raise ValueError("fits: need at least one lattice fit")
    vectors = np.mean([f.vectors for f in fits], axis=0)
    covariance = np.sum([f.covariance for f in fits], axis=0) / len(fits) ** 2

    def derived(v):
        v = v.reshape(2, 2)
        matrix = pitch * np.linalg.inv(v)
        return np.concatenate([matrix.ravel(), [np.sqrt(abs(np.linalg.det(matrix)))]])

    value = derived(vectors.ravel())
    jacobian = np.empty((5, 4))
    for k in range(4):  # the derived values are smooth; central differences of 1e-6 relative
        step = np.zeros(4)
        step[k] = 1e-6 * pitch
        jacobian[:, k] = (derived(vectors.ravel() + step) - derived(vectors.ravel() - step)) / (
            2 * step[k]
        )
    sigma = np.sqrt(np.diag(jacobian @ covariance @ jacobian.T))
    spread = np.zeros(5)  # the passes' standard error of the mean: the drift's share
    if len(fits) > 1:
        passes = np.array([derived(f.vectors.ravel()) for f in fits])
        spread = passes.std(axis=0, ddof=1) / np.sqrt(len(fits))
    total = np.hypot(sigma, spread)
    return LateralScale(
        matrix=value[:4].reshape(2, 2),
        matrix_sigma=total[:4].reshape(2, 2),
        scale=float(value[4]),
        scale_sigma=float(total[4]),
        fit_sigma=float(sigma[4]),
        pitch=pitch,
        particles=int(sum(f.particles for f in fits)),
        residual_rms=float(
            np.sqrt(
                sum(f.residual_rms**2 * f.particles for f in fits) / sum(f.particles for f in fits)
            )
        ),
        pass_scales=tuple(float(pitch / np.sqrt(abs(np.linalg.det(f.vectors)))) for f in fits),
    )


def measure_lateral_scale(
    instrument,
    pitch: float,
    *,
    centre=None,
    size: float = MAP_SIZE,
    pixels: int = MAP_PIXELS,
    line_rate: float = MAP_LINE_RATE,
    overshoot: float = RASTER_APPROACH_OVERSHOOT.default,
    settle: float = 120.0,
    min_height: float = 10e-9,
) -> LateralScale:
    """Image the reference lattice of `pitch` (m) centred at `centre` (m, scanner frame; the
    range centre by default) like the maps, once slow axis up and once down, and measure the
    images' scale against it. Each image is approached from `overshoot` image sizes beyond its
    first sample (the driver's raster approach) and the tip rests `settle` s there first (the
    approach's creep). ValueError naming the field for bad input or a reference that does not
    show a lattice of that pitch."""
    pitch = checks.positive("pitch", pitch, "m")
    size = checks.positive("size", size, "m")
    if pitch > size / 3:
        raise ValueError(
            f"pitch={pitch:.4g} m: at most size/3 = {size / 3:.4g} m (a 3 x 3 patch in the image)"
        )
    settle = checks.non_negative("settle", settle, "s")
    centre = range_centre(instrument) if centre is None else checks.point("centre", centre)
    speed = instrument.limits.max_speed / 10  # the driver's approach speed
    fits = []
    for slow_up in (True, False):
        request = ScanRequest(
            float(centre[0] - size / 2),
            float(centre[1] - size / 2),
            size,
            size,
            pixels,
            pixels,
            slow_scan_up=slow_up,
            line_rate=line_rate,
        )
        request.validate(instrument.limits)
        if overshoot > 0:
            instrument.move_tip(*approach_point(request, overshoot, instrument.limits), speed)
        instrument.move_tip(*request.first_point(), speed)
        wait(instrument, settle)
        scan = instrument.raster_scan(request)
        marks = scan_landmarks(scan, min_height=min_height)
        fits.append(fit_lattice([(m.x, m.y) for m in marks if m.kind == "sphere"], pitch))
    return lateral_scale_from_fits(fits, pitch)
