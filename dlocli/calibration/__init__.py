"""Fit a simulated rod to a recorded cable: replay, calibration, simulated marker data."""
