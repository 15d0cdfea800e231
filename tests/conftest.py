"""Shared fixtures. Real-data tests ask for ``data_dir`` (``TORCHTRACK_DATA`` or ``../shared/data``
beside the repository): they skip with a reason when it is absent on a user's machine, and fail
under ``CI=true``, where the data must be there."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def find_data_dir() -> Path | None:
    env = os.environ.get("TORCHTRACK_DATA")
    candidates = [Path(env)] if env else []
    candidates.append(REPO.parent / "shared" / "data")
    for c in candidates:
        if c.is_dir():
            return c
    return None


@pytest.fixture(scope="session")
def data_dir() -> Path:
    d = find_data_dir()
    if d is None:
        msg = "real data not found: set TORCHTRACK_DATA or place shared/data beside the repository"
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(msg + " (CI=true: real-data tests must not skip)")
        pytest.skip(msg)
    return d


@pytest.fixture(scope="module")
def one_thread():
    """One torch thread for a test module (small per-frame tensors: extra intra-op threads only
    wait on each other, and on a shared machine make the tests many times slower)."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
