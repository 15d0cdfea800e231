"""The detectors shipped inside the package, usable by name wherever a model path is accepted.

``pedestrian`` (128x64 window, INRIA Person crops) and ``vehicle`` (40x100 window, side-view
UIUC car crops) live in ``torchtrack/models/<name>.safetensors``; ``train/default_models.py``
rebuilds them from ``configs/<name>.toml`` (see ``torchtrack/models/README.md`` for the exact
commands, data, held-out splits and metrics).

Example::

    from torchtrack.detect.bundled import load_model
    det = load_model("pedestrian")              # or a path: load_model("my_model.safetensors")

A string that names an existing file is always taken as a path, so a local file called
``vehicle`` still wins over the bundled model; anything else that looks like a path (it has a
suffix or a folder separator) and does not exist is reported as a missing file.
"""

from __future__ import annotations

import os
from pathlib import Path

from torchtrack.detect.detector import Detector
from torchtrack.errors import ConfigError, ModelFormatError

__all__ = ["MODELS_DIR", "bundled_models", "load_model", "resolve_model"]

MODELS_DIR = Path(__file__).resolve().parents[1] / "models"
_SUFFIX = ".safetensors"


def bundled_models() -> list[str]:
    """Names of the detectors shipped with the package, sorted (e.g. ``["pedestrian",
    "vehicle"]``)."""
    if not MODELS_DIR.is_dir():
        return []
    return sorted(p.stem for p in MODELS_DIR.glob(f"*{_SUFFIX}") if p.is_file())


def _looks_like_path(s: str) -> bool:
    return os.sep in s or "/" in s or (os.altsep is not None and os.altsep in s) or "." in s


def resolve_model(name_or_path: str | os.PathLike) -> Path:
    """The model file for a bundled name (``"pedestrian"``) or a path.

    Raises:
        ConfigError: neither an existing file nor a bundled name, an empty string, or not a
            string or path at all (the message lists the bundled names).
        ModelFormatError: a path-like string (with a suffix or a folder) that does not exist.
    """
    # None or 5 was Path's TypeError; "" is Path("."), which was reported as 'a folder'
    if not isinstance(name_or_path, (str, os.PathLike)) or name_or_path == "":
        names = bundled_models()
        got = repr(name_or_path) if isinstance(name_or_path, str) else type(name_or_path).__name__
        raise ConfigError(
            f"model must be a model file's path or a bundled model's name, got {got}; bundled "
            f"models: {', '.join(names) or 'none installed'}"
        )
    p = Path(name_or_path)
    if p.is_file():
        return p
    s = str(name_or_path)
    names = bundled_models()
    if s in names:
        return MODELS_DIR / f"{s}{_SUFFIX}"
    if p.is_dir():
        raise ModelFormatError(
            f"model {s!r} is a folder, not a model file (give a .safetensors file or a bundled "
            f"name: {', '.join(names) or 'none installed'})"
        )
    if p.exists():  # a device, a pipe, a socket: "does not exist" was wrong
        raise ModelFormatError(
            f"model {s!r} is not a regular file (a device or a pipe?); give a .safetensors file "
            f"or a bundled name: {', '.join(names) or 'none installed'}"
        )
    if isinstance(name_or_path, os.PathLike) or _looks_like_path(s):
        raise ModelFormatError(
            f"model file {s!r} does not exist (bundled models, usable by name: "
            f"{', '.join(names) or 'none installed'})"
        )
    raise ConfigError(
        f"unknown model {s!r}: not a file and not a bundled model; bundled models: "
        f"{', '.join(names) or 'none installed'}"
    )


def load_model(name_or_path: str | os.PathLike) -> Detector:
    """Load a bundled detector by name or a model file by path (validated, see
    :func:`torchtrack.detect.load_detector`).

    Raises:
        ConfigError: an unknown name, an empty string or neither a string nor a path (the
            message lists the bundled names).
        ModelFormatError: a missing, truncated, edited or future-version model file.
    """
    from torchtrack.detect.model_file import load_detector

    return load_detector(resolve_model(name_or_path))
