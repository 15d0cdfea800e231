"""Scoring heads: the tensor form of trained classifiers and calibrators that a detector runs.

A detector never runs a scikit-learn object. Training produces estimators (``torchtrack.learn``
or scikit-learn); :func:`scorer_from_estimator` and :func:`calibrator_from_estimator` turn them
into these small tensor heads, which score batches in torch on any device and are what model
files store (tensors + a JSON description, no pickle).

Scorers map selected features ``X (M, K)`` to margins ``m (M,)``:

* :class:`StumpScorer` -- boosted decision stumps, ``m(f) = sum_i (f[j_i] > t_i ? r_i : l_i)``.
  Discrete AdaBoost (paper eq. 9: ``alpha_i h_i(f)`` with ``h`` in {0, 1}) is ``l = 0,
  r = alpha`` (or swapped for a reversed polarity); Real and Gentle AdaBoost store their two
  leaf values.
* :class:`KernelScorer` -- an SVM (paper eq. 10), ``m(f) = sum_s c_s K(sv_s, z) + b`` on
  standardised features ``z = (f - mean) / scale``; RBF or linear kernel.

Calibrators map margins to probabilities:

* :class:`SigmoidCalibrator` -- Platt, ``P = 1 / (1 + exp(A m + B))`` (paper eq. 5 / 8).
* :class:`IsotonicCalibrator` -- piecewise-linear interpolation of an isotonic fit, clipped at
  the ends (scikit-learn's ``IsotonicRegression(out_of_bounds="clip")``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from torchtrack.errors import ModelFormatError, ShapeError

__all__ = [
    "IsotonicCalibrator",
    "KernelScorer",
    "SigmoidCalibrator",
    "StumpScorer",
    "calibrator_from_estimator",
    "calibrator_from_state",
    "scorer_from_estimator",
    "scorer_from_state",
]


def _as_t(x: Any, dtype=torch.float32) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.detach().to(dtype=dtype).cpu().contiguous()
    return torch.as_tensor(np.array(x), dtype=dtype).contiguous()


def _check_x(x: torch.Tensor, k: int) -> None:
    if not isinstance(x, torch.Tensor) or x.ndim != 2 or x.shape[1] != k:
        got = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
        raise ShapeError(f"features must have shape (M, {k}), got {got}")


@dataclass
class StumpScorer:
    """Boosted stumps: ``feature (T,)`` int64 column of X, ``threshold (T,)`` float64, ``left``,
    ``right (T,)`` float32; a stump gives ``right`` when ``X[:, feature] > threshold``, else ``left``."""

    feature: torch.Tensor
    threshold: torch.Tensor
    left: torch.Tensor
    right: torch.Tensor
    kind: str = "stumps"

    def __post_init__(self) -> None:
        self.feature = _as_t(self.feature, torch.int64)
        # float64: stump thresholds are midpoints of float32 values; rounding them to float32
        # could move a threshold onto a data value and flip its side.
        self.threshold = _as_t(self.threshold, torch.float64)
        self.left = _as_t(self.left)
        self.right = _as_t(self.right)
        n = self.feature.shape
        for name in ("threshold", "left", "right"):
            if getattr(self, name).shape != n or len(n) != 1:
                raise ModelFormatError(
                    f"stump {name} has shape {tuple(getattr(self, name).shape)}, expected {tuple(n)}"
                )

    @property
    def n_inputs(self) -> int:
        return int(self.feature.max()) + 1 if self.feature.numel() else 0

    def decision_function(self, x: torch.Tensor) -> torch.Tensor:
        """``x (M, K)`` -> margins ``(M,)``."""
        if x.ndim != 2:
            _check_x(x, self.n_inputs)
        dev = x.device
        f = x[:, self.feature.to(dev)]  # (M, T)
        hit = f.to(torch.float64) > self.threshold.to(dev)
        return torch.where(hit, self.right.to(dev, x.dtype), self.left.to(dev, x.dtype)).sum(1)

    def state(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        t = {
            "feature": self.feature,
            "threshold": self.threshold,
            "left": self.left,
            "right": self.right,
        }
        return t, {"type": "stumps", "n_stumps": int(self.feature.numel())}


@dataclass
class KernelScorer:
    """SVM margin: ``support (S, K)``, ``coef (S,)`` (alpha_i y_i), ``intercept`` b, kernel
    ``"rbf"`` (``exp(-gamma |sv - z|^2)``) or ``"linear"`` (``sv . z``), on
    ``z = (x - mean) / scale`` with ``mean, scale (K,)``."""

    support: torch.Tensor
    coef: torch.Tensor
    intercept: float
    kernel: str
    gamma: float
    mean: torch.Tensor
    scale: torch.Tensor

    def __post_init__(self) -> None:
        self.support = _as_t(self.support)
        self.coef = _as_t(self.coef).reshape(-1)
        self.mean = _as_t(self.mean).reshape(-1)
        self.scale = _as_t(self.scale).reshape(-1)
        if self.kernel not in ("rbf", "linear"):
            raise ModelFormatError(f"SVM kernel must be 'rbf' or 'linear', got {self.kernel!r}")
        if self.support.ndim != 2 or self.support.shape[0] != self.coef.shape[0]:
            raise ModelFormatError(
                f"SVM support {tuple(self.support.shape)} and coef {tuple(self.coef.shape)} disagree"
            )
        k = self.support.shape[1]
        if self.mean.shape != (k,) or self.scale.shape != (k,):
            raise ModelFormatError(f"SVM mean/scale must have shape ({k},)")
        if not (math.isfinite(self.intercept) and math.isfinite(self.gamma)):
            raise ModelFormatError("SVM intercept and gamma must be finite")

    @property
    def n_inputs(self) -> int:
        return int(self.support.shape[1])

    def decision_function(self, x: torch.Tensor) -> torch.Tensor:
        """``x (M, K)`` -> margins ``(M,)`` (paper eq. 10)."""
        _check_x(x, self.n_inputs)
        dev, dt = x.device, x.dtype
        z = (x - self.mean.to(dev, dt)) / self.scale.to(dev, dt)
        sv = self.support.to(dev, dt)
        if self.kernel == "linear":
            k = z @ sv.T
        else:
            d2 = (z * z).sum(1, keepdim=True) - 2 * z @ sv.T + (sv * sv).sum(1)[None]
            k = torch.exp(-self.gamma * d2.clamp(min=0))
        return k @ self.coef.to(dev, dt) + self.intercept

    def state(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        t = {"support": self.support, "coef": self.coef, "mean": self.mean, "scale": self.scale}
        return t, {
            "type": "svm",
            "kernel": self.kernel,
            "gamma": float(self.gamma),
            "intercept": float(self.intercept),
            "n_support": int(self.support.shape[0]),
        }


@dataclass
class SigmoidCalibrator:
    """Platt scaling ``P = 1 / (1 + exp(A m + B))`` (paper eq. 5)."""

    a: float
    b: float

    def __post_init__(self) -> None:
        self.a, self.b = float(self.a), float(self.b)
        if not (math.isfinite(self.a) and math.isfinite(self.b)):
            raise ModelFormatError(f"sigmoid A, B must be finite, got {self.a}, {self.b}")

    def __call__(self, m: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(-(self.a * m + self.b))

    def state(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        return {}, {"type": "sigmoid", "A": self.a, "B": self.b}


@dataclass
class IsotonicCalibrator:
    """Isotonic calibration: increasing knots ``x (J,)`` with values ``y (J,)`` in [0, 1]."""

    x: torch.Tensor
    y: torch.Tensor

    def __post_init__(self) -> None:
        self.x = _as_t(self.x, torch.float64).reshape(-1)
        self.y = _as_t(self.y, torch.float64).reshape(-1)
        if self.x.shape != self.y.shape or self.x.numel() < 1:
            raise ModelFormatError("isotonic knots x and y must be non-empty and of equal length")
        if bool((self.x[1:] < self.x[:-1]).any()) or bool((self.y[1:] < self.y[:-1]).any()):
            raise ModelFormatError("isotonic knots must be non-decreasing")

    def __call__(self, m: torch.Tensor) -> torch.Tensor:
        xk = self.x.to(m.device)
        yk = self.y.to(m.device)
        v = m.to(torch.float64).clamp(float(xk[0]), float(xk[-1]))
        if xk.numel() == 1:
            return yk.expand_as(v).to(m.dtype)
        i = torch.searchsorted(xk, v.contiguous(), right=True).clamp(1, xk.numel() - 1)
        x0, x1, y0, y1 = xk[i - 1], xk[i], yk[i - 1], yk[i]
        span = x1 - x0
        t = torch.where(span > 0, (v - x0) / torch.where(span > 0, span, 1), torch.ones_like(v))
        return (y0 + t * (y1 - y0)).to(m.dtype)

    def state(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        return {"x": self.x, "y": self.y}, {"type": "isotonic", "n_knots": int(self.x.numel())}


def scorer_from_state(tensors: dict[str, torch.Tensor], meta: dict[str, Any]):
    """Rebuild a scorer from :meth:`state` output (used by model files)."""
    kind = meta.get("type")
    try:
        if kind == "stumps":
            return StumpScorer(
                tensors["feature"], tensors["threshold"], tensors["left"], tensors["right"]
            )
        if kind == "svm":
            return KernelScorer(
                tensors["support"],
                tensors["coef"],
                float(meta["intercept"]),
                str(meta["kernel"]),
                float(meta["gamma"]),
                tensors["mean"],
                tensors["scale"],
            )
    except KeyError as exc:
        raise ModelFormatError(f"classifier of type {kind!r} lacks {exc.args[0]!r}") from None
    raise ModelFormatError(f"unknown classifier type {kind!r}; known: 'stumps', 'svm'")


def calibrator_from_state(tensors: dict[str, torch.Tensor], meta: dict[str, Any]):
    """Rebuild a calibrator from :meth:`state` output (used by model files)."""
    kind = meta.get("type")
    try:
        if kind == "sigmoid":
            return SigmoidCalibrator(meta["A"], meta["B"])
        if kind == "isotonic":
            return IsotonicCalibrator(tensors["x"], tensors["y"])
    except KeyError as exc:
        raise ModelFormatError(f"calibration of type {kind!r} lacks {exc.args[0]!r}") from None
    raise ModelFormatError(f"unknown calibration type {kind!r}; known: 'sigmoid', 'isotonic'")


def _is_head(obj: Any) -> bool:
    return isinstance(obj, (StumpScorer, KernelScorer, SigmoidCalibrator, IsotonicCalibrator))


def scorer_from_estimator(est: Any, *, mean=None, scale=None):
    """A tensor scorer from a fitted estimator.

    Accepts a scorer head as is; any object with ``to_scorer()`` (torchtrack's learners);
    scikit-learn ``SVC`` / ``LinearSVC`` (optionally with the standardisation ``mean`` /
    ``scale`` they were trained after, or as the last step of a ``Pipeline`` with a
    ``StandardScaler``); and scikit-learn ``AdaBoostClassifier`` on depth-1 trees.

    Raises:
        NotFittedError / TypeError: the estimator is not fitted or not supported.
    """
    if _is_head(est):
        return est
    if hasattr(est, "to_scorer"):
        return est.to_scorer()
    name = type(est).__name__
    if name == "Pipeline":
        steps = [s for _, s in est.steps]
        if len(steps) == 2 and type(steps[0]).__name__ == "StandardScaler":
            return scorer_from_estimator(steps[1], mean=steps[0].mean_, scale=steps[0].scale_)
        raise TypeError("only Pipeline(StandardScaler, SVC|LinearSVC) can be exported")
    if name in ("SVC", "LinearSVC"):
        return _svm_scorer(est, mean, scale)
    if name == "AdaBoostClassifier":
        return _sklearn_adaboost_scorer(est)
    raise TypeError(f"cannot export a {name} as a detector scorer")


def _svm_scorer(est: Any, mean, scale) -> KernelScorer:
    from sklearn.utils.validation import check_is_fitted

    check_is_fitted(est)
    name = type(est).__name__
    if name == "LinearSVC" or getattr(est, "kernel", None) == "linear":
        w = np.asarray(est.coef_, dtype=np.float64).reshape(1, -1)
        k = w.shape[1]
        sv, coef, kernel, gamma = w, np.ones(1), "linear", 0.0
    else:
        if est.kernel != "rbf":
            raise TypeError(f"only RBF and linear SVMs can be exported, got kernel={est.kernel!r}")
        sv = np.asarray(est.support_vectors_, dtype=np.float64)
        coef = np.asarray(est.dual_coef_, dtype=np.float64).reshape(-1)
        k = sv.shape[1]
        kernel, gamma = "rbf", float(est._gamma)
    b = float(np.asarray(est.intercept_).reshape(-1)[0])
    mean = np.zeros(k) if mean is None else np.asarray(mean)
    scale = np.ones(k) if scale is None else np.asarray(scale)
    return KernelScorer(sv, coef, b, kernel, gamma, mean, scale)


def _sklearn_adaboost_scorer(est: Any) -> StumpScorer:
    """SAMME on stumps. For two classes scikit-learn's decision_function is
    ``sum_i w_i * c_i / sum_i w_i`` with ``c_i = +1`` when tree i votes class 1 and ``-1``
    otherwise, and the two class columns are differenced, which doubles it: so ``2 w_i / sum w``."""
    from sklearn.utils.validation import check_is_fitted

    check_is_fitted(est)
    if len(est.classes_) != 2:
        raise TypeError("only binary AdaBoostClassifier models can be exported")
    wsum = float(np.sum(est.estimator_weights_[: len(est.estimators_)])) / 2.0
    feat, thr, left, right = [], [], [], []
    for tree, w in zip(est.estimators_, est.estimator_weights_, strict=False):
        t = tree.tree_
        if t.node_count == 1:  # a constant tree
            cls = int(np.argmax(t.value[0]))
            v = (1.0 if cls == 1 else -1.0) * w / wsum
            feat.append(0)
            thr.append(0.0)
            left.append(v)
            right.append(v)
            continue
        if t.node_count != 3:
            raise TypeError("only depth-1 trees (stumps) can be exported")
        lv = 1.0 if int(np.argmax(t.value[t.children_left[0]])) == 1 else -1.0
        rv = 1.0 if int(np.argmax(t.value[t.children_right[0]])) == 1 else -1.0
        feat.append(int(t.feature[0]))
        # sklearn goes left when x <= threshold; thresholds are float64 midpoints, stored float32.
        thr.append(float(t.threshold[0]))
        left.append(lv * w / wsum)
        right.append(rv * w / wsum)
    return StumpScorer(np.array(feat), np.array(thr), np.array(left), np.array(right))


def calibrator_from_estimator(cal: Any):
    """A calibrator head from a calibrator head, an object with ``to_calibrator()``, an object
    with ``a_`` / ``b_`` (scikit-learn's sigmoid convention ``1 / (1 + exp(a m + b))``), or a
    fitted ``IsotonicRegression``."""
    if _is_head(cal):
        return cal
    if hasattr(cal, "to_calibrator"):
        return cal.to_calibrator()
    if hasattr(cal, "X_thresholds_") and hasattr(cal, "y_thresholds_"):
        return IsotonicCalibrator(cal.X_thresholds_, cal.y_thresholds_)
    if hasattr(cal, "a_") and hasattr(cal, "b_"):
        return SigmoidCalibrator(float(cal.a_), float(cal.b_))
    raise TypeError(f"cannot export a {type(cal).__name__} as a calibrator")
