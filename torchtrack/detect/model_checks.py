"""What a valid detector model description is: the limits, one check per section, and the
validator of each format version (used by :mod:`torchtrack.detect.model_file` on load and on
save).

Every check runs on the JSON description and the header's tensor entries (dtype, shape) before
any tensor is read, so nothing is allocated for a file that fails; the value checks that need
the tensors (:attr:`Description.checks`) run after they are read. Each failure is a
:class:`~torchtrack.errors.ModelFormatError` naming the field.

Version 1: Chateau's grey Haar bank under ``bank``. Version 2 (written now): the bank under
``features`` with a ``kind`` (``haar`` or ``channels``: integral channel features, whose
channel set and geometry the features layer validates, :meth:`ChannelBank.check_header
<torchtrack.features.channels.ChannelBank.check_header>`), and boosted trees among the
classifiers.

**Adding a format version.** Write ``_validate_vN(meta, entries) -> Description`` from the
section functions: reuse the unchanged ones and add one per new section (a section check takes
its part of the description and the tensor entries, checks JSON types and ranges and that the
tensors' dtypes and shapes agree, and returns the value check to run after loading, or
``None``); register it in ``_VALIDATORS`` and raise ``FORMAT_VERSION``. Its builder goes in
:data:`torchtrack.detect.model_file._BUILDERS`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from torchtrack.detect.detector import check_object_box
from torchtrack.errors import ModelFormatError
from torchtrack.features.haar import KINDS

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "LIMITS",
    "Description",
    "Limits",
    "TensorEntry",
    "check_tensor_values",
    "name_error",
    "validate_description",
]

FORMAT = "torchtrack-detector"
FORMAT_VERSION = 2


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


def name_error(name: Any) -> str | None:
    """What is wrong with a model name (``None``: nothing): a string of 1 to
    ``LIMITS.name_chars`` characters, the one rule for model files and training configs."""
    if isinstance(name, str) and 0 < len(name) <= LIMITS.name_chars:
        return None
    got = f"{len(name)} characters" if isinstance(name, str) else repr(name)
    return f"name must be a string of 1 to {LIMITS.name_chars} characters, got {got}"


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


@dataclass(frozen=True)
class TensorEntry:
    """A tensor's header entry: safetensors dtype name, shape, byte range in the data section."""

    dtype: str
    shape: tuple[int, ...]
    begin: int
    end: int


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


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
    return _check_haar_bank(meta["bank"], window)


#: how :func:`_check_haar_bank` names a bank's fields in its messages (a model file's)
_BANK_NAMES = {
    "sizes": "bank sizes",
    "size": "bank filter size",
    "stride": "bank stride",
    "min_std": "bank min_std",
}


def _check_haar_bank(
    bank: Any, window: tuple[int, int], names: dict[str, str] | None = None
) -> tuple[int, float]:
    """A Haar bank description's feature count (computed, not built) and value bound.
    ``names``: the fields' names in the messages (a training config's keys; default a model
    file's, :data:`_BANK_NAMES`)."""
    n = {**_BANK_NAMES, **(names or {})}
    b = _mapping(bank, "bank", {"window", "sizes"}, {"stride", "min_std", "kinds"})
    if b["window"] != list(window):
        raise ModelFormatError(f"bank window {b['window']!r} disagrees with window {list(window)}")
    if "kinds" in b and b["kinds"] != list(KINDS):
        raise ModelFormatError(
            f"bank kinds {b['kinds']!r} differ from this version's {list(KINDS)}"
        )
    sizes = b["sizes"]
    if not isinstance(sizes, list) or not 1 <= len(sizes) <= LIMITS.bank_sizes:
        raise ModelFormatError(f"{n['sizes']} must be a list of 1 to {LIMITS.bank_sizes} sizes")
    h, w = window
    for t in sizes:
        _int_in(t, n["size"], 4, min(h, w))
        if t % 4:
            raise ModelFormatError(f"{n['size']} {t} is not a multiple of 4")
    if len(set(sizes)) != len(sizes):
        raise ModelFormatError(f"{n['sizes']} must be distinct, got {sizes}")
    stride = _int_in(b.get("stride", 1), n["stride"], 1, max(h, w))
    min_std = _num_in(b.get("min_std", 1.0), n["min_std"], 1e-3, 255.0)
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


def _check_trees(c: dict, entries: dict[str, TensorEntry], k: int, bound: float):
    from torchtrack.learn.boosting import VARIANTS

    _mapping(
        c,
        "classifier",
        {"kind", "variant", "max_depth", "n_estimators", "n_features_in", "classes"},
    )
    if c["variant"] not in VARIANTS:
        raise ModelFormatError(f"classifier.variant {c['variant']!r} is not one of {VARIANTS}")
    depth = _int_in(c["max_depth"], "classifier.max_depth", 1, 4)
    _int_in(c["n_estimators"], "classifier.n_estimators", 1, LIMITS.stumps)
    if c["n_features_in"] != k:
        raise ModelFormatError(
            f"classifier.n_features_in is {c['n_features_in']!r} but {k} features are selected"
        )
    _check_classes(c["classes"])
    n_int = (1 << depth) - 1
    r, _ = _entry(entries, "classifier.feature", "I64", (None, n_int))
    if not 1 <= r <= LIMITS.stumps:
        raise ModelFormatError(f"classifier has {r} trees, expected 1 to {LIMITS.stumps}")
    _entry(entries, "classifier.threshold", "F32", (r, n_int))
    _entry(entries, "classifier.leaf", "F32", (r, n_int + 1))
    _entry(entries, "classifier.reject", "F32", (r,))
    _no_extra(entries, "classifier.", {"feature", "threshold", "leaf", "reject"})
    big = float(torch.finfo(torch.float32).max)  # "never go right" / "never reject"

    def values(t: dict[str, torch.Tensor]) -> None:
        f = t["classifier.feature"]
        if bool(((f < 0) | (f >= k)).any()):
            raise ModelFormatError(f"classifier.feature: indices outside [0, {k})")
        thr = t["classifier.threshold"]
        _finite_within(thr[thr != big], "classifier.threshold", bound)
        _finite_within(t["classifier.leaf"], "classifier.leaf", LIMITS.stump_output)
        rej = t["classifier.reject"]
        _finite_within(rej[rej != -big], "classifier.reject", LIMITS.stump_output * r)

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


def platt_slope_ok(a: float) -> bool:
    """Whether ``a`` can be a detector's Platt slope: ``p = 1 / (1 + exp(a m + b))`` rises with
    the margin only for ``a < 0``, and ``|a|`` stays within ``LIMITS.coefficient`` (the rule of
    model files and of ``torchtrack track --det-calibration``)."""
    return -LIMITS.coefficient <= a < 0


def _check_platt(c: dict, entries: dict[str, TensorEntry]):
    _mapping(c, "calibration", {"kind", "a", "b"})
    cap = LIMITS.coefficient
    _num_in(c["a"], "calibration.a (the Platt slope, negative)", -cap, 0.0)
    if not platt_slope_ok(c["a"]):  # in range, so 0
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
_CLASSIFIER_SECTIONS: dict[str, Callable] = {
    "boosted_stumps": _check_stumps,
    "boosted_trees": _check_trees,
    "svm": _check_svm,
}
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
    if name_error(name):
        raise ModelFormatError(name_error(name))
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


def _check_features(
    meta: dict, entries: dict[str, TensorEntry], window: tuple[int, int]
) -> tuple[int, float, Callable | None]:
    """Version 2's ``features`` section: the bank (Chateau's grey Haar bank, or integral
    channel features whose description the features layer validates) and its tables. Returns
    the bank size, the bound on its feature values and the value check of its tables."""
    from torchtrack.errors import ConfigError
    from torchtrack.features import BANK_KINDS
    from torchtrack.features.channels import ChannelBank

    d = meta["features"]
    if not isinstance(d, dict) or d.get("kind") not in BANK_KINDS:
        kind = d.get("kind") if isinstance(d, dict) else type(d).__name__
        raise ModelFormatError(f"features.kind {kind!r} is not one of {', '.join(BANK_KINDS)}")
    if d["kind"] == "haar":
        n, bound = _check_haar_bank({k: v for k, v in d.items() if k != "kind"}, window)
        _no_extra(entries, "features.", {"index"})
        return n, bound, None
    try:
        cs, win, cell, n = ChannelBank.check_header(d)
    except ConfigError as exc:
        raise ModelFormatError(f"features: {exc}") from None
    if list(win) != list(window):
        raise ModelFormatError(f"features window {list(win)} disagrees with window {list(window)}")
    _entry(entries, "features.rects", "I32", (n, 4, 5))
    _entry(entries, "features.channel", "I64", (n,))
    _no_extra(entries, "features.", {"index", "rects", "channel"})
    # A feature sums at most four weighted (|w| <= 4) rectangle means of one channel, times
    # the power-law factor r ** lambda: LUV is within [-2, 2]; a normalised gradient channel
    # within norm_radius + 1 (unnormalised: sqrt(2) / norm_const).
    grad = (cs.norm_radius + 1.0) if cs.norm_radius > 0 else 1.5 / cs.norm_const
    bound = 16.0 * max(2.0, grad) * 8.0

    def values(t: dict[str, torch.Tensor]) -> None:
        try:
            ChannelBank(win, cs, t["features.rects"], t["features.channel"], cell)
        except ConfigError as exc:
            raise ModelFormatError(f"features: {exc}") from None

    return n, bound, values


_V2_KEYS = {
    "format",
    "format_version",
    "name",
    "window",
    "features",
    "classifier",
    "calibration",
    "training",
}


def _check_tracking_head(meta: dict, entries: dict[str, TensorEntry]) -> None:
    """``tracking_head``: the first ``trees`` trees of a boosted-trees classifier, Platt."""
    head = _mapping(meta["tracking_head"], "tracking_head", {"trees", "calibration"})
    c = meta["classifier"]
    if c.get("kind") != "boosted_trees":
        raise ModelFormatError("tracking_head belongs to boosted-trees classifiers only")
    r = entries["classifier.feature"].shape[0]
    _int_in(head["trees"], "tracking_head.trees", 1, r)
    cal = head["calibration"]
    if not isinstance(cal, dict) or cal.get("kind") != "platt":
        raise ModelFormatError("tracking_head.calibration must be a Platt calibration")
    try:
        _check_platt(cal, {})
    except ModelFormatError as exc:
        raise ModelFormatError(f"tracking_head: {exc}") from None


def _check_box_regression(meta: dict, entries: dict[str, TensorEntry], k: int) -> Callable:
    """``box_regression``: a linear map of the ``k`` selected features to a window's move
    (tensors ``box_regression.weight (3, k)`` and ``box_regression.bias (3,)``, float32)."""
    reg = _mapping(meta["box_regression"], "box_regression", {"limit", "summary"})
    lim = reg["limit"]
    if not isinstance(lim, list) or len(lim) != 3:
        raise ModelFormatError(f"box_regression.limit must be a list of 3 numbers, got {lim!r}")
    for v in lim:
        _num_in(v, "box_regression.limit", 0.0, 1.0, open_lo=True)
    if not isinstance(reg["summary"], dict):
        raise ModelFormatError("box_regression.summary must be a JSON object")
    _entry(entries, "box_regression.weight", "F32", (3, k))
    _entry(entries, "box_regression.bias", "F32", (3,))
    _no_extra(entries, "box_regression.", {"weight", "bias"})

    def values(t: dict[str, torch.Tensor]) -> None:
        for name in ("box_regression.weight", "box_regression.bias"):
            if not bool(torch.isfinite(t[name]).all()):
                raise ModelFormatError(f"{name} holds values that are not finite")

    return values


def _validate_v2(meta: dict, entries: dict[str, TensorEntry]) -> Description:
    """Version 2: the feature bank under ``features`` with a ``kind`` (``haar``: the version 1
    bank plus its ``selected_features``; ``channels``: channel set, lattice and feature tables
    ``features.rects`` / ``features.channel``); classifiers include boosted trees."""
    _mapping(
        meta,
        "the description",
        _V2_KEYS,
        {"object_box", "selected_features", "tracking_head", "box_regression"},
    )
    name = meta["name"]
    if name_error(name):
        raise ModelFormatError(name_error(name))
    if not isinstance(meta["training"], dict):
        raise ModelFormatError("training must be a JSON object")
    if "object_box" in meta:
        check_object_box(meta["object_box"])
    window = _check_window(meta)
    n_bank, bound, table_check = _check_features(meta, entries, window)
    haar = meta["features"]["kind"] == "haar"
    if haar:
        if "selected_features" not in meta:
            raise ModelFormatError(
                "the description lacks ['selected_features'] (a Haar model lists them)"
            )
        k = _check_selected(meta, entries, n_bank)
    else:
        if "selected_features" in meta:
            raise ModelFormatError("selected_features belongs to Haar models only")
        (k,) = _entry(entries, "features.index", "I64", (None,))
        if not 1 <= k <= min(LIMITS.selected, n_bank):
            raise ModelFormatError(
                f"features.index selects {k} features; expected 1 to {min(LIMITS.selected, n_bank)}"
            )
    checks: dict[str, Callable] = {}

    def index_values(t: dict[str, torch.Tensor]) -> None:
        idx = t["features.index"]
        if bool(((idx < 0) | (idx >= n_bank)).any()):
            raise ModelFormatError(f"features.index: indices outside the bank [0, {n_bank})")
        if table_check is not None:
            table_check(t)

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
    if "tracking_head" in meta:
        _check_tracking_head(meta, entries)
    prefixes = ("features.", "classifier.", "calibration.")
    if "box_regression" in meta:
        checks["box_regression"] = _check_box_regression(meta, entries, k)
        prefixes += ("box_regression.",)
    extra = sorted(n for n in entries if not n.startswith(prefixes))
    if extra:
        raise ModelFormatError(f"unexpected tensor(s) {extra}")
    return Description(2, meta, window, meta["features"], n_bank, bound, k, checks)


#: format version -> validator(meta, entries) -> Description
_VALIDATORS: dict[int, Callable[[dict, dict[str, TensorEntry]], Description]] = {
    1: _validate_v1,
    2: _validate_v2,
}


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
