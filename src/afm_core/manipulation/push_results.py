"""What a push and an assembly report: progress while they run, the result when they end, and
the two ways they stop short (refused before anything moved, failed after)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from afm_core.manipulation.closed_loop import PushCost
from afm_core.manipulation.execute import ExecutionResult
from afm_core.manipulation.plans import PushPlan
from afm_core.manipulation.push_steps import TipEstimate
from afm_core.manipulation.verdict import PushVerdict
from afm_core.manipulation.verify import VerificationResult


class PushRefused(Exception):
    """A push (or an assembly) refused before anything moved; the message says why."""


class PushFailed(Exception):
    """A push that started could not finish, or was cancelled; the message says what happened
    and where things are. `execution`: the strokes run, when the failure came after them."""

    def __init__(self, message: str, execution: ExecutionResult | None = None):
        super().__init__(message)
        self.execution = execution


@dataclass(frozen=True)
class Progress:
    """One progress report. phase: "scanning" (step: control pits made of steps_total, the
    before image the last), "localizing", "pushing" (step 0 before the first stroke, then
    after each), "observing" (closed_loop: after a leg, what the local scan lines found, in
    `note`, with why the leg ended), "verifying". A closed-loop push reports each leg's plan
    on its first "pushing" report, its steps counted within the leg."""

    phase: str
    particle_id: int
    particle_estimate: np.ndarray  # (2,) task frame, m
    particle_covariance: np.ndarray  # (2, 2) m^2, the map's
    time: float  # s, instrument clock
    step: int = 0
    steps_total: int = 0
    tip: TipEstimate | None = None
    peak_lateral_force: float = 0.0  # N, this stroke
    peak_normal_force: float = 0.0  # N
    plan: PushPlan | None = None  # on the report before the first stroke: the strokes planned
    index: int = 0  # position in an assembly's order
    note: str = ""  # closed_loop: why the leg ended (a stroke) / what was observed and decided
    # What particle_estimate is for a live view: PREDICTED (the push model after the strokes
    # done, no measurement since), OBSERVED (local scan lines saw it; belief_covariance is the
    # observation's), or "" (the map's or the plan's position, nothing new)
    belief: str = ""
    belief_covariance: np.ndarray | None = None  # (2, 2) m^2 when known


@dataclass
class PushResult:
    particle_id: int
    goal: np.ndarray  # (2,) task frame
    achieved: np.ndarray  # (2,) verified position after the rescan, task frame
    error: float  # m, |achieved - goal|
    tolerance: float  # m
    steps: int  # strokes in contact
    message: str
    plan: PushPlan
    execution: ExecutionResult
    verification: VerificationResult
    cost: PushCost = field(default_factory=PushCost)
    # a tube or rod: its axis's goal, verified angle (task frame, rad) and the error between
    # them folded into a half turn; NaN for a sphere
    goal_angle: float = math.nan
    achieved_angle: float = math.nan
    angle_error: float = math.nan  # rad, >= 0
    angle_tolerance: float = math.nan  # rad
    # the rescan's measurement: error with its sigma and whether it supports "within
    # tolerance" (afm_core.manipulation.verdict); None: judged by error <= tolerance alone
    verdict: PushVerdict | None = None

    @property
    def success(self) -> bool:
        """Within tolerance as far as the rescan can tell (verdict WITHIN), the angle too."""
        turned = (
            not math.isfinite(self.angle_tolerance) or self.angle_error <= self.angle_tolerance
        )
        within = self.error <= self.tolerance if self.verdict is None else self.verdict.within
        return within and turned


@dataclass
class AssemblyResult:
    particle_ids: list[int]  # as given
    order: list[int]  # as pushed (or planned, when a push failed)
    # per particle_ids: verified position, or the map's if not pushed (one already within
    # tolerance is not pushed, and its error is the map's distance)
    achieved: list[np.ndarray]
    errors: list[float]  # per particle_ids, m (NaN: not pushed, not within tolerance)
    success: bool
    message: str
    pushes: list[PushResult] = field(default_factory=list)
