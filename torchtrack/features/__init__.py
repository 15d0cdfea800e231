"""Integral images and feature banks (Haar wavelets, integral channel features, centre-surround,
pixel colour / texture).

A detector's feature bank is a :class:`~torchtrack.features.haar.HaarBank` (Chateau et al.'s
grey Haar wavelets, the paper setting) or a :class:`~torchtrack.features.channels.ChannelBank`
(Haar-like features over colour and gradient channels). Both offer ``window``, ``len()``,
``describe(i)``, ``integrals(frames)`` and ``features_at(ints, boxes, index, check=...)``; the
functions below store either in a model file as a JSON description plus tensors.
"""

from __future__ import annotations

from typing import Any

import torch

from torchtrack.errors import ConfigError

__all__ = ["BANK_KINDS", "bank_from_dict", "bank_tensor_shapes", "bank_to_dict"]

BANK_KINDS = ("haar", "channels")


def bank_to_dict(bank: Any) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """``(description, tensors)`` of a feature bank; the description has ``"kind"``."""
    from torchtrack.features.channels import ChannelBank
    from torchtrack.features.haar import HaarBank

    if isinstance(bank, HaarBank):
        return {"kind": "haar", **bank.to_dict()}, {}
    if isinstance(bank, ChannelBank):
        return bank.to_dict(), bank.tensors()
    raise ConfigError(f"not a feature bank: {type(bank).__name__}")


def bank_tensor_shapes(d: Any) -> dict[str, tuple[int, ...]]:
    """Validate a bank description (types, ranges, channel names) without reading any tensor,
    and return the shapes its tensors must have.

    Raises:
        ConfigError: an unknown kind, unknown keys, wrong types or ranges (named).
    """
    from torchtrack.features.channels import ChannelBank
    from torchtrack.features.haar import HaarBank

    if not isinstance(d, dict) or d.get("kind") not in BANK_KINDS:
        kind = d.get("kind") if isinstance(d, dict) else None
        raise ConfigError(
            f"unknown feature bank kind {kind!r}; known kinds: {', '.join(BANK_KINDS)}"
        )
    if d["kind"] == "haar":
        win = d.get("window")
        # bound the bank before building its table: the table grows with the window area
        if not (
            isinstance(win, list)
            and len(win) == 2
            and all(isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 1024 for v in win)
        ):
            raise ConfigError(f"Haar bank window must be [H, W] integers in [1, 1024], got {win!r}")
        HaarBank.from_dict({k: v for k, v in d.items() if k != "kind"})
        return {}
    _, _, _, n = ChannelBank.check_header(d)
    return {"rects": (n, 4, 5), "channel": (n,)}


def bank_from_dict(d: Any, tensors: dict[str, torch.Tensor] | None = None) -> Any:
    """Inverse of :func:`bank_to_dict` (every field validated).

    Raises:
        ConfigError: an invalid description or tensors (named).
    """
    from torchtrack.features.channels import ChannelBank
    from torchtrack.features.haar import HaarBank

    bank_tensor_shapes(d)
    if d["kind"] == "haar":
        return HaarBank.from_dict({k: v for k, v in d.items() if k != "kind"})
    return ChannelBank.from_dict(d, tensors or {})
