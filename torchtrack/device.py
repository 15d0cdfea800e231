"""Where tensors live: the one check of a device a user names (``--device``, ``device=``).

Every tensor the library makes follows its input's device, so a tracker runs on a GPU when its
frames are there. A caller that moves frames for the user (the CLI, the evaluator) names the
device once and checks it here, before any file is read or written.
"""

from __future__ import annotations

import torch

from torchtrack.errors import ConfigError

__all__ = ["check_device"]


def check_device(device: torch.device | str | None) -> torch.device:
    """``device`` (``"cpu"``, ``"cuda"``, ``"cuda:1"``, a :class:`torch.device`; ``None`` =
    the CPU) as a :class:`torch.device` that exists here.

    Raises:
        ConfigError: not a device name, a device type other than CPU or CUDA, or a CUDA device
            this machine does not have.
    """
    if device is None:
        return torch.device("cpu")
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise ConfigError(f"device: expected 'cpu', 'cuda' or 'cuda:N', got {device!r}") from None
    if dev.type == "cpu":
        if dev.index not in (None, 0):  # torch accepts "cpu:3"; there is one CPU device
            raise ConfigError(f"device {device!r}: the CPU is one device, name it 'cpu'")
        return dev
    if dev.type != "cuda":
        raise ConfigError(f"device: only 'cpu' and 'cuda' are supported, got {device!r}")
    if not torch.cuda.is_available():
        raise ConfigError(
            f"device {device!r}: no CUDA device here (torch.cuda.is_available() is False: no "
            "NVIDIA GPU, or a CPU-only build of torch); use --device cpu"
        )
    n = torch.cuda.device_count()
    if dev.index is not None and dev.index >= n:
        raise ConfigError(f"device {device!r}: this machine has {n} CUDA device(s) (0..{n - 1})")
    return dev
