"""Online real AdaBoost with feature selectors (Jin et al. sec. 3.1, Algorithm 1).

The strong classifier has N selectors; selector n keeps M candidate features, each a
confidence-rated weak hypothesis over the feature's value blocks ``X_1..X_K`` (integer bin
codes): per (selector, candidate, block, label) a weight histogram ``w_{n,m}(X_j, y)`` and

    h_{n,m}(x) = 1/2 ln((w_{n,m}(x, +1) + eps) / (w_{n,m}(x, -1) + eps)).

A sample (x, y) enters with importance lambda = 1 and passes the selectors in turn; selector n

1. accumulates ``lambda |h(x)|`` into each candidate's correct (``h y >= 0``) or wrong weight and
   estimates the cumulated error ``e_{n,m} = wrong / (wrong + correct)`` (both start at one);
2. adds lambda to the histogram cell of x's block and label, for every candidate;
3. selects ``m+ = argmin_m e_{n,m}``, sets ``alpha_n = ln((1 - e) / e)`` (Algorithm 1's
   voting weight) and updates the importance: ``lambda /= 2 (1 - e)`` when ``h_{n,m+} y >= 0``,
   else ``lambda /= 2 e``. When ``e >= 0.5`` (the paper's "cumulated error beyond a threshold")
   the selector gets ``alpha_n = 0`` and lambda passes unchanged;
4. replaces its worst candidate ``m- = argmax_m e_{n,m}`` (never the selected one) by a random
   feature with an empty histogram and ``correct = wrong = 1``.

The strong classifier is ``conf(x) = sum_n alpha_n h_{n,m+}(x)``, label ``sign(conf)``.

Order within a selector: a sample is scored by the histograms *before* it is added (test, then
train), so the cumulated error is an out-of-sample estimate. Algorithm 1 adds the sample first;
with mini-batches of thousands of pixels from one frame that order lets a freshly replaced
candidate fit the batch it is scored on, look error-free and take over the selector (seen on the
dev sequences: every pixel turned negative after a border-negatives-only update).

Vectorisation: one :meth:`OnlineRealBoost.partial_fit` call treats its P samples as one
mini-batch. Because scoring uses the histograms from before the batch, the weak outputs of all
N x M candidates for all P samples come from one gather; the loop over selectors (the
algorithm's own sequential dependency, through lambda) is then a few (P,)-vector operations per
selector (cumulated errors as ``lambda @ |h|`` products, selection, importance update); finally
every sample adds the importance it had on reaching each selector to the histograms in one
``index_add_``, and the worst candidate of every selector is replaced (once per call). With
P = 1 this is Algorithm 1 with the test-then-train order above.
"""

from __future__ import annotations

import math
from typing import Any

import torch

from torchtrack.errors import ConfigError, DataError, ShapeError, is_integer, is_number
from torchtrack.filter._random import randint
from torchtrack.learn._base import check_fitted

__all__ = ["OnlineRealBoost"]


class OnlineRealBoost:
    """Online real AdaBoost over integer-coded features (Jin et al. Algorithm 1).

    Args:
        n_selectors: N, the number of selectors (weak hypotheses voting in the strong one).
        n_candidates: M, candidate features per selector.
        n_bins: K, the number of value blocks; feature codes must lie in ``0..K-1``.
        eps: the small positive constant of the weak hypotheses.
        dtype: histogram dtype (float64 default: weights accumulate over many frames).

    Attributes (after the first :meth:`partial_fit`):
        features_: ``(N, M)`` int64 feature index of each candidate.
        hist_: ``(N, M, K, 2)`` weight histograms (last axis: label -1, +1).
        correct_, wrong_: ``(N, M)`` cumulated correct / wrong weights.
        selected_: ``(N,)`` int64 selected candidate ``m+`` per selector.
        alpha_: ``(N,)`` voting weights.
        n_features_in_: F, the number of features.
        n_samples_seen_: samples used so far.
    """

    def __init__(
        self,
        n_selectors: int = 10,
        n_candidates: int = 4,
        n_bins: int = 256,
        eps: float = 1e-3,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        self.n_selectors = n_selectors
        self.n_candidates = n_candidates
        self.n_bins = n_bins
        self.eps = eps
        self.dtype = dtype

    # -- validation ----------------------------------------------------------------------------
    def _check_params(self) -> None:
        for name in ("n_selectors", "n_candidates", "n_bins"):
            v = getattr(self, name)
            if not is_integer(v) or v < 1:
                raise ConfigError(f"OnlineRealBoost: {name} must be an integer >= 1, got {v!r}")
        eps = self.eps  # True was an eps of 1, inf made every weak hypothesis 0
        if not is_number(eps) or not 0 < eps < math.inf:
            raise ConfigError(f"OnlineRealBoost: eps must be a finite number > 0, got {eps!r}")

    def _check_codes(self, codes: Any) -> torch.Tensor:
        if not isinstance(codes, torch.Tensor) or codes.ndim != 2:
            shape = tuple(codes.shape) if isinstance(codes, torch.Tensor) else type(codes).__name__
            raise ShapeError(f"codes must be a (P, F) integer tensor, got {shape}")
        if codes.is_floating_point() or codes.dtype == torch.bool:
            raise ShapeError(f"codes must be integer bin codes, got {codes.dtype}")
        if hasattr(self, "n_features_in_") and codes.shape[1] != self.n_features_in_:
            raise ShapeError(
                f"codes have {codes.shape[1]} features, the classifier was fitted on "
                f"{self.n_features_in_}"
            )
        if codes.numel() and (int(codes.min()) < 0 or int(codes.max()) >= self.n_bins):
            raise ShapeError(
                f"codes must lie in 0..{self.n_bins - 1} (n_bins), got "
                f"{int(codes.min())}..{int(codes.max())}"
            )
        return codes.long()

    def _start(self, f: int, device: torch.device, generator: torch.Generator | None) -> None:
        self._check_params()
        n, m, k = self.n_selectors, self.n_candidates, self.n_bins
        self.n_features_in_ = f
        # "strong classifier initialized randomly": random candidate features.
        self.features_ = randint(0, f, (n, m), generator, device)
        self.hist_ = torch.zeros((n, m, k, 2), dtype=self.dtype, device=device)
        self.correct_ = torch.ones((n, m), dtype=self.dtype, device=device)
        self.wrong_ = torch.ones((n, m), dtype=self.dtype, device=device)
        self.selected_ = torch.zeros(n, dtype=torch.long, device=device)
        self.alpha_ = torch.zeros(n, dtype=self.dtype, device=device)
        self.n_samples_seen_ = 0

    # -- learning ------------------------------------------------------------------------------
    def weak_table(self) -> torch.Tensor:
        """``(N, M, K)`` weak hypotheses ``1/2 ln((w+ + eps) / (w- + eps))`` of every block."""
        check_fitted(self, "hist_")
        return 0.5 * torch.log((self.hist_[..., 1] + self.eps) / (self.hist_[..., 0] + self.eps))

    def partial_fit(
        self,
        codes: torch.Tensor,
        y: torch.Tensor,
        sample_weight: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> OnlineRealBoost:
        """One online update with the P samples of ``codes`` (one mini-batch, see module doc).

        Args:
            codes: ``(P, F)`` integer feature codes in ``0..n_bins-1``.
            y: ``(P,)`` labels in {-1, +1} (or {0, 1}: 0 is read as -1).
            sample_weight: optional ``(P,)`` initial importances (default one, Algorithm 1).
            generator: random source of the initial and replacement features.

        Returns:
            self.

        Raises:
            ShapeError: bad shapes, codes out of range or labels not binary.
            DataError: a sample weight that is not finite or is negative.
            ConfigError: bad hyper-parameters.
        """
        codes = self._check_codes(codes)
        p = codes.shape[0]
        y = torch.as_tensor(y, device=codes.device)
        if y.shape != (p,):
            raise ShapeError(f"y must be ({p},) matching codes, got {tuple(y.shape)}")
        if p and not bool(((y == 1) | (y == -1) | (y == 0)).all()):
            raise ShapeError("y must hold labels -1/+1 (or 0/1)")
        lam = (
            torch.ones(p, dtype=self.dtype, device=codes.device)
            if sample_weight is None
            else torch.as_tensor(sample_weight, dtype=self.dtype, device=codes.device).clone()
        )
        if lam.shape != (p,):
            raise ShapeError(f"sample_weight must be ({p},), got {tuple(lam.shape)}")
        if sample_weight is not None and not bool(((lam >= 0) & (lam < math.inf)).all()):
            # a NaN importance went into the histograms for good (every later score NaN), a
            # negative one trained against the label
            raise DataError("OnlineRealBoost: sample_weight must be finite and >= 0")
        if not hasattr(self, "hist_"):
            self._start(codes.shape[1], codes.device, generator)
        if p == 0:
            return self
        ys = torch.where(y > 0, 1.0, -1.0).to(self.dtype)
        lab = (y > 0).long()
        n_sel, m, k = self.n_selectors, self.n_candidates, self.n_bins
        dev = codes.device
        # Replacement features are drawn up front (one per selector), so the random stream does
        # not depend on the data.
        fresh = randint(0, self.n_features_in_, (n_sel,), generator, dev)
        # Test, then train: every selector scores the batch with its histograms from before the
        # batch, so all N x M weak outputs come from one gather, independent of lambda.
        flat = torch.arange(n_sel * m, device=dev).view(1, n_sel, m) * k + codes[
            :, self.features_.flatten()
        ].view(p, n_sel, m)  # (P, N, M) cell index into the (N*M*K) histogram table
        hist = self.hist_.view(n_sel * m * k, 2)
        table = 0.5 * torch.log((hist[:, 1] + self.eps) / (hist[:, 0] + self.eps))
        h = table[flat]  # (P, N, M)
        right = h * ys.view(p, 1, 1) >= 0
        habs = h.abs()
        mass_right = torch.where(right, habs, 0.0)  # (P, N, M)
        mass_wrong = habs - mass_right
        lams = torch.empty((n_sel, p), dtype=self.dtype, device=dev)
        # The sequential part of Algorithm 1 (lambda passes the selectors in turn) is now
        # a few (P,)-vector operations per selector.
        for n in range(n_sel):
            lams[n] = lam
            self.correct_[n] += lam @ mass_right[:, n]
            self.wrong_[n] += lam @ mass_wrong[:, n]
            e = self.wrong_[n] / (self.wrong_[n] + self.correct_[n])
            best = torch.argmin(e)
            eb = e[best]
            ok = eb < 0.5
            ebc = eb.clamp(1e-12, 1 - 1e-12)
            self.selected_[n] = best
            self.alpha_[n] = torch.where(ok, torch.log((1 - ebc) / ebc), 0.0)
            right_b = right[:, n, best]
            new_lam = torch.where(right_b, lam / (2 * (1 - ebc)), lam / (2 * ebc))
            lam = torch.where(ok, new_lam, lam)
        # Train: every sample adds the importance it had on reaching each selector.
        cell = flat * 2 + lab.view(p, 1, 1)  # (P, N, M) index into hist_ flattened
        wts = lams.T.unsqueeze(2).expand(p, n_sel, m)
        self.hist_.view(-1).index_add_(0, cell.flatten(), wts.flatten())
        if m > 1:  # replace the worst candidate (never the selected one) by a fresh one
            e = self.wrong_ / (self.wrong_ + self.correct_)  # (N, M)
            e = e.scatter(1, self.selected_.view(n_sel, 1), -math.inf)
            worst = torch.argmax(e, 1)
            rows = torch.arange(n_sel, device=dev)
            self.features_[rows, worst] = fresh
            self.hist_[rows, worst] = 0.0
            self.correct_[rows, worst] = 1.0
            self.wrong_[rows, worst] = 1.0
        self.n_samples_seen_ += p
        return self

    # -- prediction ----------------------------------------------------------------------------
    def decision_function(self, codes: torch.Tensor) -> torch.Tensor:
        """``conf(x) = sum_n alpha_n h_n^sel(x)``: ``codes (P, F)`` -> ``(P,)`` confidences.

        Raises:
            NotFittedError: before the first :meth:`partial_fit`. ShapeError: bad codes.
        """
        check_fitted(self, "hist_")
        codes = self._check_codes(codes)
        n = self.n_selectors
        rows = torch.arange(n, device=codes.device)
        feats = self.features_[rows, self.selected_]  # (N,)
        sel_hist = self.hist_[rows, self.selected_]  # (N, K, 2)
        table = 0.5 * torch.log((sel_hist[..., 1] + self.eps) / (sel_hist[..., 0] + self.eps))
        # Selectors that chose the same feature share one lookup: fold alpha_n h_n into one
        # (K,) table per distinct feature, then gather once per feature used.
        used, slot = torch.unique(feats, return_inverse=True)
        folded = torch.zeros((used.numel(), self.n_bins), dtype=table.dtype, device=table.device)
        folded.index_add_(0, slot, self.alpha_.unsqueeze(1) * table)
        out = torch.zeros(codes.shape[0], dtype=table.dtype, device=codes.device)
        for u in range(used.numel()):
            out += folded[u][codes[:, used[u]]]
        return out

    def predict(self, codes: torch.Tensor) -> torch.Tensor:
        """``(P,)`` labels in {-1, +1} (``conf >= 0`` is +1)."""
        return torch.where(self.decision_function(codes) >= 0, 1, -1)
