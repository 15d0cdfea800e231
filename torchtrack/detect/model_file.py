"""Detector model files: safetensors tensors + a JSON description, checksummed, never pickle.

Layout: a standard safetensors file. Its tensors are ``features.index``, the feature bank's
tables ``features.<name>`` (channel banks: ``features.rects``, ``features.channel``),
``classifier.*`` and ``calibration.*``; its ``__metadata__`` holds one key, ``torchtrack``, whose
value is a JSON document::

    {"format": "torchtrack-detector", "format_version": 2,
     "name": ..., "window": [H, W],
     "features": {"kind": "haar", window, sizes, stride, min_std, kinds}
               | {"kind": "channels", window, cell, n_features,
                  "channels": {names, orientations, norm_radius, norm_const, gradient_lambda}},
     "selected_features": [{kind, size, y, x}, ...]   (Haar banks only),
     "classifier": {"kind": "boosted_stumps" | "boosted_trees" | "svm", ...},
     "calibration": {"kind": "platt" | "isotonic", ...} | null,
     "training": {...data counts, split, held-out metrics...},
     "object_box": [x, y, w, h] fractions of the window | absent (the object fills the window),
     "sha256": hex digest of the JSON without this key plus every tensor's name, dtype, shape
               and bytes}

Version 1 files (the grey Haar bank under ``"bank"``, no ``"features"``) still load. The
feature description (channel names, geometry, table shapes in the safetensors header) is
validated before any tensor is read.

Loading reads the whole file, parses the header by hand (so a truncated file is detected
before any tensor is touched), checks the format name and version, recomputes the checksum and
rebuilds every part through the validating ``from_state`` loaders of :mod:`torchtrack.learn`. Any failure is a :class:`ModelFormatError`
that names the file and the problem.
"""

from __future__ import annotations

import hashlib
import json
import os
import struct
from pathlib import Path
from typing import Any

import torch

from torchtrack.detect.detector import Detector
from torchtrack.errors import ConfigError, ModelFormatError
from torchtrack.features import bank_from_dict, bank_tensor_shapes, bank_to_dict
from torchtrack.features.haar import HaarBank
from torchtrack.io.atomic import atomic_path

__all__ = ["FORMAT", "FORMAT_VERSION", "load_detector", "read_model_metadata", "save_detector"]

FORMAT = "torchtrack-detector"
FORMAT_VERSION = 2
_MAX_HEADER = 100 * 1024 * 1024


def _digest(meta: dict[str, Any], tensors: dict[str, torch.Tensor]) -> str:
    h = hashlib.sha256()
    h.update(json.dumps(meta, sort_keys=True, separators=(",", ":")).encode())
    for name in sorted(tensors):
        t = tensors[name].contiguous().cpu()
        h.update(f"{name}|{t.dtype}|{list(t.shape)}|".encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def save_detector(path: str | os.PathLike, det: Detector) -> Path:
    """Write ``det`` to ``path`` (atomically: a crash never leaves half a model).

    Returns:
        the path written.
    """
    from safetensors.torch import save_file

    sc_t, sc_m = det.classifier.to_state()
    bank_d, bank_t = bank_to_dict(det.bank)
    tensors = {"features.index": det.feature_index.contiguous()}
    tensors.update({f"features.{k}": v.contiguous() for k, v in bank_t.items()})
    tensors.update({f"classifier.{k}": v.contiguous() for k, v in sc_t.items()})
    cal_m = None
    if det.calibrator is not None:
        cal_t, cal_m = det.calibrator.to_state()
        tensors.update({f"calibration.{k}": v.contiguous() for k, v in cal_t.items()})
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "name": det.name,
        "window": list(det.window),
        "features": bank_d,
        "classifier": sc_m,
        "calibration": cal_m,
        "training": det.summary,
    }
    if isinstance(det.bank, HaarBank):
        meta["selected_features"] = det.selected_features()
    if det.object_box is not None:
        meta["object_box"] = list(det.object_box)
    try:
        json.dumps(meta, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"the detector's metadata is not JSON-safe: {exc}") from None
    meta["sha256"] = _digest(meta, tensors)
    text = json.dumps(meta, sort_keys=True, allow_nan=False)
    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata={"torchtrack": text})
    return Path(path)


def _read(path: str | os.PathLike) -> tuple[bytes, dict[str, Any], dict[str, Any]]:
    p = Path(path)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise ModelFormatError(f"model file {str(p)!r} does not exist") from None
    except OSError as exc:
        raise ModelFormatError(f"model file {str(p)!r} cannot be read: {exc}") from None
    if len(data) < 8:
        raise ModelFormatError(f"{str(p)!r} is not a torchtrack model (only {len(data)} bytes)")
    (n,) = struct.unpack("<Q", data[:8])
    if n > _MAX_HEADER or 8 + n > len(data):
        raise ModelFormatError(
            f"{str(p)!r} is truncated or not a safetensors model file (header says {n} bytes, "
            f"the file has {len(data) - 8} after the length field)"
        )
    try:
        header = json.loads(data[8 : 8 + n].decode("utf-8"))
        text = header["__metadata__"]["torchtrack"]
        meta = json.loads(text)
    except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError):
        raise ModelFormatError(
            f"{str(p)!r} is not a torchtrack detector file (no torchtrack metadata in its header)"
        ) from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ModelFormatError(f"{str(p)!r} is not a {FORMAT} file (format {meta.get('format')!r})")
    ver = meta.get("format_version")
    if not isinstance(ver, int):
        raise ModelFormatError(f"{str(p)!r} has no valid format_version")
    if ver > FORMAT_VERSION:
        raise ModelFormatError(
            f"{str(p)!r} has format version {ver}, newer than this torchtrack reads "
            f"({FORMAT_VERSION}); upgrade torchtrack"
        )
    if ver < 1:
        raise ModelFormatError(f"{str(p)!r} has an invalid format version {ver}")
    # The tensor section must end exactly at the end of the file.
    ends = [v["data_offsets"][1] for k, v in header.items() if k != "__metadata__"]
    if 8 + n + (max(ends) if ends else 0) != len(data):
        raise ModelFormatError(
            f"{str(p)!r} is truncated or has trailing bytes: tensors end at byte "
            f"{8 + n + (max(ends) if ends else 0)}, the file has {len(data)}"
        )
    return data, header, meta


def _check_features_header(p: Path, meta: dict[str, Any], header: dict[str, Any]) -> None:
    """Validate the feature description and the declared shapes of its tables before any
    tensor is read (version 2; version 1 files have the grey Haar bank under ``"bank"``)."""
    if meta["format_version"] == 1:
        if not isinstance(meta.get("bank"), dict):
            raise ModelFormatError(
                f"{str(p)!r}: a version 1 model needs its Haar 'bank' description"
            )
        return
    try:
        shapes = bank_tensor_shapes(meta.get("features"))
    except ConfigError as exc:
        raise ModelFormatError(f"{str(p)!r}: invalid feature description ({exc})") from None
    for name, shape in shapes.items():
        entry = header.get(f"features.{name}")
        got = entry.get("shape") if isinstance(entry, dict) else None
        if got != list(shape):
            raise ModelFormatError(
                f"{str(p)!r}: tensor 'features.{name}' must have shape {list(shape)}, got {got}"
            )


def read_model_metadata(path: str | os.PathLike) -> dict[str, Any]:
    """The JSON description of a model file, after the format and version checks."""
    return _read(path)[2]


def load_detector(path: str | os.PathLike) -> Detector:
    """Load and validate a detector file written by :func:`save_detector`.

    Raises:
        ModelFormatError: the file is missing, truncated, edited (checksum mismatch), of an
            unknown or future format version, or internally inconsistent.
    """
    from safetensors.torch import load as st_load

    from torchtrack.learn import calibrator_from_state, classifier_from_state

    p = Path(path)
    data, header, meta = _read(p)
    _check_features_header(p, meta, header)
    try:
        tensors = st_load(data)
    except Exception as exc:  # safetensors raises its own error types
        raise ModelFormatError(f"{str(p)!r}: cannot read its tensors ({exc})") from None
    stored = meta.pop("sha256", None)
    if not isinstance(stored, str) or _digest(meta, tensors) != stored:
        raise ModelFormatError(
            f"{str(p)!r} fails its checksum: it was edited or corrupted after it was written; "
            "retrain or restore the original file"
        )
    try:
        if meta["format_version"] == 1:
            bank = HaarBank.from_dict(meta["bank"])
        else:
            bank_t = {
                k[len("features.") :]: v
                for k, v in tensors.items()
                if k.startswith("features.") and k != "features.index"
            }
            bank = bank_from_dict(meta["features"], bank_t)
        if list(bank.window) != list(meta["window"]):
            raise ModelFormatError("window and bank window disagree")
        sc_t = {
            k[len("classifier.") :]: v for k, v in tensors.items() if k.startswith("classifier.")
        }
        clf = classifier_from_state(sc_t, meta["classifier"])
        cal = None
        if meta.get("calibration") is not None:
            cal_t = {
                k[len("calibration.") :]: v
                for k, v in tensors.items()
                if k.startswith("calibration.")
            }
            cal = calibrator_from_state(cal_t, meta["calibration"])
        det = Detector(
            bank,
            tensors["features.index"],
            clf,
            cal,
            name=str(meta.get("name", "detector")),
            summary=meta.get("training") or {},
            object_box=meta.get("object_box"),
        )
        if isinstance(bank, HaarBank) and det.selected_features() != meta["selected_features"]:
            raise ModelFormatError("selected feature descriptions disagree with the feature index")
    except ModelFormatError as exc:
        raise ModelFormatError(f"{str(p)!r}: {exc}") from None
    except (KeyError, TypeError, ValueError, ConfigError) as exc:
        raise ModelFormatError(f"{str(p)!r}: invalid model description ({exc})") from None
    for name, t in tensors.items():
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise ModelFormatError(f"{str(p)!r}: tensor {name!r} holds NaN or inf")
    return det
