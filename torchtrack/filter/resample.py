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
forms; multinomial and residual counts merge sorted uniforms (exponential spacings, no sort)
with the CDF through unit-width bins (``_count_below``), with no binary search. Randomness comes
only from ``generator``. On CPU, fresh large buffers cost page faults (a visible share of the
time at N = 10^5), so the schemes work in place, in int32 where values allow, and keep few
temporaries alive at once.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable

import numpy as np
import torch

from torchtrack.errors import ConfigError, FilterError, ShapeError
from torchtrack.filter._random import GeneratorLike, rand
from torchtrack.filter.particles import _capturing, ess, normalize_log_weights

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


_BAD_WEIGHTS = (
    "resampling weights must be non-negative with a positive finite sum in every row "
    "(use resample() with log-weights to get all-zero rows restarted uniform)"
)


def _totals(c: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Row totals ``(B, 1)`` of a cumulative sum (a view: callers divide it before writing to
    ``c``); FilterError unless positive and finite, or if a weight of ``weights`` (whose sums
    ``c`` holds) is negative. One read from the device for both checks."""
    last = c[:, -1:]
    if _capturing(c):  # a CUDA graph being recorded: checked after replay (GraphedSIR)
        return last
    lo, hi = torch.aminmax(last)
    lo, hi, least = torch.stack([lo, hi, weights.amin().to(lo.dtype)]).tolist()
    if not (lo > 0 and hi < math.inf) or least < 0:  # also false for NaN
        raise FilterError(_BAD_WEIGHTS)
    return last


def _cdf(weights: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
    """``(B, N)`` float64 CDF times ``scale`` (the last entry ``scale`` up to rounding)."""
    c = weights.to(torch.float64).cumsum(1)
    return c.mul_(scale / _totals(c, weights))


def _histogram(x: torch.Tensor, size: int) -> torch.Tensor:
    """``torch.bincount(x, minlength=size)`` for ``0 <= x < size``; off the CPU a scatter-add,
    which needs no read of ``x.max()`` back to the host."""
    if x.device.type == "cpu":
        return torch.bincount(x, minlength=size)
    h = torch.zeros(size, dtype=torch.int64, device=x.device)
    return h.index_add_(0, x, torch.ones_like(x, dtype=torch.int64))


def _invert(cdf: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Ancestors for uniforms ``u (B, M)`` in [0, 1): the first index with ``cdf > u``."""
    idx = torch.searchsorted(cdf, u.contiguous(), right=True)
    # u < 1 = cdf[-1] always; the clamp only guards rounding on u -> 1.
    return idx.clamp_(max=cdf.shape[1] - 1)


def _ancestors(pos: torch.Tensor, b: int, m: int) -> torch.Tensor:
    """Row-offset cumulative offspring counts -> sorted ancestors ``(B, M)``.

    ``pos (B * N,)`` or ``(B, N)``: ``b * (M + 1) + cum[b, i]``, where ``cum[b, i]`` (non-
    decreasing along the row, at most M) is the number of offspring of particles ``0..i``. The
    ancestor of new particle j is ``#{i : cum[b, i] <= j}``: one histogram and one cumulative
    sum, O(N) with no search.
    """
    h = _histogram(pos.reshape(-1), b * (m + 1)).view(b, m + 1)
    # In place where the slice stays contiguous (B = 1): a fresh buffer costs page faults.
    return h.cumsum_(1)[:, :m] if b == 1 else h[:, :m].cumsum(1)


def _row_offsets(b: int, stride: int, device: torch.device, dtype=torch.int64) -> torch.Tensor:
    """``(B, 1)`` ``b * stride``: row offsets into a flattened ``(B, stride)`` layout."""
    return (torch.arange(b, device=device, dtype=dtype) * stride).unsqueeze(1)


# Forward steps of _count_below over all values at once (and sentinels padding _sorted_uniforms),
# then over the values still moving, _WINDOW at a time.
_STEPS = 3
_WINDOW = 8


def _sorted_uniforms(
    b: int,
    k: int,
    generator: GeneratorLike,
    device: torch.device,
    count: torch.Tensor | None = None,
    top: torch.Tensor | None = None,
) -> torch.Tensor:
    """Row-sorted i.i.d. uniforms, flat: ``(B * (k + 1) + _STEPS,)`` float64.

    Row b (``[b * (k + 1), (b + 1) * (k + 1))``) holds ``count[b] <= k`` sorted uniforms (k if
    ``count`` is None) on ``[0, top[b])`` (``[0, k)`` if ``top`` is None), then the sentinel
    ``k + 1``, above every CDF value given to ``_count_below``; ``_STEPS`` more sentinels end
    the buffer. ``S_j / S_{c+1}`` (S: cumulative sums of c + 1 Exp(1) draws) are the order
    statistics of c i.i.d. uniforms: O(k), no sort. Row b draws ``count[b] + 1`` numbers from
    its generator when ``generator`` is a list (so a batch of B equals B single runs), the whole
    ``(B, k + 1)`` block from a single generator.
    """
    row = k + 1
    flat = torch.empty(b * row + _STEPS, dtype=torch.float64, device=device)
    flat[b * row :] = row
    s = flat[: b * row].view(b, row)
    lengths = None if count is None else [c + 1 for c in count.tolist()]
    rand((b, row), generator, torch.float64, device, out=s, lengths=lengths)
    # log(1 - U) = -Exp(1), in place (fresh buffers cost page faults on CPU); its cumulative sum
    # is -S, and the ratios below cancel the sign exactly.
    s.neg_().log1p_().cumsum_(1)
    if count is None:
        s.mul_(k / s[:, -1:])
        s[:, -1] = row
    else:
        s.mul_(top.unsqueeze(1) / torch.gather(s, 1, count.unsqueeze(1)))  # top S_j / S_{c+1}
        if b == 1:
            s[0, lengths[0] - 1 :] = row
        else:
            j = torch.arange(row, device=device, dtype=torch.int32).unsqueeze(0)
            s.masked_fill_(j >= count.unsqueeze(1), row)
    return flat


def _index_dtype(numel: int) -> torch.dtype:
    """int32 for bins, positions and counts below 2^31 (half the memory of int64)."""
    return torch.int32 if numel < 2**31 else torch.int64


def _nonzero(mask: torch.Tensor) -> torch.Tensor:
    """Indices of the True entries of a 1-D ``mask`` (NumPy's on CPU: several times faster)."""
    if mask.device.type == "cpu":
        return torch.from_numpy(np.flatnonzero(mask.numpy()))
    return mask.nonzero().squeeze(1)


def _count_below(u: torch.Tensor, b: int, cdf: torch.Tensor) -> torch.Tensor:
    """``b * L + #{j : s[b, j] < cdf[b, i]}`` as flat ``(B * N,)`` positions
    (``_index_dtype(B * (L + 2))``).

    ``u``: ``_sorted_uniforms``' buffer, rows ``s (B, L)`` sorted with values in ``[0, L]``,
    each ending with the sentinel L; ``cdf (B, N)`` float64 in ``[0, L)``. Up to 2^13 values
    take a binary search each (``torch.searchsorted``), more the merge of ``_merge_below``: the
    same counts, whichever is faster (measured on CPU: the merge's ~40 tensor operations cost
    more than the searches below ~8000 values, the searches several times more at 10^5).
    """
    row = (u.numel() - _STEPS) // b
    if cdf.numel() > 2**13:
        return _merge_below(u, b, cdf)
    s = u[: b * row].view(b, row)
    pos = torch.searchsorted(
        s, cdf, right=False, out_int32=_index_dtype(b * (row + 2)) == torch.int32
    )
    if b > 1:
        pos += _row_offsets(b, row, u.device, pos.dtype)
    return pos.view(-1)


def _merge_below(u: torch.Tensor, b: int, cdf: torch.Tensor) -> torch.Tensor:
    """``_count_below`` by a merge of the sorted rows, with no binary search per value
    (``torch.searchsorted`` costs ~17 dependent, mispredicted steps per value at N = 10^5).

    Unit-width bins ``floor(x)`` are monotone in x (in floating point too), so every ``s`` in a
    lower bin than ``c`` is below it and every one in a higher bin is above it. A histogram of
    the bins of ``s`` and its cumulative sum give the position of the first ``s`` in the bin of
    each ``c``; stepping forward over the ``s`` of that bin below ``c`` (Poisson(1)-many when
    the uniforms spread over ``[0, L - 1)``) finishes the count: ``_STEPS`` steps over all
    values, then steps over the few that still move. Memory: fresh buffers cost page faults on
    CPU, a visible share of the time, so temporaries are few, int32 where they can be, and
    released early.
    """
    row = (u.numel() - _STEPS) // b
    s = u[: b * row].view(b, row)
    cf = cdf.reshape(-1)
    it = _index_dtype(b * (row + 2))
    ks = s.to(it)  # bins 0..L; + 1 makes the cumulative sum below exclusive
    ks += 1 if b == 1 else _row_offsets(b, row + 2, u.device, it) + 1
    hist = _histogram(ks.view(-1), b * (row + 2))
    del ks
    start = hist.cumsum_(0).to(it)  # flat index of the first s in each bin
    del hist
    kc = cdf.to(it)
    if b > 1:
        kc += _row_offsets(b, row + 2, u.device, it)
    pos = start.index_select(0, kc.view(-1))
    del kc, start
    # Step t reads u at pos + t (the padding keeps the last row in range) and counts only while
    # every earlier step did: a row's sentinel stops the run before the next row's small values.
    v = torch.empty_like(cf)
    run = torch.lt(torch.index_select(u, 0, pos, out=v), cf)
    ahead, step = run.to(torch.uint8), torch.empty_like(run)
    for t in range(1, _STEPS):
        torch.lt(torch.index_select(u[t:], 0, pos, out=v), cf, out=step)
        ahead += run.logical_and_(step)
    # pos += ahead, with v's memory holding ahead in pos' dtype (a mixed-dtype add would
    # allocate that copy).
    pos += v.view(pos.dtype)[: pos.numel()].copy_(ahead)
    del v, step, ahead
    # The few still below c after _STEPS steps take their next _WINDOW steps at once (prefix
    # products keep the count to the run before the first u not below c), more only if needed.
    moving = _nonzero(run)
    del run
    window = torch.arange(_WINDOW, device=u.device, dtype=pos.dtype)
    while moving.numel():
        p, c = pos.index_select(0, moving), cf.index_select(0, moving)
        at = (p.unsqueeze(1) + window).clamp_(max=u.numel() - 1).view(-1)
        below = torch.lt(u.index_select(0, at).view(-1, _WINDOW), c.unsqueeze(1))
        below = below.to(pos.dtype).cumprod_(1)
        pos.index_copy_(0, moving, p.add_(below.sum(1, dtype=pos.dtype)))
        more = below[:, -1]
        moving = moving[more.bool()] if bool(more.any()) else moving[:0]
    return pos


def _check_weights(weights: torch.Tensor, n_out: int | None) -> tuple[int, int]:
    """``(B, M)`` for weights ``(B, N)``; ShapeError for another shape, ConfigError for an
    ``n_out`` that is not a positive integer (negative weights, NaN and rows without positive
    finite mass are caught by ``_totals``)."""
    if not isinstance(weights, torch.Tensor) or weights.ndim != 2 or weights.shape[1] == 0:
        shape = tuple(weights.shape) if isinstance(weights, torch.Tensor) else type(weights)
        raise ShapeError(f"weights must be a (B, N) tensor with N >= 1, got {shape}")
    if n_out is None:
        return weights.shape[0], weights.shape[1]
    # -3 raised torch's RuntimeError, 0 an IndexError (stratified), 2.5 drew 2, silently
    if isinstance(n_out, bool) or not isinstance(n_out, (int, np.integer)) or n_out < 1:
        raise ConfigError(f"n_out must be None or an integer >= 1 (particles drawn), got {n_out!r}")
    return weights.shape[0], int(n_out)


def _no_rows(n: int, device: torch.device) -> torch.Tensor:
    return torch.zeros(0, n, dtype=torch.int64, device=device)


def multinomial(
    weights: torch.Tensor, generator: GeneratorLike = None, n_out: int | None = None
) -> torch.Tensor:
    """Multinomial resampling: i.i.d. draws from the weights, ``(B, N) -> (B, M)``.

    Sorted uniforms come from normalised cumulative sums of exponential spacings (O(N), no
    sort), as in ``particles.resampling.multinomial``; their counts below each CDF value come
    from a merge through unit-width bins (``_count_below``); the ancestors come out sorted.
    """
    b, n = _check_weights(weights, n_out)
    if b == 0:
        return _no_rows(n, weights.device)
    u = _sorted_uniforms(b, n, generator, weights.device)  # on [0, M)
    pos = _count_below(u, b, _cdf(weights, n))  # CDF scaled to [0, M] like the uniforms
    del u
    return _ancestors(pos, b, n)


def stratified(
    weights: torch.Tensor, generator: GeneratorLike = None, n_out: int | None = None
) -> torch.Tensor:
    """Stratified resampling: one uniform in each stratum ``[j/M, (j+1)/M)``.

    Offspring counts need no search: with ``k = floor(M c)``, the number of points
    ``(j + U_j) / M`` below a CDF value c is ``k + [U_k < M c - k]``.
    """
    b, n = _check_weights(weights, n_out)
    if b == 0:
        return _no_rows(n, weights.device)
    uj = rand((b, n), generator, torch.float64, weights.device)
    x = _cdf(weights, n)
    # k = floor(M c) clamped to M - 1; at c = 1 the fraction is then 1 and U_k < 1 counts the
    # last point, so cum = M there as it must.
    k = x.long().clamp_(max=n - 1)
    frac = x.sub_(k)
    if b > 1:  # flat indices into uj (B * M,)
        k += _row_offsets(b, n, weights.device)
    k += uj.view(-1).index_select(0, k.view(-1)).view(b, -1) < frac
    if b > 1:  # row offsets b * M -> b * (M + 1) for _ancestors
        k += _row_offsets(b, 1, weights.device)
    return _ancestors(k, b, n)


def systematic(
    weights: torch.Tensor, generator: GeneratorLike = None, n_out: int | None = None
) -> torch.Tensor:
    """Systematic resampling: points ``(j + U) / M`` with one uniform U per row.

    Offspring counts need no search: ``ceil(M c - U)`` points lie below a CDF value c.
    """
    b, n = _check_weights(weights, n_out)
    if b == 0:
        return _no_rows(n, weights.device)
    u = rand((b, 1), generator, torch.float64, weights.device)
    c = weights.to(torch.float64).cumsum(1)
    # c <- M c / c_last - U in one fused pass; 0 <= c / c_last <= 1 exactly (monotone cumsum of
    # non-negative weights), so ceil lies in [0, M] without a clamp.
    torch.addcmul(-u, c, n / _totals(c, weights), out=c)
    cum = c.ceil_().long()
    if b > 1:
        cum += _row_offsets(b, n + 1, weights.device)
    return _ancestors(cum, b, n)


def residual(
    weights: torch.Tensor, generator: GeneratorLike = None, n_out: int | None = None
) -> torch.Tensor:
    """Residual resampling: ``floor(M w_i)`` deterministic copies, the remaining
    ``R = M - sum floor(M w_i)`` drawn multinomially from the residuals ``M w_i - floor(M w_i)``.

    Row b draws ``R_b + 1`` uniforms (with a list of generators, from its own; from one
    generator, ``max_b R_b + 1`` per row), as ``particles.resampling.residual`` does.
    """
    b, n = _check_weights(weights, n_out)
    if b == 0:
        return _no_rows(n, weights.device)
    nw = weights.to(torch.float64, copy=True)
    nw.mul_(n / _totals(nw.sum(1, keepdim=True), weights))
    floor = nw.to(_index_dtype(b * (n + 1)))  # floor(M w) (M w >= 0)
    # Residuals M w - floor(M w) = frac(M w) exactly, in place, and their unnormalised CDF.
    rest = nw.frac_().cumsum_(1)
    r = n - floor.sum(1)  # (B,) residual draws per row, 0 <= r <= M
    k = int(r.max())
    # r sorted uniforms per row, scaled to [0, R_total): no normalisation pass over the CDF.
    u = _sorted_uniforms(b, k, generator, weights.device, count=r, top=rest[:, -1])
    pos = _count_below(u, b, rest)  # b * (k + 1) + residual offspring of particles 0..i
    del u, rest
    floor.cumsum_(1)
    if b > 1:  # row offsets b * (k + 1) -> b * (M + 1) for _ancestors
        floor += _row_offsets(b, n - k, weights.device, floor.dtype)
    pos = pos.to(floor.dtype)  # the same dtype unless B * (M + 1) >= 2^31 > B * (k + 3)
    pos += floor.view(-1)
    return _ancestors(pos, b, n)


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
        ConfigError: unknown scheme or ``ess_fraction`` not a number in (0, 1] (a string or a
            bool is refused).
        FilterError: NaN log-weights.
    """
    fn = get_resampler(scheme)
    # "0.5" and True passed through float(); NaN fails the comparison and is refused too
    if ess_fraction is not None and (
        isinstance(ess_fraction, bool)
        or not isinstance(ess_fraction, numbers.Real)
        or not (0.0 < float(ess_fraction) <= 1.0)
    ):
        raise ConfigError(
            f"ess_fraction must be None or in (0, 1] (a number), got {ess_fraction!r}"
        )
    lw, _ = normalize_log_weights(log_weights, step=step)
    b, n = lw.shape
    ancestors = fn(lw.exp(), generator)
    uniform = torch.full_like(lw, -math.log(n))
    if ess_fraction is None:  # every row resampled: no selection pass needed
        return ancestors, uniform, torch.ones(b, dtype=torch.bool, device=lw.device)
    do = ess(lw) < float(ess_fraction) * n
    identity = torch.arange(n, device=lw.device).expand(b, n)
    ancestors = torch.where(do.unsqueeze(1), ancestors, identity)
    new_lw = torch.where(do.unsqueeze(1), uniform, lw)
    return ancestors, new_lw, do
