"""Detectors: window + features + classifier + calibrator; safe model files; scanning."""
