"""Random draws for batched filters, from an explicit generator or one generator per batch row.

Every random number the filter package uses goes through these helpers, so that a caller can
pass either one ``torch.Generator`` (one stream for the whole batch: fastest) or a sequence of
``B`` generators (one stream per batch row). The second form makes a row's result independent of
which other rows share the batch: a batch of B equals B single runs with the same generators,
which multi-target trackers need when targets come and go.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from torchtrack.errors import ConfigError

__all__ = [
    "GeneratorLike",
    "check_generator",
    "multinomial",
    "rand",
    "randint",
    "randn",
    "randperm",
    "subset",
]

GeneratorLike = torch.Generator | Sequence[torch.Generator] | None


def check_generator(generator: object) -> None:
    """ConfigError unless ``generator`` is None, a ``torch.Generator`` or a sequence of them
    (one per batch row): 5 was 'int' object is not iterable, a string a 'sequence of 4'
    generators, ``[None]`` reached torch."""
    if generator is None or isinstance(generator, torch.Generator):
        return
    if isinstance(generator, Sequence) and not isinstance(generator, (str, bytes)):
        odd = [g for g in generator if not isinstance(g, torch.Generator)]
        if not odd:
            return
        got = f"a sequence holding {type(odd[0]).__name__}"
    else:
        got = f"{type(generator).__name__} {generator!r}"
    raise ConfigError(
        "generator must be None, a torch.Generator or a sequence of torch.Generator (one per "
        f"batch row), got {got}"
    )


def _draw(
    fn,
    shape: tuple[int, ...],
    generator: GeneratorLike,
    dtype,
    device,
    active=None,
    out=None,
    lengths=None,
) -> torch.Tensor:
    if generator is None or isinstance(generator, torch.Generator):
        if out is not None and not _elsewhere(generator, device):
            return fn(shape, generator=generator, out=out)
        got = _one(fn, shape, generator, dtype, device)
        return got if out is None else out.copy_(got)
    check_generator(generator)
    gens = list(generator)
    if len(gens) != shape[0]:
        raise ConfigError(
            f"generator: expected one torch.Generator or a sequence of B={shape[0]} generators "
            f"(one per batch row), got a sequence of {len(gens)}"
        )
    if not gens:
        return torch.empty(shape, dtype=dtype, device=device)
    # One call per batch row (a loop over targets, not over particles). Inactive rows draw
    # nothing (zeros), so their streams advance exactly as in a single run of that row.
    flags = [True] * len(gens) if active is None else [bool(v) for v in active.tolist()]
    zeros = torch.zeros(shape[1:], dtype=dtype, device=device)
    if lengths is None:
        rows = [
            _one(fn, shape[1:], g, dtype, device) if on else zeros
            for g, on in zip(gens, flags, strict=True)
        ]
    else:  # row b draws its first lengths[b] entries only (2-D shapes)
        rows = [
            torch.cat([_one(fn, (k,), g, dtype, device), zeros[k:]]) if on else zeros
            for g, on, k in zip(gens, flags, lengths, strict=True)
        ]
    return torch.stack(rows) if out is None else torch.stack(rows, out=out)


def rand(
    shape: tuple[int, ...],
    generator: GeneratorLike,
    dtype: torch.dtype,
    device: torch.device,
    active: torch.Tensor | None = None,
    out: torch.Tensor | None = None,
    lengths: list[int] | None = None,
) -> torch.Tensor:
    """Uniform [0, 1) draws of ``shape = (B, ...)``; row b comes from ``generator[b]`` if a list.

    ``active (B,)`` bool: with a list of generators, inactive rows get zeros and consume
    nothing from their generator (ignored for a single generator). ``out``: a contiguous tensor
    of ``shape`` and ``dtype`` to draw into (the same numbers as without it). ``lengths`` (B
    ints, 2-D shapes): with a list of generators, row b draws only its first ``lengths[b]``
    entries (zeros after), so its stream advances as in a single run of ``(1, lengths[b])``;
    a single generator fills the whole shape.
    """
    return _draw(torch.rand, tuple(shape), generator, dtype, device, active, out, lengths)


def randn(
    shape: tuple[int, ...],
    generator: GeneratorLike,
    dtype: torch.dtype,
    device: torch.device,
    active: torch.Tensor | None = None,
) -> torch.Tensor:
    """Standard normal draws of ``shape = (B, ...)``; row b from ``generator[b]`` if a list
    (see ``rand`` for ``active``)."""
    return _draw(torch.randn, tuple(shape), generator, dtype, device, active)


def _one(fn, shape: tuple[int, ...], generator: torch.Generator | None, dtype, device):
    """``fn(shape)`` from ``generator`` on ``device``; a generator of another device type
    draws its own stream where it lives, then the draw is moved to ``device``."""
    if not _elsewhere(generator, device):
        return fn(shape, generator=generator, dtype=dtype, device=device)
    return fn(shape, generator=generator, dtype=dtype, device=generator.device).to(device)


def _elsewhere(generator: torch.Generator | None, device) -> bool:
    """Whether ``generator`` lives on another device type than ``device`` (a CPU generator
    drawing for CUDA tensors or the reverse: torch refuses to draw there directly)."""
    if generator is None:
        return False
    want = torch.device(device) if device is not None else torch.device("cpu")
    return generator.device.type != want.type


def randperm(
    n: int, generator: torch.Generator | None, device: torch.device | None = None
) -> torch.Tensor:
    """A random permutation of ``0..n-1`` (int64) on ``device``, drawn from ``generator``
    wherever that generator lives (the same numbers as ``torch.randperm`` there)."""
    where = generator.device if generator is not None else device
    return torch.randperm(n, generator=generator, device=where).to(device or "cpu")


def randint(
    low: int,
    high: int,
    shape: tuple[int, ...],
    generator: torch.Generator | None,
    device: torch.device | None = None,
) -> torch.Tensor:
    """Uniform integers in ``[low, high)`` of ``shape`` (int64) on ``device``, drawn from
    ``generator`` wherever that generator lives."""
    where = generator.device if generator is not None else device
    return torch.randint(low, high, tuple(shape), generator=generator, device=where).to(
        device or "cpu"
    )


def multinomial(
    probs: torch.Tensor, n: int, generator: torch.Generator | None, replacement: bool = False
) -> torch.Tensor:
    """``torch.multinomial(probs, n)`` on ``probs``' device, drawn from ``generator`` wherever
    that generator lives (the same numbers as ``torch.multinomial`` there)."""
    where = probs if generator is None else probs.to(generator.device)
    draw = torch.multinomial(where, n, replacement=replacement, generator=generator)
    return draw.to(probs.device)


def subset(generator: GeneratorLike, rows: list[int]) -> GeneratorLike:
    """The generators of batch ``rows`` (a list stays a list; a single generator is shared)."""
    if generator is None or isinstance(generator, torch.Generator):
        return generator
    gens = list(generator)
    return [gens[r] for r in rows]
