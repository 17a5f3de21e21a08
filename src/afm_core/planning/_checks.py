"""Input checks of the planning modules beyond afm_core.checks: a point the plans keep, a
covariance, a sigma pair, the motion noise and a line direction. Each takes the field's name
first and the value second, and raises ValueError naming the field and the limit.
"""

from __future__ import annotations

import numpy as np

from afm_core import checks
from afm_core.localization.motion_noise import MotionNoise

PSD_TOLERANCE = (
    1e-30  # m^2: eigenvalues down to -this count as zero (rounding of nm^2-sized numbers)
)


def point_copy(name: str, value) -> np.ndarray:
    """A finite (x, y) point in metres (afm_core.checks.point), as a copy: the plans keep it,
    and a caller's array changed afterwards must not change them."""
    return checks.point(name, value).copy()


def covariance_matrix(name: str, value) -> np.ndarray:
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


def sigma_pair(name: str, value) -> np.ndarray:
    """A (sigma_x, sigma_y) pair or one number for both, in metres."""
    try:
        s = np.broadcast_to(np.array(value, dtype=float).reshape(-1), (2,)).copy()
    except (TypeError, ValueError):
        raise ValueError(
            f"{name}: must be a number or an (x, y) pair of standard deviations in metres, "
            f"got {value!r}"
        ) from None
    for axis, v in zip("xy", s):
        checks.positive(f"{name} ({axis})", v, "m")
    return s


def noise_model(name: str, value) -> MotionNoise:
    if not isinstance(value, MotionNoise):
        raise ValueError(
            f"{name}: must be an afm_core.localization.MotionNoise, got {type(value).__name__}"
        )
    return value


def line_axis(name: str, value) -> int:
    """'h' (a line along x) -> axis 0, 'v' (along y) -> axis 1."""
    if value not in ("h", "v"):
        raise ValueError(f"{name}={value!r}: must be 'h' (line along x) or 'v' (line along y)")
    return 0 if value == "h" else 1
