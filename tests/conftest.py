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
def ray():
    """Ray, for the Ray backend's tests (the ray extra; CI installs it)."""
    return require_module("ray", "pip install 'torchtrack[ray]'")


@pytest.fixture(scope="session")
def motmetrics():
    """motmetrics, the MOTA / IDF1 cross-check (the test extra)."""
    return require_module("motmetrics", 'pip install -e ".[test]"')


def forge_model_file(
    src,
    dst,
    *,
    meta_edit=None,
    meta_replace=None,
    tensor_edit=None,
    header_edit=None,
    recompute: bool = True,
    keep_signature: bool = True,
):
    """Write an edited copy of the model file ``src`` to ``dst``, as a forger would.

    ``meta_edit(meta)`` edits the torchtrack description (a dict) in place, ``meta_replace(meta)``
    returns a replacement (e.g. a list), ``tensor_edit(tensors)`` edits the tensor dict in place;
    with ``recompute`` the checksum is recomputed so that only range checks and signatures can
    catch the edit. ``header_edit(header)`` edits the raw safetensors header JSON in place, last
    (tensor bytes kept). Return values of the ``*_edit`` functions are ignored.
    """
    import json
    import struct

    from safetensors.torch import load, save_file

    from torchtrack.detect.model_file import _digest
    from torchtrack.detect.signing import SIGNATURE_KEY

    data = Path(src).read_bytes()
    (n,) = struct.unpack("<Q", data[:8])
    md = json.loads(data[8 : 8 + n])["__metadata__"]
    meta = json.loads(md["torchtrack"])
    tensors = load(data)
    if meta_edit is not None:
        meta_edit(meta)
    if tensor_edit is not None:
        tensor_edit(tensors)
    if recompute:
        meta.pop("sha256", None)
        meta["sha256"] = _digest(meta, tensors)
    if meta_replace is not None:
        meta = meta_replace(meta)
    new_md = {"torchtrack": json.dumps(meta)}
    if keep_signature and SIGNATURE_KEY in md:
        new_md[SIGNATURE_KEY] = md[SIGNATURE_KEY]
    save_file({k: v.contiguous() for k, v in tensors.items()}, str(dst), metadata=new_md)
    if header_edit is not None:
        data = Path(dst).read_bytes()
        (n,) = struct.unpack("<Q", data[:8])
        header = json.loads(data[8 : 8 + n])
        header_edit(header)
        h = json.dumps(header).encode()
        h += b" " * (-len(h) % 8)
        Path(dst).write_bytes(struct.pack("<Q", len(h)) + h + data[8 + n :])
    return Path(dst)


@pytest.fixture(scope="session")
def forge_model():
    """:func:`forge_model_file`, for tests that forge model files."""
    return forge_model_file
