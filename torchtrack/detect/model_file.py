"""Detector model files: safetensors tensors + a JSON description, checksummed, optionally
signed, never pickle.

Layout: a standard safetensors file. Its tensors are ``features.index``, the channel bank's
tables ``features.rects`` / ``features.channel`` (channel models), ``classifier.*`` and
``calibration.*``; its ``__metadata__`` holds ``torchtrack``, whose value is a JSON document::

    {"format": "torchtrack-detector", "format_version": 2,
     "name": ..., "window": [H, W],
     "features": {"kind": "haar", "window", "sizes", "stride", "min_std", "kinds"}
               | {"kind": "channels", "window", "cell", "n_features",
                  "channels": {"names", "orientations", "norm_radius", "norm_const",
                               "gradient_lambda"}},
     "selected_features": [{kind, size, y, x}, ...]   (Haar banks only),
     "classifier": {"kind": "boosted_stumps" | "boosted_trees" | "svm", ...},
     "calibration": {"kind": "platt" | "isotonic", ...} | null,
     "training": {...data counts, split, held-out metrics...},
     "object_box": [x, y, w, h] fractions of the window | absent (the object fills the window),
     "tracking_head": {"trees": n, "calibration": {"kind": "platt", "a", "b"}} | absent
               (boosted trees: the first n trees and their own Platt, for particle filters),
     "box_regression": {"limit": [dx, dy, ds], "summary": {...}} | absent
               (tensors box_regression.weight (3, K), .bias (3,): where the object lies in a
               detection window, :mod:`torchtrack.detect.box_regression`),
     "sha256": hex digest of the JSON without this key plus every tensor's name, dtype, shape
               and bytes}

and, in a signed file, ``torchtrack.signature`` (:mod:`torchtrack.detect.signing`). Version 1
files (the grey Haar bank under ``"bank"``, no ``"features"``) still load.

**Loading validates before it allocates.** :func:`load_detector` reads the file (its size is
capped), then

1. :func:`parse_container` checks the safetensors framing: the header length, that the header
   is a JSON object whose tensor entries each have a known dtype, a shape of at most four
   non-negative dimensions and ``data_offsets`` that tile the data section exactly (so a
   truncated file or trailing bytes are caught before any tensor is touched);
2. :func:`~torchtrack.detect.model_checks.validate_description` checks the JSON description,
   one function per section
   (``window``, ``bank``, ``selected_features``, ``classifier``, ``calibration``,
   ``object_box``, ``name``, ``training``): JSON types, ranges (window sides, bank size,
   classifier sizes, finite calibration) and that every tensor's dtype and shape agrees with
   the description; the bank's size is computed, not built, so a forged 100000 x 100000
   window is refused without allocating anything;
3. only then are the tensors read, the checksum recomputed and the signature checked against
   the trust policy;
4. :func:`~torchtrack.detect.model_checks.check_tensor_values` checks the values: feature indices inside the bank, stump
   thresholds inside the range a feature value can take, finite outputs, SVM coefficients
   within ``C``, isotonic maps monotone in ``[0, 1]``;
5. the parts are rebuilt through the validating ``from_state`` loaders of
   :mod:`torchtrack.learn`.

Every failure is a :class:`ModelFormatError` naming the file and the field. Saving runs the
same validator on what it is about to write, so a file that would not load is never written.

**Adding a format version.** Its validator goes in :mod:`torchtrack.detect.model_checks`
(``_VALIDATORS``), its builder ``(description, tensors) -> Detector`` in ``_BUILDERS`` here,
and :func:`save_detector` writes it.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from torchtrack.detect.detector import Detector
from torchtrack.detect.model_checks import (
    _DTYPES,
    FORMAT,
    FORMAT_VERSION,
    LIMITS,
    Description,
    Limits,
    TensorEntry,
    _is_int,
    check_tensor_values,
    validate_description,
)
from torchtrack.detect.signing import SIGNATURE_KEY, TrustPolicy, check_signature, sign_digest
from torchtrack.errors import ConfigError, ModelFormatError
from torchtrack.features import bank_from_dict, bank_to_dict
from torchtrack.features.haar import HaarBank
from torchtrack.io.atomic import atomic_path

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "LIMITS",
    "Description",
    "Limits",
    "check_tensor_values",
    "load_detector",
    "model_signature",
    "parse_container",
    "read_model_metadata",
    "save_detector",
    "sign_model",
    "validate_description",
]

_MAX_HEADER = 100 * 1024 * 1024


# --------------------------------------------------------------------------------- framing
@dataclass(frozen=True)
class Container:
    """A parsed safetensors container: the raw header, the torchtrack description (still
    unvalidated), the signature block (or ``None``) and the tensor entries."""

    header: dict[str, Any]
    meta: Any
    signature: str | None
    entries: dict[str, TensorEntry]
    data_start: int


def _fail(where: str, what: str) -> ModelFormatError:
    return ModelFormatError(f"{where}: {what}")


def parse_container(data: bytes, where: str) -> Container:
    """Check the safetensors framing of ``data`` and return its parts (no tensor is read).

    Raises:
        ModelFormatError: too short, a header length past the end, a header that is not a JSON
            object, no torchtrack description, a malformed tensor entry, or tensor byte ranges
            that do not tile the data section exactly (truncated file, trailing bytes).
    """
    if len(data) < 8:
        raise ModelFormatError(f"{where} is not a torchtrack model (only {len(data)} bytes)")
    (n,) = struct.unpack("<Q", data[:8])
    if n > _MAX_HEADER or 8 + n > len(data):
        raise ModelFormatError(
            f"{where} is truncated or not a safetensors model file (header says {n} bytes, "
            f"the file has {len(data) - 8} after the length field)"
        )
    try:
        header = json.loads(data[8 : 8 + n].decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        header = None
    except RecursionError:  # '[[[[...' nested 10^5 deep: Python's own traceback
        raise _fail(where, "its header nests JSON arrays or objects too deeply to read") from None
    md = header.get("__metadata__") if isinstance(header, dict) else None
    text = md.get("torchtrack") if isinstance(md, dict) else None
    if not isinstance(text, str):
        raise ModelFormatError(
            f"{where} is not a torchtrack detector file (no torchtrack metadata in its header)"
        )
    if not all(isinstance(k, str) and isinstance(v, str) for k, v in md.items()):
        raise _fail(where, "the header's __metadata__ must map strings to strings")
    try:
        meta = json.loads(text)
    except ValueError:
        raise _fail(where, "the torchtrack description is not valid JSON") from None
    except RecursionError:
        raise _fail(
            where, "the torchtrack description nests JSON arrays or objects too deeply to read"
        ) from None
    sig = md.get(SIGNATURE_KEY)
    entries: dict[str, TensorEntry] = {}
    items = [(k, v) for k, v in header.items() if k != "__metadata__"]
    if len(items) > LIMITS.tensors:
        raise _fail(where, f"{len(items)} tensors (at most {LIMITS.tensors})")
    for name, e in items:
        if not isinstance(e, dict) or set(e) != {"dtype", "shape", "data_offsets"}:
            raise _fail(where, f"tensor entry {name!r} must hold dtype, shape and data_offsets")
        dt, shape, off = e["dtype"], e["shape"], e["data_offsets"]
        if dt not in _DTYPES:
            raise _fail(where, f"tensor {name!r} has an unknown dtype {dt!r}")
        if (
            not isinstance(shape, list)
            or len(shape) > 4
            or not all(_is_int(s) and 0 <= s < 2**40 for s in shape)
        ):
            raise _fail(where, f"tensor {name!r} has an invalid shape {shape!r}")
        if not isinstance(off, list) or len(off) != 2 or not all(_is_int(o) for o in off):
            raise _fail(where, f"tensor {name!r} has invalid data_offsets {off!r}")
        begin, end = off
        size = math.prod(shape) * _DTYPES[dt][1]
        if not 0 <= begin <= end or end - begin != size:
            raise _fail(
                where,
                f"tensor {name!r}: data_offsets {off} do not match its shape {shape} and dtype "
                f"{dt} ({size} bytes)",
            )
        entries[name] = TensorEntry(dt, tuple(shape), begin, end)
    pos = 0
    for name, e in sorted(entries.items(), key=lambda kv: (kv[1].begin, kv[1].end)):
        if e.begin != pos:
            raise _fail(where, f"tensor {name!r} starts at byte {e.begin}, expected {pos}")
        pos = e.end
    if 8 + n + pos != len(data):
        raise ModelFormatError(
            f"{where} is truncated or has trailing bytes: tensors end at byte {8 + n + pos}, "
            f"the file has {len(data)}"
        )
    return Container(header, meta, sig, entries, 8 + n)


# ----------------------------------------------------------------------------- the digest
def _digest(meta: dict[str, Any], tensors: dict[str, torch.Tensor]) -> str:
    h = hashlib.sha256()
    h.update(json.dumps(meta, sort_keys=True, separators=(",", ":")).encode())
    for name in sorted(tensors):
        t = tensors[name].contiguous().cpu()
        h.update(f"{name}|{t.dtype}|{list(t.shape)}|".encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


_TORCH_TO_ST = {v[0]: k for k, v in _DTYPES.items()}


def _entries_of(tensors: dict[str, torch.Tensor]) -> dict[str, TensorEntry]:
    return {
        k: TensorEntry(_TORCH_TO_ST.get(v.dtype, str(v.dtype)), tuple(v.shape), 0, 0)
        for k, v in tensors.items()
    }


# ------------------------------------------------------------------------------- writing
def save_detector(
    path: str | os.PathLike, det: Detector, *, signing_key: str | os.PathLike | Any = None
) -> Path:
    """Write ``det`` to ``path`` (atomically: a crash never leaves half a model).

    Args:
        path: the model file to write.
        det: the detector.
        signing_key: an Ed25519 private key (or its PEM file) to sign the file with.

    Raises:
        ModelFormatError: the detector would make a file that does not load (a value outside
            the ranges :func:`load_detector` accepts, e.g. a calibration whose probability
            falls as the margin rises).
        ConfigError: metadata that is not JSON-safe, or an unreadable signing key.

    Returns:
        the path written.
    """
    from safetensors.torch import save_file

    key = _private_key(signing_key)
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
    if det.tracking_head is not None:
        n_trees, head_cal = det.tracking_head
        head_t, head_m = head_cal.to_state()
        if head_t:
            raise ConfigError("a tracking head's calibration must be Platt (no tensors)")
        meta["tracking_head"] = {"trees": int(n_trees), "calibration": head_m}
    if det.box_regressor is not None:
        reg_t, reg_m = det.box_regressor.to_state()
        tensors.update({f"box_regression.{k}": v.contiguous() for k, v in reg_t.items()})
        meta["box_regression"] = reg_m
    try:
        meta = json.loads(json.dumps(meta, allow_nan=False))
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"the detector's metadata is not JSON-safe: {exc}") from None
    try:
        desc = validate_description(meta, _entries_of(tensors))
        check_tensor_values(desc, tensors)
    except ModelFormatError as exc:
        raise ModelFormatError(f"not writing {os.fspath(path)!r}: {exc}") from None
    digest = _digest(meta, tensors)
    meta["sha256"] = digest
    header_meta = {"torchtrack": json.dumps(meta, sort_keys=True, allow_nan=False)}
    if key is not None:
        header_meta[SIGNATURE_KEY] = sign_digest(key, digest)
    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata=header_meta)
    return Path(path)


def _private_key(key: Any) -> Any:
    if key is None or hasattr(key, "sign"):
        return key
    from torchtrack.detect.signing import load_private_key

    return load_private_key(key)


# ------------------------------------------------------------------------------- reading
def _read_bytes(p: Path) -> bytes:
    where = repr(str(p))
    try:
        size = p.stat().st_size
        if p.is_dir():
            raise ModelFormatError(f"model file {where} is a folder")
        if size > LIMITS.file_bytes:
            raise ModelFormatError(
                f"{where} has {size:,} bytes, more than a model file may have "
                f"({LIMITS.file_bytes:,})"
            )
        return p.read_bytes()
    except FileNotFoundError:
        raise ModelFormatError(f"model file {where} does not exist") from None
    except OSError as exc:
        raise ModelFormatError(
            f"model file {where} cannot be read: {exc.strerror or exc}"
        ) from None


def _open(p: Path) -> tuple[bytes, Container, Description]:
    data = _read_bytes(p)
    where = repr(str(p))
    cont = parse_container(data, where)
    meta = cont.meta
    if isinstance(meta, dict):
        meta = dict(meta)
        meta.pop("sha256", None)
    try:
        desc = validate_description(meta, cont.entries)
    except ModelFormatError as exc:
        raise ModelFormatError(f"{where}: {exc}") from None
    return data, cont, desc


def read_model_metadata(path: str | os.PathLike) -> dict[str, Any]:
    """The JSON description of a model file (with its ``sha256``), after the framing and
    description checks (no tensor is read)."""
    _, cont, _ = _open(Path(path))
    return dict(cont.meta)


@dataclass(frozen=True)
class SignatureStatus:
    """A model file's signature: ``status`` is ``"verified"`` (by a trusted key),
    ``"unsigned"`` or ``"untrusted"`` (signed by a key not trusted here); ``key_id`` of the
    signer; ``digest`` the file's SHA-256 digest."""

    status: str
    key_id: str | None
    digest: str


def _section(tensors: dict[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    return {k[len(prefix) :]: v for k, v in tensors.items() if k.startswith(prefix)}


def _build(meta: dict, bank: Any, tensors: dict[str, torch.Tensor]) -> Detector:
    """A :class:`Detector` of ``bank`` from a validated description and its checked tensors."""
    from torchtrack.learn import calibrator_from_state, classifier_from_state

    clf = classifier_from_state(_section(tensors, "classifier."), meta["classifier"])
    cal = None
    if meta["calibration"] is not None:
        cal = calibrator_from_state(_section(tensors, "calibration."), meta["calibration"])
    from torchtrack.detect.box_regression import BoxRegressor

    head = meta.get("tracking_head")
    reg = meta.get("box_regression")
    det = Detector(
        bank,
        tensors["features.index"],
        clf,
        cal,
        name=meta["name"],
        summary=meta["training"],
        object_box=meta.get("object_box"),
        tracking_head=(
            None
            if head is None
            else (int(head["trees"]), calibrator_from_state({}, head["calibration"]))
        ),
        box_regressor=(
            None
            if reg is None
            else BoxRegressor.from_state(_section(tensors, "box_regression."), reg)
        ),
    )
    if isinstance(bank, HaarBank) and det.selected_features() != meta["selected_features"]:
        raise ModelFormatError("selected feature descriptions disagree with the feature index")
    return det


def _build_v1(desc: Description, tensors: dict[str, torch.Tensor]) -> Detector:
    """Version 1: Chateau's grey Haar bank under ``bank``."""
    return _build(desc.meta, HaarBank.from_dict(desc.meta["bank"]), tensors)


def _build_v2(desc: Description, tensors: dict[str, torch.Tensor]) -> Detector:
    """Version 2: any feature bank under ``features`` (tables in ``features.*`` tensors)."""
    tables = {k: v for k, v in _section(tensors, "features.").items() if k != "index"}
    return _build(desc.meta, bank_from_dict(desc.meta["features"], tables), tensors)


#: format version -> builder(description, tensors) -> Detector
_BUILDERS: dict[int, Callable[[Description, dict[str, torch.Tensor]], Detector]] = {
    1: _build_v1,
    2: _build_v2,
}


def _load(p: Path, trust: TrustPolicy | None) -> tuple[Detector, SignatureStatus]:
    from safetensors.torch import load as st_load

    where = repr(str(p))
    data, cont, desc = _open(p)
    try:
        tensors = st_load(data)
    except Exception as exc:  # safetensors raises its own error types
        raise ModelFormatError(f"{where}: cannot read its tensors ({exc})") from None
    stored = cont.meta.get("sha256")
    digest = _digest(desc.meta, tensors)
    if not isinstance(stored, str) or digest != stored:
        raise ModelFormatError(
            f"{where} fails its checksum: it was edited or corrupted after it was written; "
            "retrain or restore the original file"
        )
    policy = trust if trust is not None else TrustPolicy.from_env()
    status, kid = check_signature(cont.signature, digest, policy, where)
    try:
        check_tensor_values(desc, tensors)
        det = _BUILDERS[desc.version](desc, tensors)
    except ModelFormatError as exc:
        raise ModelFormatError(f"{where}: {exc}") from None
    except ConfigError as exc:
        raise ModelFormatError(f"{where}: invalid model description ({exc})") from None
    return det, SignatureStatus(status, kid, digest)


def load_detector(path: str | os.PathLike, *, trust: TrustPolicy | None = None) -> Detector:
    """Load and validate a detector file written by :func:`save_detector`.

    Args:
        path: the model file.
        trust: which signatures to trust and whether one is required (default: the bundled key
            plus ``TORCHTRACK_TRUSTED_KEYS``, required when ``TORCHTRACK_REQUIRE_SIGNED`` is
            set; see :mod:`torchtrack.detect.signing`).

    Raises:
        ModelFormatError: the file is missing, truncated, malformed, edited (checksum mismatch),
            of an unknown or future format version, internally inconsistent, holds values
            outside their ranges, or fails the trust policy (forged signature; unsigned or
            signed by an untrusted key while signatures are required).
        ConfigError: a trusted key file named in the environment cannot be read.
    """
    return _load(Path(path), trust)[0]


def model_signature(
    path: str | os.PathLike, *, trust: TrustPolicy | None = None
) -> SignatureStatus:
    """Validate a model file like :func:`load_detector` and say how it is signed.

    Raises:
        ModelFormatError: as :func:`load_detector`.
    """
    return _load(Path(path), trust)[1]


def sign_model(
    path: str | os.PathLike,
    key: str | os.PathLike | Any,
    out: str | os.PathLike | None = None,
) -> Path:
    """Sign a model file with an Ed25519 private key (or its PEM file), writing ``out``
    (default: in place, atomically). The file is fully validated first (a file that fails its
    checksum or a present signature is never signed); the description and tensors are kept
    byte for byte, only the signature entry of the header changes.

    Raises:
        ModelFormatError: the file does not load.
        ConfigError: the key cannot be read.
    """
    from torchtrack.detect.signing import key_id
    from torchtrack.io.atomic import write_bytes_atomic

    priv = _private_key(key)
    p = Path(path)
    # Trust the signing key too: a file that claims this key's signature but no longer
    # verifies was altered after it was signed, and is not signed again.
    base = TrustPolicy.build([])
    pub = priv.public_key()
    policy = TrustPolicy({**base.keys, key_id(pub): pub}, False, base.sources)
    _, st = _load(p, policy)
    data = p.read_bytes()
    (n,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8 : 8 + n].decode("utf-8"))
    header["__metadata__"][SIGNATURE_KEY] = sign_digest(priv, st.digest)
    text = json.dumps(header, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 8)  # safetensors keeps the data section 8-byte aligned
    dest = Path(out) if out is not None else p
    write_bytes_atomic(dest, struct.pack("<Q", len(text)) + text + data[8 + n :])
    return dest
