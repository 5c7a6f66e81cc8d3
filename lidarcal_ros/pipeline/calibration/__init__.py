"""Calibration of a mission, batch and live (the calibrator node's work)."""
