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

__all__ = ["GeneratorLike", "rand", "randn", "subset"]

GeneratorLike = torch.Generator | Sequence[torch.Generator] | None


def _draw(
    fn, shape: tuple[int, ...], generator: GeneratorLike, dtype, device, active=None
) -> torch.Tensor:
    if generator is None or isinstance(generator, torch.Generator):
        return fn(shape, generator=generator, dtype=dtype, device=device)
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
    return torch.stack(
        [
            fn(shape[1:], generator=g, dtype=dtype, device=device)
            if on
            else torch.zeros(shape[1:], dtype=dtype, device=device)
            for g, on in zip(gens, flags, strict=True)
        ]
    )


def rand(
    shape: tuple[int, ...],
    generator: GeneratorLike,
    dtype: torch.dtype,
    device: torch.device,
    active: torch.Tensor | None = None,
) -> torch.Tensor:
    """Uniform [0, 1) draws of ``shape = (B, ...)``; row b comes from ``generator[b]`` if a list.

    ``active (B,)`` bool: with a list of generators, inactive rows get zeros and consume
    nothing from their generator (ignored for a single generator).
    """
    return _draw(torch.rand, tuple(shape), generator, dtype, device, active)


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


def subset(generator: GeneratorLike, rows: list[int]) -> GeneratorLike:
    """The generators of batch ``rows`` (a list stays a list; a single generator is shared)."""
    if generator is None or isinstance(generator, torch.Generator):
        return generator
    gens = list(generator)
    return [gens[r] for r in rows]
