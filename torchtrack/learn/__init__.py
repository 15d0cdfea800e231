"""Offline and online learning: boosting with feature selection, SVM export, calibration."""
