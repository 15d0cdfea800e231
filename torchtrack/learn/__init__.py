"""Offline learning: boosting with feature selection, boosted trees with a soft cascade, SVM
export, calibration.

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
    prior_shift,
    prior_weights,
    reliability_bins,
    reliability_diagram,
    with_prior,
)
from torchtrack.learn.svm import SVMClassifier
from torchtrack.learn.trees import BoostedTrees

__all__ = [
    "CALIBRATORS",
    "CLASSIFIERS",
    "BoostedStumps",
    "BoostedTrees",
    "CalibratedFit",
    "IsotonicCalibrator",
    "NotFittedError",
    "PlattCalibrator",
    "SVMClassifier",
    "calibration_metrics",
    "calibrator_from_dict",
    "calibrator_from_state",
    "calibrator_to_dict",
    "classifier_from_state",
    "fit_calibrated",
    "make_calibrator",
    "prior_shift",
    "prior_weights",
    "reliability_bins",
    "reliability_diagram",
    "select_features",
    "with_prior",
]

CLASSIFIERS: dict[str, type] = {
    "boosted_stumps": BoostedStumps,
    "boosted_trees": BoostedTrees,
    "svm": SVMClassifier,
}
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
    """Rebuild a classifier (``BoostedStumps``, ``BoostedTrees`` or ``SVMClassifier``) from
    ``to_state`` output.

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


def calibrator_to_dict(calibrator: Any) -> dict[str, Any]:
    """A fitted calibrator as a JSON-safe dict: ``{"calibrator": meta, "tensors": {name: list}}``.

    Tensors become lists of Python floats (float64 values round-trip exactly through JSON).
    """
    tensors, meta = calibrator.to_state()
    return {
        "calibrator": meta,
        "tensors": {
            k: {"dtype": str(v.dtype).removeprefix("torch."), "data": v.tolist()}
            for k, v in tensors.items()
        },
    }


_JSON_DTYPES = {"float64": torch.float64, "float32": torch.float32, "int64": torch.int64}


def calibrator_from_dict(d: Mapping[str, Any]) -> Any:
    """Inverse of :func:`calibrator_to_dict`, validated like a model file.

    Raises:
        ModelFormatError: missing keys, unknown dtypes or kinds, or an invalid field (named).
    """
    if not isinstance(d, Mapping) or not isinstance(d.get("calibrator"), Mapping):
        raise errors.ModelFormatError("calibration JSON needs a 'calibrator' object")
    raw = d.get("tensors", {})
    if not isinstance(raw, Mapping):
        raise errors.ModelFormatError("calibration JSON: 'tensors' must be an object")
    tensors = {}
    for name, entry in raw.items():
        if not isinstance(entry, Mapping) or entry.get("dtype") not in _JSON_DTYPES:
            raise errors.ModelFormatError(
                f"calibration JSON: tensor {name!r} needs a dtype in {sorted(_JSON_DTYPES)}"
            )
        try:
            tensors[name] = torch.tensor(entry.get("data"), dtype=_JSON_DTYPES[entry["dtype"]])
        except (TypeError, ValueError, RuntimeError, OverflowError) as exc:  # 10**400: Overflow
            raise errors.ModelFormatError(f"calibration JSON: tensor {name!r}: {exc}") from None
    return calibrator_from_state(tensors, d["calibrator"])
