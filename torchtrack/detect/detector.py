"""The class detector: window + selected Haar features + classifier + calibrator.

``Detector.score(frames, boxes)`` returns the calibrated probability that each box holds an
object of the class (Chateau et al. eq. 11), for boxes of any size and position, straight from
one integral image per frame. This is the likelihood a particle filter uses.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import torch

from torchtrack.detect.heads import (
    IsotonicCalibrator,
    KernelScorer,
    SigmoidCalibrator,
    StumpScorer,
    calibrator_from_estimator,
    scorer_from_estimator,
)
from torchtrack.errors import ModelFormatError, NotFittedError, ShapeError
from torchtrack.features.haar import HaarBank, Integrals, haar_features_at, integrals

__all__ = ["Detector"]

Scorer = StumpScorer | KernelScorer
Calibrator = SigmoidCalibrator | IsotonicCalibrator


@dataclass
class Detector:
    """A trained detector.

    Attributes:
        bank: the full Haar bank of the training window.
        feature_index: ``(K,)`` int64, the selected features (indices into ``bank``); the
            classifier sees them in this order.
        scorer: margins from the ``(M, K)`` selected features (stumps or SVM head).
        calibrator: margins -> probabilities (Platt sigmoid or isotonic); ``None`` until
            calibrated.
        name: a label, e.g. ``"pedestrian"``.
        summary: JSON-safe training summary (data counts, held-out metrics, split).

    Build one from fitted estimators with :meth:`from_estimators`; save and load it with
    :func:`torchtrack.detect.save_detector` / :func:`~torchtrack.detect.load_detector`.
    """

    bank: HaarBank
    feature_index: torch.Tensor
    scorer: Scorer
    calibrator: Calibrator | None = None
    name: str = "detector"
    summary: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.feature_index = (
            torch.as_tensor(self.feature_index, dtype=torch.int64).reshape(-1).cpu()
        )
        k = self.feature_index.numel()
        if k == 0:
            raise ModelFormatError("a detector needs at least one selected feature")
        if int(self.feature_index.min()) < 0 or int(self.feature_index.max()) >= len(self.bank):
            raise ModelFormatError(
                f"selected feature indices must lie in [0, {len(self.bank)}) for this bank"
            )
        if self.scorer.n_inputs > k:
            raise ModelFormatError(
                f"the classifier reads {self.scorer.n_inputs} features but only {k} are selected"
            )

    @classmethod
    def from_estimators(
        cls,
        bank: HaarBank,
        feature_index: torch.Tensor,
        classifier: Any,
        calibrator: Any = None,
        **kwargs: Any,
    ) -> Detector:
        """Export fitted estimators (torchtrack learners or scikit-learn, see
        :func:`~torchtrack.detect.heads.scorer_from_estimator`) into tensor heads."""
        scorer = scorer_from_estimator(classifier)
        cal = None if calibrator is None else calibrator_from_estimator(calibrator)
        return cls(bank, feature_index, scorer, cal, **kwargs)

    @property
    def window(self) -> tuple[int, int]:
        """``(H, W)`` of the training window."""
        return self.bank.window

    def with_calibrator(self, calibrator: Any) -> Detector:
        """A copy with another calibration (a head or a fitted calibrator)."""
        return replace(self, calibrator=calibrator_from_estimator(calibrator))

    def features(self, frames: torch.Tensor | Integrals, boxes: torch.Tensor) -> torch.Tensor:
        """Selected features ``(B, N, K)`` of ``boxes (B, N, 4)`` (x, y, w, h pixels) on
        ``frames (B, C, H, W)`` (0..255, C = 1 or RGB) or on precomputed :class:`Integrals`."""
        ints = frames if isinstance(frames, Integrals) else integrals(frames)
        return haar_features_at(ints, boxes, self.bank, self.feature_index)

    def margin_from_features(self, feats: torch.Tensor) -> torch.Tensor:
        """Raw classifier margins ``m(f)`` of selected features ``(..., K)`` -> ``(...)``."""
        if feats.shape[-1] != self.feature_index.numel():
            raise ShapeError(
                f"expected {self.feature_index.numel()} selected features in the last axis, "
                f"got shape {tuple(feats.shape)}"
            )
        lead = feats.shape[:-1]
        return self.scorer.decision_function(feats.reshape(-1, feats.shape[-1])).reshape(lead)

    def proba_from_margin(self, margin: torch.Tensor) -> torch.Tensor:
        """Calibrated probabilities of margins (eq. 8)."""
        if self.calibrator is None:
            raise NotFittedError(
                f"detector {self.name!r} has no calibration; fit one with `torchtrack calibrate`"
            )
        return self.calibrator(margin)

    def decision_function(
        self, frames: torch.Tensor | Integrals, boxes: torch.Tensor
    ) -> torch.Tensor:
        """Raw margins ``(B, N)`` of ``boxes (B, N, 4)``."""
        return self.margin_from_features(self.features(frames, boxes))

    def score(self, frames: torch.Tensor | Integrals, boxes: torch.Tensor) -> torch.Tensor:
        """Calibrated probabilities ``(B, N)`` that each box of ``boxes (B, N, 4)`` (x, y, w, h
        in pixels, any size) holds the class, on ``frames (B, C, H, W)`` or their
        :class:`Integrals` (compute once per frame with :func:`~torchtrack.features.integrals`
        when scoring several box sets).

        Raises:
            BoxError: a box is not finite, under one pixel, or entirely outside its frame.
            NotFittedError: the detector has no calibration.
        """
        return self.proba_from_margin(self.decision_function(frames, boxes))

    def selected_features(self) -> list[dict[str, Any]]:
        """The selected features as ``{"kind", "size", "y", "x"}`` records, in order."""
        return [self.bank.describe(int(i)) for i in self.feature_index]
