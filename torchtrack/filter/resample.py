"""Resampling schemes, batched over B, chosen by name from one registry.

Every scheme maps normalised weights ``(B, N)`` to ancestor indices ``(B, M)`` (int64; M = N
unless ``n_out`` says otherwise, e.g. SEIR's selection of N out of 3N): the new
particle j of row b is a copy of old particle ``ancestors[b, j]``. Returning indices rather than
states lets callers carry any per-particle data along the ancestry (per-particle observation
models, Klein et al. section III).

All schemes invert the weights' cumulative distribution with ``torch.searchsorted`` on sorted
uniforms; the CDF is accumulated in float64 whatever the weights' dtype, so float32 weights
with N = 10^6 do not lose mass to rounding. Randomness comes only from ``generator``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from torchtrack.errors import ConfigError, ShapeError
from torchtrack.filter._random import GeneratorLike, rand
from torchtrack.filter.particles import ess, normalize_log_weights

__all__ = [
    "RESAMPLERS",
    "get_resampler",
    "multinomial",
    "resample",
    "residual",
    "stratified",
    "systematic",
]

Resampler = Callable[..., torch.Tensor]


def _cdf(weights: torch.Tensor) -> torch.Tensor:
    """``(B, N)`` float64 CDF with the last entry exactly 1."""
    c = weights.to(torch.float64).cumsum(1)
    return c / c[:, -1:]


def _invert(cdf: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Ancestors for uniforms ``u (B, M)`` in [0, 1): the first index with ``cdf > u``."""
    idx = torch.searchsorted(cdf, u.contiguous(), right=True)
    # u < 1 = cdf[-1] always; the clamp only guards rounding on u -> 1.
    return idx.clamp_(max=cdf.shape[1] - 1)


def _check_weights(weights: torch.Tensor) -> None:
    if not isinstance(weights, torch.Tensor) or weights.ndim != 2 or weights.shape[1] == 0:
        shape = tuple(weights.shape) if isinstance(weights, torch.Tensor) else type(weights)
        raise ShapeError(f"weights must be a (B, N) tensor with N >= 1, got {shape}")


def multinomial(
    weights: torch.Tensor, generator: GeneratorLike = None, n_out: int | None = None
) -> torch.Tensor:
    """Multinomial resampling: N i.i.d. draws from the weights, ``(B, N) -> (B, N)``.

    Sorted uniforms come from normalised cumulative sums of exponential spacings (O(N), no
    sort), as in ``particles.resampling.multinomial``; the ancestors come out sorted.
    """
    _check_weights(weights)
    b, n_in = weights.shape
    n = n_in if n_out is None else int(n_out)
    e = -torch.log1p(-rand((b, n + 1), generator, torch.float64, weights.device))
    s = e.cumsum(1)
    u = s[:, :-1] / s[:, -1:]
    return _invert(_cdf(weights), u)


def stratified(
    weights: torch.Tensor, generator: GeneratorLike = None, n_out: int | None = None
) -> torch.Tensor:
    """Stratified resampling: one uniform in each stratum ``[j/N, (j+1)/N)``."""
    _check_weights(weights)
    b, n_in = weights.shape
    n = n_in if n_out is None else int(n_out)
    j = torch.arange(n, dtype=torch.float64, device=weights.device)
    u = (j + rand((b, n), generator, torch.float64, weights.device)) / n
    return _invert(_cdf(weights), u)


def systematic(
    weights: torch.Tensor, generator: GeneratorLike = None, n_out: int | None = None
) -> torch.Tensor:
    """Systematic resampling: one uniform per row, shifted by ``j/N``."""
    _check_weights(weights)
    b, n_in = weights.shape
    n = n_in if n_out is None else int(n_out)
    j = torch.arange(n, dtype=torch.float64, device=weights.device)
    u = (j + rand((b, 1), generator, torch.float64, weights.device)) / n
    return _invert(_cdf(weights), u)


def residual(
    weights: torch.Tensor, generator: GeneratorLike = None, n_out: int | None = None
) -> torch.Tensor:
    """Residual resampling: ``floor(N w_i)`` deterministic copies, the rest multinomial on the
    residual weights ``N w_i - floor(N w_i)``."""
    _check_weights(weights)
    b, n_in = weights.shape
    n = n_in if n_out is None else int(n_out)
    w64 = weights.to(torch.float64)
    nw = w64 * (n / w64.sum(1, keepdim=True))
    counts = nw.floor()
    rest = nw - counts
    counts = counts.long()
    r = n - counts.sum(1)  # (B,) residual draws per row, 0 <= r < N
    # N unsorted i.i.d. draws per row; only the first r[b] count (i.i.d., so any r of them do).
    u = rand((b, n), generator, torch.float64, weights.device)
    has_rest = rest.sum(1, keepdim=True) > 0
    rest = torch.where(has_rest, rest, torch.ones_like(rest))
    extra = _invert(_cdf(rest), u)
    keep = torch.arange(n, device=weights.device).unsqueeze(0) < r.unsqueeze(1)
    counts.scatter_add_(1, extra, keep.long())
    # counts -> indices: each row sums to N, so the flat repeat has B * N entries.
    flat = torch.repeat_interleave(
        torch.arange(b * n_in, device=weights.device), counts.flatten(), output_size=b * n
    )
    return flat.view(b, n) - (torch.arange(b, device=weights.device) * n_in).unsqueeze(1)


RESAMPLERS: dict[str, Resampler] = {
    "multinomial": multinomial,
    "residual": residual,
    "stratified": stratified,
    "systematic": systematic,
}


def get_resampler(name: str) -> Resampler:
    """The resampler registered under ``name``.

    Raises:
        ConfigError: unknown name (the message lists the valid ones).
    """
    try:
        return RESAMPLERS[name]
    except (KeyError, TypeError):
        raise ConfigError(
            f"unknown resampling scheme {name!r}; valid: {', '.join(sorted(RESAMPLERS))}"
        ) from None


def resample(
    log_weights: torch.Tensor,
    scheme: str = "systematic",
    ess_fraction: float | None = None,
    generator: GeneratorLike = None,
    step: str = "resample",
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Resample each batch row always, or only where ESS falls below a threshold.

    Args:
        log_weights: ``(B, N)`` log-weights, normalised or not.
        scheme: a name in ``RESAMPLERS``.
        ess_fraction: None resamples every row; a float ``f`` in (0, 1] resamples only the rows
            with ``ESS < f * N`` (the others keep their particles and weights).
        generator: a ``torch.Generator``, a sequence of B generators (one per row) or None.
        step: caller name for error messages.

    Returns:
        ``(ancestors (B, N) int64, new_log_weights (B, N), resampled (B,) bool)``. Rows not
        resampled have identity ancestors and keep their (normalised) log-weights; resampled
        rows get ``-log N``.

    Raises:
        ConfigError: unknown scheme or ``ess_fraction`` outside (0, 1].
        FilterError: NaN log-weights.
    """
    fn = get_resampler(scheme)
    if ess_fraction is not None and not (0.0 < float(ess_fraction) <= 1.0):
        raise ConfigError(f"ess_fraction must be None or in (0, 1], got {ess_fraction!r}")
    lw, _ = normalize_log_weights(log_weights, step=step)
    b, n = lw.shape
    ancestors = fn(lw.exp(), generator)
    if ess_fraction is None:
        do = torch.ones(b, dtype=torch.bool, device=lw.device)
    else:
        do = ess(lw) < float(ess_fraction) * n
        identity = torch.arange(n, device=lw.device).expand(b, n)
        ancestors = torch.where(do.unsqueeze(1), ancestors, identity)
    uniform = torch.full_like(lw, -math.log(n))
    new_lw = torch.where(do.unsqueeze(1), uniform, lw)
    return ancestors, new_lw, do
