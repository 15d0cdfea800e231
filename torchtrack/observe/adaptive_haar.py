"""Klein et al. (2010) observation model: boosted centre-surround classifier, eq. (3).

``p(Z_t | x_t^j) = c * exp(lambda * C_t^j(x_t^j, Z_t))`` with the classifier confidence
``C in [0, 1]`` (:meth:`torchtrack.learn.online_gentle.StumpEnsemble.confidence`) and
``lambda = 20``; ``c`` is the normalisation of the particle weights, so the filter only needs the
log-likelihood ``lambda * C``.

Each particle is scored by its own classifier (``model (B, N)`` indexes a
:class:`~torchtrack.learn.online_gentle.StumpEnsemble`): in the global modes every particle of
target b uses model b, in the per-particle mode each particle the model it inherited. One
integral image per frame serves all particles; one batched gather reads all ``N x n`` selected
features.
"""

from __future__ import annotations

import torch

from torchtrack.boxes import inside_fraction
from torchtrack.errors import ConfigError, ShapeError
from torchtrack.features.centre_surround import (
    CentreSurroundPool,
    ChannelIntegrals,
    centre_surround_features,
)
from torchtrack.learn.online_gentle import StumpEnsemble

__all__ = ["MIN_INSIDE", "AdaptiveHaarObservation", "classifier_confidence"]

#: boxes with less of their area inside the frame get confidence 0
MIN_INSIDE = 0.5


def classifier_confidence(
    ints: ChannelIntegrals,
    boxes: torch.Tensor,
    pool: CentreSurroundPool,
    ens: StumpEnsemble,
    model: torch.Tensor,
) -> torch.Tensor:
    """Confidence of each box's classifier on one frame.

    Args:
        ints: integral images of ONE frame (``ints.batch == 1``).
        boxes: ``(B, N, 4)`` x, y, w, h: B targets on that frame.
        pool: the feature pool of ``ens``.
        ens: the classifiers.
        model: ``(B, N)`` int64 model of each box.

    Returns:
        ``(B, N)`` float32 in [0, 1].
    """
    if ints.batch != 1:
        raise ShapeError(f"classifier_confidence scores boxes on one frame, got {ints.batch}")
    if boxes.ndim != 3 or model.shape != boxes.shape[:2]:
        raise ShapeError(
            f"boxes must be (B, N, 4) and model (B, N), got {tuple(boxes.shape)} and "
            f"{tuple(model.shape)}"
        )
    b, n = model.shape
    first = model[:, :1]
    if b == 1 and bool((model == first).all()):
        # One classifier for every box: one shared feature index (the fast path).
        m = int(first[0, 0])
        one = ens.select(torch.tensor([m], device=model.device))
        x = centre_surround_features(ints, boxes.reshape(1, n, 4), pool, one.feature[0])
        return one.confidence(x).view(b, n)
    idx = ens.feature[model]  # (B, N, n)
    x = centre_surround_features(
        ints, boxes.reshape(1, b * n, 4), pool, idx.reshape(1, b * n, -1)
    ).view(b, n, -1)
    return ens.confidence(x, model)


class AdaptiveHaarObservation:
    """Log-likelihood ``lambda * C`` of eq. (3).

    Args:
        pool: the centre-surround feature pool.
        lam: ``lambda`` (paper: 20).
    """

    def __init__(self, pool: CentreSurroundPool, lam: float = 20.0) -> None:
        if not lam > 0:
            raise ConfigError(f"lambda must be > 0, got {lam}")
        self.pool = pool
        self.lam = float(lam)

    def confidence(
        self, ints: ChannelIntegrals, boxes: torch.Tensor, ens: StumpEnsemble, model: torch.Tensor
    ) -> torch.Tensor:
        """``(B, N)`` classifier confidences (see :func:`classifier_confidence`); 0 for a box
        with less than half of its area inside the frame: the features of the part outside
        read the zero padding of the integral image, which is no evidence of the target (a
        classifier adapted on such boxes kept a lost track "visible" outside the frame)."""
        conf = classifier_confidence(ints, boxes, self.pool, ens, model)
        inside = inside_fraction(boxes.to(torch.float64), ints.size).to(conf.device)
        return torch.where(inside >= MIN_INSIDE, conf, torch.zeros_like(conf))

    def log_likelihood(self, confidence: torch.Tensor) -> torch.Tensor:
        """Eq. (3) up to the constant: ``lambda * C``."""
        return self.lam * confidence
