"""Observation planning: the local scan lines that must find a landmark (book 6.1, eq. 6.1-6.10).

The tip believes it is at `tip_mean`; its true position is tip_mean + e with e ~ N(0, P).
A scan line commanded at the across coordinate y (y = the particle's own across coordinate
plus an offset o) really runs at y + e_across(t), and it crosses a particle of radius R_P
when |o + e_across(t)| < R_P. While the tip moves, e grows by the motion noise: w(t) with
variance A(t) (MotionNoise, slopes K_h1, K_h2, K_v1, K_v2). Line k therefore crosses the
particle for every |w| <= 3 sqrt(A_k) (the book's 3-sigma principle, A_k taken at the end of
the line, its worst point) when the initial error lies in its *band*

    e_across in [-o_k - h_k, -o_k + h_k],   h_k = R_P - 3 sqrt(A_k)       (eq. 6.3-6.5)

Plan (Fig. 6.1, Steps 1-5):
1. Approach: move to the start of L0 on the particle's across coordinate, on the side of the
   particle where the tip is, so far out that 3 sigma_along + R_T + R_P clears the particle
   centre (the tip never taps it before the scan). The Gaussian at that point is the plan's
   reference: its 3-sigma ellipse (half-extent E = 3 sigma_across) is what must be covered.
2. L0 (offset 0) runs through the particle's centre line to the far side; its end is the
   root of eq. 6.2, l = 3 sqrt(sigma^2 + K_along (l_1 + l)) + R_T + R_P, a quadratic in l.
3. If L0's band does not cover the ellipse: step across by u and scan back (Steps 2-3), u the
   largest step whose band still touches the covered part: u + 3 sqrt(A + K_across u) = B,
   a quadratic in sqrt(A + K_across u) (eq. 6.5-6.8; the line's own growth K_along-across l
   is estimated from the previous line first, like the book's K_v2 u'_y estimate for eq. 6.6).
   Repeat until the band reaches +E (Area 1), then go to the other side of L0 and do the same
   until -E (Area 3, Steps 4-5).
4. Probability of finding the particle on line k (eq. 6.9): the Gaussian mass of its area (the
   part of the 3-sigma ellipse whose across error lies in its band and not in an earlier
   line's band), normalised over the kept lines. For an ellipse with Mahalanobis radius 3 the
   mass of the strip t1 <= e/sigma <= t2 is the integral of phi(t) (2 Phi(sqrt(9 - t^2)) - 1):
   the chord at t is +-sqrt(9 - t^2) conditional sigmas wide, whatever the correlation. A
   line whose probability (its area's mass over the whole ellipse's, 1 - e^-4.5) is below
   `min_line_probability` (book: TH = 0.01) is a small-probability event: it and the lines
   beyond it on that side are not planned (`success_probability` says what that gives up).
5. Expected cost (eq. 6.10, read as expected travel): the particle is found on line k with
   probability p_k, after the approach, every earlier line, the steps between them and line k.

All SI (m, m^2). Lines are axis-aligned: direction "h" scans along x, "v" along y. The
approach is one straight move: the caller brings the tip round the particle first when it
starts on the far side (landmark_paths does, with corner waypoints).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from scipy import special

from afm_core import checks
from afm_core.localization.motion_noise import MotionNoise
from afm_core.planning._checks import covariance_matrix, line_axis, noise_model, point_copy

THREE_SIGMA_MASS = 1.0 - math.exp(
    -4.5
)  # mass of a 2-D Gaussian inside its 3-sigma (Mahalanobis) ellipse
MAX_LINES = 200


@dataclass(frozen=True)
class ScanLine:
    """One local scan line L_k of an observation plan."""

    start: np.ndarray  # (2,) m, commanded
    end: np.ndarray  # (2,) m
    offset: float  # m, across offset of the line from the particle centre
    band: tuple[
        float, float
    ]  # m: initial across errors for which this line must cross the particle
    probability: float  # eq. 6.9, normalised over the plan's lines
    raw_probability: float  # Gaussian mass of the line's area (part of the ellipse)
    side: int  # 0 for L0, +1 lines covering e_across > 0 (Area 1), -1 (Area 3)
    start_covariance: np.ndarray  # 2x2 m^2, predicted at the start (no observation yet)
    end_covariance: np.ndarray  # 2x2 m^2, predicted at the end

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.end - self.start))


@dataclass(frozen=True)
class ObservationPlan:
    """Scan lines that find a particle if it is anywhere in the tip's 3-sigma ellipse
    (eq. 6.1-6.10)."""

    direction: str  # "h" (lines along x) or "v" (along y)
    particle_center: np.ndarray  # (2,) m
    particle_radius: float  # m
    tip_radius: float  # m
    approach_start: np.ndarray  # (2,) m, the tip's mean when planning
    approach_length: float  # m, from approach_start to lines[0].start
    reference_covariance: (
        np.ndarray
    )  # 2x2 m^2 at lines[0].start: the Gaussian whose ellipse is covered
    lines: tuple[ScanLine, ...]
    step_lengths: tuple[float, ...]  # m, move from lines[k-1].end to lines[k].start (k >= 1)
    expected_cost: float  # m, expected travel until the particle is found (eq. 6.10)
    success_probability: float  # P(initial across error within the union of the bands)
    covered: tuple[float, float]  # m, the union of the bands (initial across error)


@dataclass(frozen=True)
class _Slopes:
    along: float  # along variance per m moved along the line
    cross: float  # across variance per m moved along the line
    across: float  # across variance per m moved across
    along_per_across: float
    offset_along: float
    offset_across: float


def _slopes(noise: MotionNoise, axis: int) -> _Slopes:
    if axis == 0:
        return _Slopes(
            noise.k_h1, noise.k_h2, noise.k_v1, noise.k_v2, noise.offset_x, noise.offset_y
        )
    return _Slopes(noise.k_v1, noise.k_v2, noise.k_h1, noise.k_h2, noise.offset_y, noise.offset_x)


def line_end_distance(
    variance_along: float, slope_along: float, travelled_before_centre: float, clearance: float
) -> float:
    """Eq. 6.2: distance l past the particle centre at which a line may end, the root
    >= clearance of l = 3 sqrt(variance + slope (l_1 + l)) + clearance (clearance = R_T + R_P;
    variance at the line's start, l_1 its distance to the centre). (l - c)^2 = 9 (W + K l) is a
    quadratic with one root >= c."""
    k, c = slope_along, clearance
    w = variance_along + k * travelled_before_centre
    b = 2 * c + 9 * k
    return 0.5 * (b + math.sqrt(max(b * b - 4 * (c * c - 9 * w), 0.0)))


def across_step(accumulated: float, slope_across: float, reach: float) -> float:
    """Eq. 6.5-6.8: the largest across step u with u + 3 sqrt(A + K u) <= reach, i.e. the band of
    the next line still touches what is covered. With s = sqrt(A + K u):
    s^2 + 3 K s - (A + K reach) = 0."""
    k, a = slope_across, accumulated
    if k == 0:
        return reach - 3 * math.sqrt(a)
    s = 0.5 * (-3 * k + math.sqrt(9 * k * k + 4 * (a + k * reach)))
    return (s * s - a) / k


_GAUSS_NODES, _GAUSS_WEIGHTS = np.polynomial.legendre.leggauss(32)


def _strip_mass(t1: float, t2: float) -> float:
    """Mass of a 2-D Gaussian inside its 3-sigma ellipse and in the across strip
    t1 <= e/sigma <= t2: the integral of phi(t) P(|conditional along error| <= sqrt(9 - t^2)
    conditional sigmas). With t = 3 sin(theta) the integrand, 3 cos(theta) phi(t)
    erf(3 cos(theta) / sqrt 2), is smooth on [-pi/2, pi/2] (the square root's kink at t = +-3 is
    gone), so 32-point Gauss-Legendre gets it to ~1e-13 in ~10 us (adaptive quad needed ~500
    evaluations of the kinked integrand and was most of a plan's time)."""
    t1, t2 = max(t1, -3.0), min(t2, 3.0)
    if t2 <= t1:
        return 0.0
    a, b = math.asin(t1 / 3.0), math.asin(t2 / 3.0)
    theta = 0.5 * (b - a) * _GAUSS_NODES + 0.5 * (a + b)
    c = np.cos(theta)
    t = 3.0 * np.sin(theta)
    f = 3.0 * c * np.exp(-0.5 * t * t) * special.erf(3.0 * c / math.sqrt(2.0))
    return float(0.5 * (b - a) * np.dot(_GAUSS_WEIGHTS, f) / math.sqrt(2.0 * math.pi))


def _normal_mass(t1: float, t2: float) -> float:
    return float(special.ndtr(t2) - special.ndtr(t1))


def plan_observation(
    tip_mean,
    tip_covariance,
    particle_center,
    particle_radius: float,
    tip_radius: float,
    noise: MotionNoise,
    direction: str = "h",
    min_line_probability: float = 0.01,
    first_side: int = 1,
) -> ObservationPlan:
    """Plan the local scan lines L0, L1, ... that find the particle (see the module docstring).

    Raises ValueError naming the argument for bad input (NaN, non-PSD covariance, non-positive
    radius, unknown direction) and when no line can be guaranteed to cross the particle because
    3 sqrt(accumulated across variance) >= R_P (the particle is too small for the motion noise).
    """
    mean = point_copy("tip_mean", tip_mean)
    cov0 = covariance_matrix("tip_covariance", tip_covariance)
    centre = point_copy("particle_center", particle_center)
    r_p = checks.positive("particle_radius", particle_radius)
    r_t = checks.non_negative("tip_radius", tip_radius)
    noise = noise_model("noise", noise)
    a = line_axis("direction", direction)
    if not (0 <= min_line_probability < 0.5):
        raise ValueError(f"min_line_probability={min_line_probability}: must be in [0, 0.5)")
    if first_side not in (1, -1):
        raise ValueError(f"first_side={first_side}: must be +1 or -1")
    frame = _LineFrame(a, centre, noise, _slopes(noise, a), r_t + r_p, r_p)
    along0, cov_start = _approach(frame, mean, cov0)
    approach_length = float(np.linalg.norm(frame.at(along0, 0.0) - mean))
    reference = _Reference(math.sqrt(cov_start[1 - a, 1 - a]), cov_start[1 - a, 1 - a])
    lines, steps, covered, state = _first_line(frame, along0, cov_start, reference)
    for side in (first_side, -first_side):
        state = _cover_side(
            frame, side, state, covered, lines, steps, reference, min_line_probability
        )
    normalised, expected = _normalised(lines, steps, approach_length)
    return ObservationPlan(
        direction,
        centre,
        r_p,
        r_t,
        mean,
        approach_length,
        cov_start,
        normalised,
        tuple(steps),
        expected,
        _normal_mass(covered[0] / reference.sigma, covered[1] / reference.sigma),
        (covered[0], covered[1]),
    )


@dataclass(frozen=True)
class _LineFrame:
    """The particle's frame of one plan: lines run along axis `a` (0: x), their offsets are
    across it, positions are relative to the particle centre."""

    a: int
    centre: np.ndarray
    noise: MotionNoise
    k: _Slopes
    clearance: float  # R_T + R_P
    r_p: float

    @property
    def b(self) -> int:
        return 1 - self.a

    def move(self, cov: np.ndarray, d_along: float, d_across: float) -> np.ndarray:
        """Covariance after a move by d_along along the lines and d_across across them."""
        d = np.zeros(2)
        d[self.a], d[self.b] = d_along, d_across
        return self.noise.predict(cov, d[0], d[1])

    def at(self, along: float, offset: float) -> np.ndarray:
        """The point `along` the line direction and `offset` across it from the centre."""
        p = np.empty(2)
        p[self.a], p[self.b] = self.centre[self.a] + along, self.centre[self.b] + offset
        return p

    def scan(
        self, cov: np.ndarray, along_start: float, var_across_ref: float
    ) -> tuple[np.ndarray, float, float]:
        """A line from along_start (signed) across the centre: covariance and along position at
        its end (eq. 6.2), and the half-width h of its band (eq. 6.3-6.5)."""
        a, b, k = self.a, self.b, self.k
        end_distance = line_end_distance(
            cov[a, a] + k.offset_along, k.along, abs(along_start), self.clearance
        )
        along_end = -math.copysign(end_distance, along_start)
        cov_end = self.move(cov, along_end - along_start, 0.0)
        accumulated = cov_end[b, b] - var_across_ref
        return cov_end, along_end, self.r_p - 3 * math.sqrt(max(accumulated, 0.0))


@dataclass(frozen=True)
class _Reference:
    """The Gaussian at L0's start whose 3-sigma ellipse the lines cover (across the lines)."""

    sigma: float  # m
    variance: float  # m^2


def _approach(frame: _LineFrame, mean: np.ndarray, cov0: np.ndarray) -> tuple[float, np.ndarray]:
    """Step 1: the along position (signed, on the tip's side) of L0's start, far enough out for
    its own predicted sigma, and the covariance there. A fixed point: the start's distance
    changes the move and so the variance only slightly, dvar/dl ~ 1e-10."""
    a, b = frame.a, frame.b
    rel = mean - frame.centre
    side_along = -1.0 if rel[a] <= 0 else 1.0
    distance = abs(rel[a])
    start_distance = frame.clearance
    for _ in range(60):
        cov_start = frame.move(
            cov0, distance - start_distance if distance != start_distance else 0.0, -rel[b]
        )
        new = 3 * math.sqrt(cov_start[a, a]) + frame.clearance
        if abs(new - start_distance) < 1e-15:
            break
        start_distance = new
    cov_start = frame.move(cov0, abs(distance - start_distance), rel[b])
    return side_along * start_distance, cov_start


def _first_line(
    frame: _LineFrame, along0: float, cov_start: np.ndarray, reference: _Reference
) -> tuple[list[ScanLine], list[float], list[float], tuple]:
    """Step 2, L0 through the particle's centre line: the lines and steps so far, the covered
    interval of initial across errors, and the state after it (covariance, along position,
    offset of the tip)."""
    cov_end, along_end, h0 = frame.scan(cov_start, along0, reference.variance)
    if h0 <= 0:
        raise ValueError(
            f"particle_radius={frame.r_p} m: too small for the motion noise; 3 sigma of the "
            f"across error added by the approach and L0 is {frame.r_p - h0:.3g} m >= R_P, so no "
            "line is sure to cross the particle"
        )
    mass = _strip_mass(-h0 / reference.sigma, h0 / reference.sigma)
    line = ScanLine(
        frame.at(along0, 0.0),
        frame.at(along_end, 0.0),
        0.0,
        (-h0, h0),
        mass,
        mass,
        0,
        cov_start,
        cov_end,
    )
    return [line], [], [-h0, h0], (cov_end, along_end, 0.0)


def _cover_side(
    frame: _LineFrame,
    side: int,
    state: tuple,
    covered: list[float],
    lines: list[ScanLine],
    steps: list[float],
    reference: _Reference,
    min_line_probability: float,
) -> tuple:
    """Steps 3-5 on one side of L0 (+1: Area 1, -1: Area 3): lines until their bands reach the
    ellipse's edge or the next one is a small-probability event. Appends to `lines` and
    `steps`, widens `covered`; returns the state after the last line."""
    edge_index = 1 if side > 0 else 0
    while side * covered[edge_index] < 3 * reference.sigma:
        if len(lines) >= MAX_LINES:
            raise ValueError(
                f"tip_covariance: needs more than {MAX_LINES} scan lines to cover its "
                f"3-sigma ellipse (sigma_across {reference.sigma:.3g} m, R_P {frame.r_p:.3g} m)"
            )
        along_now = state[1]
        line = _next_line(frame, side, state, covered[edge_index], reference, len(lines))
        band = (-line.offset - line.h, -line.offset + line.h)
        new_part = (covered[1], band[1]) if side > 0 else (band[0], covered[0])
        mass = _strip_mass(new_part[0] / reference.sigma, new_part[1] / reference.sigma)
        if mass / THREE_SIGMA_MASS < min_line_probability:
            break  # small-probability event (TH): not planned, nor beyond it
        covered[edge_index] = band[edge_index]
        steps.append(float(math.hypot(line.along_start - along_now, line.u)))
        lines.append(
            ScanLine(
                frame.at(line.along_start, line.offset),
                frame.at(line.along_end, line.offset),
                line.offset,
                band,
                mass,
                mass,
                side,
                line.start_covariance,
                line.end_covariance,
            )
        )
        state = (line.end_covariance, line.along_end, line.offset)
    return state


@dataclass(frozen=True)
class _NextLine:
    u: float  # m, the across step to it
    offset: float  # m, its across offset from the centre
    along_start: float  # m, signed
    along_end: float
    start_covariance: np.ndarray
    end_covariance: np.ndarray
    h: float  # m, half-width of its band


def _next_line(
    frame: _LineFrame, side: int, state: tuple, edge: float, reference: _Reference, count: int
) -> _NextLine:
    """Steps 2-3 (eq. 6.5-6.8): the next line beyond the covered `edge` on `side`, the largest
    across step whose band still touches it. The line's own growth is first estimated from
    the previous line, then from the line itself; the step shrinks while a gap is left."""
    a, b, k, r_p = frame.a, frame.b, frame.k, frame.r_p
    cov, along_now, offset_now = state
    reach = side * edge + side * offset_now + r_p
    line_growth = k.cross * 2 * abs(along_now)  # first estimate of the line's own growth
    shortfall = 0.0
    for _ in range(8):
        accumulated = cov[b, b] - reference.variance + k.offset_across + line_growth
        u = across_step(accumulated, k.across, reach) - shortfall
        if u <= 0:
            raise ValueError(
                f"particle_radius={r_p} m: too small for the motion noise; after {count} lines "
                "3 sigma of the added across error reaches R_P, so the next line cannot be sure "
                f"to cross (tip_covariance sigma_across {reference.sigma:.3g} m)"
            )
        offset_new = offset_now - side * u
        # the line starts where the last one ended, moved out if its sigma_along grew
        cov_step = frame.move(cov, 0.0, u)
        # moving out by x - s along as well: x = 3 sqrt(var + K_along (x - s)) + R_T + R_P
        need = line_end_distance(cov_step[a, a], k.along, -abs(along_now), frame.clearance)
        along_new = math.copysign(max(abs(along_now), need), along_now)
        cov_step = frame.move(cov, along_new - along_now, u)
        cov_e, along_e, h = frame.scan(cov_step, along_new, reference.variance)
        line_growth = cov_e[b, b] - cov_step[b, b]
        if h <= 0:
            raise ValueError(
                f"particle_radius={r_p} m: too small for the motion noise; after {count} lines "
                f"3 sigma of the added across error ({r_p - h:.3g} m) reaches R_P, so the next "
                f"line cannot be sure to cross (tip_covariance sigma_across "
                f"{reference.sigma:.3g} m)"
            )
        # the band's near edge must reach what is covered (no gap); shrink the step if not
        near_edge = -offset_new - side * h
        gap = side * (near_edge - edge)
        if gap <= 1e-15:
            return _NextLine(u, offset_new, along_new, along_e, cov_step, cov_e, h)
        shortfall += max(gap, 0.0) + 1e-15
    raise ValueError(
        f"particle_radius={r_p} m: no across step keeps the bands of the lines contiguous after "
        f"{count} lines (motion noise too large)"
    )


def _normalised(
    lines: list[ScanLine], steps: list[float], approach_length: float
) -> tuple[tuple[ScanLine, ...], float]:
    """Steps 4-5: each line's probability normalised over the plan's lines (eq. 6.9) and the
    expected travel until the particle is found (eq. 6.10)."""
    total = sum(line.raw_probability for line in lines)
    travelled, expected = approach_length, 0.0
    normalised = []
    for i, line in enumerate(lines):
        travelled += (steps[i - 1] if i else 0.0) + line.length
        p = line.raw_probability / total
        expected += p * travelled
        normalised.append(dataclasses.replace(line, probability=p))
    return tuple(normalised), expected
