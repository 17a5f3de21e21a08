"""A push's own verdict from its rescan (book 7.3.1 step 4): where the particle ended in the
maps' frame, how well the rescan knows it, and whether that supports "within tolerance".

Frame. The before and after images are in commanded scanner coordinates on the images'
hysteresis branch, the frame the maps are in; `Calibration.image_matrix` takes an image
displacement into the calibration's (the maps') frame (the identity for a calibration measured
in images). The calibration's scanner matrix is the gain of a short move after a reversal, not
the images': converting with it put every 500 nm push's verified displacement ~7 nm beyond the
truth in y on the simulated instrument (1.4 % there), and with the closed loop landing 5 nm
from the goal the verdict at 10 nm said "failed" for half of the pushes that had landed.

Drift. Between the images and during each the sample drifts; the start and the end of the
push lie on rows the before image passed `pass_time` apart (500 nm at 8 nm per line and 4 lines
per second: 15.6 s), so the drift's velocity v stretches the displacement by v * pass_time
(3.2 nm in y for such a push at the simulator's 0.2 nm/s spread of v; the residual of the
same-direction pair was 96 % correlated with the seed's v). The after image is therefore scanned
with its slow axis the other way (`reversed_scan`): the control points then have elapsed times
tens of seconds apart and `verify_push` fits the offset as c + v * elapsed (c: the scanner's
shift between the images), which measures v; the particle's displacement is raw - start - c -
v * elapsed at its own elapsed time. Without that (both images the same way, or fewer than two
timed control points) the calibration's mean drift velocity is taken out and its spread times
pass_time is the largest term of the uncertainty. When the control points' elapsed times do not
span MIN_ELAPSED_SPAN (a push along the fast axis: its corner pits on the same rows), the
substrate's bands join them (`afm_core.manipulation.verify_substrate`), and failing that the
calibration's velocity is used with its sigma (`drift_prior`, `drift_prior_sigma`) over the
particle's elapsed time from the control points' (`drift_velocity_sigma` set).

The map's own drift: the rescans measure the push drift-free, but a map that is one image is
stretched by the drift between its rows (22 nm over 800 nm of its slow axis at 1 nm/s).
`push_verdict(map_time=...)` adds that (`map_stretch`); without it the map is taken as
drift-free (a drift-corrected 0/90 pair's).

Uncertainty (per axis, the images' frame): the fit's prediction at the particle's elapsed time
(CONTROL_SIGMA per control point) and the model's (DRIFT_MODEL_RELATIVE), or the drift term and
the offset's; the particle's centre in
each image (CENTRE_SIGMA); the rescans' gain against the maps' (GAIN_SIGMA of the displacement).

Verdict. With e the measured error vector and sigma^2 the covariance's largest eigenvalue, the
true error's |e_true|^2 / sigma^2 is noncentral chi^2 (2 degrees, noncentrality |e|^2 /
sigma^2) under a flat prior; P = P(|e_true| <= tolerance). P >= CONFIDENCE: WITHIN; P <= 1 -
CONFIDENCE: OUTSIDE; otherwise CANNOT_TELL (the measurement cannot decide at this tolerance:
not a failure of the push).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from scipy.stats import ncx2

from afm_core.instrument import ScanRequest
from afm_core.localization.calibration.model import Calibration
from afm_core.manipulation.verify import VerificationResult

WITHIN = "within tolerance"
OUTSIDE = "outside tolerance"
CANNOT_TELL = "cannot tell at this tolerance"
CONFIDENCE = 0.95
# a sphere's centre in one rescan image (8 nm pixels), 1 sigma per axis: the verified x
# displacement (no drift stretch across a push along y) scattered 0.75 nm about the truth over
# 10 seeds, which holds two centres and the control points' offset
CENTRE_SIGMA = 0.5e-9  # m
# one control point's displacement between the images, 1 sigma per axis (a pit's or a static
# particle's centre in two images; with the drift fitted, the verified displacement scattered
# 0.5 nm in x and 0.7 nm in y about its mean over 20 seeds)
CONTROL_SIGMA = 1.0e-9  # m
# the rescans' scale against the maps', relative, 1 sigma: the up and down rescans (1.3 um)
# measured 500 nm pushes 2.3 nm (sd 0.7) longer in y than the truth in the map scan's own frame
# (20 seeds), a systematic the control points cannot see. It stays without drift and with both
# images scanned the same way (2.2 nm, 4 seeds), so it is not the drift fit's; the rescan's gain
# against the map scan's makes 0.5 nm of it (a sphere imaged at the push's start and end), the
# rest is not located (the after image's scanner state, after the push's moves, is one suspect).
# In each seed's own map frame (drift included) the same pushes read 2.2 nm (sd 3.1) longer. On a
# drift-corrected 0/90 pair's map (the graph's) the rescans read them 5.1 nm (sd 1.0) shorter
# than the map's frame, 1 %, which this does not cover: the pair takes the fast axis's gain on
# both axes (docs/manipulation.md, "The truth's frame")
GAIN_SIGMA = 0.005
# the calibration's drift velocity when the control points cannot measure it (verify_push's
# drift_prior): at least this share of its mean, 1 sigma. Its stated spread is the velocity's
# wander, not the mean's error, which a run measures to ~13 % (y of a 100 um scanner at
# (1.0, -0.5) nm/s, inside the run's interval); on the default drift it adds < 0.1 nm
DRIFT_PRIOR_RELATIVE = 0.15
# the offset model c + v * elapsed carried from the control points' mean elapsed time to the
# particle's, per axis 1 sigma of |v| times that time: at (1.0, -0.5) nm/s, 700 nm pushes along
# the fast axis (the control points ~45 s before the particle) were verified 5-7 nm off the truth
# in y (8 seeds), 4.5 sigma of the fit's own 1.3 nm; a static particle 1-3 nm. Not located (the
# drift's wander is 0.1 nm/s; the rescans' gain and the creep after the push are suspects). At
# the default drift (~0.2 nm/s) it adds ~1 nm
DRIFT_MODEL_RELATIVE = 0.1
SIGMA_FLOOR = 0.1e-9  # m, keeps the chi^2 finite for a degenerate covariance


@dataclass(frozen=True)
class PushVerdict:
    achieved: np.ndarray  # (2,) maps' frame, m
    covariance: np.ndarray  # (2, 2) m^2, of achieved (the start's map position is the reference)
    error: float  # m, |achieved - goal|
    sigma: float  # m, sqrt of the covariance's largest eigenvalue
    within_probability: float  # P(true error <= tolerance | the measurement)
    verdict: str  # WITHIN | OUTSIDE | CANNOT_TELL

    @property
    def within(self) -> bool:
        return self.verdict == WITHIN

    def message(
        self, strategy: str, particle_id: int, tolerance: float, pose: str, controls: int
    ) -> str:
        """The push's result message (pose: a rod's angle text, "" for a sphere)."""
        a = self.achieved * 1e9
        return (
            f"{strategy}: particle {particle_id} at ({a[0]:.1f} nm, {a[1]:.1f} nm), "
            f"{self.error * 1e9:.1f} +- {self.sigma * 1e9:.1f} nm from the goal: {self.verdict} "
            f"(P within {self.within_probability:.2f}; tolerance {tolerance * 1e9:.1f} nm{pose}; "
            f"{controls} control point(s))"
        )


def reversed_scan(request: ScanRequest) -> ScanRequest:
    """The after image's request: the before image's, its slow axis the other way, so the
    control points' elapsed times differ across the image and the drift's velocity can be
    fitted (module docstring)."""
    return replace(request, slow_scan_up=not request.slow_scan_up)


def within_probability(error_vector, covariance, tolerance: float) -> float:
    """P(|true error| <= tolerance) for a measured error vector with that covariance (module
    docstring, verdict)."""
    variance = max(float(np.linalg.eigvalsh(np.asarray(covariance, float)).max()), SIGMA_FLOOR**2)
    error2 = float(np.sum(np.asarray(error_vector, float) ** 2))
    return float(ncx2.cdf(tolerance**2 / variance, 2, error2 / variance))


def judge(probability: float) -> str:
    if probability >= CONFIDENCE:
        return WITHIN
    if probability <= 1.0 - CONFIDENCE:
        return OUTSIDE
    return CANNOT_TELL


def verdict_shares(verdicts, truly) -> dict:
    """How a set of pushes' verdicts read against the truth (truly: each push's true error within
    its tolerance): the three answers' shares and the agreement of the definite ones."""
    verdicts, truly = np.asarray(verdicts), np.asarray(truly, bool)
    within, outside = verdicts == WITHIN, verdicts == OUTSIDE
    definite = within | outside
    return {
        "share_within": float(np.mean(within)),
        "share_outside": float(np.mean(outside)),
        "share_cannot_tell": float(np.mean(~definite)),
        "agreement_definite": float(np.mean((within == truly)[definite]))
        if definite.any()
        else 1.0,
    }


def drift_prior_sigma(mean, sigma) -> np.ndarray:
    """The sigma of the calibration's drift velocity as a prior for one push (m/s, per axis):
    its stated spread, at least DRIFT_PRIOR_RELATIVE of its mean."""
    mean, sigma = np.asarray(mean, float), np.asarray(sigma, float)
    return np.hypot(sigma, DRIFT_PRIOR_RELATIVE * np.abs(mean))


def drift_prior(calibration: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """`verify_push`'s drift_prior from a calibration: its mean drift velocity in the images'
    frame (image_matrix's inverse) and its spread (calibration's frame: the matrix is within a
    few % of the identity)."""
    matrix = np.asarray(calibration.image_matrix, float)
    mean = np.linalg.solve(matrix, np.asarray(calibration.drift_mean_velocity, float))
    return mean, np.asarray(calibration.drift_sigma_velocity, float)


def maps_displacement(
    verification: VerificationResult, calibration: Calibration
) -> tuple[np.ndarray, np.ndarray]:
    """The particle's displacement from its start in the maps' frame and its covariance
    (module docstring): the before image's drift stretch taken out, through image_matrix."""
    if verification.displacement is None:
        raise ValueError("verification.displacement: verify_push was given no start")
    image = np.asarray(verification.displacement, float)
    variance = np.full(2, 2 * CENTRE_SIGMA**2)
    used = [c for c in verification.control_points if c.used]
    if verification.drift_velocity_sigma is not None:
        # v given (the calibration's; too few control points, or too close in time): the shift's
        # spread over the control points, and v's sigma over the particle's elapsed time from
        # theirs (the offset's extrapolation and the before image's stretch together)
        mean_elapsed = float(np.mean([c.elapsed for c in used]))
        variance += max(verification.offset_spread, CONTROL_SIGMA) ** 2 / len(used)
        variance += (
            drift_prior_sigma(verification.drift_velocity, verification.drift_velocity_sigma)
            * (verification.elapsed - mean_elapsed)
        ) ** 2
    elif verification.drift_velocity is not None:
        # the fit c + v * elapsed at the particle's elapsed time (least squares' variance)
        design = np.column_stack([np.ones(len(used)), [c.elapsed for c in used]])
        at = np.array([1.0, verification.elapsed])
        variance += CONTROL_SIGMA**2 * float(at @ np.linalg.inv(design.T @ design) @ at)
    if verification.drift_velocity is not None and used:
        # the model c + v * elapsed carried from the control points' times to the particle's
        mean_elapsed = float(np.mean([c.elapsed for c in used]))
        speed = float(np.hypot(*verification.drift_velocity))
        variance += (DRIFT_MODEL_RELATIVE * speed * (verification.elapsed - mean_elapsed)) ** 2
    if verification.drift_velocity is None:
        dt = verification.pass_time if math.isfinite(verification.pass_time) else 0.0
        image = image - np.asarray(calibration.drift_mean_velocity, float) * dt
        variance += (np.asarray(calibration.drift_sigma_velocity, float) * dt) ** 2
        variance += max(verification.offset_spread, CONTROL_SIGMA) ** 2 / max(len(used), 1)
    variance += (GAIN_SIGMA * float(np.hypot(*image))) ** 2
    matrix = np.asarray(calibration.image_matrix, float)
    return matrix @ image, matrix @ np.diag(variance) @ matrix.T


def map_stretch(
    calibration: Calibration, start, end, map_time: Callable[[np.ndarray], float]
) -> tuple[np.ndarray, np.ndarray]:
    """The map's own drift between its passes over `start` and `end` (maps' frame, m): the
    calibration's mean drift velocity times map_time(end) - map_time(start) (s), and its
    covariance (drift_prior_sigma times that time). What a displacement measured drift-free
    (the rescans') needs to be one in a map that was not drift-corrected (module docstring)."""
    dt = float(map_time(np.asarray(end, float))) - float(map_time(np.asarray(start, float)))
    if not math.isfinite(dt):
        raise ValueError(f"map_time: gave {dt} s between the start and the end; need finite")
    mean = np.asarray(calibration.drift_mean_velocity, float)
    sigma = drift_prior_sigma(mean, calibration.drift_sigma_velocity)
    return mean * dt, np.diag((sigma * dt) ** 2)


def push_verdict(
    verification: VerificationResult,
    calibration: Calibration,
    start,
    goal,
    tolerance: float,
    map_time: Callable[[np.ndarray], float] | None = None,
) -> PushVerdict:
    """The push's verdict: the particle's map position `start` plus its verified displacement
    (maps' frame) against `goal`, at `tolerance` (m). map_time: when the map passed a point of
    it (s; e.g. `functools.partial(verify.scan_time, map_scan)`) for a map that was not
    drift-corrected: its drift stretch over the push is added (`map_stretch`); None: the map is
    taken as drift-free (a drift-corrected pair's)."""
    displacement, covariance = maps_displacement(verification, calibration)
    if map_time is not None:
        start_xy = np.asarray(start, float)
        stretch, added = map_stretch(calibration, start_xy, start_xy + displacement, map_time)
        displacement, covariance = displacement + stretch, covariance + added
    achieved = np.asarray(start, float) + displacement
    error_vector = achieved - np.asarray(goal, float)
    probability = within_probability(error_vector, covariance, tolerance)
    sigma = math.sqrt(max(float(np.linalg.eigvalsh(covariance).max()), 0.0))
    return PushVerdict(
        achieved,
        covariance,
        float(np.hypot(*error_vector)),
        sigma,
        probability,
        judge(probability),
    )
