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


def size_job(calls: str, source: str, out: str | None = None, note: str | None = None) -> dict:
    """A corpus job: writes the source's name and size to ``out`` (and ``note``); appends the
    source to the ``calls`` file; raises on sources named ``bad*``, writes nothing for
    ``empty*``, stops the run (Ctrl-C) on ``stop*``."""
    name = Path(source).name
    with open(calls, "a") as f:
        f.write(source + "\n")
    if name.startswith("bad"):
        raise ValueError(f"cannot read {name}")
    if name.startswith("stop"):
        raise KeyboardInterrupt
    size = Path(source).stat().st_size
    for path in (out, note):
        if path and not name.startswith("empty"):
            Path(path).write_text(f"{name},{size}\n")
    return {"bytes": size}


def cwd() -> str:
    return os.getcwd()


def getenv(name: str) -> str | None:
    return os.environ.get(name)
