"""Tip localization: the motion model, calibration, landmark observation and the Kalman filter."""

from .filter import GATE_CHI2_1DOF_99, GATE_CHI2_1DOF_999, TipFilter, UpdateResult
from .landmark_observation import (
    LineObservation,
    MapLandmark,
    find_crossings,
    observation_variance,
    observe_line,
)
from .localizer import LineResult, Localizer, MoveOutcome, ObservationResult
from .motion import DRIFT_SIGN, MotionModel, MotionState, MotionStep
from .motion_noise import MotionNoise

__all__ = [
    "MotionNoise",
    "MotionModel",
    "MotionState",
    "MotionStep",
    "DRIFT_SIGN",
    "MapLandmark",
    "LineObservation",
    "observe_line",
    "find_crossings",
    "observation_variance",
    "TipFilter",
    "UpdateResult",
    "GATE_CHI2_1DOF_99",
    "GATE_CHI2_1DOF_999",
    "Localizer",
    "LineResult",
    "ObservationResult",
    "MoveOutcome",
]
