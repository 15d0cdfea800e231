"""Support vector machine on the selected features, trained by scikit-learn, scored in torch.

Chateau et al. (2006), eq. 10: ``m(f) = sum_i alpha_i y_i K(f_i, f) + b``. Training uses
scikit-learn's ``SVC`` (libsvm) on standardised features; the support vectors, the signed dual
coefficients ``alpha_i y_i``, the intercept ``b``, the kernel's ``gamma`` and the standardisation
are exported as tensors, so scoring is a batched torch computation on any device and equals
``SVC.decision_function`` (computed in float64).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from sklearn.base import BaseEstimator, ClassifierMixin

from torchtrack import errors
from torchtrack.learn._base import (
    as_binary_labels,
    as_float_tensor,
    check_fitted,
    check_kind,
    check_weighted_classes,
    state_meta,
    state_tensor,
)

__all__ = ["KERNELS", "SVMClassifier"]

KERNELS = ("rbf", "linear")


class SVMClassifier(ClassifierMixin, BaseEstimator):
    """Binary SVM (RBF or linear kernel) with a torch decision function (Chateau eq. 10).

    Features are standardised (mean 0, standard deviation 1 per column, on the training data;
    constant columns get scale 1) before ``SVC`` sees them; the standardisation is part of the
    exported model. ``SVC(probability=True)`` is not used: probabilities come from a separate
    calibrator (Platt scaling on held-out data).

    Args:
        kernel: ``"rbf"`` (``K = exp(-gamma |u - v|^2)``) or ``"linear"`` (``K = u . v``).
        C: soft-margin penalty.
        gamma: RBF width: ``"scale"`` (scikit-learn's ``1 / (T var(X))`` on standardised X, i.e.
            about ``1 / T``), ``"auto"`` (``1 / T``) or a positive float.
        standardize: standardise columns before training.
        class_weight, tol, max_iter, cache_size: passed to ``SVC``.

    Attributes:
        classes_, n_features_in_: as in scikit-learn.
        support_vectors_: ``(S, T)`` float64, in standardised units.
        dual_coef_: ``(S,)`` float64 signed coefficients ``alpha_i y_i``.
        intercept_: float ``b``. gamma_: float (RBF) or 0.0 (linear).
        mean_, scale_: ``(T,)`` float64 standardisation.
    """

    def __init__(
        self,
        kernel: str = "rbf",
        C: float = 1.0,
        gamma: str | float = "scale",
        standardize: bool = True,
        class_weight: Any = None,
        tol: float = 1e-3,
        max_iter: int = -1,
        cache_size: float = 500.0,
    ) -> None:
        self.kernel = kernel
        self.C = C
        self.gamma = gamma
        self.standardize = standardize
        self.class_weight = class_weight
        self.tol = tol
        self.max_iter = max_iter
        self.cache_size = cache_size

    def fit(self, X: Any, y: Any, sample_weight: Any = None) -> SVMClassifier:
        """Fit on ``X (n, T)`` and ``y (n,)``; returns ``self``.

        Raises:
            ConfigError: unknown kernel.
            ShapeError / DataError: bad shapes, NaN / inf features, a single class.
        """
        from sklearn.svm import SVC

        if self.kernel not in KERNELS:
            raise errors.ConfigError(
                f"kernel must be one of {', '.join(KERNELS)}; got {self.kernel!r}"
            )
        Xt = as_float_tensor(X, "X", ndim=2, dtype=torch.float64).cpu()
        n, T = Xt.shape
        y01, classes = as_binary_labels(y, n)
        if self.standardize:
            mean = Xt.mean(0)
            scale = Xt.std(0, unbiased=False)
            scale = torch.where(scale > 0, scale, torch.ones_like(scale))
        else:
            mean, scale = torch.zeros(T, dtype=torch.float64), torch.ones(T, dtype=torch.float64)
        Z = ((Xt - mean) / scale).numpy()
        sw = None
        if sample_weight is not None:
            # checked here as BoostedStumps does: a wrong length, negative or all-zero weights
            # reached scikit-learn's untyped ValueError
            swt = as_float_tensor(sample_weight, "sample_weight", ndim=1, dtype=torch.float64)
            swt = swt.cpu()
            if swt.shape[0] != n:
                raise errors.ShapeError(
                    f"sample_weight must have shape ({n},), got {tuple(swt.shape)}"
                )
            if bool((swt < 0).any()) or float(swt.sum()) <= 0:
                raise errors.DataError("sample_weight must be non-negative with a positive sum")
            check_weighted_classes(swt, y01, classes)
            sw = swt.numpy()
        svc = SVC(
            kernel=self.kernel,
            C=self.C,
            gamma=self.gamma,
            class_weight=self.class_weight,
            tol=self.tol,
            max_iter=self.max_iter,
            cache_size=self.cache_size,
        )
        svc.fit(Z, y01.cpu().numpy(), sample_weight=sw)
        self.svc_ = svc  # kept for reference checks; not serialised
        self.classes_ = classes
        self.n_features_in_ = int(T)
        self.mean_ = mean
        self.scale_ = scale
        self.support_vectors_ = torch.as_tensor(svc.support_vectors_, dtype=torch.float64)
        # binary SVC: decision_function = dual_coef_ @ K(SV, x) + intercept_, > 0 for classes_[1]
        self.dual_coef_ = torch.as_tensor(svc.dual_coef_[0], dtype=torch.float64)
        self.intercept_ = float(svc.intercept_[0])
        self.gamma_ = float(svc._gamma) if self.kernel == "rbf" else 0.0
        return self

    def _standardised(self, X: Any) -> tuple[torch.Tensor, tuple[int, ...], bool]:
        check_fitted(self, "dual_coef_")
        is_numpy = not isinstance(X, torch.Tensor)
        Xt = as_float_tensor(X, "X", dtype=torch.float64, check_finite=False)
        if Xt.ndim == 0 or Xt.shape[-1] != self.n_features_in_:
            raise errors.ShapeError(
                f"X must have {self.n_features_in_} columns (last axis), got shape {tuple(Xt.shape)}"
            )
        lead = tuple(Xt.shape[:-1])
        dev = Xt.device
        Z = (Xt.reshape(-1, self.n_features_in_) - self.mean_.to(dev)) / self.scale_.to(dev)
        return Z, lead, is_numpy

    def decision_function(self, X: Any, chunk_size: int = 4096) -> Any:
        """Margins ``m(f) = sum_i alpha_i y_i K(f_i, f) + b`` (Chateau eq. 10).

        Args:
            X: ``(..., T)`` torch tensor (any leading batch dims, any device) or numpy array.
            chunk_size: rows per kernel block (memory ``chunk_size * S`` float64).

        Returns:
            ``(...)`` margins: float32 torch tensor on ``X``'s device (numpy in -> float64 numpy).
        """
        Z, lead, is_numpy = self._standardised(X)
        dev = Z.device
        sv = self.support_vectors_.to(dev)
        coef = self.dual_coef_.to(dev)
        out = torch.empty(Z.shape[0], dtype=torch.float64, device=dev)
        if self.kernel == "linear":
            out = Z @ (coef @ sv) + self.intercept_
        else:
            sv_sq = (sv * sv).sum(1)
            for r0 in range(0, Z.shape[0], chunk_size):
                z = Z[r0 : r0 + chunk_size]
                d2 = ((z * z).sum(1, keepdim=True) + sv_sq - 2.0 * (z @ sv.T)).clamp_min_(0.0)
                out[r0 : r0 + chunk_size] = torch.exp(-self.gamma_ * d2) @ coef + self.intercept_
        out = out.reshape(lead)
        return out.cpu().numpy() if is_numpy else out.to(torch.float32)

    def predict(self, X: Any) -> Any:
        """Class labels: ``classes_[1]`` where the margin is positive."""
        m = self.decision_function(X)
        pos = np.asarray(m > 0) if not isinstance(m, torch.Tensor) else (m > 0).cpu().numpy()
        return self.classes_[pos.astype(np.int64)]

    def to_state(self) -> tuple[dict[str, torch.Tensor], dict]:
        """Tensors (support vectors, dual coefficients, standardisation) and metadata
        (``kind = "svm"``, kernel, gamma, intercept, classes)."""
        check_fitted(self, "dual_coef_")
        tensors = {
            "support_vectors": self.support_vectors_.clone(),
            "dual_coef": self.dual_coef_.clone(),
            "mean": self.mean_.clone(),
            "scale": self.scale_.clone(),
        }
        meta = {
            "kind": "svm",
            "kernel": self.kernel,
            "C": float(self.C),
            "gamma": float(self.gamma_),
            "intercept": float(self.intercept_),
            "n_features_in": self.n_features_in_,
            "classes": [c.item() for c in self.classes_],
        }
        return tensors, meta

    @classmethod
    def from_state(cls, tensors: dict[str, torch.Tensor], meta: dict) -> SVMClassifier:
        """Rebuild from :meth:`to_state`, validating every field (``ModelFormatError``)."""
        kind = "svm"
        check_kind(meta, kind)
        kernel = state_meta(meta, "kernel", kind, str)
        if kernel not in KERNELS:
            raise errors.ModelFormatError(f"{kind}.kernel: unknown kernel {kernel!r}")
        T = state_meta(meta, "n_features_in", kind, int)
        gamma = float(state_meta(meta, "gamma", kind, (int, float)))
        if kernel == "rbf" and gamma <= 0:
            raise errors.ModelFormatError(f"{kind}.gamma: must be > 0 for the RBF kernel")
        intercept = float(state_meta(meta, "intercept", kind, (int, float)))
        C = float(state_meta(meta, "C", kind, (int, float)))
        classes = state_meta(meta, "classes", kind, list)
        if len(classes) != 2:
            raise errors.ModelFormatError(f"{kind}.classes: expected 2 classes, got {classes}")
        if T < 1:
            raise errors.ModelFormatError(f"{kind}.n_features_in: must be >= 1")
        sv = state_tensor(tensors, "support_vectors", kind, shape=(None, T), dtype=torch.float64)
        S = sv.shape[0]
        if S < 1:
            raise errors.ModelFormatError(f"{kind}.support_vectors: no support vectors")
        coef = state_tensor(tensors, "dual_coef", kind, shape=(S,), dtype=torch.float64)
        mean = state_tensor(tensors, "mean", kind, shape=(T,), dtype=torch.float64)
        scale = state_tensor(tensors, "scale", kind, shape=(T,), dtype=torch.float64)
        if bool((scale <= 0).any()):
            raise errors.ModelFormatError(f"{kind}.scale: must be positive")
        est = cls(kernel=kernel, C=C)
        est.classes_ = np.asarray(classes)
        est.n_features_in_ = T
        est.support_vectors_ = sv.clone()
        est.dual_coef_ = coef.clone()
        est.mean_ = mean.clone()
        est.scale_ = scale.clone()
        est.intercept_ = intercept
        est.gamma_ = gamma
        return est
