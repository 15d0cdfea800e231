"""Data association for multi-target tracking: costs between targets and detections, and the
optimal one-to-one assignment (Hungarian / Jonker-Volgenant, ``scipy.optimize.linear_sum_assignment``).

The cost of pairing target ``t`` with detection ``d`` is built from two cues, each in [0, 1]:

* **overlap through the filter**: the expected IoU of the detection with the target's box under
  the particle distribution, ``sum_j w_j IoU(box_j, d)`` (the filter's predictive belief, not
  only its mean: a spread-out target after a miss overlaps less, a multi-modal one overlaps its
  modes);
* **appearance**: the Bhattacharyya coefficient between the target's colour model and the
  detection's histogram (Pérez et al. 2002), the cue that tells two people of the same class
  apart when they cross.

``cost = 1 - (w_o O + w_a A) / (w_o + w_a)``; a pair whose overlap is below the gate is not
allowed (cost ``inf``). Both weights are configurable, so a user can plug their own balance,
like norfair's distance functions.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from torchtrack.boxes import _check_last4, box_iou_matrix
from torchtrack.errors import ConfigError, ShapeError, is_number

__all__ = ["Assignment", "association_cost", "expected_iou", "linear_assignment"]


def expected_iou(
    particle_boxes: torch.Tensor, log_weights: torch.Tensor, detections: torch.Tensor
) -> torch.Tensor:
    """Expected IoU of each detection with each target under its particle distribution.

    Args:
        particle_boxes: ``(T, N, 4)`` x, y, w, h boxes of each target's particles.
        log_weights: ``(T, N)`` normalised log-weights.
        detections: ``(M, 4)`` x, y, w, h.

    Returns:
        ``(T, M)`` float64 in [0, 1].

    Raises:
        ShapeError: shapes as above not met, or boxes that are not real numbers.
    """
    if particle_boxes.ndim != 3 or particle_boxes.shape[-1] != 4 or detections.ndim != 2:
        raise ShapeError(
            f"particle_boxes must be (T, N, 4) and detections (M, 4), got "
            f"{tuple(particle_boxes.shape)} and {tuple(detections.shape)}"
        )
    _check_last4(particle_boxes, "particle_boxes")  # bool boxes were read as 0 / 1 pixels
    _check_last4(detections, "detections")
    t, n = particle_boxes.shape[:2]
    if not isinstance(log_weights, torch.Tensor) or tuple(log_weights.shape) != (t, n):
        # a (T, 1) one broadcast: every particle took the one weight (overlaps summed N times)
        got = tuple(log_weights.shape) if isinstance(log_weights, torch.Tensor) else log_weights
        raise ShapeError(f"log_weights must be (T, N) = {(t, n)} like particle_boxes, got {got}")
    m = detections.shape[0]
    if t == 0 or m == 0:
        return torch.zeros((t, m), dtype=torch.float64)
    iou = box_iou_matrix(
        particle_boxes.reshape(t * n, 4).double(), detections.double().to(particle_boxes.device)
    ).reshape(t, n, m)
    w = log_weights.double().exp().unsqueeze(-1)
    return (w * iou).sum(1).clamp(0.0, 1.0)


def association_cost(
    overlap: torch.Tensor,
    appearance: torch.Tensor | None = None,
    *,
    w_overlap: float = 1.0,
    w_appearance: float = 1.0,
    gate: float = 0.1,
) -> torch.Tensor:
    """Pairing costs from the cues (see the module notes).

    Args:
        overlap: ``(T, M)`` overlap cue in [0, 1] (e.g. :func:`expected_iou`).
        appearance: ``(T, M)`` appearance similarity in [0, 1], or ``None`` (overlap only).
        w_overlap, w_appearance: weights of the cues (>= 0, not both 0).
        gate: pairs whose overlap is below this are not allowed (``inf``).

    Returns:
        ``(T, M)`` float64 costs in [0, 1] or ``inf``.

    Raises:
        ConfigError: a weight that is not a finite number >= 0 (bool included) or a ``gate``
            that is not a finite number.
    """
    for name, v in (("w_overlap", w_overlap), ("w_appearance", w_appearance), ("gate", gate)):
        # a negative weight or NaN gave costs outside [0, 1] or NaN
        if not (is_number(v) and math.isfinite(v)) or (name != "gate" and float(v) < 0):
            least = "finite number" if name == "gate" else "finite number >= 0"
            raise ConfigError(f"association_cost: {name} must be a {least}, got {v!r}")
    overlap = overlap.double()
    if appearance is None or w_appearance == 0:
        cost = 1.0 - overlap
    else:
        if appearance.shape != overlap.shape:
            raise ShapeError(
                f"appearance {tuple(appearance.shape)} and overlap {tuple(overlap.shape)} differ"
            )
        total = w_overlap + w_appearance
        cost = 1.0 - (w_overlap * overlap + w_appearance * appearance.double()) / total
    return torch.where(overlap >= gate, cost, torch.full_like(cost, float("inf")))


class Assignment:
    """Result of :func:`linear_assignment`.

    Attributes:
        pairs: ``(P, 2)`` int64 rows ``(target, detection)``.
        unmatched_targets: ``(T - P,)`` int64.
        unmatched_detections: ``(M - P,)`` int64.
    """

    def __init__(self, pairs: np.ndarray, n_targets: int, n_detections: int) -> None:
        self.pairs = torch.as_tensor(pairs, dtype=torch.int64).reshape(-1, 2)
        t_used = set(self.pairs[:, 0].tolist())
        d_used = set(self.pairs[:, 1].tolist())
        self.unmatched_targets = torch.tensor(
            [i for i in range(n_targets) if i not in t_used], dtype=torch.int64
        )
        self.unmatched_detections = torch.tensor(
            [j for j in range(n_detections) if j not in d_used], dtype=torch.int64
        )

    def __len__(self) -> int:
        return int(self.pairs.shape[0])


def linear_assignment(cost: torch.Tensor, max_cost: float = 1.0) -> Assignment:
    """Minimum-cost one-to-one assignment of targets (rows) to detections (columns).

    Pairs costing ``inf`` or more than ``max_cost`` are never made: they are replaced by a large
    finite cost for the solver and dropped from its answer, so every kept pair is allowed.

    Args:
        cost: ``(T, M)`` costs.
        max_cost: the largest cost of a kept pair.

    Returns:
        :class:`Assignment`.

    Raises:
        ShapeError: ``cost`` not 2-D.
        ConfigError: ``max_cost`` not a number (NaN made every pair forbidden).
    """
    from scipy.optimize import linear_sum_assignment

    if cost.ndim != 2:
        raise ShapeError(f"cost must be (T, M), got {tuple(cost.shape)}")
    if not (is_number(max_cost) and (math.isfinite(max_cost) or max_cost == math.inf)):
        raise ConfigError(f"linear_assignment: max_cost must be a number, got {max_cost!r}")
    t, m = cost.shape
    if t == 0 or m == 0:
        return Assignment(np.zeros((0, 2), dtype=np.int64), t, m)
    c = cost.detach().double().cpu().numpy()
    allowed = np.isfinite(c) & (c <= max_cost)
    big = 1e6
    rows, cols = linear_sum_assignment(np.where(allowed, c, big))
    keep = allowed[rows, cols]
    return Assignment(np.stack([rows[keep], cols[keep]], 1), t, m)
