"""Module-level task functions for the backend tests: workers (spawned processes, Ray) import
them by name."""

from __future__ import annotations

import os
from pathlib import Path


def task(x: int, fail: int = -1, die: int = -1) -> int:
    """``x * x``; raises on ``fail``; kills its own process on ``die`` (as a segfault in
    native code would)."""
    if x == fail:
        raise ValueError(f"no {fail}, please")
    if x == die:
        os._exit(3)
    return x * x


def threads() -> tuple[int, int]:
    """The torch and OpenCV thread counts a worker runs with."""
    import cv2
    import torch

    return torch.get_num_threads(), cv2.getNumThreads()


def die_once(x: int, marker: str) -> tuple[int, int]:
    """Kills its process the first time it runs on 0 (``marker`` records that it did)."""
    if x == 0 and not Path(marker).exists():
        Path(marker).write_text("died once\n")
        os._exit(3)
    return x, os.getpid()
