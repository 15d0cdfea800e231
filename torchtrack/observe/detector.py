"""Calibrated-detector observation model (Chateau et al. 2006, sec. 2.4, eq. 8 and 11).

The likelihood of a particle is the detector's Platt-calibrated probability that the window
``R(X) = c + s W`` (eq. 3) holds an object of the class:
``P(Z | X) = 1 / (1 + exp(A m(f) + B))`` (eq. 8), with ``m(f)`` the classifier margin of the
window's selected Haar features. No tuning parameter such as the ``lambda`` of
``exp(-lambda d)`` likelihoods is involved: the calibration set it.

Every particle window of a frame is scored from one set of integral images
(:meth:`~torchtrack.detect.Detector.integrals`). :class:`DetectorObservation` computes them only
over the part of the frame the windows cover plus the context the detector's features need
(``crop=True``, the default; :meth:`~torchtrack.detect.Detector.integrals_for`), which gives
the same values as the full frame (parts of a window outside the frame read as zero either way)
at a fraction of the cost when the target is small. Any detector works: Chateau's grey Haar
bank or integral channel features.

Windows that cannot be scored (not finite, under one pixel, or entirely outside the frame, e.g.
particles of a target leaving the view) get probability 0 instead of an error.
"""

from __future__ import annotations

import math

import torch

from torchtrack.boxes import _check_frame_size
from torchtrack.errors import ConfigError, ShapeError, is_number

__all__ = ["DetectorObservation", "scorable_boxes"]


def scorable_boxes(boxes: torch.Tensor, frame_size: tuple[int, int]) -> torch.Tensor:
    """``(..., 4)`` x, y, w, h -> ``(...)`` bool: finite, at least one pixel wide and high, and
    overlapping a frame of size ``(H, W)`` (what :func:`torchtrack.boxes.check_boxes` demands).

    Raises:
        ShapeError: ``frame_size`` not two finite sizes >= 0 (a bool among them included).
    """
    fh, fw = _check_frame_size(frame_size)
    x, y, w, h = boxes.unbind(-1)
    return (
        torch.isfinite(boxes).all(-1)
        & (w >= 1.0)
        & (h >= 1.0)
        & (x < fw)
        & (y < fh)
        & (x + w > 0)
        & (y + h > 0)
    )


class DetectorObservation:
    """Detector probabilities of particle windows, batched over targets and particles.

    Args:
        detector: a calibrated :class:`~torchtrack.detect.Detector`.
        floor: smallest likelihood used in :meth:`log_likelihood` (keeps log-weights finite
            when every window scores ~0; ``0`` allows ``-inf``).
        crop: compute the integral image only over the region the windows cover.
        head: score with the detector's tracking head (:meth:`Detector.tracking_model`: its
            first trees with their own Platt calibration, a fraction of the cost) when it has
            one; ``False``: the whole classifier.

    Example::

        obs = DetectorObservation(detector)
        p = obs.probabilities(frames, boxes)     # frames (B, C, H, W), boxes (B, N, 4) -> (B, N)
    """

    def __init__(self, detector, floor: float = 1e-6, crop: bool = True, head: bool = True) -> None:
        if detector.calibrator is None:
            from torchtrack.errors import NotFittedError

            raise NotFittedError(
                f"detector {detector.name!r} has no calibration; the tracker needs calibrated "
                "probabilities (fit one with `torchtrack calibrate`)"
            )
        # floor=True clamped every probability to 1 (a flat likelihood: the detector ignored),
        # a negative or NaN one was no floor at all
        if not is_number(floor) or not 0 <= floor < 1:
            raise ConfigError(
                f"DetectorObservation: floor must be a number in [0, 1) (the smallest "
                f"likelihood), got {floor!r}"
            )
        tracking_model = getattr(detector, "tracking_model", None)
        self.detector = tracking_model() if head and tracking_model is not None else detector
        self.floor = float(floor)
        self.crop = bool(crop)
        #: the last one-frame call's crop: ``(integrals, (dx, dy) crop origin, (x0, y0, x1, y1)
        #: the scored windows' hull inside the frame)``; a window inside the hull reads the
        #: same features from these integrals as from the whole frame (the multi-target
        #: tracker reads its reported boxes' features from them). None: not cropped.
        self.last_crop: tuple | None = None

    def margins(self, frames: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
        """Uncalibrated classifier margins ``m(f)`` of windows on frames.

        Args:
            frames: ``(B, C, H, W)`` uint8 or float 0..255 (C = 1 or 3).
            boxes: ``(B, N, 4)`` windows x, y, w, h in pixels (one set per frame).

        Returns:
            ``(B, N)`` float64; ``-inf`` for windows that cannot be scored (see module doc).

        Raises:
            ShapeError: wrong shapes.
        """
        if frames.ndim != 4 or boxes.ndim != 3 or boxes.shape[-1] != 4:
            raise ShapeError(
                f"frames must be (B, C, H, W) and boxes (B, N, 4), got {tuple(frames.shape)} "
                f"and {tuple(boxes.shape)}"
            )
        if boxes.shape[0] != frames.shape[0]:
            raise ShapeError(
                f"boxes are for {boxes.shape[0]} frame(s) but {frames.shape[0]} were given"
            )
        b, n = boxes.shape[:2]
        fh, fw = int(frames.shape[-2]), int(frames.shape[-1])
        out = torch.full((b, n), -math.inf, dtype=torch.float64, device=frames.device)
        if n == 0:
            return out
        boxes = boxes.to(device=frames.device, dtype=torch.float64)
        ok = scorable_boxes(boxes, (fh, fw))
        if not bool(ok.any()):
            return out
        # Unscorable windows are replaced by a harmless in-frame one and masked afterwards.
        safe = torch.where(ok.unsqueeze(-1), boxes, boxes.new_tensor([0.0, 0.0, 1.0, 1.0]))
        det = self.detector
        self.last_crop = None
        if self.crop:
            ints, moved = det.integrals_for(frames, safe, ok)
            if b == 1:
                i = int(torch.nonzero(ok[0])[0, 0])
                dx, dy = (safe[0, i, :2] - moved[0, i, :2]).tolist()
                x, y, w, h = boxes[0][ok[0]].unbind(-1)
                hull = (
                    float(x.clamp(0, fw).min()),
                    float(y.clamp(0, fh).min()),
                    float((x + w).clamp(0, fw).max()),
                    float((y + h).clamp(0, fh).max()),
                )
                self.last_crop = (ints, (dx, dy), hull)
            safe = moved
        else:
            ints = det.integrals(frames)
        feats = det.features(ints, safe, check=False)
        m = det.margin_from_features(feats).to(torch.float64)
        return torch.where(ok, m, out)

    def probabilities_from_margins(self, margins: torch.Tensor) -> torch.Tensor:
        """Calibrated probabilities (eq. 8) of :meth:`margins` output: ``(B, N)`` float32, 0
        where the margin is ``-inf`` (unscorable window)."""
        ok = torch.isfinite(margins)
        safe = torch.where(ok, margins, torch.zeros_like(margins))
        p = self.detector.proba_from_margin(safe).to(torch.float32)
        return torch.where(ok, p, torch.zeros_like(p))

    def probabilities(self, frames: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
        """Calibrated probabilities (eq. 8) of windows on frames.

        Args:
            frames: ``(B, C, H, W)`` uint8 or float 0..255 (C = 1 or 3).
            boxes: ``(B, N, 4)`` windows x, y, w, h in pixels (one set per frame).

        Returns:
            ``(B, N)`` float32 in [0, 1]; 0 for windows that cannot be scored (see module doc).

        Raises:
            ShapeError: wrong shapes.
        """
        return self.probabilities_from_margins(self.margins(frames, boxes))

    def log_likelihood(self, frames: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
        """``log(max(p, floor))`` of :meth:`probabilities`: ``(B, N)`` float64."""
        p = self.probabilities(frames, boxes).to(torch.float64)
        if self.floor > 0:
            return p.clamp_min(self.floor).log()
        return p.log()
