"""Detector model files: safetensors tensors + a JSON description, checksummed, optionally
signed, never pickle.

Layout: a standard safetensors file. Its tensors are ``features.index``, ``classifier.*`` and
``calibration.*``; its ``__metadata__`` holds ``torchtrack``, whose value is a JSON document::

    {"format": "torchtrack-detector", "format_version": 1,
     "name": ..., "window": [H, W], "bank": {...}, "selected_features": [{kind, size, y, x}, ...],
     "classifier": {"kind": "boosted_stumps" | "svm", ...},
     "calibration": {"kind": "platt" | "isotonic", ...} | null,
     "training": {...data counts, split, held-out metrics...},
     "object_box": [x, y, w, h] fractions of the window | absent (the object fills the window),
     "sha256": hex digest of the JSON without this key plus every tensor's name, dtype, shape
               and bytes}

and, in a signed file, ``torchtrack.signature`` (:mod:`torchtrack.detect.signing`).

**Loading validates before it allocates.** :func:`load_detector` reads the file (its size is
capped), then

1. :func:`parse_container` checks the safetensors framing: the header length, that the header
   is a JSON object whose tensor entries each have a known dtype, a shape of at most four
   non-negative dimensions and ``data_offsets`` that tile the data section exactly (so a
   truncated file or trailing bytes are caught before any tensor is touched);
2. :func:`validate_description` checks the JSON description, one function per section
   (``window``, ``bank``, ``selected_features``, ``classifier``, ``calibration``,
   ``object_box``, ``name``, ``training``): JSON types, ranges (window sides, bank size,
   classifier sizes, finite calibration) and that every tensor's dtype and shape agrees with
   the description; the bank's size is computed, not built, so a forged 100000 x 100000
   window is refused without allocating anything;
3. only then are the tensors read, the checksum recomputed and the signature checked against
   the trust policy;
4. :func:`check_tensor_values` checks the values: feature indices inside the bank, stump
   thresholds inside the range a feature value can take, finite outputs, SVM coefficients
   within ``C``, isotonic maps monotone in ``[0, 1]``;
5. the parts are rebuilt through the validating ``from_state`` loaders of
   :mod:`torchtrack.learn`.

Every failure is a :class:`ModelFormatError` naming the file and the field. Saving runs the
same validator on what it is about to write, so a file that would not load is never written.

**Adding a format version.** Write ``_validate_vN(meta, entries) -> Description`` from the
section functions (reuse the unchanged ones, add new ones for new sections) and register it in
``_VALIDATORS``; a version-specific builder goes in ``_BUILDERS``.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from torchtrack.detect.detector import Detector, check_object_box
from torchtrack.detect.signing import SIGNATURE_KEY, TrustPolicy, check_signature, sign_digest
from torchtrack.errors import ConfigError, ModelFormatError
from torchtrack.features.haar import KINDS, HaarBank
from torchtrack.io.atomic import atomic_path

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "LIMITS",
    "Description",
    "check_tensor_values",
    "load_detector",
    "model_signature",
    "parse_container",
    "read_model_metadata",
    "save_detector",
    "sign_model",
    "validate_description",
]

FORMAT = "torchtrack-detector"
FORMAT_VERSION = 1
_MAX_HEADER = 100 * 1024 * 1024


@dataclass(frozen=True)
class Limits:
    """Ranges a model file must respect (checked before anything is allocated).

    Attributes:
        file_bytes: largest model file read.
        window_side: largest window height / width in pixels.
        bank_features: largest Haar bank (its feature table is built on load: 32 bytes a row).
        bank_sizes: most filter sizes in a bank.
        selected: most selected features.
        stumps: most boosted stumps.
        support_vectors: most SVM support vectors.
        isotonic_points: most isotonic thresholds.
        stump_output: largest ``|left|`` / ``|right|`` of a stump (AdaBoost's alpha is at most
            ``0.5 ln(1e10) = 11.5``; real and gentle outputs are smaller).
        coefficient: largest magnitude of a calibration parameter, an SVM intercept, ``C`` or
            ``gamma``, and of isotonic thresholds.
        name_chars: longest model name.
        tensors: most tensors in a file.
    """

    file_bytes: int = 512 * 1024 * 1024
    window_side: int = 512
    bank_features: int = 2_000_000
    bank_sizes: int = 8
    selected: int = 100_000
    stumps: int = 100_000
    support_vectors: int = 1_000_000
    isotonic_points: int = 1_000_000
    stump_output: float = 100.0
    coefficient: float = 1e6
    name_chars: int = 256
    tensors: int = 64


LIMITS = Limits()

#: safetensors dtype names -> (torch dtype, bytes per element)
_DTYPES: dict[str, tuple[torch.dtype, int]] = {
    "F64": (torch.float64, 8),
    "F32": (torch.float32, 4),
    "F16": (torch.float16, 2),
    "BF16": (torch.bfloat16, 2),
    "I64": (torch.int64, 8),
    "I32": (torch.int32, 4),
    "I16": (torch.int16, 2),
    "I8": (torch.int8, 1),
    "U8": (torch.uint8, 1),
    "BOOL": (torch.bool, 1),
}


# --------------------------------------------------------------------------------- framing
@dataclass(frozen=True)
class TensorEntry:
    """A tensor's header entry: safetensors dtype name, shape, byte range in the data section."""

    dtype: str
    shape: tuple[int, ...]
    begin: int
    end: int


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


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


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


# ------------------------------------------------------------------------ the description
@dataclass
class Description:
    """A validated description: what the builder needs, with the sizes it implies.

    Attributes:
        version: the format version.
        meta: the description itself (JSON, minus ``sha256``).
        window: ``(H, W)``.
        bank: the bank description (checked, not yet built) and ``bank_features`` its size.
        value_bound: largest magnitude a feature value of this bank can take.
        n_selected: K, the number of selected features.
        checks: value checks to run on the loaded tensors (section name -> function).
    """

    version: int
    meta: dict[str, Any]
    window: tuple[int, int]
    bank: dict[str, Any]
    bank_features: int
    value_bound: float
    n_selected: int
    checks: dict[str, Callable[[dict[str, torch.Tensor]], None]] = field(default_factory=dict)


def _entry(
    entries: dict[str, TensorEntry], name: str, dtype: str, shape: tuple[int | None, ...]
) -> tuple[int, ...]:
    """Check that tensor ``name`` exists with ``dtype`` and ``shape`` (None: any length)."""
    e = entries.get(name)
    if e is None:
        raise ModelFormatError(f"tensor {name!r} is missing")
    if e.dtype != dtype:
        raise ModelFormatError(f"tensor {name!r} has dtype {e.dtype}, expected {dtype}")
    if len(e.shape) != len(shape) or any(
        s is not None and s != d for s, d in zip(shape, e.shape, strict=True)
    ):
        want = tuple("*" if s is None else s for s in shape)
        raise ModelFormatError(f"tensor {name!r} has shape {list(e.shape)}, expected {list(want)}")
    return e.shape


def _no_extra(entries: dict[str, TensorEntry], prefix: str, allowed: set[str]) -> None:
    extra = sorted(k for k in entries if k.startswith(prefix) and k[len(prefix) :] not in allowed)
    if extra:
        raise ModelFormatError(f"unexpected tensor(s) {extra}")


def _mapping(v: Any, what: str, required: set[str], optional: set[str] = frozenset()) -> dict:
    if not isinstance(v, dict):
        raise ModelFormatError(f"{what} must be a JSON object, got {type(v).__name__}")
    missing = required - set(v)
    if missing:
        raise ModelFormatError(f"{what} lacks {sorted(missing)}")
    unknown = set(v) - required - set(optional)
    if unknown:
        raise ModelFormatError(f"{what} has unknown key(s) {sorted(unknown)}")
    return v


def _int_in(v: Any, what: str, lo: int, hi: int) -> int:
    if not _is_int(v) or not lo <= v <= hi:
        raise ModelFormatError(f"{what} must be an integer in [{lo}, {hi}], got {v!r}")
    return v


def _num_in(v: Any, what: str, lo: float, hi: float, *, open_lo: bool = False) -> float:
    if not _is_num(v) or not (lo < v if open_lo else lo <= v) or not v <= hi:
        bracket = "(" if open_lo else "["
        raise ModelFormatError(f"{what} must be a finite number in {bracket}{lo}, {hi}], got {v!r}")
    return float(v)


def _check_window(meta: dict) -> tuple[int, int]:
    w = meta["window"]
    if not isinstance(w, list) or len(w) != 2:
        raise ModelFormatError(f"window must be [H, W], got {w!r}")
    side = LIMITS.window_side
    return (_int_in(w[0], "window height", 4, side), _int_in(w[1], "window width", 4, side))


def _check_bank(meta: dict, window: tuple[int, int]) -> tuple[int, float]:
    """The bank's feature count (computed, not built) and the bound on its feature values."""
    b = _mapping(meta["bank"], "bank", {"window", "sizes"}, {"stride", "min_std", "kinds"})
    if b["window"] != list(window):
        raise ModelFormatError(f"bank window {b['window']!r} disagrees with window {list(window)}")
    if "kinds" in b and b["kinds"] != list(KINDS):
        raise ModelFormatError(
            f"bank kinds {b['kinds']!r} differ from this version's {list(KINDS)}"
        )
    sizes = b["sizes"]
    if not isinstance(sizes, list) or not 1 <= len(sizes) <= LIMITS.bank_sizes:
        raise ModelFormatError(f"bank sizes must be a list of 1 to {LIMITS.bank_sizes} sizes")
    h, w = window
    for t in sizes:
        _int_in(t, "bank filter size", 4, min(h, w))
        if t % 4:
            raise ModelFormatError(f"bank filter size {t} is not a multiple of 4")
    if len(set(sizes)) != len(sizes):
        raise ModelFormatError(f"bank sizes must be distinct, got {sizes}")
    stride = _int_in(b.get("stride", 1), "bank stride", 1, max(h, w))
    min_std = _num_in(b.get("min_std", 1.0), "bank min_std", 1e-3, 255.0)
    n = len(KINDS) * sum(((h - t) // stride + 1) * ((w - t) // stride + 1) for t in sizes)
    if n > LIMITS.bank_features:
        raise ModelFormatError(
            f"the bank has {n:,} features, more than a model file may ask for "
            f"({LIMITS.bank_features:,})"
        )
    # A feature is a zero-mean +-1 filter response / area / window std (floored at min_std):
    # |f| <= 127.5 / min_std; twice that leaves room for interpolation and rounding.
    return n, 255.0 / min_std


def _check_selected(meta: dict, entries: dict[str, TensorEntry], bank_features: int) -> int:
    sel = meta["selected_features"]
    (k,) = _entry(entries, "features.index", "I64", (None,))
    if not 1 <= k <= min(LIMITS.selected, bank_features):
        raise ModelFormatError(
            f"features.index selects {k} features; expected 1 to "
            f"{min(LIMITS.selected, bank_features)}"
        )
    if not isinstance(sel, list) or len(sel) != k:
        raise ModelFormatError(
            f"selected_features must list the {k} selected features, got "
            f"{len(sel) if isinstance(sel, list) else type(sel).__name__}"
        )
    for i, d in enumerate(sel):
        d = _mapping(d, f"selected_features[{i}]", {"kind", "size", "y", "x"})
        if d["kind"] not in KINDS or not all(_is_int(d[c]) for c in ("size", "y", "x")):
            raise ModelFormatError(f"selected_features[{i}] is not a valid feature: {d!r}")
    return k


def _check_classes(classes: Any) -> None:
    if (
        not isinstance(classes, list)
        or len(classes) != 2
        or not all(_is_int(v) for v in classes)
        or classes[0] == classes[1]
    ):
        raise ModelFormatError(f"classifier.classes must be two distinct integers, got {classes!r}")


def _check_stumps(c: dict, entries: dict[str, TensorEntry], k: int, bound: float):
    from torchtrack.learn.boosting import VARIANTS

    _mapping(c, "classifier", {"kind", "variant", "n_estimators", "n_features_in", "classes"})
    if c["variant"] not in VARIANTS:
        raise ModelFormatError(f"classifier.variant {c['variant']!r} is not one of {VARIANTS}")
    _int_in(c["n_estimators"], "classifier.n_estimators", 1, LIMITS.stumps)
    if c["n_features_in"] != k:
        raise ModelFormatError(
            f"classifier.n_features_in is {c['n_features_in']!r} but {k} features are selected"
        )
    _check_classes(c["classes"])
    (r,) = _entry(entries, "classifier.feature", "I64", (None,))
    if not 1 <= r <= LIMITS.stumps:
        raise ModelFormatError(f"classifier has {r} stumps, expected 1 to {LIMITS.stumps}")
    for name in ("threshold", "left", "right"):
        _entry(entries, f"classifier.{name}", "F32", (r,))
    _no_extra(entries, "classifier.", {"feature", "threshold", "left", "right"})

    def values(t: dict[str, torch.Tensor]) -> None:
        f = t["classifier.feature"]
        if bool(((f < 0) | (f >= k)).any()):
            raise ModelFormatError(f"classifier.feature: indices outside [0, {k})")
        _finite_within(t["classifier.threshold"], "classifier.threshold", bound)
        for name in ("left", "right"):
            _finite_within(t[f"classifier.{name}"], f"classifier.{name}", LIMITS.stump_output)

    return values


def _check_svm(c: dict, entries: dict[str, TensorEntry], k: int, bound: float):
    from torchtrack.learn.svm import KERNELS

    _mapping(
        c, "classifier", {"kind", "kernel", "C", "gamma", "intercept", "n_features_in", "classes"}
    )
    if c["kernel"] not in KERNELS:
        raise ModelFormatError(f"classifier.kernel {c['kernel']!r} is not one of {KERNELS}")
    cap = LIMITS.coefficient
    C = _num_in(c["C"], "classifier.C", 0.0, cap, open_lo=True)
    if c["kernel"] == "rbf":
        _num_in(c["gamma"], "classifier.gamma", 0.0, cap, open_lo=True)
    else:
        _num_in(c["gamma"], "classifier.gamma", 0.0, cap)
    _num_in(c["intercept"], "classifier.intercept", -cap, cap)
    if c["n_features_in"] != k:
        raise ModelFormatError(
            f"classifier.n_features_in is {c['n_features_in']!r} but {k} features are selected"
        )
    _check_classes(c["classes"])
    s, _ = _entry(entries, "classifier.support_vectors", "F64", (None, k))
    if not 1 <= s <= LIMITS.support_vectors:
        raise ModelFormatError(
            f"classifier has {s} support vectors, expected 1 to {LIMITS.support_vectors}"
        )
    _entry(entries, "classifier.dual_coef", "F64", (s,))
    _entry(entries, "classifier.mean", "F64", (k,))
    _entry(entries, "classifier.scale", "F64", (k,))
    _no_extra(entries, "classifier.", {"support_vectors", "dual_coef", "mean", "scale"})

    def values(t: dict[str, torch.Tensor]) -> None:
        _finite_within(t["classifier.support_vectors"], "classifier.support_vectors", math.inf)
        # libsvm's dual coefficients alpha_i y_i satisfy |alpha_i| <= C.
        _finite_within(t["classifier.dual_coef"], "classifier.dual_coef", C * (1 + 1e-6))
        _finite_within(t["classifier.mean"], "classifier.mean", bound)
        scale = t["classifier.scale"]
        _finite_within(scale, "classifier.scale", 2 * bound)
        if bool((scale <= 0).any()):
            raise ModelFormatError("classifier.scale: must be positive")

    return values


def _check_platt(c: dict, entries: dict[str, TensorEntry]):
    _mapping(c, "calibration", {"kind", "a", "b"})
    cap = LIMITS.coefficient
    # p = 1 / (1 + exp(a m + b)): a detector's probability rises with its margin, so a < 0.
    _num_in(c["a"], "calibration.a (the Platt slope, negative)", -cap, 0.0)
    if c["a"] == 0:
        raise ModelFormatError("calibration.a is 0: the probability would ignore the margin")
    _num_in(c["b"], "calibration.b", -cap, cap)
    _no_extra(entries, "calibration.", set())
    return None


def _check_isotonic(c: dict, entries: dict[str, TensorEntry]):
    _mapping(c, "calibration", {"kind"})
    (n,) = _entry(entries, "calibration.x", "F64", (None,))
    if not 1 <= n <= LIMITS.isotonic_points:
        raise ModelFormatError(f"calibration has {n} isotonic thresholds")
    _entry(entries, "calibration.y", "F64", (n,))
    _no_extra(entries, "calibration.", {"x", "y"})

    def values(t: dict[str, torch.Tensor]) -> None:
        x, y = t["calibration.x"], t["calibration.y"]
        _finite_within(x, "calibration.x", LIMITS.coefficient)
        _finite_within(y, "calibration.y", 1.0)
        if bool((x[1:] < x[:-1]).any()):
            raise ModelFormatError("calibration.x: thresholds not sorted")
        if bool((y < 0).any()) or bool((y[1:] < y[:-1]).any()):
            raise ModelFormatError("calibration.y: values not monotone in [0, 1]")

    return values


#: classifier kind -> section check(classifier meta, entries, K, feature value bound)
_CLASSIFIER_SECTIONS: dict[str, Callable] = {"boosted_stumps": _check_stumps, "svm": _check_svm}
#: calibration kind -> section check(calibration meta, entries)
_CALIBRATION_SECTIONS: dict[str, Callable] = {"platt": _check_platt, "isotonic": _check_isotonic}


def _check_kinded(section: str, v: Any, registry: dict[str, Callable]) -> Callable:
    if not isinstance(v, dict) or not isinstance(v.get("kind"), str):
        raise ModelFormatError(f"{section} must be a JSON object with a 'kind' string")
    if v["kind"] not in registry:
        raise ModelFormatError(
            f"unknown {section} kind {v['kind']!r}; known kinds: {', '.join(sorted(registry))}"
        )
    return registry[v["kind"]]


def _finite_within(t: torch.Tensor, what: str, bound: float) -> None:
    if t.is_floating_point() and not bool(torch.isfinite(t).all()):
        raise ModelFormatError(f"tensor {what!r} holds NaN or inf")
    if t.numel() and float(t.abs().max()) > bound:
        raise ModelFormatError(
            f"tensor {what!r} holds {float(t.abs().max()):.4g}, outside the range its values "
            f"can take (|value| <= {bound:.4g})"
        )


_V1_KEYS = {
    "format",
    "format_version",
    "name",
    "window",
    "bank",
    "selected_features",
    "classifier",
    "calibration",
    "training",
}


def _validate_v1(meta: dict, entries: dict[str, TensorEntry]) -> Description:
    _mapping(meta, "the description", _V1_KEYS, {"object_box"})
    name = meta["name"]
    if not isinstance(name, str) or not 0 < len(name) <= LIMITS.name_chars:
        raise ModelFormatError(f"name must be a string of 1 to {LIMITS.name_chars} characters")
    if not isinstance(meta["training"], dict):
        raise ModelFormatError("training must be a JSON object")
    if "object_box" in meta:
        check_object_box(meta["object_box"])
    window = _check_window(meta)
    n_bank, bound = _check_bank(meta, window)
    k = _check_selected(meta, entries, n_bank)
    checks: dict[str, Callable] = {}

    def index_values(t: dict[str, torch.Tensor]) -> None:
        idx = t["features.index"]
        if bool(((idx < 0) | (idx >= n_bank)).any()):
            raise ModelFormatError(f"features.index: indices outside the bank [0, {n_bank})")

    checks["features"] = index_values
    clf = _check_kinded("classifier", meta["classifier"], _CLASSIFIER_SECTIONS)
    if (v := clf(meta["classifier"], entries, k, bound)) is not None:
        checks["classifier"] = v
    if meta["calibration"] is not None:
        cal = _check_kinded("calibration", meta["calibration"], _CALIBRATION_SECTIONS)
        if (v := cal(meta["calibration"], entries)) is not None:
            checks["calibration"] = v
    else:
        _no_extra(entries, "calibration.", set())
    known = {"features.index"}
    extra = sorted(
        n for n in entries if n not in known and not n.startswith(("classifier.", "calibration."))
    )
    if extra:
        raise ModelFormatError(f"unexpected tensor(s) {extra}")
    return Description(1, meta, window, meta["bank"], n_bank, bound, k, checks)


#: format version -> validator(meta, entries) -> Description
_VALIDATORS: dict[int, Callable[[dict, dict[str, TensorEntry]], Description]] = {1: _validate_v1}


def validate_description(meta: Any, entries: dict[str, TensorEntry]) -> Description:
    """Check a model description (without its ``sha256``) against the tensor entries, before
    any tensor is read.

    Raises:
        ModelFormatError: not a torchtrack detector, an unknown or future version, or any
            section that fails its check (the message names the field).
    """
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        got = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
        raise ModelFormatError(f"not a {FORMAT} file (format {got!r})")
    ver = meta.get("format_version")
    if not _is_int(ver) or ver < 1:
        raise ModelFormatError(f"invalid format_version {ver!r}")
    if ver > FORMAT_VERSION:
        raise ModelFormatError(
            f"format version {ver}, newer than this torchtrack reads ({FORMAT_VERSION}); "
            "upgrade torchtrack"
        )
    if ver not in _VALIDATORS:
        raise ModelFormatError(f"format version {ver} is no longer supported")
    return _VALIDATORS[ver](meta, entries)


def check_tensor_values(desc: Description, tensors: dict[str, torch.Tensor]) -> None:
    """Run the value checks of every section on the loaded tensors.

    Raises:
        ModelFormatError: an index outside its range, a non-finite value or one outside the
            range the section allows (named).
    """
    for fn in desc.checks.values():
        fn(tensors)


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
    tensors = {"features.index": det.feature_index.contiguous()}
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
        "bank": det.bank.to_dict(),
        "selected_features": det.selected_features(),
        "classifier": sc_m,
        "calibration": cal_m,
        "training": det.summary,
    }
    if det.object_box is not None:
        meta["object_box"] = list(det.object_box)
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


def _build_v1(desc: Description, tensors: dict[str, torch.Tensor]) -> Detector:
    """A :class:`Detector` from a validated version-1 description and its checked tensors."""
    from torchtrack.learn import calibrator_from_state, classifier_from_state

    meta = desc.meta
    bank = HaarBank.from_dict(meta["bank"])
    clf = classifier_from_state(_section(tensors, "classifier."), meta["classifier"])
    cal = None
    if meta["calibration"] is not None:
        cal = calibrator_from_state(_section(tensors, "calibration."), meta["calibration"])
    det = Detector(
        bank,
        tensors["features.index"],
        clf,
        cal,
        name=meta["name"],
        summary=meta["training"],
        object_box=meta.get("object_box"),
    )
    if det.selected_features() != meta["selected_features"]:
        raise ModelFormatError("selected feature descriptions disagree with the feature index")
    return det


#: format version -> builder(description, tensors) -> Detector
_BUILDERS: dict[int, Callable[[Description, dict[str, torch.Tensor]], Detector]] = {1: _build_v1}


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
