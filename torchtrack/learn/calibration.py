"""Probability calibration of classifier scores: Platt scaling and isotonic regression.

Chateau et al. (2006), section 2.4: the particle-filter likelihood is the calibrated posterior
``P(positive | m) = 1 / (1 + exp(A m + B))`` (eq. 5, 8), with ``A, B`` the maximum-likelihood fit
(eq. 6-7) on a calibration set held out from classifier training (30% in the paper) or obtained
by cross-validation. The sign convention matches scikit-learn's ``_SigmoidCalibration``
(``expit(-(a m + b))``), so a good classifier gets ``A < 0``.

Diagnostics: negative log-likelihood, Brier score and expected calibration error (ECE) with
equal-width probability bins (default 15), plus a reliability diagram written as PNG; all can
weight the samples (:func:`prior_weights`: as if positives were another share of them).

A calibrated probability is calibrated to the share of positives it was fitted on: a Platt fit
on crops of which a third are persons over-states every window of a scan, where persons are a
few in a thousand. :func:`with_prior` moves a fitted calibrator to another share (Saerens,
Latinne & Decaestecker 2002).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from sklearn.base import BaseEstimator, clone

from torchtrack import errors
from torchtrack.learn._base import (
    as_binary_labels,
    as_float_tensor,
    check_fitted,
    check_kind,
    check_weighted_classes,
    is_integer,
    is_number,
    state_meta,
    state_tensor,
)

__all__ = [
    "CalibratedFit",
    "IsotonicCalibrator",
    "PlattCalibrator",
    "calibration_metrics",
    "fit_calibrated",
    "make_calibrator",
    "platt_fit",
    "prior_shift",
    "prior_weights",
    "reliability_diagram",
    "with_prior",
]

METHODS = ("platt", "isotonic")
#: the most ECE / reliability bins: more cannot be told apart on any data set (1e9 allocated
#: 16 GB, 1e20 overflowed)
MAX_BINS = 1000


def _scores(scores: Any, name: str = "scores") -> torch.Tensor:
    """1-D float64 scores, NaN / inf rejected with the index (DataError)."""
    return as_float_tensor(scores, name, ndim=1, dtype=torch.float64)


def _sample_weight(sample_weight: Any, s: torch.Tensor) -> torch.Tensor | None:
    """``sample_weight`` as ``(n,)`` float64 on the scores' device (None stays None).

    Raises:
        ShapeError: not one weight per score.
        DataError: a weight not finite or negative, or all weights zero (the isotonic fit
            raised scikit-learn's ValueError, the Platt fit ignored the scores with a warning).
    """
    if sample_weight is None:
        return None
    sw = as_float_tensor(sample_weight, "sample_weight", ndim=1, dtype=torch.float64)
    sw = sw.to(s.device)
    if sw.shape != s.shape:
        raise errors.ShapeError(
            f"sample_weight must have shape {tuple(s.shape)}, got {tuple(sw.shape)}"
        )
    if bool((sw < 0).any()) or float(sw.sum()) <= 0:
        raise errors.DataError("sample_weight must be non-negative with a positive sum")
    return sw


def _predict_input(scores: Any) -> tuple[torch.Tensor, bool]:
    """``scores`` as a tensor (a tensor as is, else float64) and whether it was one; no check
    of the values (the tracker's hot path).

    Raises:
        DataError: not convertible to numbers (numpy's ValueError escaped).
    """
    if isinstance(scores, torch.Tensor):
        return scores, True
    try:
        return torch.as_tensor(np.asarray(scores, dtype=np.float64)), False
    except (TypeError, ValueError) as exc:
        raise errors.DataError(
            f"scores must be numbers, got {type(scores).__name__}: {exc}"
        ) from None


def _to_like(p: torch.Tensor, like: Any) -> Any:
    return p if isinstance(like, torch.Tensor) else p.cpu().numpy()


# ------------------------------------------------------------------------------ Platt


def platt_fit(
    scores: torch.Tensor,
    y01: torch.Tensor,
    sample_weight: torch.Tensor | None = None,
    *,
    max_iter: int = 100,
    tol: float = 1e-10,
    min_step: float = 1e-10,
    sigma: float = 1e-12,
) -> tuple[float, float, int]:
    """Platt's sigmoid fit by the robust Newton method of Lin, Lin & Weng (2007, Algorithm 1).

    Minimises the cross-entropy (Chateau eq. 6) against Platt's smoothed targets
    ``t+ = (N+ + 1) / (N+ + 2)``, ``t- = 1 / (N- + 2)`` (``N`` are weight sums when
    ``sample_weight`` is given, as in scikit-learn). Each Newton step uses the Hessian plus
    ``sigma`` on its diagonal and a backtracking line search with the Armijo condition
    (``1e-4``), and the loss is evaluated in the overflow-free form of Lin et al.

    Args:
        scores: ``(n,)`` float64 classifier margins.
        y01: ``(n,)`` labels in ``{0, 1}``.
        sample_weight: optional ``(n,)`` non-negative weights.
        tol: stop when both gradient components, divided by the total weight, are below ``tol``.

    Returns:
        ``(A, B, n_iter)``.

    Raises:
        DataError: a score not finite, a label other than 0 / 1, a weight negative or not
            finite (all of which gave a fit of some numbers, without a word).
        ShapeError: lengths that differ.
    """
    f = _scores(scores)
    y = _labels01(y01, "y01", f)
    sw = _sample_weight(sample_weight, f)
    w = torch.ones_like(f) if sw is None else sw
    pos = y.bool()
    prior1 = float(w[pos].sum())
    prior0 = float(w[~pos].sum())
    hi, lo = (prior1 + 1.0) / (prior1 + 2.0), 1.0 / (prior0 + 2.0)
    t = torch.where(pos, hi, lo).to(torch.float64)
    total = float(w.sum())

    def loss(a: float, b: float) -> float:
        z = f * a + b  # fApB
        # t z + log(1 + exp(-z)) for z >= 0, (t - 1) z + log(1 + exp(z)) otherwise
        val = torch.where(
            z >= 0, t * z + torch.log1p(torch.exp(-z)), (t - 1) * z + torch.log1p(torch.exp(z))
        )
        return float((w * val).sum())

    A, B = 0.0, math.log((prior0 + 1.0) / (prior1 + 1.0))
    fval = loss(A, B)
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 (n_iter is returned)
        z = f * A + B
        p = torch.sigmoid(-z)  # P(positive) = 1 / (1 + exp(z))
        q = 1.0 - p
        d2 = w * p * q
        h11 = float((f * f * d2).sum()) + sigma
        h22 = float(d2.sum()) + sigma
        h21 = float((f * d2).sum())
        d1 = w * (t - p)
        g1 = float((f * d1).sum())
        g2 = float(d1.sum())
        if abs(g1) < tol * total and abs(g2) < tol * total:
            break
        det = h11 * h22 - h21 * h21
        dA = -(h22 * g1 - h21 * g2) / det
        dB = -(-h21 * g1 + h11 * g2) / det
        gd = g1 * dA + g2 * dB
        step = 1.0
        while step >= min_step:
            newA, newB = A + step * dA, B + step * dB
            newf = loss(newA, newB)
            if newf < fval + 1e-4 * step * gd:
                A, B, fval = newA, newB, newf
                break
            step /= 2.0
        if step < min_step:  # no decrease possible: at the optimum to working precision
            break
    return A, B, it


class PlattCalibrator(BaseEstimator):
    """Platt scaling: ``P(positive | m) = 1 / (1 + exp(A m + B))`` (Chateau eq. 5-8).

    ``fit`` is the maximum-likelihood fit with Platt's smoothed targets by the robust Newton
    method of Lin, Lin & Weng (2007), see :func:`platt_fit`.

    All-identical scores carry no ranking information; then ``A = 0`` and ``B`` gives the
    (smoothed) base rate of the positive class, with a ``UserWarning``. A fit that cannot leave
    ``A = 0`` (scores so large that their squares overflow, or so small that they underflow)
    warns the same way.

    Attributes:
        a_, b_: the fitted ``A`` and ``B``.
        n_iter_: Newton iterations used.
    """

    def __init__(self, max_iter: int = 100, tol: float = 1e-10) -> None:
        self.max_iter = max_iter
        self.tol = tol

    def fit(self, scores: Any, y: Any, sample_weight: Any = None) -> PlattCalibrator:
        """Fit on classifier margins ``scores (n,)`` and labels ``y (n,)``; returns ``self``.

        Raises:
            ConfigError: ``max_iter`` not an integer >= 1 or ``tol`` not a finite number >= 0.
            DataError: NaN / inf scores (index named), a single class, bad sample weights,
                a fit that is not finite.
            ShapeError: mismatched lengths.
        """
        # max_iter=0 ran no Newton step and only warned that A stayed 0; tol=-1 was taken
        if not is_integer(self.max_iter) or self.max_iter < 1:
            raise errors.ConfigError(
                f"max_iter must be a positive integer (Newton iterations), got {self.max_iter!r}"
            )
        if not is_number(self.tol) or not 0.0 <= float(self.tol) < math.inf:
            raise errors.ConfigError(
                f"tol must be a finite number >= 0 (gradient tolerance), got {self.tol!r}"
            )
        s = _scores(scores)
        y01, classes = as_binary_labels(y, s.shape[0])
        y01 = y01.to(s.device)
        sw = _sample_weight(sample_weight, s)
        if sw is not None:  # one class weighted: A = 0 and only a warning
            check_weighted_classes(sw, y01, classes)
        if bool((s == s[0]).all()):
            warnings.warn(
                "all calibration scores are identical: the calibrator returns the (smoothed) "
                "positive rate for every score (A = 0)",
                UserWarning,
                stacklevel=2,
            )
            w = torch.ones_like(s) if sw is None else sw
            n1, n0 = float(w[y01 == 1].sum()), float(w[y01 == 0].sum())
            t_mean = (n1 * (n1 + 1) / (n1 + 2) + n0 / (n0 + 2)) / (n1 + n0)
            self.a_, self.b_, self.n_iter_ = 0.0, math.log((1 - t_mean) / t_mean), 0
            return self
        self.a_, self.b_, self.n_iter_ = platt_fit(
            s, y01, sw, max_iter=int(self.max_iter), tol=float(self.tol)
        )
        if not (math.isfinite(self.a_) and math.isfinite(self.b_)):
            raise errors.DataError(
                f"the Platt fit is not finite (A = {self.a_}, B = {self.b_}) on scores up to "
                f"{float(s.abs().max()):.3g} in magnitude; rescale the scores"
            )
        top = float(s.abs().max())
        if abs(self.a_) * top < 1e-9:
            # Newton could not leave A = 0 (or left it by nothing): the scores carry a ranking,
            # but their products overflow (magnitudes near 1e300) or underflow (near 1e-300)
            why = "overflows" if top >= 1 else "is too small for (their squares underflow)"
            warnings.warn(
                f"the Platt fit did not move from A = 0 (A = {self.a_:.3g}): the calibrator "
                "ignores the scores and returns the positive rate for every score; their "
                f"magnitude (up to {top:.3g}) {why} the fit: rescale them, or calibrate with the "
                "isotonic method",
                UserWarning,
                stacklevel=2,
            )
        return self

    def predict_proba(self, scores: Any) -> Any:
        """Calibrated ``P(positive)`` for margins ``scores (...)`` (any shape, torch or numpy).

        Returns the same shape; float32 for float32 torch input, else float64. NaN scores give
        NaN probabilities (no check here: this runs in the tracker's hot path).
        """
        check_fitted(self, "a_")
        s, is_t = _predict_input(scores)
        if not s.is_floating_point():
            s = s.to(torch.float64)
        p = torch.sigmoid(-(s * self.a_ + self.b_))
        return p if is_t else p.numpy()

    def to_state(self) -> tuple[dict[str, torch.Tensor], dict]:
        """No tensors; ``A`` and ``B`` live in the JSON metadata (``kind = "platt"``)."""
        check_fitted(self, "a_")
        return {}, {"kind": "platt", "a": float(self.a_), "b": float(self.b_)}

    @classmethod
    def from_state(cls, tensors: dict[str, torch.Tensor], meta: dict) -> PlattCalibrator:
        """Rebuild from :meth:`to_state`; raises ``ModelFormatError`` naming a bad field."""
        check_kind(meta, "platt")
        est = cls()
        est.a_ = float(state_meta(meta, "a", "platt", (int, float)))
        est.b_ = float(state_meta(meta, "b", "platt", (int, float)))
        est.n_iter_ = 0
        return est


# --------------------------------------------------------------------------- isotonic


def _interp(x: torch.Tensor, xp: torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
    """Piecewise-linear interpolation of ``(xp, fp)`` at ``x`` (clipped to ``xp``'s range)."""
    if xp.numel() == 1:
        return fp.expand_as(x).clone()
    xc = x.clamp(xp[0], xp[-1])
    idx = torch.searchsorted(xp, xc.contiguous(), right=True).clamp(1, xp.numel() - 1)
    x0, x1 = xp[idx - 1], xp[idx]
    y0, y1 = fp[idx - 1], fp[idx]
    dx = x1 - x0
    frac = torch.where(dx > 0, (xc - x0) / torch.where(dx > 0, dx, 1.0), 0.0)
    return y0 + frac * (y1 - y0)


class IsotonicCalibrator(BaseEstimator):
    """Isotonic-regression calibration (Zadrozny & Elkan): a monotone step-linear map to [0, 1].

    Fitted with scikit-learn's ``IsotonicRegression(increasing=True, out_of_bounds="clip")``,
    exported as its threshold tensors and interpolated in torch (linear between thresholds,
    constant outside), equal to scikit-learn's ``predict``.

    Attributes:
        x_thresholds_, y_thresholds_: ``(K,)`` float64 tensors.
    """

    def fit(self, scores: Any, y: Any, sample_weight: Any = None) -> IsotonicCalibrator:
        """Fit on ``scores (n,)`` and labels ``y (n,)``; returns ``self``.

        Raises:
            DataError: NaN / inf scores (index named), scores whose range overflows, a single
                class, or negative sample weights.
            ShapeError: mismatched lengths.
        """
        from sklearn.isotonic import IsotonicRegression

        s = _scores(scores)
        lo, hi = float(s.min()), float(s.max())
        if not math.isfinite(hi - lo):  # interpolation between them gave NaN probabilities
            raise errors.DataError(
                f"scores span {lo:.3g} to {hi:.3g}, a range beyond the float range: rescale them"
            )
        y01, classes = as_binary_labels(y, s.shape[0])
        sw = _sample_weight(sample_weight, s)
        if sw is not None:  # one class weighted: a map of that class's label everywhere
            check_weighted_classes(sw, y01, classes)
            sw = sw.cpu().numpy()
        iso = IsotonicRegression(y_min=0.0, y_max=1.0, increasing=True, out_of_bounds="clip")
        iso.fit(s.cpu().numpy(), y01.cpu().numpy().astype(np.float64), sample_weight=sw)
        self.x_thresholds_ = torch.as_tensor(iso.X_thresholds_, dtype=torch.float64)
        self.y_thresholds_ = torch.as_tensor(iso.y_thresholds_, dtype=torch.float64)
        return self

    def predict_proba(self, scores: Any) -> Any:
        """Calibrated ``P(positive)`` for ``scores (...)``, same shape (torch or numpy)."""
        check_fitted(self, "x_thresholds_")
        s, is_t = _predict_input(scores)
        dt = s.dtype if s.is_floating_point() else torch.float64
        xp = self.x_thresholds_.to(s.device)
        fp = self.y_thresholds_.to(s.device)
        p = _interp(s.to(torch.float64).reshape(-1), xp, fp).reshape(s.shape).to(dt)
        return p if is_t else p.numpy()

    def to_state(self) -> tuple[dict[str, torch.Tensor], dict]:
        check_fitted(self, "x_thresholds_")
        tensors = {"x": self.x_thresholds_.clone(), "y": self.y_thresholds_.clone()}
        return tensors, {"kind": "isotonic"}

    @classmethod
    def from_state(cls, tensors: dict[str, torch.Tensor], meta: dict) -> IsotonicCalibrator:
        """Rebuild from :meth:`to_state`; raises ``ModelFormatError`` naming a bad field."""
        kind = "isotonic"
        check_kind(meta, kind)
        x = state_tensor(tensors, "x", kind, ndim=1, dtype=torch.float64)
        y = state_tensor(tensors, "y", kind, shape=(x.shape[0],), dtype=torch.float64)
        if x.numel() < 1:
            raise errors.ModelFormatError(f"{kind}.x: empty")
        if bool((x[1:] < x[:-1]).any()):
            raise errors.ModelFormatError(f"{kind}.x: thresholds not sorted")
        if bool(((y < 0) | (y > 1)).any()) or bool((y[1:] < y[:-1]).any()):
            raise errors.ModelFormatError(f"{kind}.y: values not monotone in [0, 1]")
        est = cls()
        est.x_thresholds_ = x.clone()
        est.y_thresholds_ = y.clone()
        return est


def make_calibrator(method: str) -> PlattCalibrator | IsotonicCalibrator:
    """A new unfitted calibrator by name: ``"platt"`` or ``"isotonic"``."""
    if method == "platt":
        return PlattCalibrator()
    if method == "isotonic":
        return IsotonicCalibrator()
    raise errors.ConfigError(
        f"calibration method must be one of {', '.join(METHODS)}; got {method!r}"
    )


# ------------------------------------------------------------------------ diagnostics


def calibration_metrics(
    p: Any, y: Any, n_bins: int = 15, sample_weight: Any = None
) -> dict[str, float]:
    """NLL, Brier score and ECE of probabilities ``p (n,)`` for labels ``y (n,)`` in ``{0, 1}``.

    * ``nll``: mean of ``-[y log p + (1 - y) log(1 - p)]``, ``p`` clipped to ``[1e-15, 1 - 1e-15]``.
    * ``brier``: mean of ``(p - y)^2``.
    * ``ece``: ``sum_b (n_b / n) |mean(y in b) - mean(p in b)|`` over ``n_bins`` equal-width bins
      of ``[0, 1]`` (bin ``b`` holds ``b / n_bins <= p < (b + 1) / n_bins``; ``p = 1`` goes to the
      last bin); empty bins contribute nothing.

    With ``sample_weight (n,)`` every mean and count is weighted (e.g. :func:`prior_weights`:
    the metrics the same scores would have where positives are a given share).

    Raises:
        DataError: probabilities outside ``[0, 1]`` or NaN; labels other than 0 / 1; bad
            sample weights (negative, not finite, all zero).
        ConfigError: ``n_bins`` outside ``[1, MAX_BINS]``.
    """
    pt, yt = _probabilities_and_labels(p, y)
    pc = pt.clamp(1e-15, 1 - 1e-15)
    loss = -(yt * pc.log() + (1 - yt) * (1 - pc).log())
    sw = _sample_weight(sample_weight, pt)
    if sw is None:
        nll = float(loss.mean())
        brier = float(((pt - yt) ** 2).mean())
        total = float(pt.numel())
    else:
        total = float(sw.sum())
        nll = float((sw * loss).sum() / total)
        brier = float((sw * (pt - yt) ** 2).sum() / total)
    _, sp, sy = _bin_sums(pt, yt, n_bins, sw)
    # sum_b (n_b / n) |mean_b(p) - mean_b(y)| = sum_b |sum_b(p) - sum_b(y)| / n
    ece = float((sp - sy).abs().sum() / total)
    return {"nll": nll, "brier": brier, "ece": ece}


def prior_weights(y: Any, prior: float) -> torch.Tensor:
    """Sample weights ``(n,)`` float64 that make positives a share ``prior`` of labels ``y (n,)``
    in ``{0, 1}``: ``prior / pi`` for each positive, ``(1 - prior) / (1 - pi)`` for each
    negative, ``pi`` the share of positives in ``y`` (their mean is 1).

    Raises:
        ConfigError: ``prior`` not a number in ``(0, 1)``.
        DataError: ``y`` holds one class only (no share to move), or labels other than 0 / 1.
    """
    check_prior(prior, "prior")
    yt = _labels01(y, "y")
    pi = float(yt.mean()) if yt.numel() else 0.0
    if not 0.0 < pi < 1.0:
        raise errors.DataError("prior weights need labels of both classes")
    pos = torch.full_like(yt, prior / pi)
    return torch.where(yt == 1, pos, torch.full_like(yt, (1.0 - prior) / (1.0 - pi)))


def check_prior(prior: Any, name: str) -> None:
    """:class:`ConfigError` unless ``prior`` is a share of positives in ``(0, 1)``, naming it
    ``name``."""
    if not (is_number(prior) and 0.0 < float(prior) < 1.0):
        raise errors.ConfigError(
            f"{name} must be a share of positives in (0, 1) (exclusive), got {prior!r}"
        )


def prior_shift(prior: float, base_prior: float) -> float:
    """The log-odds shift ``logit(prior) - logit(base_prior)`` that :func:`with_prior` applies.

    Raises:
        ConfigError: ``prior`` or ``base_prior`` not in ``(0, 1)``.
    """
    check_prior(prior, "prior")
    check_prior(base_prior, "base_prior")
    return math.log(prior / (1.0 - prior)) - math.log(base_prior / (1.0 - base_prior))


def with_prior(
    calibrator: PlattCalibrator | IsotonicCalibrator, prior: float, base_prior: float
) -> PlattCalibrator | IsotonicCalibrator:
    """A copy of a fitted ``calibrator`` for data whose positives are a share ``prior``, when it
    was fitted on data where they were a share ``base_prior``: every calibrated log-odds moves
    by ``logit(prior) - logit(base_prior)`` (the change of priors of Saerens, Latinne &
    Decaestecker 2002, exact when the classes' score distributions stay the same). Platt: ``B``
    moves by minus that shift; isotonic: every level ``y`` becomes ``sigmoid(logit(y) +
    shift)`` (0 and 1 stay). The scores' ranking is untouched.

    Raises:
        ConfigError: ``prior`` or ``base_prior`` not in ``(0, 1)``; not a calibrator of this
            module.
        NotFittedError: an unfitted calibrator.
    """
    shift = prior_shift(prior, base_prior)
    if isinstance(calibrator, PlattCalibrator):
        check_fitted(calibrator, "a_")
        out = PlattCalibrator(calibrator.max_iter, calibrator.tol)
        out.a_, out.b_, out.n_iter_ = calibrator.a_, calibrator.b_ - shift, calibrator.n_iter_
        return out
    if isinstance(calibrator, IsotonicCalibrator):
        check_fitted(calibrator, "x_thresholds_")
        out = IsotonicCalibrator()
        y = calibrator.y_thresholds_
        moved = torch.sigmoid(torch.logit(y.to(torch.float64)) + shift).to(y.dtype)
        out.x_thresholds_ = calibrator.x_thresholds_.clone()
        out.y_thresholds_ = torch.where((y == 0) | (y == 1), y, moved)
        return out
    raise errors.ConfigError(
        f"with_prior takes a PlattCalibrator or an IsotonicCalibrator, got "
        f"{type(calibrator).__name__}"
    )


def _labels01(y: Any, name: str, like: torch.Tensor | None = None) -> torch.Tensor:
    """``(n,)`` float64 labels in ``{0, 1}`` on ``like``'s device and of its shape, checked
    (ShapeError / DataError naming ``name``)."""
    yt = as_float_tensor(y, name, ndim=1, dtype=torch.float64)
    if like is not None:
        yt = yt.to(like.device)
        if yt.shape != like.shape:
            raise errors.ShapeError(
                f"{name} must have shape {tuple(like.shape)}, got {tuple(yt.shape)}"
            )
    if bool(((yt != 0) & (yt != 1)).any()):
        raise errors.DataError(f"{name} must contain only 0 and 1")
    return yt


def _probabilities_and_labels(p: Any, y: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """``(n,)`` float64 probabilities in ``[0, 1]`` and labels in ``{0, 1}``, checked."""
    pt = as_float_tensor(p, "p", ndim=1, dtype=torch.float64)
    if bool(((pt < 0) | (pt > 1)).any()):
        first = int(((pt < 0) | (pt > 1)).nonzero()[0, 0])
        raise errors.DataError(f"p must lie in [0, 1]; p[{first}] = {pt[first].item()}")
    return pt, _labels01(y, "y", pt)


def _check_bins(n_bins: Any) -> None:
    """:class:`ConfigError` unless ``n_bins`` is an integer in ``[1, MAX_BINS]`` (15.0, '15'
    and None were TypeErrors from torch.bincount or int(), NaN a ValueError)."""
    if not (is_integer(n_bins) and 1 <= n_bins <= MAX_BINS):
        raise errors.ConfigError(f"n_bins must be an integer in [1, {MAX_BINS}], got {n_bins!r}")


def _bin_sums(
    pt: torch.Tensor, yt: torch.Tensor, n_bins: int, sw: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per equal-width bin of ``[0, 1]`` (``p = 1`` in the last): count, sum of ``p``, sum
    of ``y`` (with weights ``sw``: their sum and the weighted sums)."""
    _check_bins(n_bins)
    b = (pt * n_bins).floor().long().clamp(0, n_bins - 1)
    if sw is not None:
        return (
            torch.bincount(b, weights=sw, minlength=n_bins),
            torch.bincount(b, weights=sw * pt, minlength=n_bins),
            torch.bincount(b, weights=sw * yt, minlength=n_bins),
        )
    cnt = torch.bincount(b, minlength=n_bins)
    return (
        cnt,
        torch.bincount(b, weights=pt, minlength=n_bins),
        torch.bincount(b, weights=yt, minlength=n_bins),
    )


def reliability_bins(p: Any, y: Any, n_bins: int = 15) -> list[dict[str, float]]:
    """The numbers behind a reliability diagram: for every non-empty equal-width bin of the
    predicted probabilities ``p (n,)`` (labels ``y (n,)`` in ``{0, 1}``; the bins of
    :func:`calibration_metrics`), ``lo``, ``hi`` (its edges), ``count``, ``mean_p`` and
    ``frequency`` (the observed fraction of positives), and ``ece_share`` (its term of the
    ECE: ``|sum p - sum y| / n``).

    Raises:
        DataError / ShapeError: as :func:`calibration_metrics`.
    """
    pt, yt = _probabilities_and_labels(p, y)
    cnt, sp, sy = _bin_sums(pt, yt, n_bins)
    out = []
    for b in torch.nonzero(cnt).flatten().tolist():
        c = float(cnt[b])
        out.append(
            {
                "lo": b / n_bins,
                "hi": (b + 1) / n_bins,
                "count": int(c),
                "mean_p": float(sp[b]) / c,
                "frequency": float(sy[b]) / c,
                "ece_share": abs(float(sp[b] - sy[b])) / pt.numel(),
            }
        )
    return out


def reliability_diagram(
    p: Any,
    y: Any,
    path: str | Path,
    *,
    n_bins: int = 15,
    title: str | None = None,
    label: str = "calibrated",
    sample_weight: Any = None,
) -> Path:
    """Write a reliability diagram (PNG, atomically) and return its path.

    Top: the observed positive frequency against the mean predicted probability per equal-width
    bin (one curve per entry when ``p`` is a dict ``{label: probabilities}``, e.g. before and
    after calibration), with the diagonal. Bottom: histogram of the predicted probabilities.
    Uses matplotlib's Agg canvas directly (no pyplot, no global backend change).

    Args:
        p: probabilities ``(n,)``, or a dict of label -> ``(n,)`` probabilities.
        y: labels ``(n,)`` in ``{0, 1}``.
        path: destination ``.png`` file.
        sample_weight: optional ``(n,)`` weights of the samples (:func:`prior_weights`): the
            frequencies, means and metrics are weighted, the histogram counts them.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from torchtrack.io.atomic import atomic_path

    _check_bins(n_bins)  # before np.linspace sizes its edges by it
    curves = p if isinstance(p, dict) else {label: p}
    yt = as_float_tensor(y, "y", ndim=1, dtype=torch.float64).cpu()
    fig = Figure(figsize=(5.5, 6.5))
    FigureCanvasAgg(fig)
    ax, axh = fig.subplots(2, 1, gridspec_kw={"height_ratios": [3, 1]}, sharex=True)
    ax.plot([0, 1], [0, 1], ls="--", color="0.5", lw=1, label="perfect")
    edges = np.linspace(0, 1, n_bins + 1)
    for name, pv in curves.items():
        pt = as_float_tensor(pv, f"p[{name}]", ndim=1, dtype=torch.float64).cpu()
        m = calibration_metrics(pt, yt, n_bins, sample_weight)
        sw = None if sample_weight is None else _sample_weight(sample_weight, pt)
        cnt, sp, sy = _bin_sums(pt, yt, n_bins, sw)
        mp, my = sp / cnt.clamp_min(1), sy / cnt.clamp_min(1)
        keep = (cnt > 0).numpy()
        ax.plot(
            mp.numpy()[keep],
            my.numpy()[keep],
            marker="o",
            label=f"{name} (ECE {m['ece']:.3f}, NLL {m['nll']:.3f})",
        )
        axh.hist(
            pt.numpy(),
            bins=edges,
            histtype="step",
            label=name,
            weights=None if sw is None else sw.numpy(),
        )
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_ylabel("observed positive frequency")
    ax.set_title(title or f"Reliability diagram ({n_bins} equal-width bins)")
    ax.legend(loc="upper left", fontsize=8)
    axh.set_xlabel("predicted probability")
    axh.set_ylabel("count" if sample_weight is None else "weighted count")
    axh.set_yscale("log")
    fig.tight_layout()
    dest = Path(path)
    with atomic_path(dest) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    return dest


# ----------------------------------------------------------------- fit with hold-out / CV


@dataclass
class CalibratedFit:
    """Result of :func:`fit_calibrated`.

    Attributes:
        classifier: fitted classifier (on the training part, or on all data with ``cv``).
        calibrator: fitted calibrator.
        scores: ``(m,)`` calibration margins (hold-out part or out-of-fold scores), float64.
        labels: ``(m,)`` their labels in ``{0, 1}``.
        train_index, calib_index: sample indices used for the classifier and the calibrator
            (with ``cv``, both are all samples: scores come out of fold).
    """

    classifier: Any
    calibrator: PlattCalibrator | IsotonicCalibrator
    scores: torch.Tensor
    labels: torch.Tensor
    train_index: torch.Tensor
    calib_index: torch.Tensor


def _stratified_perm(y01: torch.Tensor, generator: torch.Generator | None) -> list[torch.Tensor]:
    out = []
    for c in (0, 1):
        idx = (y01 == c).nonzero().squeeze(1).cpu()
        out.append(idx[torch.randperm(idx.numel(), generator=generator)])
    return out


def _margins(clf: Any, X: Any) -> torch.Tensor:
    m = clf.decision_function(X)
    return torch.as_tensor(
        np.asarray(m.cpu() if isinstance(m, torch.Tensor) else m), dtype=torch.float64
    )


def _take(X: Any, idx: torch.Tensor) -> Any:
    if isinstance(X, torch.Tensor):
        return X.index_select(0, idx.to(X.device))
    return np.asarray(X)[idx.numpy()]


def fit_calibrated(
    classifier: BaseEstimator,
    X: Any,
    y: Any,
    *,
    method: str = "platt",
    holdout: float = 0.3,
    cv: int | None = None,
    generator: torch.Generator | None = None,
) -> CalibratedFit:
    """Fit a classifier and a calibrator on separate data (Chateau section 2.4; Platt 1999).

    * ``cv=None``: a stratified random ``holdout`` fraction (default 0.3, as in the paper) is
      kept out of classifier training and used to fit the calibrator.
    * ``cv=K``: K stratified folds; a clone of the classifier is fit on K-1 folds and scores the
      remaining one; the calibrator is fit on all out-of-fold scores and the returned classifier
      is refit on all data (Platt's cross-validation scheme).

    Args:
        classifier: unfitted sklearn-style estimator with ``decision_function`` (cloned).
        X: features ``(n, T)``; y: labels ``(n,)``.
        generator: torch generator for the split (reproducible runs).

    Raises:
        ConfigError: ``holdout`` outside (0, 1), ``cv < 2``, unknown method, or too few samples
            of a class for the split.
    """
    make_calibrator(method)  # validate the name before any fitting
    if not hasattr(X, "shape"):  # a nested list: X.shape was an AttributeError
        X = as_float_tensor(X, "X", ndim=2)
    n = int(X.shape[0])
    y01, _ = as_binary_labels(y, n)
    y01 = y01.cpu()
    per_class = _stratified_perm(y01, generator)
    yv = y if isinstance(y, torch.Tensor) else torch.as_tensor(np.asarray(y))
    if cv is None:
        # holdout='x' was a ValueError from float(), None a TypeError
        if not (is_number(holdout) and 0.0 < float(holdout) < 1.0):
            raise errors.ConfigError(f"holdout must be in (0, 1), got {holdout!r}")
        train, calib = [], []
        for idx in per_class:
            k = round(float(holdout) * idx.numel())
            if k < 1 or k >= idx.numel():
                raise errors.ConfigError(
                    f"holdout={holdout} leaves no samples of a class for training or calibration "
                    f"({idx.numel()} samples in that class)"
                )
            calib.append(idx[:k])
            train.append(idx[k:])
        tr, ca = torch.cat(train).sort().values, torch.cat(calib).sort().values
        clf = clone(classifier).fit(_take(X, tr), _take(yv, tr))
        scores = _margins(clf, _take(X, ca))
        labels = y01[ca]
    else:
        # int() took cv=2.5 as 2 folds; 'x' was a ValueError, inf an OverflowError
        if not (is_integer(cv) and cv >= 2):
            raise errors.ConfigError(f"cv must be >= 2 folds (an integer), got {cv!r}")
        K = int(cv)
        if min(idx.numel() for idx in per_class) < K:
            raise errors.ConfigError(f"cv={K} folds need at least {K} samples of each class")
        fold = torch.empty(n, dtype=torch.long)
        for idx in per_class:
            fold[idx] = torch.arange(idx.numel()) % K
        scores = torch.empty(n, dtype=torch.float64)
        for k in range(K):
            tr = (fold != k).nonzero().squeeze(1)
            te = (fold == k).nonzero().squeeze(1)
            part = clone(classifier).fit(_take(X, tr), _take(yv, tr))
            scores[te] = _margins(part, _take(X, te))
        clf = clone(classifier).fit(X, y)
        tr = ca = torch.arange(n)
        labels = y01
    cal = make_calibrator(method).fit(scores, labels)
    return CalibratedFit(clf, cal, scores, labels, tr, ca)
