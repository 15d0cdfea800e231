"""Scanning a detector over images: multi-scale sliding windows and non-maximum suppression.

Used for hard-negative mining and for detection (paper section 4.2: the first frame is scanned
over translations and scales). Every window is scored from one integral image per frame.
"""

from __future__ import annotations

import math

import torch

from torchtrack.boxes import xywh_to_xyxy
from torchtrack.errors import ConfigError, ShapeError
from torchtrack.features.haar import integrals

__all__ = ["nms", "scan", "scan_batch", "sliding_windows"]


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
    """Greedy non-maximum suppression (kornia's ``nms`` on our x, y, w, h boxes).

    Args:
        boxes: ``(N, 4)`` x, y, w, h; scores: ``(N,)``.
        iou_threshold: a box is dropped when its IoU with a kept, higher-scoring box exceeds this.

    Returns:
        ``(K,)`` int64 indices of kept boxes, by decreasing score.
    """
    from kornia.geometry.bbox import nms as kornia_nms

    if boxes.ndim != 2 or boxes.shape[-1] != 4 or scores.shape != boxes.shape[:1]:
        raise ShapeError(
            f"nms needs boxes (N, 4) and scores (N,), got {tuple(boxes.shape)} and "
            f"{tuple(scores.shape)}"
        )
    if boxes.shape[0] == 0:
        return torch.zeros(0, dtype=torch.int64, device=boxes.device)
    # kornia loops over kept boxes only and never builds the N x N IoU matrix (N can be
    # tens of thousands of windows when no threshold is applied).
    return kornia_nms(xywh_to_xyxy(boxes.float()), scores, iou_threshold).to(torch.int64)


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
    batch: int = 16_384,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Detect by scoring every sliding window of one frame.

    Args:
        detector: a :class:`~torchtrack.detect.Detector`.
        frame: ``(C, H, W)`` or ``(1, C, H, W)``, 0..255 (C = 1 or RGB; scored on luma).
        threshold: keep windows scoring at least this (``None``: keep all).
        margin: score with raw classifier margins instead of calibrated probabilities.
        scale_step, stride, min_scale, max_scale: see :func:`sliding_windows`; ``min_scale``
            below 1 scans windows smaller than the training window (objects smaller than the
            training crops: the filters shrink with the box, no image is resized).
        nms_iou: IoU for non-maximum suppression (``None``: no suppression).
        batch: windows per scoring call (bounds memory).

    Returns:
        ``boxes (K, 4)`` and ``scores (K,)``, by decreasing score.

    Raises:
        ShapeError: not one frame, or a frame smaller than the window at ``min_scale``.
    """
    if frame.ndim == 3:
        frame = frame[None]
    if frame.ndim != 4 or frame.shape[0] != 1:
        raise ShapeError(
            f"scan takes one frame (C, H, W) or (1, C, H, W), got {tuple(frame.shape)}"
        )
    return scan_batch(
        detector,
        frame,
        threshold=threshold,
        margin=margin,
        scale_step=scale_step,
        stride=stride,
        min_scale=min_scale,
        max_scale=max_scale,
        nms_iou=nms_iou,
        batch=batch,
    )[0]


def scan_batch(
    detector,
    frames: torch.Tensor,
    *,
    threshold: float | None = 0.5,
    margin: bool = False,
    scale_step: float = 1.2,
    stride: float = 0.1,
    min_scale: float = 1.0,
    max_scale: float | None = None,
    nms_iou: float | None = 0.3,
    batch: int = 16_384,
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """:func:`scan` over a batch of same-size frames: one batched integral image, the same
    windows scored on every frame in one call per chunk, then threshold and NMS per frame.

    Args:
        frames: ``(B, C, H, W)``, 0..255. Other arguments as in :func:`scan`; ``batch`` bounds
            the windows scored per call over all frames (``B x N_chunk``).

    Returns:
        B pairs ``(boxes (K_b, 4), scores (K_b,))``, by decreasing score.

    Raises:
        ShapeError: frames not ``(B, C, H, W)``, or smaller than the window at ``min_scale``.
    """
    if frames.ndim != 4:
        raise ShapeError(f"scan_batch takes frames (B, C, H, W), got {tuple(frames.shape)}")
    fh, fw = frames.shape[-2:]
    wh, ww = detector.window
    if fh < wh * min_scale or fw < ww * min_scale:
        raise ShapeError(
            f"frame {fh}x{fw} (HxW) is smaller than the detector window {wh}x{ww} at the "
            f"smallest scan scale {min_scale:g} ({wh * min_scale:g}x{ww * min_scale:g}); "
            f"scan with min_scale <= {min(fh / wh, fw / ww):.3g} or use larger frames"
        )
    boxes = sliding_windows(
        (fh, fw),
        detector.window,
        scale_step=scale_step,
        stride=stride,
        min_scale=min_scale,
        max_scale=max_scale,
    ).to(frames.device)
    nb = frames.shape[0]
    ints = integrals(frames)
    parts = []
    step = max(1, batch // nb)  # bounds memory: B x step windows per scoring call
    for i in range(0, boxes.shape[0], step):
        b = boxes[None, i : i + step].expand(nb, -1, -1)
        s = detector.decision_function(ints, b) if margin else detector.score(ints, b)
        parts.append(s)
    all_scores = (
        torch.cat(parts, 1) if parts else torch.zeros((nb, 0), device=frames.device)
    )  # (B, N)
    out = []
    for f in range(nb):
        bx, sc = boxes, all_scores[f]
        if threshold is not None:
            keep = sc >= threshold
            bx, sc = bx[keep], sc[keep]
        if nms_iou is not None and bx.shape[0]:
            keep = nms(bx, sc, nms_iou)
        else:
            keep = sc.argsort(descending=True)
        out.append((bx[keep], sc[keep]))
    return out
