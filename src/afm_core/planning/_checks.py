"""Input checks shared by the planning modules: each raises ValueError naming the field and the limit."""

from __future__ import annotations

import math

import numpy as np

from afm_core.localization.motion_noise import MotionNoise

PSD_TOLERANCE = (
    1e-30  # m^2: eigenvalues down to -this count as zero (rounding of nm^2-sized numbers)
)


def point(value, name: str) -> np.ndarray:
    try:
        p = np.array(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(
            f"{name}: must be an (x, y) pair of numbers in metres, got {value!r}"
        ) from None
    if p.shape != (2,):
        raise ValueError(f"{name}: must be an (x, y) pair in metres, got {p.size} values")
    if not np.isfinite(p).all():
        raise ValueError(f"{name}: must be finite, got {p.tolist()}")
    return p


def covariance(value, name: str) -> np.ndarray:
    try:
        c = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(
            f"{name}: must be a 2x2 covariance matrix in m^2, got {value!r}"
        ) from None
    if c.shape != (2, 2):
        raise ValueError(f"{name}: must be a 2x2 covariance matrix in m^2, got shape {c.shape}")
    if not np.isfinite(c).all():
        raise ValueError(f"{name}: must be finite, got {c.tolist()}")
    if abs(c[0, 1] - c[1, 0]) > 1e-9 * max(abs(c[0, 0]), abs(c[1, 1]), PSD_TOLERANCE):
        raise ValueError(f"{name}: must be symmetric, got off-diagonal {c[0, 1]} and {c[1, 0]}")
    c = 0.5 * (c + c.T)
    smallest = float(np.linalg.eigvalsh(c)[0])
    if smallest < -PSD_TOLERANCE:
        raise ValueError(
            f"{name}: must be positive semi-definite, smallest eigenvalue {smallest} m^2 < 0"
        )
    return c


def positive(value, name: str, allow_zero: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: must be a number, got {value!r}") from None
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        limit = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name}={value}: must be finite and {limit}")
    return v


def sigma_pair(value, name: str, allow_zero: bool = False) -> np.ndarray:
    """A (sigma_x, sigma_y) pair or one number for both, in metres."""
    try:
        s = np.broadcast_to(np.array(value, dtype=float).reshape(-1), (2,)).copy()
    except (TypeError, ValueError):
        raise ValueError(
            f"{name}: must be a number or an (x, y) pair of standard deviations in metres, "
            f"got {value!r}"
        ) from None
    for axis, v in zip("xy", s):
        positive(v, f"{name} ({axis})", allow_zero)
    return s


def motion_noise(value, name: str = "noise") -> MotionNoise:
    if not isinstance(value, MotionNoise):
        raise ValueError(
            f"{name}: must be an afm_core.localization.MotionNoise, got {type(value).__name__}"
        )
    return value


def direction(value, name: str = "direction") -> int:
    """'h' (a line along x) -> axis 0, 'v' (along y) -> axis 1."""
    if value not in ("h", "v"):
        raise ValueError(f"{name}={value!r}: must be 'h' (line along x) or 'v' (line along y)")
    return 0 if value == "h" else 1
