"""Co-trained pixel likelihood (Jin et al. sec. 4.3, eq. 13).

A particle's likelihood is the accumulated fused confidence of the pixels in a window of the
target's size centred on the particle, ``l(X)``, times a Gaussian gate around the predicted
position, ``g(X; mu, sigma)``:

    p(Y | X) = l(X) g(X; mu, sigma)                                              (13)

Window sums come from an integral image of the region's confidence map (four lookups per
particle, any window size). Pixels outside the candidate region contribute nothing. Only object
evidence is accumulated: ``l(X)`` sums the positive part ``max(conf, 0)`` of the fused map (the
"accumulated confidence scores" of Jin's Fig. 7; a signed sum is dominated by the large negative
confidences of unseen background patterns and would be negative almost everywhere). A window
without a single object pixel gets weight zero; when every particle does, the filter restarts
with uniform weights (``StepResult.recovered``). ``sharpness`` beta raises ``l`` to a power (beta = 1 is the
paper's eq. 13).
"""

from __future__ import annotations

import torch

from torchtrack.errors import ConfigError, ShapeError
from torchtrack.features.integral import integral_image

__all__ = ["CoTrainLikelihood", "window_sums"]


def window_sums(
    ii: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor, x1: torch.Tensor, y1: torch.Tensor
) -> torch.Tensor:
    """Sums over pixel rows ``y0..y1-1`` and columns ``x0..x1-1`` of the map whose integral
    image is ``ii (h + 1, w + 1)``; bounds are integer tensors of any equal shape, clipped to the
    map (an empty window sums to 0)."""
    h, w = ii.shape[0] - 1, ii.shape[1] - 1
    x0, x1 = x0.clamp(0, w), x1.clamp(0, w)
    y0, y1 = y0.clamp(0, h), y1.clamp(0, h)
    x1, y1 = torch.maximum(x1, x0), torch.maximum(y1, y0)
    return ii[y1, x1] - ii[y0, x1] - ii[y1, x0] + ii[y0, x0]


class CoTrainLikelihood:
    """``likelihood(states (B, N, D)) -> (B, N)`` log-likelihoods of eq. (13) for one target.

    Args:
        conf: ``(h, w)`` fused confidence map of the candidate region (signed; its positive
            part is accumulated).
        origin: ``(x0, y0)`` frame position of the map's top-left pixel.
        size: ``(w, h)`` window size in pixels (the target box).
        mean: ``(cx, cy)`` predicted position, the gate's centre mu.
        gate_sigma: ``(sx, sy)`` standard deviations of the gate, pixels (> 0).
        sharpness: exponent beta on ``l``.

    States carry the window centre in their first two components ``(cx, cy, ...)``.

    Raises:
        ShapeError: ``conf`` not 2-D. ConfigError: non-positive sizes or sigmas.
    """

    def __init__(
        self,
        conf: torch.Tensor,
        origin: tuple[float, float],
        size: tuple[float, float],
        mean: tuple[float, float],
        gate_sigma: tuple[float, float],
        sharpness: float = 1.0,
    ) -> None:
        if not isinstance(conf, torch.Tensor) or conf.ndim != 2:
            shape = tuple(conf.shape) if isinstance(conf, torch.Tensor) else type(conf).__name__
            raise ShapeError(f"conf must be an (h, w) confidence map, got {shape}")
        if not (size[0] > 0 and size[1] > 0):
            raise ConfigError(f"window size must be positive, got {tuple(size)}")
        if not (gate_sigma[0] > 0 and gate_sigma[1] > 0):
            raise ConfigError(f"gate_sigma must be positive, got {tuple(gate_sigma)}")
        if not sharpness > 0:
            raise ConfigError(f"sharpness must be > 0, got {sharpness}")
        self.ii = integral_image(conf.clamp_min(0)[None, None].to(torch.float64))[0, 0]
        self.origin = (float(origin[0]), float(origin[1]))
        self.size = (float(size[0]), float(size[1]))
        self.mean = (float(mean[0]), float(mean[1]))
        self.gate_sigma = (float(gate_sigma[0]), float(gate_sigma[1]))
        self.sharpness = float(sharpness)

    def accumulated(self, states: torch.Tensor) -> torch.Tensor:
        """``l(X)``: ``(B, N)`` window sums of the positive confidence."""
        if states.ndim != 3 or states.shape[2] < 2:
            raise ShapeError(f"states must be (B, N, D >= 2), got {tuple(states.shape)}")
        cx = states[..., 0].to(torch.float64) - self.origin[0]
        cy = states[..., 1].to(torch.float64) - self.origin[1]
        x0 = torch.round(cx - self.size[0] / 2).long()
        y0 = torch.round(cy - self.size[1] / 2).long()
        x1 = x0 + max(round(self.size[0]), 1)
        y1 = y0 + max(round(self.size[1]), 1)
        return window_sums(self.ii.to(states.device), x0, y0, x1, y1)

    def __call__(self, states: torch.Tensor) -> torch.Tensor:
        """``(B, N, D) -> (B, N)`` log p(Y | X) (``-inf`` where ``l <= 0``)."""
        acc = self.accumulated(states)
        log_l = self.sharpness * torch.log(acc.clamp_min(0))
        dx = (states[..., 0].to(torch.float64) - self.mean[0]) / self.gate_sigma[0]
        dy = (states[..., 1].to(torch.float64) - self.mean[1]) / self.gate_sigma[1]
        return (log_l - 0.5 * (dx * dx + dy * dy)).to(states.dtype)


def mean_positive_confidence(
    ii: torch.Tensor, origin: tuple[float, float], boxes: torch.Tensor
) -> torch.Tensor:
    """Mean positive confidence of boxes: window sums of the positive fused map over each box's
    pixels, divided by the box area.

    Args:
        ii: ``(h + 1, w + 1)`` float64 integral image of ``max(conf, 0)`` of a region.
        origin: ``(x0, y0)`` frame position of the region's top-left pixel.
        boxes: ``(..., 4)`` x, y, w, h in frame pixels (rounded to whole pixels; the parts outside
            the region count as zero confidence).

    Returns:
        ``(...)`` float64 in [0, max conf].
    """
    b = boxes.to(torch.float64)
    x0 = torch.round(b[..., 0] - origin[0]).long()
    y0 = torch.round(b[..., 1] - origin[1]).long()
    w = torch.round(b[..., 2]).long().clamp_min(1)
    h = torch.round(b[..., 3]).long().clamp_min(1)
    s = window_sums(ii.to(boxes.device), x0, y0, x0 + w, y0 + h)
    return s / (w * h).to(torch.float64)


class CoTrainCue:
    """Jin et al.'s co-trained pixel classifier as one cue of a box particle filter.

    ``log L(box) = log max(m(box), floor)`` with ``m`` the mean positive fused confidence of the
    pixels in the box (:func:`mean_positive_confidence`), so that the cue prefers a box that is
    filled with object pixels at any size (a window *sum*, eq. 13, grows with the box). Per
    frame: :meth:`score` computes the maps of a candidate region ``search_scale`` times the
    target around a centre, :meth:`log_likelihood` reads them for any boxes, :meth:`update`
    retrains the classifiers on the most confident blob (Algorithm 2, as the ``cotrain``
    tracker). Used by the ``fused`` tracker (with a calibrated detector) and by the
    ``adaptive-haar`` tracker's ``cotrain_weight`` (with the adaptive Haar classifier).

    Args:
        trainer: the :class:`~torchtrack.learn.cotrain.CoTrainer`.
        search_scale: candidate region side over the target's (>= 1).
        floor: smallest ``m`` in the log (keeps it finite off the object).
    """

    def __init__(self, trainer, search_scale: float = 2.0, floor: float = 1e-4) -> None:
        if not search_scale >= 1:
            raise ConfigError(f"search_scale must be >= 1, got {search_scale}")
        if not floor > 0:
            raise ConfigError(f"floor must be > 0, got {floor}")
        self.trainer = trainer
        self.search_scale = float(search_scale)
        self.floor = float(floor)
        self.maps = None
        self._ii: torch.Tensor | None = None

    def init(
        self,
        frame: torch.Tensor,
        box: tuple[float, float, float, float],
        frame_size: tuple[int, int],
        generator: torch.Generator | None = None,
    ) -> None:
        """Train on the first frame's ``box`` (x, y, w, h).

        Raises:
            ConfigError: the box leaves no region to learn from.
        """
        from torchtrack.learn.cotrain import region_around

        x, y, w, h = (float(v) for v in box)
        region = region_around((x + w / 2, y + h / 2), (w, h), self.search_scale, frame_size)
        if region is None:
            raise ConfigError(f"init box {(x, y, w, h)} leaves no region to learn from")
        self.trainer.init(frame, (x, y, w, h), region, generator)
        self.maps, self._ii = None, None

    def score(
        self,
        frame: torch.Tensor,
        centre: tuple[float, float],
        size: tuple[float, float],
        frame_size: tuple[int, int],
    ) -> bool:
        """Score the candidate region around ``centre`` for a target of ``size`` (w, h);
        False when the region left the frame (no evidence this frame)."""
        from torchtrack.learn.cotrain import region_around

        region = region_around(centre, size, self.search_scale, frame_size)
        if region is None:
            self.maps, self._ii = None, None
            return False
        self.maps = self.trainer.score(frame, region)
        self._ii = integral_image(self.maps.opened.clamp_min(0)[None, None].to(torch.float64))[0, 0]
        return True

    def mean_confidence(self, boxes: torch.Tensor) -> torch.Tensor:
        """``m(box)`` of ``boxes (..., 4)`` on this frame's maps (zeros without maps)."""
        if self.maps is None:
            return torch.zeros(boxes.shape[:-1], dtype=torch.float64, device=boxes.device)
        return mean_positive_confidence(self._ii, self.maps.region[:2], boxes)

    def log_likelihood(self, boxes: torch.Tensor) -> torch.Tensor:
        """``(..., 4) -> (...)`` float64 ``log max(m, floor)``; 0 everywhere when this frame has
        no maps (a cue without evidence does not weigh)."""
        if self.maps is None:
            return torch.zeros(boxes.shape[:-1], dtype=torch.float64, device=boxes.device)
        return self.mean_confidence(boxes).clamp_min(self.floor).log()

    def update(
        self,
        generator: torch.Generator | None = None,
        within: tuple[float, float, float, float] | None = None,
    ) -> tuple[bool, bool]:
        """Retrain on this frame's most confident blob: ``(blob found, positives accepted)``."""
        if self.maps is None:
            return False, False
        blob = self.trainer.locate(self.maps)
        if blob is None:
            return False, False
        return True, bool(self.trainer.update(self.maps, blob, generator, within))
