"""Resampling schemes, batched over B, chosen by name from one registry.

Every scheme maps normalised weights ``(B, N)`` to ancestor indices ``(B, M)`` (int64; M = N
unless ``n_out`` says otherwise, e.g. SEIR's selection of N out of 3N): the new
particle j of row b is a copy of old particle ``ancestors[b, j]``. Returning indices rather than
states lets callers carry any per-particle data along the ancestry (per-particle observation
models, Klein et al. section III).

All schemes turn the weights' cumulative distribution (accumulated in float64 whatever the
weights' dtype, so float32 weights with N = 10^6 lose no mass to rounding) into cumulative
offspring counts, then counts into sorted ancestors with one histogram and one cumulative sum:
O(N) per row, no Python loop over particles or rows. Systematic and stratified counts are closed
forms; multinomial and residual counts need one sorted search. Randomness comes only from
``generator``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from torchtrack.errors import ConfigError, FilterError, ShapeError
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


def _totals(c: torch.Tensor) -> torch.Tensor:
    """Row totals ``(B, 1)`` of a cumulative sum; FilterError unless positive and finite."""
    last = c[:, -1:].clone()
    if not bool(((last > 0) & torch.isfinite(last)).all()):
        raise FilterError(
            "resampling weights must be non-negative with a positive finite sum in every row "
            "(use resample() with log-weights to get all-zero rows restarted uniform)"
        )
    return last


def _cdf(weights: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
    """``(B, N)`` float64 CDF times ``scale``, the last entry exactly ``scale``."""
    c = weights.to(torch.float64).cumsum(1)
    # In place: fresh large allocations cost page faults on CPU, a visible share of the time.
    return c.mul_(scale / _totals(c))


def _invert(cdf: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Ancestors for uniforms ``u (B, M)`` in [0, 1): the first index with ``cdf > u``."""
    idx = torch.searchsorted(cdf, u.contiguous(), right=True)
    # u < 1 = cdf[-1] always; the clamp only guards rounding on u -> 1.
    return idx.clamp_(max=cdf.shape[1] - 1)


def _ancestors_from_cumcounts(cum: torch.Tensor, n_out: int) -> torch.Tensor:
    """Offspring cumulative counts ``cum (B, N)`` (non-decreasing, last = n_out) -> ancestors.

    ``cum[b, i]`` is the number of offspring of particles ``0..i``; the ancestor of new particle
    j is ``#{i : cum[b, i] <= j}``: a histogram of ``cum`` and a cumulative sum, O(N) with no
    search (faster than a binary search per particle).
    """
    b = cum.shape[0]
    if b > 1:
        cum = cum + (torch.arange(b, device=cum.device) * (n_out + 1)).unsqueeze(1)
    hist = torch.bincount(cum.flatten(), minlength=b * (n_out + 1)).view(b, n_out + 1)
    return hist[:, :n_out].cumsum(1)


def _count_below(u: torch.Tensor, cdf: torch.Tensor) -> torch.Tensor:
    """``#{j : u[b, j] < cdf[b, i]}`` for row-sorted ``u (B, M)`` and ``cdf (B, N)`` -> (B, N).

    On CPU one NumPy ``searchsorted`` over all rows at once (rows shifted apart by 2 b; NumPy's
    search exploits sorted queries and is several times faster than ``torch.searchsorted``).
    """
    if u.device.type == "cpu":
        import numpy as np

        b, m = u.shape
        shift = 2.0 * torch.arange(b, dtype=torch.float64).unsqueeze(1)
        uu = (u + shift).flatten().numpy()
        cc = (cdf + shift).flatten().numpy()
        cnt = torch.from_numpy(np.searchsorted(uu, cc, side="left")).view(b, -1)
        return cnt - (torch.arange(b) * m).unsqueeze(1)
    return torch.searchsorted(u.contiguous(), cdf.contiguous(), right=False)


def _sorted_uniforms(
    b: int,
    m: int,
    generator: GeneratorLike,
    device: torch.device,
    count: torch.Tensor | None = None,
) -> torch.Tensor:
    """Row-sorted i.i.d. uniforms ``(B, m)`` from normalised sums of exponential spacings (O(m),
    no sort). With ``count (B,)``, row b holds ``count[b]`` sorted uniforms followed by 2.0
    (never below a CDF value)."""
    # -log(1 - U) ~ Exp(1), computed in place (fresh buffers cost page faults on CPU).
    s = rand((b, m + 1), generator, torch.float64, device).neg_().log1p_().neg_().cumsum_(1)
    if count is None:
        return s[:, :m].div_(s[:, -1:])
    u = s[:, :m].div_(torch.gather(s, 1, count.unsqueeze(1)))  # S_j / S_{count+1}
    j = torch.arange(m, device=device).unsqueeze(0)
    return u.masked_fill_(j >= count.unsqueeze(1), 2.0)


def _check_weights(weights: torch.Tensor) -> None:
    if not isinstance(weights, torch.Tensor) or weights.ndim != 2 or weights.shape[1] == 0:
        shape = tuple(weights.shape) if isinstance(weights, torch.Tensor) else type(weights)
        raise ShapeError(f"weights must be a (B, N) tensor with N >= 1, got {shape}")


def multinomial(
    weights: torch.Tensor, generator: GeneratorLike = None, n_out: int | None = None
) -> torch.Tensor:
    """Multinomial resampling: i.i.d. draws from the weights, ``(B, N) -> (B, M)``.

    Sorted uniforms come from normalised cumulative sums of exponential spacings (O(N), no
    sort), as in ``particles.resampling.multinomial``; the ancestors come out sorted.
    """
    _check_weights(weights)
    b, n_in = weights.shape
    n = n_in if n_out is None else int(n_out)
    u = _sorted_uniforms(b, n, generator, weights.device)
    return _ancestors_from_cumcounts(_count_below(u, _cdf(weights)), n)


def stratified(
    weights: torch.Tensor, generator: GeneratorLike = None, n_out: int | None = None
) -> torch.Tensor:
    """Stratified resampling: one uniform in each stratum ``[j/M, (j+1)/M)``.

    Offspring counts need no search: with ``k = floor(M c)``, the number of points
    ``(j + U_j) / M`` below a CDF value c is ``k + [U_k < M c - k]``.
    """
    _check_weights(weights)
    b, n_in = weights.shape
    n = n_in if n_out is None else int(n_out)
    uj = rand((b, n), generator, torch.float64, weights.device)
    x = _cdf(weights, n)
    # k = floor(M c) clamped to M - 1; at c = 1 the fraction is then 1 and U_k < 1 counts the
    # last point, so cum = M there as it must.
    k = x.floor().clamp_(max=n - 1)
    frac = x.sub_(k)
    ki = k.long()
    return _ancestors_from_cumcounts(ki.add_(torch.gather(uj, 1, ki) < frac), n)


def systematic(
    weights: torch.Tensor, generator: GeneratorLike = None, n_out: int | None = None
) -> torch.Tensor:
    """Systematic resampling: points ``(j + U) / M`` with one uniform U per row.

    Offspring counts need no search: ``ceil(M c - U)`` points lie below a CDF value c.
    """
    _check_weights(weights)
    b, n_in = weights.shape
    n = n_in if n_out is None else int(n_out)
    u = rand((b, 1), generator, torch.float64, weights.device)
    c = weights.to(torch.float64).cumsum(1)
    # c <- M c / c_last - U in one fused pass; 0 <= c / c_last <= 1 exactly (monotone cumsum of
    # non-negative weights), so ceil lies in [0, M] without a clamp.
    torch.addcmul(-u, c, n / _totals(c), out=c)
    return _ancestors_from_cumcounts(c.ceil_().long(), n)


def residual(
    weights: torch.Tensor, generator: GeneratorLike = None, n_out: int | None = None
) -> torch.Tensor:
    """Residual resampling: ``floor(M w_i)`` deterministic copies, the remaining
    ``R = M - sum floor(M w_i)`` drawn multinomially from the residuals ``M w_i - floor(M w_i)``."""
    _check_weights(weights)
    b, n_in = weights.shape
    n = n_in if n_out is None else int(n_out)
    nw = weights.to(torch.float64, copy=True)
    nw.mul_(n / _totals(nw.sum(1, keepdim=True)))
    floor = nw.floor()
    rest = nw.sub_(floor)  # residual weights M w - floor(M w), in place
    floor = floor.long()
    r = n - floor.sum(1)  # (B,) residual draws per row, 0 <= r <= M
    empty = rest.sum(1) <= 0
    if bool(empty.any()):  # every weight an exact multiple of 1/M: no residual mass
        rest[empty] = 1.0
    # Always M uniforms per row (not max(r)): a row's random stream must not depend on the
    # other rows of the batch (a batch of B equals B single runs with the same generators).
    u = _sorted_uniforms(b, n, generator, weights.device, count=r)
    cum = floor.cumsum_(1).add_(_count_below(u, _cdf(rest)))
    return _ancestors_from_cumcounts(cum, n)


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
