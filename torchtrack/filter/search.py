"""Search proposals: a coarse scan around the prediction, particles drawn around its best cells,
and the importance weights that keep the filter a filter.

A particle filter whose particles only come from the motion model cannot follow a target that
moves further in one frame than the motion noise reaches (fast motion, a panning camera), and
once it has lost the target it finds it again only by chance. The fix used here is importance
sampling from a mixture (Okuma et al. 2004's boosted particle filter; the weights are the
*balance heuristic* of multiple importance sampling, Veach and Guibas 1995):

1. **Coarse stage** (:func:`search_grid`): candidate boxes on a regular grid around the
   predicted position, ``radius`` wide (the whole frame when the target is lost), at a few
   scales of the current box; the observation model scores them (cheap: a grid of tens to a few
   thousand boxes against thousands of particles).
2. **Fine stage** (:func:`draw_around`): a fraction ``f`` of the particles is drawn around the
   best cells (a mixture of Gaussians ``d(x)``, cell probabilities from their scores); the
   others come from the motion model as usual.
3. **Weights** (:func:`search_log_weights`): the motion prior is a two-component mixture,
   ``p(x) = (1 - eps) g(x) + eps u(x)``: ``g`` the usual motion model and ``u`` a uniform
   *jump* anywhere in the searched region with small probability ``eps``. The posterior
   ``L p`` is then the sum of ``(1 - eps) L g`` and ``eps L u``, and each term is estimated
   with its own particles (importance sampling of a mixture with a fixed allocation): the
   ``N - M`` predicted particles, drawn from ``g``, weigh ``(1 - eps) L / (N - M)``; the ``M``
   search particles, drawn from ``d``, weigh ``eps L u / (d M)``. No density of the predicted
   cloud is needed. A search cell far from the prediction has to beat the predicted
   particles' likelihood by the ratio of those factors (a few tenths of a confidence for
   Klein's ``exp(20 C)``) before it takes the track: a target that is tracked well is not
   handed to a look-alike nearby, but a target that left the particle cloud is found and
   followed (the cloud's likelihood has collapsed, the search cell's has not).

All functions work on positions ``(cx, cy)`` in pixels, batched over ``B`` targets; boxes are
``x, y, w, h`` (:mod:`torchtrack.boxes`).
"""

from __future__ import annotations

import math

import torch

from torchtrack.errors import ConfigError, ShapeError
from torchtrack.filter._random import GeneratorLike, rand, randn

__all__ = ["draw_around", "search_grid", "search_log_weights", "top_cells"]

_LOG_2PI = math.log(2.0 * math.pi)


def search_grid(
    centre: torch.Tensor,
    size: torch.Tensor,
    radius: torch.Tensor,
    stride: torch.Tensor,
    frame_size: tuple[int, int],
    scales: tuple[float, ...] = (1.0,),
    max_boxes: int = 4096,
) -> torch.Tensor:
    """Candidate boxes on a grid around ``centre``.

    Args:
        centre: ``(B, 2)`` grid centre ``(cx, cy)`` in pixels.
        size: ``(B, 2)`` box ``(w, h)`` at scale 1.
        radius: ``(B, 2)`` half extent of the grid in x and y (pixels); the grid is also cut to
            the frame (box centres inside ``[0, W] x [0, H]``).
        stride: ``(B, 2)`` largest spacing of grid points (pixels); every row gets the same
            number of points (the largest any row needs), so rows with smaller radii get finer
            grids.
        frame_size: ``(H, W)``.
        scales: box sizes ``scale * size`` at every grid point.
        max_boxes: upper bound on the boxes per row (the spacing grows to respect it).

    Returns:
        ``(B, G, 4)`` boxes, ``G = nx * ny * len(scales)``.

    Raises:
        ShapeError: inputs not ``(B, 2)``. ConfigError: empty ``scales`` or ``max_boxes < 1``.
    """
    for name, t in (("centre", centre), ("size", size), ("radius", radius), ("stride", stride)):
        if t.ndim != 2 or t.shape[1] != 2 or t.shape[0] != centre.shape[0]:
            raise ShapeError(f"{name} must be (B, 2), got {tuple(t.shape)}")
    if not scales or max_boxes < 1:
        raise ConfigError(f"need at least one scale and max_boxes >= 1, got {scales}, {max_boxes}")
    h, w = frame_size
    hi = torch.tensor([float(w), float(h)], dtype=centre.dtype, device=centre.device)
    lo = (centre - radius).clamp_min(0.0)
    up = torch.minimum(centre + radius, hi)
    lo = torch.minimum(lo, up)
    span = up - lo  # (B, 2)
    n = (span / stride.clamp_min(1e-3)).ceil().max(0).values.long() + 1  # (2,) points per axis
    nx, ny = int(n[0]), int(n[1])
    budget = max(1, max_boxes // len(scales))
    if nx * ny > budget:
        shrink = math.sqrt(budget / (nx * ny))
        nx, ny = max(1, int(nx * shrink)), max(1, int(ny * shrink))
    tx = (
        torch.linspace(0.0, 1.0, nx, dtype=centre.dtype, device=centre.device)
        if nx > 1
        else (torch.full((1,), 0.5, dtype=centre.dtype, device=centre.device))
    )
    ty = (
        torch.linspace(0.0, 1.0, ny, dtype=centre.dtype, device=centre.device)
        if ny > 1
        else (torch.full((1,), 0.5, dtype=centre.dtype, device=centre.device))
    )
    gx = lo[:, 0:1] + tx[None] * span[:, 0:1]  # (B, nx)
    gy = lo[:, 1:2] + ty[None] * span[:, 1:2]  # (B, ny)
    b = centre.shape[0]
    cx = gx[:, None, :].expand(b, ny, nx).reshape(b, -1)
    cy = gy[:, :, None].expand(b, ny, nx).reshape(b, -1)
    out = []
    for s in scales:
        ww, hh = (size[:, 0:1] * float(s)).expand_as(cx), (size[:, 1:2] * float(s)).expand_as(cy)
        out.append(torch.stack([cx - ww / 2, cy - hh / 2, ww, hh], -1))
    return torch.cat(out, 1)


def top_cells(
    boxes: torch.Tensor, log_scores: torch.Tensor, k: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``k`` best-scoring grid boxes of each row and their mixture log-probabilities.

    Args:
        boxes: ``(B, G, 4)``; log_scores: ``(B, G)`` (e.g. the log-likelihood of each box).

    Returns:
        ``(cells (B, k, 4), log_pi (B, k))``: the boxes and ``log_softmax`` of their scores.
    """
    k = min(int(k), boxes.shape[1])
    s, idx = log_scores.topk(k, dim=1)
    cells = boxes.gather(1, idx.unsqueeze(2).expand(-1, -1, 4))
    return cells, torch.log_softmax(s.to(torch.float64), dim=1)


def draw_around(
    cells: torch.Tensor,
    log_pi: torch.Tensor,
    n: int,
    sigma: torch.Tensor,
    generator: GeneratorLike = None,
) -> torch.Tensor:
    """``n`` box centres per row from the mixture ``d(x) = sum_k pi_k N(x; c_k, diag(sigma^2))``.

    Args:
        cells: ``(B, K, 4)`` mixture component boxes (their centres are the means).
        log_pi: ``(B, K)`` normalised log mixture weights.
        n: samples per row.
        sigma: ``(B, 2)`` standard deviation in x and y (pixels).

    Returns:
        ``(centres (B, n, 2), component (B, n) int64)``.
    """
    b, k, _ = cells.shape
    u = rand((b, n), generator, torch.float64, cells.device)
    cdf = log_pi.exp().cumsum(1)
    comp = torch.searchsorted(cdf.contiguous(), u.contiguous()).clamp_max(k - 1)
    c = cells[..., 0:2] + cells[..., 2:4] / 2  # (B, K, 2)
    mu = c.gather(1, comp.unsqueeze(2).expand(b, n, 2))
    e = randn((b, n, 2), generator, mu.dtype, mu.device)
    return mu + e * sigma[:, None, :].to(mu.dtype), comp


def _log_normal(x: torch.Tensor, mu: torch.Tensor, sd: torch.Tensor) -> torch.Tensor:
    """Diagonal Gaussian log density; ``x (..., 2)``, ``mu``, ``sd`` broadcast."""
    z = (x - mu) / sd
    return -0.5 * (z * z).sum(-1) - torch.log(sd).sum(-1) - _LOG_2PI


def search_log_weights(
    x: torch.Tensor,
    cells: torch.Tensor,
    log_pi: torch.Tensor,
    cell_sd: torch.Tensor,
    log_u: torch.Tensor,
    eps: torch.Tensor | float,
    n_predicted: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Prior-over-proposal log factors of the two particle groups (module doc).

    Args:
        x: ``(B, M, 2)`` centres of the search particles (from :func:`draw_around`).
        cells, log_pi, cell_sd: the search mixture ``d``.
        log_u: ``(B,)`` log density of the uniform jump (``-log`` of the searched area,
            pixels^2).
        eps: ``(B,)`` or a float, the jump probability of the prior, in (0, 1).
        n_predicted: ``N - M``, particles drawn from the motion model.

    Returns:
        ``(log factor of the predicted particles (B,), log factors of the search particles
        (B, M))``, float64, to be added to the log-likelihoods.
    """
    b, m, _ = x.shape
    eps_t = torch.as_tensor(eps, dtype=torch.float64, device=x.device).expand(b)
    if bool(((eps_t <= 0) | (eps_t >= 1)).any()) or n_predicted < 1 or m < 1:
        raise ConfigError(
            f"need 0 < eps < 1 and particles in both groups, got eps {eps_t.tolist()}, "
            f"{n_predicted} predicted, {m} search particles"
        )
    x = x.to(torch.float64)
    c = (cells[..., 0:2] + cells[..., 2:4] / 2).to(x)  # (B, K, 2)
    log_dk = _log_normal(x[:, :, None, :], c[:, None], cell_sd[:, None, None, :].to(x))
    log_d = torch.logsumexp(log_dk + log_pi[:, None, :].to(x), dim=2)  # (B, M)
    pred = torch.log1p(-eps_t) - math.log(n_predicted)
    search = (torch.log(eps_t) + log_u.to(x) - math.log(m))[:, None] - log_d
    return pred, search
