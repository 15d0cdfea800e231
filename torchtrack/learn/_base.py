"""Shared input checks and state (de)serialisation helpers for the learning estimators.

Every estimator in :mod:`torchtrack.learn` turns user input into torch tensors through these
functions, so bad input fails the same way everywhere: a :class:`~torchtrack.errors.DataError`
(or :class:`~torchtrack.errors.ShapeError`) that names the argument and the first bad index.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from sklearn.exceptions import NotFittedError as _SklearnNotFittedError

from torchtrack import errors
from torchtrack.errors import is_integer, is_number

__all__ = [
    "NotFittedError",
    "as_binary_labels",
    "as_float_tensor",
    "check_fitted",
    "is_integer",
    "is_number",
    "state_meta",
    "state_tensor",
]


class NotFittedError(errors.NotFittedError, _SklearnNotFittedError):
    """An estimator was used before ``fit``.

    Subclass of both :class:`torchtrack.errors.NotFittedError` and scikit-learn's
    ``sklearn.exceptions.NotFittedError``, so ``except`` clauses written for either catch it.
    """


def check_fitted(estimator: Any, attribute: str) -> None:
    """Raise :class:`NotFittedError` unless ``estimator`` has the learned ``attribute``."""
    if not hasattr(estimator, attribute):
        raise NotFittedError(
            f"this {type(estimator).__name__} is not fitted yet: call fit(X, y) first "
            "(or build it with from_state)"
        )


def _to_tensor(x: Any, name: str) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x
    try:
        arr = np.asarray(x)
    except Exception as exc:  # ragged lists and the like
        raise errors.DataError(f"{name} must be array-like, got {type(x).__name__}: {exc}") from exc
    if arr.dtype == object or not (
        np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.bool_)
    ):
        raise errors.DataError(f"{name} must be numeric, got an array of dtype {arr.dtype}")
    return torch.from_numpy(np.ascontiguousarray(arr))


def as_float_tensor(
    x: Any,
    name: str,
    *,
    ndim: int | tuple[int, ...] | None = None,
    dtype: torch.dtype = torch.float32,
    check_finite: bool = True,
) -> torch.Tensor:
    """Convert array-like ``x`` to a floating tensor (device kept), checking shape and finiteness.

    Args:
        x: numpy array, torch tensor or nested list.
        name: argument name used in error messages.
        ndim: required number of dimensions (or a tuple of allowed ones).
        dtype: floating dtype of the result.
        check_finite: raise :class:`DataError` on NaN / inf, naming the first bad index.

    Raises:
        ShapeError: wrong number of dimensions or an empty array.
        DataError: non-numeric input or (with ``check_finite``) a NaN / inf entry.
    """
    t = _to_tensor(x, name)
    if ndim is not None:
        allowed = (ndim,) if isinstance(ndim, int) else ndim
        if t.ndim not in allowed:
            raise errors.ShapeError(
                f"{name} must have {' or '.join(map(str, allowed))} dimension(s), "
                f"got shape {tuple(t.shape)}"
            )
    if t.numel() == 0:
        raise errors.ShapeError(f"{name} is empty (shape {tuple(t.shape)})")
    if t.is_complex():  # .to(float) dropped the imaginary part with only a UserWarning
        raise errors.ShapeError(f"{name} must hold real numbers, got {t.dtype}")
    t = t.to(dtype)
    if check_finite:
        bad = ~torch.isfinite(t)
        if bool(bad.any()):
            first = tuple(int(i) for i in bad.nonzero()[0])
            idx = first[0] if len(first) == 1 else first
            raise errors.DataError(
                f"{name} contains {int(bad.sum())} non-finite value(s) (NaN or inf); "
                f"the first is at index {idx}: {t[first].item()}"
            )
    return t


def check_weighted_classes(sw: torch.Tensor, y01: torch.Tensor, classes: Any) -> None:
    """DataError unless the weights ``sw (n,)`` give a positive weight to samples of both
    classes of ``y01 (n,)`` (``classes``: the two original labels, for the message): weights
    that zero one class out fit a one-class model (an isotonic map of 1 everywhere)."""
    weighted = y01.to(sw.device)[sw > 0]
    if weighted.numel() and weighted.min() == weighted.max():
        raise errors.DataError(
            "sample_weight must give a positive weight to samples of both classes, "
            f"got positive weights for class {classes[int(weighted[0])]!r} only"
        )


def as_binary_labels(y: Any, n: int, name: str = "y") -> tuple[torch.Tensor, np.ndarray]:
    """Check binary labels and map them to ``{0, 1}``.

    The two distinct values are sorted and the larger one is the positive class (scikit-learn's
    ``classes_[1]``), so ``{0, 1}``, ``{False, True}`` and ``{-1, 1}`` all work.

    Args:
        y: labels, shape ``(n,)``.
        n: expected number of labels (rows of X).

    Returns:
        ``(y01, classes)``: ``y01 (n,)`` int64 tensor in ``{0, 1}`` and the sorted classes.

    Raises:
        ShapeError: wrong length or not 1-D.
        DataError: NaN labels, a single class, or more than two classes.
    """
    t = _to_tensor(y, name)
    if t.ndim != 1 or t.shape[0] != n:
        raise errors.ShapeError(f"{name} must have shape ({n},), got {tuple(t.shape)}")
    if t.is_floating_point() and not bool(torch.isfinite(t).all()):
        first = int((~torch.isfinite(t)).nonzero()[0, 0])
        raise errors.DataError(f"{name} contains a non-finite label at index {first}")
    arr = t.detach().cpu().numpy()
    classes = np.unique(arr)
    if classes.size != 2:
        found = ", ".join(repr(c.item()) for c in classes[:5])
        raise errors.DataError(
            f"{name} must contain exactly two classes (negative and positive), "
            f"found {classes.size}: {found}"
        )
    y01 = torch.from_numpy((arr == classes[1]).astype(np.int64)).to(t.device)
    return y01, classes


# ---------------------------------------------------------------- state (de)serialisation


def state_tensor(
    tensors: Mapping[str, torch.Tensor],
    key: str,
    kind: str,
    *,
    ndim: int | None = None,
    shape: tuple[int | None, ...] | None = None,
    dtype: torch.dtype | tuple[torch.dtype, ...] | None = None,
    finite: bool = True,
) -> torch.Tensor:
    """Fetch and validate ``tensors[key]`` for a ``from_state`` of ``kind``.

    Raises:
        ModelFormatError: missing key, wrong type, dimensions, shape, dtype, or non-finite values,
            naming the field.
    """
    field = f"{kind}.{key}"
    if key not in tensors:
        raise errors.ModelFormatError(f"{field}: missing tensor (have {sorted(tensors)})")
    t = tensors[key]
    if not isinstance(t, torch.Tensor):
        raise errors.ModelFormatError(f"{field}: expected a tensor, got {type(t).__name__}")
    if dtype is not None:
        allowed = (dtype,) if isinstance(dtype, torch.dtype) else dtype
        if t.dtype not in allowed:
            raise errors.ModelFormatError(f"{field}: dtype {t.dtype}, expected one of {allowed}")
    if ndim is not None and t.ndim != ndim:
        raise errors.ModelFormatError(f"{field}: {t.ndim} dimensions, expected {ndim}")
    if shape is not None:
        if t.ndim != len(shape) or any(
            s is not None and s != d for s, d in zip(shape, t.shape, strict=True)
        ):
            raise errors.ModelFormatError(
                f"{field}: shape {tuple(t.shape)}, expected {tuple('*' if s is None else s for s in shape)}"
            )
    if finite and t.is_floating_point() and not bool(torch.isfinite(t).all()):
        raise errors.ModelFormatError(f"{field}: contains NaN or inf")
    return t


def state_meta(meta: Mapping[str, Any], key: str, kind: str, types: type | tuple[type, ...]) -> Any:
    """Fetch ``meta[key]`` and check its JSON type, raising :class:`ModelFormatError` otherwise."""
    field = f"{kind}.{key}"
    if not isinstance(meta, Mapping):
        raise errors.ModelFormatError(f"{kind}: metadata must be a JSON object")
    if key not in meta:
        raise errors.ModelFormatError(f"{field}: missing metadata key")
    value = meta[key]
    if isinstance(value, bool) and bool not in (types if isinstance(types, tuple) else (types,)):
        raise errors.ModelFormatError(f"{field}: expected {types}, got a boolean")
    if not isinstance(value, types):
        raise errors.ModelFormatError(f"{field}: expected {types}, got {type(value).__name__}")
    if isinstance(value, float) and not math.isfinite(value):
        raise errors.ModelFormatError(f"{field}: not finite ({value})")
    if (
        isinstance(value, int)
        and float in (types if isinstance(types, tuple) else (types,))
        and not -sys.float_info.max <= value <= sys.float_info.max
    ):  # a JSON integer of 400 digits: float() of it was an OverflowError
        raise errors.ModelFormatError(f"{field}: not finite (an integer beyond the float range)")
    return value


def check_kind(meta: Mapping[str, Any], expected: str) -> None:
    """Raise :class:`ModelFormatError` unless ``meta["kind"] == expected``."""
    kind = state_meta(meta, "kind", expected, str)
    if kind != expected:
        raise errors.ModelFormatError(f"state of kind {kind!r} given to the {expected!r} loader")
