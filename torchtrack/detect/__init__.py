"""Detectors: window + features + classifier + calibrator; safe, signable model files; scanning."""

from torchtrack.detect.detector import Detector
from torchtrack.detect.model_file import (
    load_detector,
    model_signature,
    read_model_metadata,
    save_detector,
    sign_model,
)
from torchtrack.detect.signing import TrustPolicy, generate_key

__all__ = [
    "Detector",
    "TrustPolicy",
    "generate_key",
    "load_detector",
    "model_signature",
    "read_model_metadata",
    "save_detector",
    "sign_model",
]
