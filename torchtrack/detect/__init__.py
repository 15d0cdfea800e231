"""Detectors: window + features + classifier + calibrator; safe model files; scanning."""

from torchtrack.detect.detector import Detector
from torchtrack.detect.model_file import load_detector, read_model_metadata, save_detector

__all__ = ["Detector", "load_detector", "read_model_metadata", "save_detector"]
