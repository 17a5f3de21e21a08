"""Checks of the planner's service requests, naming the request field (start.pose.pose.position.x,
not the planning library's start_mean) and its limit. Each raises ValueError."""

from __future__ import annotations

import math

import numpy as np

from afm_core import checks
from afm_core.planning import (
    MAX_ACO_POINTS,
    MAX_HEURISTIC_POINTS,
    MAX_SEQUENCE_LANDMARKS,
)
from afm_core.planning._checks import PSD_TOLERANCE
from afm_ros.conversions import FRAME_TASK

SHOWN_IDS = 8  # ids listed in an unknown-id message; the rest are counted
COVARIANCE_FIELDS = ((0, "[0] (xx)"), (1, "[1] (xy)"), (6, "[6] (yx)"), (7, "[7] (yy)"))


def start_frame(name: str, pose) -> None:
    """The start must be in afm_task; an empty frame_id (an unset header) is taken as afm_task,
    the frame every plan is in."""
    frame = pose.header.frame_id
    if frame not in ("", FRAME_TASK):
        raise ValueError(
            f"{name}.header.frame_id={frame!r}: must be {FRAME_TASK!r} (or empty); the planner "
            "does not transform poses"
        )


def pose_mean_cov(name: str, pose) -> tuple[np.ndarray, np.ndarray]:
    """x, y and the 2x2 x/y covariance of a PoseWithCovarianceStamped, checked: finite, the
    covariance symmetric and positive semi-definite."""
    position = pose.pose.pose.position
    mean = np.array(
        [
            checks.finite(f"{name}.pose.pose.position.x", position.x, "m"),
            checks.finite(f"{name}.pose.pose.position.y", position.y, "m"),
        ]
    )
    c = pose.pose.covariance
    for index, label in COVARIANCE_FIELDS:
        checks.finite(f"{name}.pose.covariance{label}", c[index], "m^2")
    cov = np.array([[c[0], c[1]], [c[6], c[7]]], float)
    if abs(cov[0, 1] - cov[1, 0]) > 1e-9 * max(abs(cov[0, 0]), abs(cov[1, 1]), PSD_TOLERANCE):
        raise ValueError(
            f"{name}.pose.covariance: [1] (xy) = {cov[0, 1]:.4g} and [6] (yx) = {cov[1, 0]:.4g} "
            "m^2 must be equal (symmetric)"
        )
    smallest = float(np.linalg.eigvalsh(0.5 * (cov + cov.T))[0])
    if smallest < -PSD_TOLERANCE:
        raise ValueError(
            f"{name}.pose.covariance: the x/y block [0, 1, 6, 7] must be positive semi-definite; "
            f"its smallest eigenvalue is {smallest:.4g} m^2"
        )
    return mean, cov


def required_sigma(value: float) -> float | None:
    """required_sigma: 0 means as small as possible (None); negative, NaN or inf is refused."""
    sigma = checks.non_negative("required_sigma", value, "m")
    return sigma if sigma > 0 else None


def landmark_id(value: int) -> int:
    """-1: use position and radius; otherwise an id >= 0."""
    if value < -1:
        raise ValueError(
            f"landmark_id={value}: must be -1 (use position and radius) or a landmark's id >= 0"
        )
    return value


def point(name: str, p) -> np.ndarray:
    return np.array([checks.finite(f"{name}.x", p.x, "m"), checks.finite(f"{name}.y", p.y, "m")])


def unknown_id(name: str, value: int, known) -> ValueError:
    """An unknown landmark id, listing at most SHOWN_IDS of the known ones."""
    known = sorted(known)
    listed = checks.few(known, SHOWN_IDS) if known else "none yet"
    return ValueError(f"{name}={value}: unknown (known ids: {listed})")


def sequence_size(method: str, request) -> None:
    """Refuse up front a PlanSequence that would hold the planner too long (limits.py)."""
    ids = len(request.landmark_ids)
    if ids > MAX_SEQUENCE_LANDMARKS:
        raise ValueError(
            f"landmark_ids: {ids} landmarks; at most {MAX_SEQUENCE_LANDMARKS} (their "
            "observation distances take ~0.35 ms per pair); order positions instead, or split "
            "the set"
        )
    n = ids or len(request.positions) or math.isqrt(len(request.distance_matrix))
    field = (
        "landmark_ids"
        if ids
        else ("positions" if request.positions else "distance_matrix (n x n values)")
    )
    if method == "aco" and n > MAX_ACO_POINTS:
        raise ValueError(
            f"{field}: {n} points for method='aco'; at most {MAX_ACO_POINTS} (about 5 s); "
            f"use method='heuristic' (up to {MAX_HEURISTIC_POINTS})"
        )
    if method in ("heuristic", "best") and n > MAX_HEURISTIC_POINTS:
        raise ValueError(
            f"{field}: {n} points for method={method!r}; at most {MAX_HEURISTIC_POINTS} "
            "(about 3 s); split the set"
        )


def positions(request) -> np.ndarray:
    points = np.array([[p.x, p.y] for p in request.positions], float).reshape(-1, 2)
    bad = np.flatnonzero(~np.isfinite(points).all(axis=1))
    if bad.size:
        k = int(bad[0])
        raise ValueError(
            f"positions[{k}]=({points[k, 0]:.4g}, {points[k, 1]:.4g}): must be finite (m)"
            + (f"; {bad.size - 1} more not finite" if bad.size > 1 else "")
        )
    return points


# the planning library's argument names -> the request fields they come from
LIBRARY_NAMES = (
    ("start_mean", "start.pose.pose.position"),
    ("start_covariance", "start.pose.covariance"),
    ("tip_mean", "start.pose.pose.position"),
    ("tip_covariance", "start.pose.covariance"),
    ("task_point", "target"),
    ("particle_center", "position"),
    ("particle_radius", "radius (or the landmark's radius)"),
)


def request_names(message: str) -> str:
    """A planning library's refusal with its leading argument name replaced by the request
    field it came from."""
    for library, field in LIBRARY_NAMES:
        if message.startswith(library):
            return field + message[len(library) :]
    return message
