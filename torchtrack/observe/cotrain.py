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
