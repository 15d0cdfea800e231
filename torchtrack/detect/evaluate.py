"""Detector accuracy on labelled crops: detection rate at a fixed false-positive rate (paper
Table 1), ROC AUC, accuracy."""

from __future__ import annotations

import math

import torch

from torchtrack.errors import DataError

__all__ = ["crop_scores", "detection_rate_at_fpr", "roc_auc"]


def _split(scores: torch.Tensor, labels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    s = torch.as_tensor(scores, dtype=torch.float64).reshape(-1).cpu()
    y = torch.as_tensor(labels).reshape(-1).cpu().bool()
    if s.shape != y.shape:
        raise DataError(f"{s.numel()} scores but {y.numel()} labels")
    if not bool(torch.isfinite(s).all()):
        raise DataError("scores contain NaN or inf")
    pos, neg = s[y], s[~y]
    if pos.numel() == 0 or neg.numel() == 0:
        raise DataError(
            f"need both classes, got {pos.numel()} positive(s), {neg.numel()} negative(s)"
        )
    return pos, neg


def detection_rate_at_fpr(
    scores: torch.Tensor, labels: torch.Tensor, fpr: float = 0.01
) -> tuple[float, float, float]:
    """Share of positives detected when the threshold lets at most ``fpr`` of negatives through.

    The threshold is the ``(floor(fpr * n_neg) + 1)``-th highest negative score; a sample is
    detected when its score is strictly above it.

    Args:
        scores: ``(n,)`` margins or probabilities; labels: ``(n,)`` bool / {0, 1}.
        fpr: false-positive rate (paper Table 1: 0.01).

    Returns:
        ``(detection_rate, achieved_fpr, threshold)``.
    """
    pos, neg = _split(scores, labels)
    k = math.floor(fpr * neg.numel())
    thr = float(neg.sort(descending=True).values[min(k, neg.numel() - 1)])
    return float((pos > thr).double().mean()), float((neg > thr).double().mean()), thr


def roc_auc(scores: torch.Tensor, labels: torch.Tensor) -> float:
    """Area under the ROC curve (Mann-Whitney U with ties counted half)."""
    pos, neg = _split(scores, labels)
    allv = torch.cat((pos, neg))
    order = allv.argsort()
    _, inv, counts = torch.unique_consecutive(allv[order], return_inverse=True, return_counts=True)
    ends = counts.cumsum(0).double()
    ranks = torch.empty_like(allv)
    ranks[order] = (ends - (counts.double() - 1) / 2)[inv]  # average rank of each tie group
    rp = ranks[: pos.numel()].sum()
    npos, nneg = pos.numel(), neg.numel()
    return float((rp - npos * (npos + 1) / 2) / (npos * nneg))


def crop_scores(
    detector, crops: torch.Tensor, *, margin: bool = True, batch: int = 4096
) -> torch.Tensor:
    """Score window-sized crops ``(N, C, H, W)`` with a detector -> ``(N,)`` margins (or
    calibrated probabilities with ``margin=False``)."""
    from torchtrack.features.haar import integrals

    h, w = detector.window
    out = []
    for i in range(0, crops.shape[0], batch):
        c = crops[i : i + batch]
        boxes = torch.tensor([0.0, 0.0, float(w), float(h)]).expand(c.shape[0], 1, 4)
        ints = integrals(c)
        s = detector.decision_function(ints, boxes) if margin else detector.score(ints, boxes)
        out.append(s[:, 0])
    return torch.cat(out) if out else torch.zeros(0)
