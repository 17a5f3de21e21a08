"""Tip localization: calibrated motion model and landmark Kalman filter."""
