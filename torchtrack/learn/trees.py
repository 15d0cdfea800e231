"""Boosted decision trees (depth 2 by default) with a soft cascade: discrete / real / gentle
AdaBoost over trees, trained with histogram split search, evaluated with early rejection.

Boosting (Friedman, Hastie, Tibshirani 2000; Schapire & Singer 1999): every round grows one tree
greedily (each node takes the feature and threshold that are best for its variant, as if its
children were leaves), then reweights the samples by ``w <- w exp(-y h(x))`` (``y = +-1``):

* ``"discrete"``: nodes minimise the weighted error of majority leaves; the tree outputs
  ``+-alpha``, ``alpha = 1/2 ln((1 - err) / err)``.
* ``"real"``: nodes minimise ``Z = sum_leaves 2 sqrt(W+ W-)``; leaves output
  ``1/2 ln((W+ + eps) / (W- + eps))`` (Dollár's ACF trees).
* ``"gentle"``: least-squares regression trees; leaves output ``(W+ - W-) / (W+ + W-)``.

Split search works on ``uint8`` codes (every feature coded once into at most 256 bins at
quantile edges): one weighted histogram per tree level (``scatter_add_`` over the codes, the
class and the node folded into one index), then cumulative sums give every threshold of every
feature at once. Optional weight trimming (Friedman et al. sec. 9: only the samples holding
``1 - weight_trimming`` of the weight enter the search; all are reweighted) and a random
fraction of the features per tree speed up long runs.

**Soft cascade** (Bourdev & Brandt, CVPR 2005; Dollár et al.'s constant soft cascade is the
special case of one threshold): ``reject_[t]`` is a threshold on the running margin after tree
``t``; :meth:`BoostedTrees.cascade` stops evaluating a window as soon as its running margin
falls below, so most windows of a scan cost a few trees. Windows that pass get the full margin.
:meth:`BoostedTrees.fit_cascade` sets the thresholds by direct backward pruning: the smallest
running margin, tree by tree, of the positives whose final margin reaches a given value.
"""

from __future__ import annotations

import math
from collections.abc import Callable
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
    state_meta,
    state_tensor,
)
from torchtrack.learn.boosting import VARIANTS, _initial_weights, _tqdm

__all__ = ["BoostedTrees", "code_features", "quantile_edges"]

_BIG = float(torch.finfo(torch.float32).max)  # "never go right" threshold / "never reject"


def quantile_edges(X: torch.Tensor, n_bins: int = 256, n_sample: int = 8192) -> torch.Tensor:
    """Bin edges ``(F, n_bins - 1)`` float32 of the columns of ``X (n, F)`` at the quantiles of
    an evenly spaced row subsample (deterministic).

    Every edge lies halfway between a sample value and the next value larger by more than a
    tolerance (``1e-5 (1 + |v|)``), never on or beside a value itself: features often take one
    value many times (0 in a flat region), read as 0, 4e-13 or -1e-15 by two exact ways of
    reading the same feature (crops at training, integral images at detection); an edge inside
    such a cluster of values would let float rounding decide the split (a scan and a box score
    of the same window then differed by 100 in margin). An edge with no larger sample value is
    ``+inf`` (never splits).
    """
    if not 2 <= int(n_bins) <= 256:
        raise errors.ConfigError(f"n_bins must be in [2, 256], got {n_bins}")
    cols = X.to(torch.float32).t().contiguous()
    n = cols.shape[1]
    m = min(n, n_sample)
    rows = torch.linspace(0, n - 1, m, device=cols.device).round().long()
    sub = cols.index_select(1, rows).sort(dim=1).values  # (F, m)
    pos = (torch.arange(1, int(n_bins), device=cols.device) * m) // int(n_bins)
    at = sub.index_select(1, pos.clamp_max(m - 1))  # (F, n_bins - 1) sample values
    tol = 1e-5 * (1.0 + at.abs())
    nxt_i = torch.searchsorted(sub, (at + tol).contiguous(), right=True)  # first value > at + tol
    nxt = sub.gather(1, nxt_i.clamp_max(m - 1))
    top = sub.gather(1, (nxt_i - 1).clamp_min(0))  # the cluster's largest value (>= at)
    mid = (top.double() + nxt.double()).mul_(0.5).to(torch.float32)
    mid = torch.where(mid > top, mid, nxt)  # float rounding can land the midpoint on `top`
    return torch.where(nxt_i < m, mid, torch.full_like(mid, math.inf)).contiguous()


def code_features(X: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """``X (n, F)`` -> ``uint8`` codes ``(F, n)``: the number of edges ``<= x``, so that
    ``x >= edges[f, b]`` iff ``code > b``."""
    cols = X.to(torch.float32).t().contiguous()
    if not bool(torch.isfinite(cols).all()):
        bad = (~torch.isfinite(cols)).nonzero()[0]
        raise errors.DataError(
            f"features contain NaN or inf; the first at row {int(bad[1])}, column {int(bad[0])}"
        )
    return torch.searchsorted(edges.contiguous(), cols, right=True).to(torch.uint8)


def _hist(
    codes: torch.Tensor,
    feats: torch.Tensor | None,
    cols: torch.Tensor | slice,
    w: torch.Tensor,
    nb: int,
    chunk: int,
) -> torch.Tensor:
    """Weighted histograms ``(F', nb)``: ``out[f, b] = sum w[i] [codes[f, cols[i]] == b]`` over
    features ``feats`` (all when None) and samples ``cols`` (a slice or an index tensor)."""
    n_f = codes.shape[0] if feats is None else feats.numel()
    m = w.numel()
    out = torch.zeros((n_f, nb), dtype=w.dtype, device=w.device)
    if m == 0 or n_f == 0:
        return out
    buf = torch.empty((min(chunk, n_f), m), dtype=torch.long, device=codes.device)
    idx = None if isinstance(cols, slice) else cols[None, :]
    for f0 in range(0, n_f, chunk):
        f1 = min(n_f, f0 + chunk)
        block = codes[f0:f1] if feats is None else codes.index_select(0, feats[f0:f1])
        # gather with an expanded index is several times faster than index_select on dim 1
        block = block[:, cols] if idx is None else block.gather(1, idx.expand(f1 - f0, m))
        b = buf[: f1 - f0]
        b.copy_(block)
        out[f0:f1].scatter_add_(1, b, w.expand(f1 - f0, m))
    return out


def _best_splits(H: torch.Tensor, variant: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Best split of every node from histograms ``H (F, nodes, 2, nb)`` (class 0 = negative).

    Returns:
        ``(feature (nodes,), bin (nodes,))``: the split ``code > bin`` goes right.
    """
    _, nodes, _, nb = H.shape
    # float32 is plenty to rank splits and twice as fast as the float64 histograms
    cum = H.to(torch.float32).cumsum(-1)  # (F, nodes, 2, nb)
    left = cum[..., :-1]
    right = cum[..., -1:] - left
    ln, lp = left[:, :, 0], left[:, :, 1]  # (F, nodes, nb - 1)
    rn, rp = right[:, :, 0], right[:, :, 1]
    if variant == "gentle":
        lw, rw = (lp + ln).clamp_min_(1e-30), (rp + rn).clamp_min_(1e-30)
        score = (lp - ln).square_().div_(lw) + (rp - rn).square_().div_(rw)
    elif variant == "real":
        # histogram subtraction can leave tiny negative weights: clamp before the roots
        score = (lp * ln).clamp_min_(0).sqrt_().add_((rp * rn).clamp_min_(0).sqrt_()).neg_()
    else:
        score = torch.minimum(lp, ln).add_(torch.minimum(rp, rn)).neg_()
    flat = score.permute(1, 0, 2).reshape(nodes, -1)  # (nodes, F * (nb - 1))
    best = flat.argmax(1)
    return best // (nb - 1), best % (nb - 1)


#: rows per block of :meth:`BoostedTrees._tree_outputs` (bounds its workspace)
_ROW_CHUNK = 4096
#: window-features one ``read`` call of :meth:`BoostedTrees.cascade` asks for at most (a step
#: of many trees on many windows is read in runs of windows): bounds a scan's index and value
#: tables (~200 MB for box features) whatever the number of windows per cascade call
_READ_VALUES = 1 << 22


class BoostedTrees(ClassifierMixin, BaseEstimator):
    """AdaBoost (discrete / real / gentle) over depth-``max_depth`` decision trees, with a soft
    cascade for early rejection (see the module notes).

    Args:
        n_estimators: number of trees (rounds).
        max_depth: depth of every tree (2: three splits, four leaves).
        variant: ``"discrete"``, ``"real"`` or ``"gentle"``.
        n_bins: threshold bins per feature (2..256) when fitting on raw features.
        feature_fraction: share of the features searched per tree (random, from ``generator``
            of :meth:`fit_codes`); 1 searches all.
        weight_trimming: share of the total weight left out of the split search (the lightest
            samples; Friedman et al. use 0.01 - 0.1); 0 searches all samples.
        chunk_size: features per histogram chunk (default 64 on CPU, 2048 on CUDA).

    Attributes:
        classes_: the two labels; ``classes_[1]`` is positive.
        n_features_in_: number of input columns.
        feature_: ``(R, 2^d - 1)`` int64 split feature of every internal node (breadth first:
            node ``n``'s children are ``2n + 1`` (``x < threshold``) and ``2n + 2``).
        threshold_: ``(R, 2^d - 1)`` float32.
        leaf_: ``(R, 2^d)`` float32 tree outputs.
        reject_: ``(R,)`` float32 soft-cascade thresholds on the running margin (the most
            negative float32 where there is none).
    """

    def __init__(
        self,
        n_estimators: int = 1024,
        max_depth: int = 2,
        variant: str = "real",
        n_bins: int = 256,
        feature_fraction: float = 1.0,
        weight_trimming: float = 0.0,
        chunk_size: int | None = None,
    ) -> None:
        self.n_estimators = n_estimators
        self.max_depth = max_depth
        self.variant = variant
        self.n_bins = n_bins
        self.feature_fraction = feature_fraction
        self.weight_trimming = weight_trimming
        self.chunk_size = chunk_size

    # -- fitting
    def _check_params(self) -> None:
        if self.variant not in VARIANTS:
            raise errors.ConfigError(
                f"variant must be one of {', '.join(VARIANTS)}; got {self.variant!r}"
            )
        if not isinstance(self.n_estimators, int) or self.n_estimators < 1:
            raise errors.ConfigError(
                f"n_estimators must be a positive integer, got {self.n_estimators!r}"
            )
        if not isinstance(self.max_depth, int) or not 1 <= self.max_depth <= 4:
            raise errors.ConfigError(
                f"max_depth must be an integer in [1, 4], got {self.max_depth!r}"
            )
        if not 0.0 < float(self.feature_fraction) <= 1.0:
            raise errors.ConfigError(
                f"feature_fraction must be in (0, 1], got {self.feature_fraction}"
            )
        if not 0.0 <= float(self.weight_trimming) < 1.0:
            raise errors.ConfigError(
                f"weight_trimming must be in [0, 1), got {self.weight_trimming}"
            )

    def fit(self, X: Any, y: Any, sample_weight: Any = None) -> BoostedTrees:
        """Fit on raw features ``X (n, T)`` and labels ``y (n,)`` (codes them into ``n_bins``
        quantile bins first); returns ``self``.

        Raises:
            ConfigError: a bad parameter. ShapeError / DataError: bad ``X``, ``y``.
        """
        self._check_params()
        Xt = as_float_tensor(X, "X", ndim=2)
        edges = quantile_edges(Xt, int(self.n_bins))
        return self.fit_codes(code_features(Xt, edges), edges, y, sample_weight)

    def fit_codes(
        self,
        codes: torch.Tensor,
        edges: torch.Tensor,
        y: Any,
        sample_weight: Any = None,
        *,
        generator: torch.Generator | None = None,
        progress: bool = False,
    ) -> BoostedTrees:
        """Fit on coded features (the training path for large feature pools).

        Args:
            codes: ``(T, n)`` uint8, ``code > b`` iff ``x >= edges[f, b]`` (:func:`code_features`).
            edges: ``(T, n_edges)`` float32 bin edges (``+inf`` padding allowed).
            y: ``(n,)`` labels, two classes.
            sample_weight: initial weights ``(n,)`` (default: each class half of the weight).
            generator: random source of ``feature_fraction``.
            progress: a progress bar.

        Returns:
            ``self``.
        """
        self._check_params()
        if codes.ndim != 2 or codes.dtype != torch.uint8:
            raise errors.ShapeError(
                f"codes must be (T, n) uint8, got {tuple(codes.shape)} {codes.dtype}"
            )
        n_f, n = codes.shape
        if edges.ndim != 2 or edges.shape[0] != n_f:
            raise errors.ShapeError(f"edges must be ({n_f}, n_edges), got {tuple(edges.shape)}")
        y01, classes = as_binary_labels(y, n)
        dev = codes.device
        y01 = y01.to(dev)
        w = _initial_weights(y01, sample_weight, n).to(dev)
        # negatives first: each class is one contiguous range of the histogram columns
        perm = torch.argsort(y01, stable=True)
        codes = codes[:, perm]
        y01, w = y01[perm], w[perm]
        n_neg = int((y01 == 0).sum())
        nb = int(edges.shape[1]) + 1
        depth = int(self.max_depth)
        n_int, n_leaf = (1 << depth) - 1, 1 << depth
        chunk = int(self.chunk_size or (64 if dev.type == "cpu" else 2048))
        ysign = (2 * y01 - 1).to(torch.float64)
        eps = 1.0 / n
        n_sub = max(1, round(float(self.feature_fraction) * n_f))
        feat_t = torch.zeros((self.n_estimators, n_int), dtype=torch.long)
        thr_t = torch.full((self.n_estimators, n_int), _BIG, dtype=torch.float32)
        leaf_t = torch.zeros((self.n_estimators, n_leaf), dtype=torch.float32)
        bins = torch.zeros(n_int, dtype=torch.long, device=dev)
        feats_r = torch.zeros(n_int, dtype=torch.long, device=dev)
        edges_c = edges.to(dev)
        pbar = _tqdm(progress, total=self.n_estimators, desc="boosting trees", unit="tree")
        r_done = 0
        for r in range(self.n_estimators):
            feats = None
            if n_sub < n_f:
                feats = torch.randperm(n_f, generator=generator)[:n_sub].sort().values.to(dev)
            rows = self._trimmed_rows(w)
            wr = w if rows is None else w[rows]
            node = torch.zeros(wr.numel(), dtype=torch.long, device=dev)
            H = None
            for level in range(depth):
                n_nodes = 1 << level
                H = self._level_hist(codes, feats, rows, n_neg, node, wr, H, nb, chunk)
                fb, bb = _best_splits(H, self.variant)
                gf = fb if feats is None else feats[fb]
                first = n_nodes - 1
                feats_r[first : first + n_nodes] = gf
                bins[first : first + n_nodes] = bb
                feat_t[r, first : first + n_nodes] = gf.cpu()
                thr = edges_c[gf, bb]
                thr_t[r, first : first + n_nodes] = torch.where(
                    torch.isfinite(thr), thr, torch.full_like(thr, _BIG)
                ).cpu()
                if level + 1 < depth:  # route the search samples one level down
                    go = self._go(codes, gf, bb, node, rows)
                    node = node * 2 + go
            # leaf statistics over all samples
            leaf = self._leaves(codes, feats_r, bins, n)
            wp = torch.zeros(n_leaf, dtype=torch.float64, device=dev).index_add_(
                0, leaf, torch.where(y01.bool(), w, 0.0)
            )
            wn = torch.zeros(n_leaf, dtype=torch.float64, device=dev).index_add_(
                0, leaf, torch.where(y01.bool(), 0.0, w)
            )
            stop = False
            if self.variant == "gentle":
                tot = wp + wn
                vals = torch.where(tot > 0, (wp - wn) / tot.clamp_min(1e-300), 0.0)
            elif self.variant == "real":
                vals = 0.5 * torch.log((wp + eps) / (wn + eps))
            else:
                sign = torch.where(wp >= wn, 1.0, -1.0).to(torch.float64)
                err = float(torch.minimum(wp, wn).sum() / (wp + wn).sum())
                stop = err <= 0.0
                err = min(max(err, 1e-10), 1.0 - 1e-10)
                vals = sign * (0.5 * math.log((1.0 - err) / err))
            leaf_t[r] = vals.to(torch.float32).cpu()
            out = vals[leaf]
            w = w * torch.exp(-ysign * out)
            w = w / w.sum()
            r_done = r + 1
            pbar.update(1)
            if stop:
                break
        pbar.close()
        self.classes_ = classes
        self.n_features_in_ = int(n_f)
        self.feature_ = feat_t[:r_done].clone()
        self.threshold_ = thr_t[:r_done].clone()
        self.leaf_ = leaf_t[:r_done].clone()
        self.reject_ = torch.full((r_done,), -_BIG, dtype=torch.float32)
        return self

    @staticmethod
    def _level_hist(codes, feats, rows, n_neg, node, wr, parent, nb, chunk) -> torch.Tensor:
        """Histograms ``(F', nodes, 2, nb)`` (class 0 negative) of one tree level.

        Samples are sorted by class (negatives first, ``n_neg`` of them), so a class is a
        contiguous range or a split of the search rows: no index arithmetic per sample. Below
        the root only the smaller child of every split is counted; its sibling is the parent
        minus it (LightGBM's histogram subtraction), so a level costs at most half a pass.
        """
        if parent is None:
            if rows is None:
                parts = [(slice(0, n_neg), wr[:n_neg]), (slice(n_neg, None), wr[n_neg:])]
            else:
                neg = rows < n_neg
                parts = [(rows[neg], wr[neg]), (rows[~neg], wr[~neg])]
            n_f = codes.shape[0] if feats is None else feats.numel()
            h = torch.empty((n_f, 1, 2, nb), dtype=wr.dtype, device=wr.device)
            for k, (c, w) in enumerate(parts):
                h[:, 0, k] = _hist(codes, feats, c, w, nb, chunk)
            return h
        n_par = parent.shape[1]
        side = node % 2  # 0: left child, 1: right child
        par = node // 2
        allr = torch.arange(node.numel(), device=node.device) if rows is None else rows
        hs = torch.zeros_like(parent)
        small = torch.zeros(n_par, dtype=torch.bool)
        for p in range(n_par):
            inp = par == p
            n_right = int((side[inp] == 1).sum())
            small[p] = 2 * n_right < int(inp.sum())  # True: the right child is the smaller
            pick = inp & (side == int(small[p]))
            sel = torch.nonzero(pick).flatten()
            rr, ww = allr[sel], wr[sel]
            neg = rr < n_neg
            hs[:, p, 0] = _hist(codes, feats, rr[neg], ww[neg], nb, chunk)
            hs[:, p, 1] = _hist(codes, feats, rr[~neg], ww[~neg], nb, chunk)
        hb = parent - hs
        s = small.to(parent.device).view(1, n_par, 1, 1)
        left = torch.where(s, hb, hs)
        right = torch.where(s, hs, hb)
        return torch.stack((left, right), 2).reshape(hs.shape[0], 2 * n_par, 2, nb)

    def _trimmed_rows(self, w: torch.Tensor) -> torch.Tensor | None:
        beta = float(self.weight_trimming)
        if beta <= 0:
            return None
        sw, order = w.sort()
        cut = int(
            torch.searchsorted(
                sw.cumsum(0),
                torch.tensor([beta * float(w.sum())], dtype=sw.dtype, device=sw.device),
            )
        )
        if cut <= 0:
            return None
        return order[cut:].sort().values

    @staticmethod
    def _go(codes, gf, bb, node, rows) -> torch.Tensor:
        """Whether each search sample goes right at its node (``code > bin``)."""
        f = gf[node]
        cols = torch.arange(codes.shape[1], device=codes.device) if rows is None else rows
        return (codes[f, cols].long() > bb[node]).long()

    def _leaves(self, codes, feat, bins, n) -> torch.Tensor:
        """Leaf index ``(n,)`` of every training sample: node splits ``(feat, bins)``
        (``code > bin`` goes right)."""
        node = torch.zeros(n, dtype=torch.long, device=codes.device)
        cols = torch.arange(n, device=codes.device)
        for _ in range(int(self.max_depth)):
            node = node * 2 + 1 + (codes[feat[node], cols].long() > bins[node]).long()
        return node - feat.numel()

    # -- scoring
    def _tables_on(self, dev: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``feature_``, ``threshold_``, ``leaf_`` on ``dev``: copied to a GPU once per fitted
        state (a particle filter scores every frame; a copy per call would wait on the host)."""
        tables = (self.feature_, self.threshold_, self.leaf_)
        if all(t.device == dev for t in tables):
            return tables
        cache = self.__dict__.setdefault("_device_tables", {})
        hit = cache.get(dev)
        if hit is None or any(a is not b for a, b in zip(hit[0], tables, strict=True)):
            hit = (tables, tuple(t.to(dev) for t in tables))
            cache[dev] = hit
        return hit[1]

    def _tree_outputs(self, X: torch.Tensor) -> torch.Tensor:
        """Output of every tree ``(..., R)`` on raw features ``X (..., T)``.

        Rows are taken ``_ROW_CHUNK`` at a time and transposed, so that every read is a whole
        contiguous row: the split features of all trees come from one ``index_select`` on the
        first axis (reading columns of the last axis is several times slower on CPU), all
        split tests of all nodes are one comparison, and the descent gathers the tests'
        outcomes (booleans) level by level. The leaves and their order are those of the
        trees, so margins are bit-identical to a node-by-node evaluation.
        """
        dev = X.device
        feat, thr, leaf = self._tables_on(dev)
        feat, thr = feat.reshape(-1), thr.reshape(-1, 1)
        r, n_int = self.feature_.shape
        leaf_flat = leaf.reshape(-1)
        base = (torch.arange(r, device=dev) * (n_int + 1) - n_int).unsqueeze(1)  # (R, 1)
        x2 = X.reshape(-1, X.shape[-1])
        m = x2.shape[0]
        out = torch.empty((m, r), dtype=leaf.dtype, device=dev)
        for s in range(0, m, _ROW_CHUNK):
            xt = x2[s : s + _ROW_CHUNK].T.contiguous()  # (T, c)
            c = xt.shape[1]
            test = (xt.index_select(0, feat) >= thr).view(r, n_int, c)
            depth = int(self.max_depth)
            if depth == 0:
                node = torch.zeros((r, c), dtype=torch.long, device=dev)
            else:  # the root's test and (depth >= 2) its children's, selected without gathers
                right = test[:, 0]
                node = right.long() + 1  # (R, c) in {1, 2}
                if depth >= 2:
                    below = torch.where(right, test[:, 2], test[:, 1])
                    node = node * 2 + 1 + below.long()
                for _ in range(2, depth):
                    node = node * 2 + 1 + test.gather(1, node[:, None])[:, 0].long()
            vals = leaf_flat.index_select(0, (base + node).reshape(-1)).view(r, c)
            out[s : s + c] = vals.T
        return out.view(*X.shape[:-1], r)

    def _check_X(self, X: Any) -> tuple[torch.Tensor, bool]:
        check_fitted(self, "feature_")
        is_numpy = not isinstance(X, torch.Tensor)
        Xt = as_float_tensor(X, "X", check_finite=False)
        if Xt.ndim == 0 or Xt.shape[-1] != self.n_features_in_:
            raise errors.ShapeError(
                f"X must have {self.n_features_in_} columns (last axis), got shape {tuple(Xt.shape)}"
            )
        return Xt, is_numpy

    def decision_function(self, X: Any) -> Any:
        """Margins ``(...)`` float32 (sum of all tree outputs) of ``X (..., T)``; torch in,
        torch out (on ``X``'s device), numpy in, numpy out."""
        Xt, is_numpy = self._check_X(X)
        out = self._tree_outputs(Xt).sum(-1)
        return out.cpu().numpy() if is_numpy else out

    def staged_decision_function(self, X: Any) -> torch.Tensor:
        """Running margins ``(..., R)``: the margin after each tree."""
        Xt, _ = self._check_X(X)
        return self._tree_outputs(Xt).cumsum(-1)

    def predict(self, X: Any) -> Any:
        m = self.decision_function(X)
        pos = np.asarray(m > 0) if not isinstance(m, torch.Tensor) else (m > 0).cpu().numpy()
        return self.classes_[pos.astype(np.int64)]

    def margin_range(self) -> tuple[float, float]:
        """The smallest and largest margin the trees can give."""
        check_fitted(self, "leaf_")
        leaf = self.leaf_.to(torch.float64)
        return float(leaf.min(1).values.sum()), float(leaf.max(1).values.sum())

    def truncated(self, n_trees: int) -> BoostedTrees:
        """A copy made of the first ``n_trees`` trees (their running margin, as in
        :meth:`staged_decision_function`); the input columns stay the same.

        Raises:
            ConfigError: ``n_trees`` not in ``[1, R]``.
        """
        check_fitted(self, "feature_")
        r = int(self.feature_.shape[0])
        if isinstance(n_trees, bool) or not isinstance(n_trees, int) or not 1 <= n_trees <= r:
            raise errors.ConfigError(f"n_trees must be an integer in [1, {r}], got {n_trees!r}")
        est = BoostedTrees(
            n_estimators=n_trees, max_depth=self.max_depth, variant=self.variant, n_bins=self.n_bins
        )
        est.classes_ = self.classes_
        est.n_features_in_ = self.n_features_in_
        est.feature_ = self.feature_[:n_trees].clone()
        est.threshold_ = self.threshold_[:n_trees].clone()
        est.leaf_ = self.leaf_[:n_trees].clone()
        est.reject_ = self.reject_[:n_trees].clone()
        return est

    # -- soft cascade
    def fit_cascade(self, X_pos: Any, min_margin: float, *, quantile: float = 0.0) -> BoostedTrees:
        """Direct backward pruning: ``reject_[t]`` = the ``quantile`` of the running margins
        after tree ``t`` over the positives ``X_pos (n, T)`` whose final margin is at least
        ``min_margin`` (so that those are never rejected, ``quantile = 0``); no rejection when
        none qualifies.

        Returns:
            ``self``.
        """
        staged = self.staged_decision_function(torch.as_tensor(X_pos)).reshape(
            -1, self.leaf_.shape[0]
        )
        keep = staged[:, -1] >= float(min_margin)
        if not bool(keep.any()):
            self.reject_ = torch.full_like(self.leaf_[:, 0], -_BIG)
            return self
        s = staged[keep].to(torch.float64)
        q = torch.quantile(s, float(quantile), dim=0) if quantile > 0 else s.min(0).values
        # keep the guarantee exact: a hair below the smallest kept value
        self.reject_ = (q - 1e-5 * (1.0 + q.abs())).to(torch.float32).cpu()
        return self

    def cascade(
        self,
        read: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
        n: int,
        *,
        device: torch.device | str = "cpu",
        reject: bool = True,
        stages: tuple[int, ...] = (1, 4, 16, 64, 256),
        reject_at_most: float | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Soft-cascade evaluation of ``n`` windows whose features are read on demand.

        Args:
            read: ``read(rows (A,), feats) -> (A, T)`` raw feature values of windows ``rows``,
                one feature per window and tree: ``feats`` is ``(A, T)``, or ``(T,)`` when
                every window reads the same feature of a tree (the root, and both children of
                the root of depth-2 trees, read for every window and then selected: no
                per-window index tables on the scan's hottest path).
            n: number of windows (``read`` is asked for runs of them, at most
                :data:`_READ_VALUES` window-features a call).
            reject: use the rejection thresholds (False: every window gets every tree).
            stages: trees evaluated per step while windows remain: the first step evaluates
                ``stages[0]`` trees, then ``stages[1]``, ..., the last size repeating; rejection
                is checked after every tree, so the schedule changes the speed, and the result
                only by float32 rounding (a step's running margins are its trees' cumulative
                sum added to the margin so far: another schedule adds in another order, and 40
                tracker scans of PETS hashed differently for (1, 2, 8, 32, 128)). One tree
                first: on PETS frames it already rejects most windows, and the
                scans took 7% (``torchtrack detect``) and 11% (the tracker's looser cascade)
                less time than with (4, 16, 64, 256).
            reject_at_most: lower every tree's rejection threshold (``reject_``) to at most this
                running margin (a looser cascade: a constant one at this margin where the
                fitted thresholds are higher); ``None``: the fitted ones.

        Returns:
            ``(rows (M,), margins (M,))``: the windows that passed every threshold (in
            increasing order) and their full margins.
        """
        check_fitted(self, "leaf_")
        dev = torch.device(device)
        feat = self.feature_.to(dev)
        thr = self.threshold_.to(dev)
        leaf = self.leaf_.to(dev)
        rej = self.reject_.to(dev)
        if reject_at_most is not None:
            rej = rej.clamp(max=float(reject_at_most))
        r_tot, n_int = feat.shape

        def read_rows(rows: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
            # in runs of at most _READ_VALUES window-features (each window's values are its own)
            step = max(1, _READ_VALUES // max(1, f.shape[-1]))
            if rows.shape[0] <= step:
                return read(rows, f)
            return torch.cat(
                [
                    read(rows[i : i + step], f[i : i + step] if f.ndim == 2 else f)
                    for i in range(0, rows.shape[0], step)
                ]
            )

        alive = torch.arange(n, device=dev)
        score = torch.zeros(n, dtype=torch.float32, device=dev)
        # the steps' tree ranges, and the steps read together: a step after which no window
        # can be rejected (every threshold of its trees below the lowest running margin any
        # window can have there, the sum of the trees' smallest leaves) shares its read with
        # the next one (one read call and one pass of per-call work instead of two; each
        # step's arithmetic as before, so the same margins and survivors)
        bounds, t, si = [], 0, 0
        while t < r_tot:
            bounds.append((t, min(r_tot, t + stages[min(si, len(stages) - 1)])))
            t, si = bounds[-1][1], si + 1
        safe = [False] * r_tot
        if reject:
            low = torch.cumsum(leaf.min(1).values.to(torch.float64), 0)
            safe = (rej.to(torch.float64) < low - 1e-3 * (1.0 + low.abs())).tolist()
        reads: list[list[tuple[int, int]]] = [[]]
        for s0, s1 in bounds:
            reads[-1].append((s0, s1))
            if not all(safe[s0:s1]):
                reads.append([])
        for steps in filter(None, reads):
            if not alive.numel():
                break
            t0, t_end = steps[0][0], steps[-1][1]
            tf, tt = feat[t0:t_end], thr[t0:t_end]
            nt = t_end - t0
            if self.max_depth >= 2:
                # the root and both of its children, read for every window in one call (one
                # feature per tree, shared by every window), then the child on the path
                go = read_rows(alive, tf[:, :3].t().reshape(-1)) >= tt[:, :3].t().reshape(-1)
                right = go[:, :nt]  # (A, T)
                below = torch.where(right, go[:, 2 * nt :], go[:, nt : 2 * nt])
                node = 3 + 2 * right.long() + below.long() if self.max_depth > 2 else None
            else:  # root only: one feature per tree, shared by every window
                node = 1 + (read_rows(alive, tf[:, 0]) >= tt[:, 0]).long()  # (A, T) in {1, 2}
            if node is not None:
                cols = torch.arange(nt, device=dev)
                for _ in range(2, int(self.max_depth)):
                    f = tf[cols, node]  # (A, T)
                    v = read_rows(alive, f)
                    node = node * 2 + 1 + (v >= tt[cols, node]).long()
            for s0, s1 in steps:
                a, b = s0 - t0, s1 - t0
                tl = leaf[s0:s1]
                cols = torch.arange(s1 - s0, device=dev)
                if node is None:
                    # depth 2: the leaf's place in the flat leaf table in int32 and in place,
                    # leaf 2 right + below of tree t (node 3 + 2 right + below)
                    place = right[:, a:b].to(torch.int32).mul_(2).add_(below[:, a:b])
                    place += (cols * (n_int + 1)).to(torch.int32)
                else:
                    place = node[:, a:b] - n_int + cols * (n_int + 1)
                # leaf values (A, T): a flat index_select (faster on CPU than tl[cols, leaf])
                out = tl.reshape(-1).index_select(0, place.reshape(-1)).view(place.shape)
                run = score.index_select(0, alive)[:, None] + out.cumsum(1)
                score.index_copy_(0, alive, run[:, -1])
                if reject and s1 == t_end:  # the steps before it reject nothing
                    alive = alive[(run >= rej[s0:s1]).all(1)]
        return alive, score[alive]

    # -- serialisation
    def to_state(self) -> tuple[dict[str, torch.Tensor], dict]:
        """Tensors and JSON metadata (``kind = "boosted_trees"``) for a model file."""
        check_fitted(self, "feature_")
        tensors = {
            "feature": self.feature_.clone(),
            "threshold": self.threshold_.clone(),
            "leaf": self.leaf_.clone(),
            "reject": self.reject_.clone(),
        }
        meta = {
            "kind": "boosted_trees",
            "variant": self.variant,
            "max_depth": int(self.max_depth),
            "n_estimators": int(self.n_estimators),
            "n_features_in": self.n_features_in_,
            "classes": [c.item() for c in self.classes_],
        }
        return tensors, meta

    @classmethod
    def from_state(cls, tensors: dict[str, torch.Tensor], meta: dict) -> BoostedTrees:
        """Rebuild from :meth:`to_state` output, validating every field.

        Raises:
            ModelFormatError: a missing / mistyped / misshaped / non-finite field, named.
        """
        kind = "boosted_trees"
        check_kind(meta, kind)
        variant = state_meta(meta, "variant", kind, str)
        if variant not in VARIANTS:
            raise errors.ModelFormatError(f"{kind}.variant: unknown variant {variant!r}")
        depth = state_meta(meta, "max_depth", kind, int)
        if not 1 <= depth <= 4:
            raise errors.ModelFormatError(f"{kind}.max_depth: {depth} not in [1, 4]")
        n_in = state_meta(meta, "n_features_in", kind, int)
        n_est = state_meta(meta, "n_estimators", kind, int)
        classes = state_meta(meta, "classes", kind, list)
        if len(classes) != 2:
            raise errors.ModelFormatError(f"{kind}.classes: expected 2 classes, got {classes}")
        n_int = (1 << depth) - 1
        feat = state_tensor(tensors, "feature", kind, ndim=2, dtype=torch.int64)
        r = feat.shape[0]
        if r < 1 or n_in < 1 or feat.shape[1] != n_int:
            raise errors.ModelFormatError(
                f"{kind}.feature: shape {tuple(feat.shape)}, expected (R >= 1, {n_int})"
            )
        if bool(((feat < 0) | (feat >= n_in)).any()):
            raise errors.ModelFormatError(f"{kind}.feature: indices outside [0, {n_in})")
        thr = state_tensor(tensors, "threshold", kind, shape=(r, n_int), dtype=torch.float32)
        leaf = state_tensor(tensors, "leaf", kind, shape=(r, n_int + 1), dtype=torch.float32)
        rej = state_tensor(tensors, "reject", kind, shape=(r,), dtype=torch.float32)
        est = cls(n_estimators=n_est, max_depth=depth, variant=variant)
        est.classes_ = np.asarray(classes)
        est.n_features_in_ = n_in
        est.feature_ = feat.clone()
        est.threshold_ = thr.clone()
        est.leaf_ = leaf.clone()
        est.reject_ = rej.clone()
        return est
