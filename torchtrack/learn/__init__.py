"""Offline learning: boosting with feature selection, SVM export, calibration.

Classifiers and calibrators serialise to ``(tensors, meta)`` with ``to_state()``; the
``*_from_state`` functions here rebuild them from a model file, dispatching on ``meta["kind"]``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from torchtrack import errors
from torchtrack.learn._base import NotFittedError
from torchtrack.learn.boosting import BoostedStumps, select_features
from torchtrack.learn.calibration import (
    CalibratedFit,
    IsotonicCalibrator,
    PlattCalibrator,
    calibration_metrics,
    fit_calibrated,
    make_calibrator,
    reliability_diagram,
)
from torchtrack.learn.svm import SVMClassifier

__all__ = [
    "CALIBRATORS",
    "CLASSIFIERS",
    "BoostedStumps",
    "CalibratedFit",
    "IsotonicCalibrator",
    "NotFittedError",
    "PlattCalibrator",
    "SVMClassifier",
    "calibration_metrics",
    "calibrator_from_state",
    "classifier_from_state",
    "fit_calibrated",
    "make_calibrator",
    "reliability_diagram",
    "select_features",
]

CLASSIFIERS: dict[str, type] = {"boosted_stumps": BoostedStumps, "svm": SVMClassifier}
CALIBRATORS: dict[str, type] = {"platt": PlattCalibrator, "isotonic": IsotonicCalibrator}


def _dispatch(registry: dict[str, type], what: str, tensors: Any, meta: Any) -> Any:
    if not isinstance(meta, Mapping) or not isinstance(meta.get("kind"), str):
        raise errors.ModelFormatError(f"{what} metadata must be a JSON object with a 'kind' string")
    if not isinstance(tensors, Mapping) or not all(
        isinstance(v, torch.Tensor) for v in tensors.values()
    ):
        raise errors.ModelFormatError(f"{what} tensors must be a mapping of names to tensors")
    kind = meta["kind"]
    if kind not in registry:
        raise errors.ModelFormatError(
            f"unknown {what} kind {kind!r}; known kinds: {', '.join(sorted(registry))}"
        )
    return registry[kind].from_state(dict(tensors), dict(meta))


def classifier_from_state(tensors: Mapping[str, torch.Tensor], meta: Mapping[str, Any]) -> Any:
    """Rebuild a classifier (``BoostedStumps`` or ``SVMClassifier``) from ``to_state`` output.

    Raises:
        ModelFormatError: unknown ``kind`` or an invalid field (named).
    """
    return _dispatch(CLASSIFIERS, "classifier", tensors, meta)


def calibrator_from_state(tensors: Mapping[str, torch.Tensor], meta: Mapping[str, Any]) -> Any:
    """Rebuild a calibrator (``PlattCalibrator`` or ``IsotonicCalibrator``) from ``to_state``.

    Raises:
        ModelFormatError: unknown ``kind`` or an invalid field (named).
    """
    return _dispatch(CALIBRATORS, "calibrator", tensors, meta)
