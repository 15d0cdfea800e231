"""Detectors: window + features + classifier + calibrator; safe model files; scanning."""

from torchtrack.detect.detector import Detector
from torchtrack.detect.heads import (
    IsotonicCalibrator,
    KernelScorer,
    SigmoidCalibrator,
    StumpScorer,
    calibrator_from_estimator,
    scorer_from_estimator,
)
from torchtrack.detect.model_file import load_detector, read_model_metadata, save_detector

__all__ = [
    "Detector",
    "IsotonicCalibrator",
    "KernelScorer",
    "SigmoidCalibrator",
    "StumpScorer",
    "calibrator_from_estimator",
    "load_detector",
    "read_model_metadata",
    "save_detector",
    "scorer_from_estimator",
]
