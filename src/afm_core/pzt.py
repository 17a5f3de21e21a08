"""Lateral piezo (PZT) scanner: hysteresis, creep, cross-coupling and scan-line deflection.

The book (section 5.3) models each lateral piezo axis as a Prandtl-Ishlinskii (PI) hysteresis
operator followed by a multi-time-constant creep operator; the simulator uses the same chain
to turn commanded positions into true ones, and the PI model's analytic inverse is the
feed-forward that compensates it.

Units: every model here is unit-agnostic (input and output in the same unit); the scanner
works in SI (metres, seconds). All stateful objects take whole sample sequences and continue
from the last sample of the previous call, so a path may be fed in chunks of any size.

Speed: a play operator's output inside a monotone stretch of its input is a closed form
(rising: max(y_start, x - r), falling: min(y_start, x + r)), so a sequence is split at its
turning points and only the outputs at the turning points need a recursion. That recursion is
a chain of clamps, and clamps compose into clamps, so it is an associative scan evaluated in
log2(turning points) vectorised levels: O(samples * operators) numpy work, no per-sample Python.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import lfilter

# -- play operators -----------------------------------------------------------------------


def _as_sequence(values, name: str) -> np.ndarray:
    array = np.asarray(values, dtype=float)
    if array.ndim != 1:
        raise ValueError(f"{name}: expected a 1-D sample sequence, got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name}: contains non-finite samples")
    return array


def _then(lo1, hi1, lo2, hi2):
    """The clamp [lo1, hi1] followed by [lo2, hi2] is the clamp [c2(lo1), c2(hi1)]: the scan's
    associative step. Only selects among existing values, so results are bit-exact."""
    return np.minimum(np.maximum(lo1, lo2), hi2), np.minimum(np.maximum(hi1, lo2), hi2)


def _prefix_clamps(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inclusive prefix compositions of the clamps (lo[k], hi[k]) along axis 0.

    Work-efficient pairwise scan: compose neighbours, scan the half-length sequence, fill in
    the even positions. O(K) work in log2(K) vectorised levels."""
    count = lo.shape[0]
    if count == 1:
        return lo, hi
    half = count // 2
    pair_lo, pair_hi = _then(
        lo[0 : 2 * half : 2], hi[0 : 2 * half : 2], lo[1 : 2 * half : 2], hi[1 : 2 * half : 2]
    )
    pair_lo, pair_hi = _prefix_clamps(pair_lo, pair_hi)  # prefixes through 1, 3, 5, ...
    out_lo, out_hi = np.empty_like(lo), np.empty_like(hi)
    out_lo[0], out_hi[0] = lo[0], hi[0]
    out_lo[1::2], out_hi[1::2] = pair_lo, pair_hi
    evens = (count - 1) // 2
    out_lo[2::2], out_hi[2::2] = _then(pair_lo[:evens], pair_hi[:evens], lo[2::2], hi[2::2])
    return out_lo, out_hi


def _monotone_breaks(x: np.ndarray) -> np.ndarray:
    """Sorted sample indices (first, turning points, last) between which x is monotone.
    Flat steps continue the previous direction so plateaus do not split a stretch."""
    n = x.size
    if n == 1:
        return np.zeros(1, dtype=np.intp)
    step = np.sign(np.diff(x))
    last_moving = np.where(step != 0, np.arange(step.size), 0)
    np.maximum.accumulate(last_moving, out=last_moving)
    step = step[last_moving]
    turns = np.flatnonzero(step[1:] != step[:-1]) + 1
    return np.concatenate(([0], turns, [n - 1]))


class PlayOperatorBank:
    """Play (backlash) operators sharing one input: y(k) = max(x(k) - r, min(x(k) + r, y(k-1))).

    The building block of the PI model; kept separate so it can be checked against the
    textbook definition on its own."""

    def __init__(self, thresholds):
        r = np.asarray(thresholds, dtype=float)
        if r.ndim != 1 or r.size == 0 or not np.isfinite(r).all() or (r < 0).any():
            raise ValueError(
                f"thresholds={thresholds!r}: need a non-empty 1-D list of finite values >= 0"
            )
        self._r = r.copy()
        self._z = np.zeros(r.size)

    @property
    def thresholds(self) -> np.ndarray:
        return self._r.copy()

    @property
    def state(self) -> np.ndarray:
        """Each operator's last output (the whole memory of a play operator)."""
        return self._z.copy()

    @state.setter
    def state(self, value) -> None:
        z = np.asarray(value, dtype=float)
        if z.shape != self._z.shape or not np.isfinite(z).all():
            raise ValueError(f"state: expected {self._z.size} finite values, got shape {z.shape}")
        self._z = z.copy()

    def reset(self, x0=0.0) -> None:
        """Demagnetised at x0: every operator centred on the input (a scalar or one per
        operator)."""
        self.state = np.broadcast_to(np.asarray(x0, dtype=float), self._z.shape)

    def apply(self, x) -> np.ndarray:
        """Outputs of every operator, shape (len(x), n_operators)."""
        x = _as_sequence(x, "x")
        if x.size == 0:
            return np.empty((0, self._r.size))
        breaks = _monotone_breaks(x)
        r = self._r
        lo_prefix, hi_prefix = _prefix_clamps(x[breaks, None] - r, x[breaks, None] + r)
        at_breaks = np.minimum(np.maximum(self._z, lo_prefix), hi_prefix)
        # Each sample starts from the output at the last break before it; within a monotone
        # stretch the per-sample clamp of that value is the closed form.
        is_break = np.zeros(x.size, dtype=bool)
        is_break[breaks] = True
        rank = np.cumsum(is_break) - 1
        out = np.empty((x.size, r.size))
        out[0] = at_breaks[0]
        start = at_breaks[rank[:-1]]
        np.maximum(start, x[1:, None] - r, out=start)
        np.minimum(start, x[1:, None] + r, out=out[1:])
        self._z = out[-1].copy()
        return out


# -- Prandtl-Ishlinskii hysteresis ----------------------------------------------------------


def _check_polynomial(polynomial) -> tuple[float, float, float]:
    coefficients = tuple(float(c) for c in polynomial)
    if len(coefficients) != 3 or not all(math.isfinite(c) for c in coefficients):
        raise ValueError(f"polynomial={polynomial!r}: need three finite coefficients (a1, a2, a3)")
    a1, a2, a3 = coefficients
    monotone = a1 > 0 and ((a2 == 0 and a3 == 0) or (a3 > 0 and a2 * a2 < 3 * a1 * a3))
    if not monotone:
        raise ValueError(
            f"polynomial={coefficients}: p'(x) = a1 + 2 a2 x + 3 a3 x^2 must be > 0 for every x "
            "(a1 > 0, and a2 = a3 = 0 or a3 > 0 with a2^2 < 3 a1 a3)"
        )
    return coefficients


def _polynomial(x, coefficients):
    a1, a2, a3 = coefficients
    return ((a3 * x + a2) * x + a1) * x


def _polynomial_inverse(v: np.ndarray, coefficients) -> np.ndarray:
    """Root of the strictly increasing p(x) = v, sample by sample (memoryless, vectorised).

    Cardano (hyperbolic form, one real root since p' > 0) as the start, then Newton to
    machine precision: Newton converges from anywhere on a strictly monotone cubic, and the
    start already has all but the digits the closed form loses to cancellation."""
    a1, a2, a3 = coefficients
    if a3 == 0.0:
        return v / a1
    b, c = a2 / a3, a1 / a3
    p_dep = c - b * b / 3.0
    q_dep = 2.0 * b**3 / 27.0 - b * c / 3.0 - v / a3
    with np.errstate(all="ignore"):
        t = (
            -2.0
            * np.sqrt(p_dep / 3.0)
            * np.sinh(np.arcsinh(1.5 * q_dep / p_dep * np.sqrt(3.0 / p_dep)) / 3.0)
        )
        x = t - b / 3.0
    x = np.where(np.isfinite(x), x, v / a1)
    # Quadratic convergence: once the steps are 1e-13 of the signal scale, the error left is
    # ~(1e-13)^2 of it. A per-sample relative test would never pass near x = 0, where the
    # residual's rounding (set by the signal scale) keeps the steps from shrinking further.
    tolerance = 1e-13 * (np.abs(x).max() if x.size else 0.0)
    for _ in range(100):
        step = (_polynomial(x, coefficients) - v) / ((3.0 * a3 * x + 2.0 * a2) * x + a1)
        x = x - step
        if np.abs(step).max(initial=0.0) <= tolerance:
            break
    return x


class _WeightedPlayBank:
    """What a PI model and its inverse share: a play-operator bank and its weights."""

    _bank: PlayOperatorBank
    _w: np.ndarray

    @property
    def thresholds(self) -> np.ndarray:
        return self._bank.thresholds

    @property
    def weights(self) -> np.ndarray:
        return self._w.copy()

    @property
    def state(self) -> np.ndarray:
        """Play-operator states (the forward model's are in p(x) units)."""
        return self._bank.state

    @state.setter
    def state(self, value) -> None:
        self._bank.state = value


class PrandtlIshlinskii(_WeightedPlayBank):
    """Asymmetric PI hysteresis: y = H[p(x)], H[v] = sum_i w_i F_{r_i}[v] (play operators F).

    Asymmetry: p(x) = a1 x + a2 x^2 + a3 x^3 is a strictly increasing input function (the
    generalized PI of Al Janaideh, Rakheja and Su with one envelope function for both
    directions). An x^2 term breaks the odd symmetry, so the ascending and descending branches
    are no longer point-symmetric about the loop centre, which is what the book's asymmetric PI
    (Wang et al. 2010) is for. Chosen over the additive form y = p(x) + H[x] because it keeps an
    exact analytic inverse: x = p^-1(H^-1[y]), H^-1 being Kuhnen's inverse PI (play operators on
    y) and p^-1 a memoryless scalar root; the additive form would need a sequential solve at
    every turning point.

    Requirements (checked, ValueError naming the parameter): thresholds 0 = r_0 < r_1 < ...;
    every partial sum w_0 + ... + w_i > 0 (the slope of any branch, so y is strictly
    increasing in x and H is invertible); p' > 0 on the whole real line. Unit-agnostic: input
    and output in the same unit (metres of nominal displacement, or volts times a gain).
    """

    def __init__(self, thresholds, weights, polynomial=(1.0, 0.0, 0.0)):
        r = np.asarray(thresholds, dtype=float)
        w = np.asarray(weights, dtype=float)
        if (
            r.ndim != 1
            or r.size == 0
            or not np.isfinite(r).all()
            or r[0] != 0.0
            or (np.diff(r) <= 0).any()
        ):
            raise ValueError(
                f"thresholds={thresholds!r}: need finite values 0 = r_0 < r_1 < ... < r_n"
            )
        if w.shape != r.shape or not np.isfinite(w).all():
            raise ValueError(
                f"weights={weights!r}: need one finite weight per threshold ({r.size})"
            )
        partial = np.cumsum(w)
        if (partial <= 0).any():
            i = int(np.argmax(partial <= 0))
            raise ValueError(
                f"weights={weights!r}: partial sum w_0 + ... + w_{i} = {partial[i]:.4g} "
                "must be > 0 (the model would not be strictly increasing and has no inverse)"
            )
        self._poly = _check_polynomial(polynomial)
        self._w = w.copy()
        self._bank = PlayOperatorBank(r)

    @classmethod
    def from_fraction(
        cls, span: float, hysteresis_fraction: float, n: int = 8, asymmetry: float = 0.0
    ) -> PrandtlIshlinskii:
        """A physically typical model for inputs spanning [-span/2, span/2] around zero.

        Full-span triangle cycles give a major loop whose tips (where the branches meet) are
        span apart, so the output spans what the input spans, with loop width (largest vertical
        distance between the branches) exactly hysteresis_fraction * span, for any asymmetry.
        Thresholds r_i = i/(2n) * span/2 with equal weights for i >= 1 (all r_i < a quarter span,
        so the width is flat around the loop centre); w_0 makes the tip-to-tip gain 1.

        asymmetry (alpha, dimensionless): p(xi) = (1 - alpha^2) xi + alpha xi^2 + alpha^2 xi^3 in
        xi = x / (span/2): the branch slope grows from 1 - 2 alpha + 2 alpha^2 at the bottom of
        the range to 1 + 2 alpha + 2 alpha^2 at the top, and the loop is lifted by about
        alpha * span / 2 at the tips. The cubic term is the smallest that keeps p increasing on
        the whole real line (needs alpha^2 < 2/3). alpha = 0 is the symmetric classic PI.
        """
        if not (math.isfinite(span) and span > 0):
            raise ValueError(f"span={span}: must be finite and > 0")
        if int(n) != n or n < 2:
            raise ValueError(f"n={n}: need at least 2 play operators")
        if not (math.isfinite(hysteresis_fraction) and 0.0 <= hysteresis_fraction < 1.0 / 3.0):
            raise ValueError(
                f"hysteresis_fraction={hysteresis_fraction}: must be in [0, 1/3) "
                "(wider loops would need w_0 <= 0 with these thresholds)"
            )
        if not (math.isfinite(asymmetry) and asymmetry * asymmetry < 2.0 / 3.0):
            raise ValueError(
                f"asymmetry={asymmetry}: need asymmetry^2 < 2/3 for a monotone input function"
            )
        n = int(n)
        half = 0.5 * span
        rho = np.arange(n) / (2.0 * n)  # thresholds in units of the amplitude
        c = hysteresis_fraction / rho[1:].sum()  # width = span * sum_i w_i rho_i
        weights = np.full(n, c)
        weights[0] = 1.0 - c * (1.0 - rho[1:]).sum()  # tip-to-tip: sum_i w_i (1 - rho_i) = 1
        a = asymmetry
        return cls(rho * half, weights, (1.0 - a * a, a / half, a * a / half**2))

    @property
    def polynomial(self) -> tuple[float, float, float]:
        return self._poly

    def reset(self, x0: float = 0.0) -> None:
        """Demagnetised at x0; the output at rest there is sum(w) * p(x0)."""
        self._bank.reset(_polynomial(float(x0), self._poly))

    def apply(self, x) -> np.ndarray:
        x = _as_sequence(x, "x")
        return self._bank.apply(_polynomial(x, self._poly)) @ self._w

    def inverse(self) -> InversePrandtlIshlinskii:
        """The exact inverse, its state matched to this model's current state."""
        return InversePrandtlIshlinskii(self)


class InversePrandtlIshlinskii(_WeightedPlayBank):
    """x = p^-1(H^-1[y]) for a PrandtlIshlinskii y = H[p(x)] (book eq. 5.24-5.28, Kuhnen).

    H^-1 is again a PI: thresholds r'_i = sum_{j<=i} w_j (r_i - r_j) (the initial loading curve
    at r_i), weights w'_0 = 1/w_0, w'_i = 1/W_i - 1/W_{i-1} with W_i = w_0 + ... + w_i (its
    slopes are the reciprocals of the forward slopes), states
    z'_i = W_i z_i + sum_{j>i} w_j z_j. Has the feed-forward interface (apply, reset)."""

    def __init__(self, model: PrandtlIshlinskii):
        r, w = model.thresholds, model.weights
        partial = np.cumsum(w)
        inverse_thresholds = np.array([w[: i + 1] @ (r[i] - r[: i + 1]) for i in range(r.size)])
        self._w = np.empty_like(w)
        self._w[0] = 1.0 / w[0]
        self._w[1:] = -w[1:] / (partial[1:] * partial[:-1])
        self._poly = model.polynomial
        self._bank = PlayOperatorBank(inverse_thresholds)
        z = model.state
        tail = np.append(np.cumsum((w * z)[::-1])[::-1][1:], 0.0)
        self._bank.state = partial * z + tail

    def reset(self, y0: float = 0.0) -> None:
        """Demagnetised at output y0: matches the forward model's reset(x0) when
        y0 = sum(w) p(x0)."""
        self._bank.reset(float(y0))

    def apply(self, y) -> np.ndarray:
        y = _as_sequence(y, "y")
        return _polynomial_inverse(self._bank.apply(y) @ self._w, self._poly)


# -- creep ------------------------------------------------------------------------------------


class Creep:
    """Book eq. 5.29-5.31: x_i(k) = e^{-lambda_i T} x_i(k-1) + (1 - e^{-lambda_i T}) u(k-1),
    y(k) = sum_i c_i x_i(k) + a u(k).

    Timing: the operators see u(k-1), which is the exact zero-order-hold discretisation of
    dx_i/dt = lambda_i (u - x_i) with u(k) held over [kT, (k+1)T). Sample k of the output is
    therefore the continuous response at t = kT: a step applied at sample 0 reaches the
    operators from sample 1 on, and the samples equal step_response(k T) exactly (no extra
    delay to correct for). Settled gain a + sum(c); the scanner uses a = 1 - sum(c) so that
    creep only delays, never rescales, a move."""

    def __init__(self, inverse_time_constants, weights, direct_gain: float = 1.0):
        lam = np.asarray(inverse_time_constants, dtype=float)
        c = np.asarray(weights, dtype=float)
        if lam.ndim != 1 or not np.isfinite(lam).all() or (lam <= 0).any():
            raise ValueError(
                f"inverse_time_constants={inverse_time_constants!r}: need finite values > 0 (1/s)"
            )
        if c.shape != lam.shape or not np.isfinite(c).all():
            raise ValueError(
                f"weights={weights!r}: need one finite weight per time constant ({lam.size})"
            )
        if not math.isfinite(direct_gain):
            raise ValueError(f"direct_gain={direct_gain}: must be finite")
        self._lam, self._c, self._a = lam.copy(), c.copy(), float(direct_gain)
        self._x = np.zeros(lam.size)
        self._u_last = 0.0

    @property
    def state(self) -> np.ndarray:
        """[x_1, ..., x_m, u_last]: the operators and the input they have not yet seen."""
        return np.append(self._x, self._u_last)

    @state.setter
    def state(self, value) -> None:
        s = np.asarray(value, dtype=float)
        if s.shape != (self._x.size + 1,) or not np.isfinite(s).all():
            raise ValueError(
                f"state: expected {self._x.size + 1} finite values, got shape {s.shape}"
            )
        self._x, self._u_last = s[:-1].copy(), float(s[-1])

    def reset(self, u0: float = 0.0) -> None:
        """Settled at u0, as after a long rest there."""
        self._x = np.full(self._lam.size, float(u0))
        self._u_last = float(u0)

    def apply(self, u, dt: float) -> np.ndarray:
        u = _as_sequence(u, "u")
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt={dt}: must be finite and > 0 (s)")
        if u.size == 0:
            return np.empty(0)
        decay = np.exp(-self._lam * dt)
        gain = -np.expm1(-self._lam * dt)
        operators = np.empty((u.size, self._lam.size))
        for i in range(self._lam.size):
            first = decay[i] * self._x[i] + gain[i] * self._u_last  # x_i at this call's sample 0
            operators[:, i] = lfilter([0.0, gain[i]], [1.0, -decay[i]], u, zi=[first])[0]
        self._x, self._u_last = operators[-1].copy(), float(u[-1])
        return operators @ self._c + self._a * u

    def step_response(self, t) -> np.ndarray:
        """Output for a unit step at t = 0 from rest at 0: a + sum_i c_i (1 - exp(-lambda_i t))."""
        t = np.asarray(t, dtype=float)
        rise = -np.expm1(-np.multiply.outer(np.maximum(t, 0.0), self._lam)) @ self._c
        return np.where(t >= 0, self._a + rise, 0.0)


# -- slew-rate limit --------------------------------------------------------------------------


def _slew_end(x: np.ndarray, k: int, previous: float, step: float) -> int:
    """First index >= k at which a ramp from `previous` by `step` per sample no longer falls
    short of x (the ramp has caught up). Searched in doubling chunks: O(ramp length)."""
    size = 64
    start = k
    while start < x.size:
        stop = min(x.size, start + size)
        ramp = previous + step * np.arange(start - k + 1, stop - k + 1)
        caught = (x[start:stop] < ramp) if step > 0 else (x[start:stop] > ramp)
        if caught.any():
            return start + int(np.argmax(caught))
        start, size = stop, 2 * size
    return x.size


def limit_slew(samples, dt: float, max_speed: float, start: float | None = None) -> np.ndarray:
    """A copy of `samples` in which no step exceeds max_speed * dt (to rounding):
    y(k) = clip(x(k), y(k-1) - d, y(k-1) + d), y(-1) = start (default: the first sample). Where x
    moves slower than the limit the output is x itself; elsewhere it ramps at full speed until it
    catches up.

    Processed in runs (tracking runs end at the next too-fast step, ramps where they meet x),
    each vectorised, so the Python work is per run, not per sample."""
    x = _as_sequence(samples, "samples")
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt={dt}: must be finite and > 0 (s)")
    if not max_speed > 0:
        raise ValueError(f"max_speed={max_speed}: must be > 0 (m/s)")
    y = np.empty_like(x)
    if x.size == 0:
        return y
    d = max_speed * dt
    previous = float(x[0]) if start is None else float(start)
    fast_steps = np.flatnonzero(np.abs(np.diff(x)) > d) + 1
    k = 0
    while k < x.size:
        if abs(x[k] - previous) <= d:
            following = np.searchsorted(fast_steps, k, side="right")
            end = int(fast_steps[following]) if following < fast_steps.size else x.size
            y[k:end] = x[k:end]
        else:
            step = d if x[k] > previous else -d
            end = _slew_end(x, k, previous, step)
            y[k:end] = previous + step * np.arange(1, end - k + 1)
        previous, k = float(y[end - 1]), end
    return y


# -- the scanner --------------------------------------------------------------------------------


@dataclass
class ScannerParams:
    """Lateral scanner imperfections (SI units). Each effect has an `*_enabled` flag; a zero
    parameter (no hysteresis width and no asymmetry, no creep, no coupling, no angle) disables
    it exactly too. Values are typical for a tube scanner (book 5.3, Dimension 3100) and are
    meant to be identified on the real instrument."""

    range_x: float = 110e-6  # m, x travel: commands are [0, range_x]
    range_y: float = 110e-6  # m
    clamp_to_range: bool = True  # the amplifier saturates: commands clipped to [0, range]
    hysteresis_enabled: bool = True
    hysteresis_fraction: float = 0.12  # loop width / range on full-range cycles (piezos: 10-15 %)
    hysteresis_asymmetry: float = 0.03  # alpha of PrandtlIshlinskii.from_fraction (0 = symmetric)
    hysteresis_operators: int = 8  # play operators per axis
    creep_enabled: bool = True
    creep_time_constants: list[float] = field(default_factory=lambda: [0.5, 5.0, 50.0])  # s
    creep_fractions: list[float] = field(
        default_factory=lambda: [0.008, 0.006, 0.006]
    )  # of a step, each
    coupling_enabled: bool = True
    coupling_x_to_y: float = 0.01  # y displacement per unit x displacement
    coupling_y_to_x: float = 0.01  # x displacement per unit y displacement
    deflection_enabled: bool = True
    deflection_deg: float = (
        0.746  # scan-line rotation, counter-clockwise (book: mean 0.746, sd 0.393)
    )
    positioning_noise_enabled: bool = (
        True  # random, persistent error of every tip move (book eq. 5.5 w)
    )
    positioning_noise_slope: float = (
        0.0701e-9  # m^2 per m moved, each axis (Fig. 7.20b: a = 0.0701 nm^2/nm)
    )
    positioning_noise_offset: float = (
        0.4345e-18  # m^2 per move, each axis (Fig. 7.20b: b = 0.4345 nm^2)
    )
    # Scanner bow, a z artefact (not lateral, so LateralScanner ignores it; the simulated
    # instrument adds it to measured heights): the tube's free end swings on a sphere-like
    # arc, so the tip rises by 0.5 * bow_curvature * r^2 at a distance r from the range centre.
    bow_curvature: float = 0.0  # 1/m (0 = no bow; a 5 cm tube: ~20 1/m)

    def __post_init__(self):
        self.validate()

    def validate(self) -> None:
        for name in ("range_x", "range_y"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"scanner.{name}={value}: must be finite and > 0 (m)")
        if not (
            math.isfinite(self.hysteresis_fraction) and 0.0 <= self.hysteresis_fraction < 1.0 / 3.0
        ):
            raise ValueError(
                f"scanner.hysteresis_fraction={self.hysteresis_fraction}: must be in [0, 1/3)"
            )
        if not (
            math.isfinite(self.hysteresis_asymmetry) and self.hysteresis_asymmetry**2 < 2.0 / 3.0
        ):
            raise ValueError(
                f"scanner.hysteresis_asymmetry={self.hysteresis_asymmetry}: need alpha^2 < 2/3"
            )
        if (
            int(self.hysteresis_operators) != self.hysteresis_operators
            or self.hysteresis_operators < 2
        ):
            raise ValueError(
                f"scanner.hysteresis_operators={self.hysteresis_operators}: need an integer >= 2"
            )
        taus, fractions = list(self.creep_time_constants), list(self.creep_fractions)
        if len(taus) != len(fractions) or not all(math.isfinite(t) and t > 0 for t in taus):
            raise ValueError(
                f"scanner.creep_time_constants={taus}: need one finite value > 0 (s) per fraction"
            )
        if not all(math.isfinite(c) and c >= 0 for c in fractions) or sum(fractions) >= 1.0:
            raise ValueError(
                f"scanner.creep_fractions={fractions}: need values >= 0 summing to < 1"
            )
        for name in ("coupling_x_to_y", "coupling_y_to_x"):
            value = getattr(self, name)
            if not (math.isfinite(value) and abs(value) < 1.0):
                raise ValueError(f"scanner.{name}={value}: must be finite with |value| < 1")
        for name in ("positioning_noise_slope", "positioning_noise_offset"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"scanner.{name}={value}: must be finite and >= 0")
        if not math.isfinite(self.deflection_deg):
            raise ValueError(f"scanner.deflection_deg={self.deflection_deg}: must be finite")
        if not math.isfinite(self.bow_curvature):
            raise ValueError(f"scanner.bow_curvature={self.bow_curvature}: must be finite (1/m)")
        # the bow at the range corners must fit well inside any z range (7 um on the book's AFM)
        corner_bow = 0.5 * abs(self.bow_curvature) * 0.25 * (self.range_x**2 + self.range_y**2)
        if corner_bow > 1e-6:
            raise ValueError(
                f"scanner.bow_curvature={self.bow_curvature}: bows the range corners by "
                f"{corner_bow:.3g} m; at most 1e-6 m (|curvature| <= ~330 1/m on 110 um)"
            )


class ScannerAxis:
    """One piezo axis: command (m) -> clamp to [0, range] -> hysteresis -> creep -> position (m).

    The hysteresis acts on the deviation from mid-range, the neutral position of a tube
    scanner, so full-range cycles trace a loop whose tips are the range ends (calibrated gain
    1, as a sensitivity measured on a grating by full-range scans would give)."""

    def __init__(self, range_m: float, params: ScannerParams):
        self.range = float(range_m)
        self.centre = 0.5 * self.range
        self.clamp = params.clamp_to_range
        has_loop = params.hysteresis_fraction > 0 or params.hysteresis_asymmetry != 0
        self.hysteresis = (
            PrandtlIshlinskii.from_fraction(
                self.range,
                params.hysteresis_fraction,
                int(params.hysteresis_operators),
                params.hysteresis_asymmetry,
            )
            if params.hysteresis_enabled and has_loop
            else None
        )
        fractions = np.asarray(params.creep_fractions, dtype=float)
        self.creep = (
            Creep(
                1.0 / np.asarray(params.creep_time_constants, dtype=float),
                fractions,
                1.0 - fractions.sum(),
            )
            if params.creep_enabled and fractions.any()
            else None
        )
        self.reset(self.centre)

    def _clamped(self, cmd: np.ndarray) -> np.ndarray:
        return np.clip(cmd, 0.0, self.range) if self.clamp else cmd.copy()

    def reset(self, x0: float) -> None:
        """At rest at command x0 after power-on: demagnetised at mid-range, moved straight to
        x0 and left to settle (so the output there is on the initial loading curve)."""
        position = float(self._clamped(np.array([float(x0)]))[0])
        if self.hysteresis is not None:
            self.hysteresis.reset(0.0)
            position = self.centre + self.hysteresis.apply([0.0, position - self.centre])[-1]
        if self.creep is not None:
            self.creep.reset(position)

    def apply(self, cmd, dt: float) -> np.ndarray:
        position = self._clamped(_as_sequence(cmd, "cmd"))
        if self.hysteresis is not None:
            position = self.centre + self.hysteresis.apply(position - self.centre)
        if self.creep is not None:
            position = self.creep.apply(position, dt)
        return position

    def state(self) -> dict:
        return {
            "hysteresis": None if self.hysteresis is None else self.hysteresis.state,
            "creep": None if self.creep is None else self.creep.state,
        }

    def set_state(self, state: dict) -> None:
        if self.hysteresis is not None:
            self.hysteresis.state = state["hysteresis"]
        if self.creep is not None:
            self.creep.state = state["creep"]


class LateralScanner:
    """Both lateral axes: each through its ScannerAxis, then the x/y cross-coupling and the
    scan-line deflection, both linear about the range centre (the tube's neutral position):
    true - centre = R(deflection) @ [[1, c_yx], [c_xy, 1]] @ (axis outputs - centre)."""

    def __init__(self, params: ScannerParams | None = None):
        self.params = params if params is not None else ScannerParams()
        self.params.validate()
        self.axes = (
            ScannerAxis(self.params.range_x, self.params),
            ScannerAxis(self.params.range_y, self.params),
        )
        self.centre = np.array([axis.centre for axis in self.axes])
        self.mixing = self._mixing_matrix(self.params)

    @staticmethod
    def _mixing_matrix(params: ScannerParams) -> np.ndarray | None:
        """None when there is nothing to mix, so the disabled path is exactly the identity."""
        matrix = np.eye(2)
        if params.coupling_enabled and (params.coupling_x_to_y or params.coupling_y_to_x):
            matrix = np.array([[1.0, params.coupling_y_to_x], [params.coupling_x_to_y, 1.0]])
        if params.deflection_enabled and params.deflection_deg:
            theta = math.radians(params.deflection_deg)
            rotation = np.array(
                [[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]]
            )
            matrix = rotation @ matrix
        return None if (matrix == np.eye(2)).all() else matrix

    def reset(self, x0: float | None = None, y0: float | None = None) -> None:
        """At rest at command (x0, y0) (default: the range centre); see ScannerAxis.reset."""
        for axis, value in zip(self.axes, (x0, y0)):
            axis.reset(axis.centre if value is None else value)

    def apply(self, cmd_x, cmd_y, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """True positions (m) for uniformly sampled commands (m) at period dt (s)."""
        cmd_x, cmd_y = _as_sequence(cmd_x, "cmd_x"), _as_sequence(cmd_y, "cmd_y")
        if cmd_x.shape != cmd_y.shape:
            raise ValueError(
                f"cmd_x and cmd_y: need equal lengths, got {cmd_x.size} and {cmd_y.size}"
            )
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt={dt}: must be finite and > 0 (s)")
        x, y = (axis.apply(cmd, dt) for axis, cmd in zip(self.axes, (cmd_x, cmd_y)))
        if self.mixing is None:
            return x, y
        dx, dy = x - self.centre[0], y - self.centre[1]
        (m00, m01), (m10, m11) = self.mixing
        return self.centre[0] + m00 * dx + m01 * dy, self.centre[1] + m10 * dx + m11 * dy

    def state(self) -> dict:
        """A snapshot (copies) to restore with set_state."""
        return {"x": self.axes[0].state(), "y": self.axes[1].state()}

    def set_state(self, state: dict) -> None:
        self.axes[0].set_state(state["x"])
        self.axes[1].set_state(state["y"])
