"""Tip localization: the motion model, calibration, landmark observation and the Kalman filter."""
from .motion_noise import MotionNoise

__all__ = ["MotionNoise"]
