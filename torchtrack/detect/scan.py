"""Scanning a detector over images: multi-scale sliding windows and non-maximum suppression.

Used for hard-negative mining and for detection (paper section 4.2: the first frame is scanned
over translations and scales). Every window is scored from one integral image per frame.
"""

from __future__ import annotations

import math

import torch

from torchtrack.boxes import box_iou_matrix
from torchtrack.errors import ConfigError, ShapeError
from torchtrack.features.haar import integrals

__all__ = ["nms", "scan", "sliding_windows"]


def sliding_windows(
    frame_size: tuple[int, int],
    window: tuple[int, int],
    *,
    scale_step: float = 1.2,
    stride: float = 0.1,
    min_scale: float = 1.0,
    max_scale: float | None = None,
) -> torch.Tensor:
    """All windows of the window's aspect ratio inside a frame, at geometric scales.

    Args:
        frame_size: ``(H, W)`` of the frame.
        window: ``(h, w)`` of the detector window at scale 1.
        scale_step: ratio between successive scales (> 1).
        stride: step between windows as a fraction of the window width (and height) at that
            scale.
        min_scale, max_scale: scale range (default up to the largest that fits).

    Returns:
        ``(N, 4)`` float32 boxes x, y, w, h (empty when the window does not fit).
    """
    if not scale_step > 1.0:
        raise ConfigError(f"scale_step must be > 1, got {scale_step}")
    if not 0.0 < stride <= 1.0:
        raise ConfigError(f"stride must be in (0, 1], got {stride}")
    fh, fw = frame_size
    h, w = window
    top = min(fh / h, fw / w)
    if max_scale is not None:
        top = min(top, max_scale)
    out = []
    if top < min_scale:
        return torch.zeros((0, 4))
    n_scales = math.floor(math.log(top / min_scale) / math.log(scale_step) + 1e-9) + 1
    for i in range(n_scales):
        s = min_scale * scale_step**i
        bw, bh = w * s, h * s
        step_x = max(1.0, stride * bw)
        step_y = max(1.0, stride * bh)
        xs = torch.arange(0.0, fw - bw + 1e-6, step_x)
        ys = torch.arange(0.0, fh - bh + 1e-6, step_y)
        gy, gx = torch.meshgrid(ys, xs, indexing="ij")
        n = gx.numel()
        out.append(
            torch.stack(
                (gx.reshape(-1), gy.reshape(-1), torch.full((n,), bw), torch.full((n,), bh)), 1
            )
        )
    return torch.cat(out).to(torch.float32)


def nms(boxes: torch.Tensor, scores: torch.Tensor, iou_threshold: float = 0.3) -> torch.Tensor:
    """Greedy non-maximum suppression.

    Args:
        boxes: ``(N, 4)`` x, y, w, h; scores: ``(N,)``.
        iou_threshold: a box is dropped when its IoU with a kept, higher-scoring box exceeds this.

    Returns:
        ``(K,)`` int64 indices of kept boxes, by decreasing score.
    """
    if boxes.ndim != 2 or boxes.shape[-1] != 4 or scores.shape != boxes.shape[:1]:
        raise ShapeError(
            f"nms needs boxes (N, 4) and scores (N,), got {tuple(boxes.shape)} and "
            f"{tuple(scores.shape)}"
        )
    order = scores.argsort(descending=True)
    b = boxes[order]
    iou = box_iou_matrix(b, b)
    n = b.shape[0]
    keep = torch.ones(n, dtype=torch.bool, device=boxes.device)
    for i in range(n):  # loop over detections, not particles: N is small after thresholding
        if keep[i]:
            keep[i + 1 :] &= iou[i, i + 1 :] <= iou_threshold
    return order[keep]


def scan(
    detector,
    frame: torch.Tensor,
    *,
    threshold: float | None = 0.5,
    margin: bool = False,
    scale_step: float = 1.2,
    stride: float = 0.1,
    min_scale: float = 1.0,
    max_scale: float | None = None,
    nms_iou: float | None = 0.3,
    batch: int = 50_000,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Detect by scoring every sliding window of one frame.

    Args:
        detector: a :class:`~torchtrack.detect.Detector`.
        frame: ``(C, H, W)`` or ``(1, C, H, W)``, 0..255.
        threshold: keep windows scoring at least this (``None``: keep all).
        margin: score with raw classifier margins instead of calibrated probabilities.
        scale_step, stride, min_scale, max_scale: see :func:`sliding_windows`.
        nms_iou: IoU for non-maximum suppression (``None``: no suppression).
        batch: windows per scoring call.

    Returns:
        ``boxes (K, 4)`` and ``scores (K,)``, by decreasing score.
    """
    if frame.ndim == 3:
        frame = frame[None]
    if frame.ndim != 4 or frame.shape[0] != 1:
        raise ShapeError(
            f"scan takes one frame (C, H, W) or (1, C, H, W), got {tuple(frame.shape)}"
        )
    fh, fw = frame.shape[-2:]
    boxes = sliding_windows(
        (fh, fw),
        detector.window,
        scale_step=scale_step,
        stride=stride,
        min_scale=min_scale,
        max_scale=max_scale,
    ).to(frame.device)
    ints = integrals(frame)
    parts = []
    for i in range(0, boxes.shape[0], batch):
        b = boxes[None, i : i + batch]
        s = detector.decision_function(ints, b) if margin else detector.score(ints, b)
        parts.append(s[0])
    scores = torch.cat(parts) if parts else torch.zeros(0, device=frame.device)
    if threshold is not None:
        keep = scores >= threshold
        boxes, scores = boxes[keep], scores[keep]
    if nms_iou is not None and boxes.shape[0]:
        keep = nms(boxes, scores, nms_iou)
    else:
        keep = scores.argsort(descending=True)
    return boxes[keep], scores[keep]
