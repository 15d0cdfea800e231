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


def require_module(name: str, install: str):
    """Import an optional dependency, or skip with the install command (fail under CI=true)."""
    import contextlib
    import importlib
    import io

    try:
        with contextlib.redirect_stdout(io.StringIO()):  # TrackEval prints on import
            return importlib.import_module(name)
    except ImportError:
        msg = f"{name} is not installed ({install})"
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(msg + " (CI=true: tests must not skip)")
        pytest.skip(msg)


@pytest.fixture(scope="session")
def trackeval():
    """TrackEval, the MOT metrics (installed with --no-deps, see README)."""
    return require_module("trackeval", "pip install --no-deps trackeval==1.3.0")


@pytest.fixture(scope="session")
def motmetrics():
    """motmetrics, the MOTA / IDF1 cross-check (the test extra)."""
    return require_module("motmetrics", 'pip install -e ".[test]"')
