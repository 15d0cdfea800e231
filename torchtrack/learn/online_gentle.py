"""Constrained Gentle AdaBoost and its online adaptation (Klein et al. 2010, sec. III).

Everything is batched over ``M`` independent models (one per target in the global mode, one per
adapted particle in the per-particle mode), so one code path serves both.

Weak classifiers are threshold classifiers (regression stumps): stump ``m`` outputs
``right[m]`` where ``x[feature[m]] >= threshold[m]`` and ``left[m]`` elsewhere; Gentle
AdaBoost (Friedman, Hastie & Tibshirani 2000) fits both outputs by weighted least squares, i.e.
they are the weighted means of the labels ``y in {-1, +1}`` on each side, and picks the stump
with the smallest weighted squared error. The strong classifier is ``F(x) = sum_m h_m(x)``.

Constraints of sec. III-A:

* **quarter constraint**: each quarter of the object window holds ``n / 4`` weak classifiers;
  candidates are restricted to the features centred in quarters that have not reached their
  quota (a feature centred on a dividing line may fill either side; it is counted in the first
  of its quarters that has room);
* **no repeated feature** within one classifier;
* a stump must be *meaningful*: its two outputs have opposite signs (one side votes target, the
  other background). A training set on which no meaningful stump is left gets fewer stumps.

Confidence ``C in [0, 1]`` (the paper's classifier output, sec. II-D): the margin rescaled by
its attainable range, ``C = (F - F_min) / (F_max - F_min)`` with ``F_max = sum max(left,
right)`` and ``F_min = sum min(left, right)``: 1 when every stump votes its most positive
output, 0 when every one votes its most negative.

Adaptation (sec. III-B), :func:`adapt`:

1. training sets: the new positive is added until ``pos_max`` are held, afterwards it replaces
   the positive the previous classifier is most certain about, except the first positive (the
   user's box), which is always kept and weighted higher; the oldest ``ceil(neg_max / 50)``
   negatives are replaced by strong negatives (the candidates the previous classifier scores
   highest);
2. a simplified boosting over the ``n`` old stumps with their thresholds fixed selects the
   best ``n - k`` and refits their outputs ("adapt their confidences");
3. the constrained boosting over the whole pool adds stumps until ``n`` are held (``k = 1``
   normally; more where fewer than ``n - k`` old stumps are still meaningful).

Sample weights at the start of every (re)training: positives share 1/2 and negatives 1/2 (the
Viola-Jones balance), the first positive counts ``first_weight`` times an ordinary positive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from torchtrack.errors import ConfigError, ShapeError

__all__ = [
    "StumpEnsemble",
    "TrainingSet",
    "adapt",
    "add_positives",
    "fit_gentle",
    "replace_negatives",
    "reselect_stumps",
    "sample_weights",
]

_EPS = 1e-12
# Ties in the weighted error (common: with one positive, every feature on which it is the most
# extreme sample separates it perfectly) go to the split in the widest gap: score + TIE * gap,
# gap in units of the feature's standard deviation, capped at _MAX_GAP. TIE * _MAX_GAP is far
# below any real difference of weighted error, so it only orders (near-)ties.
_TIE = 1e-6
_MAX_GAP = 10.0


@dataclass
class StumpEnsemble:
    """``M`` strong classifiers of up to ``n`` stumps each.

    Attributes:
        feature: ``(M, n)`` int64 pool index of each stump (0 in unused slots).
        threshold: ``(M, n)`` float32.
        right: ``(M, n)`` float32 output where ``x >= threshold``.
        left: ``(M, n)`` float32 output where ``x < threshold``.
        quarter: ``(M, n)`` int64 quarter the stump counts towards (-1 in unused slots).
        valid: ``(M, n)`` bool, slot holds a stump.
    """

    feature: torch.Tensor
    threshold: torch.Tensor
    right: torch.Tensor
    left: torch.Tensor
    quarter: torch.Tensor
    valid: torch.Tensor

    @classmethod
    def empty(cls, m: int, n: int, device: torch.device | None = None) -> StumpEnsemble:
        z = torch.zeros((m, n), device=device)
        return cls(
            feature=torch.zeros((m, n), dtype=torch.int64, device=device),
            threshold=z.clone(),
            right=z.clone(),
            left=z.clone(),
            quarter=torch.full((m, n), -1, dtype=torch.int64, device=device),
            valid=torch.zeros((m, n), dtype=torch.bool, device=device),
        )

    @property
    def n_models(self) -> int:
        return int(self.feature.shape[0])

    @property
    def n_slots(self) -> int:
        return int(self.feature.shape[1])

    def select(self, rows: torch.Tensor) -> StumpEnsemble:
        """The models ``rows (R,)`` (copies)."""
        return StumpEnsemble(*(t.index_select(0, rows) for t in self._fields()))

    def _fields(self) -> tuple[torch.Tensor, ...]:
        return (self.feature, self.threshold, self.right, self.left, self.quarter, self.valid)

    @staticmethod
    def cat(parts: list[StumpEnsemble]) -> StumpEnsemble:
        return StumpEnsemble(
            *(torch.cat(ts) for ts in zip(*(p._fields() for p in parts), strict=False))
        )

    def margin(self, x: torch.Tensor, model: torch.Tensor | None = None) -> torch.Tensor:
        """Strong-classifier margin ``F`` of feature values taken at the stumps' features.

        Args:
            x: ``(..., n)`` values of features ``feature[model]`` (slot order).
            model: ``(...)`` int64 model of each row; default: ``x`` is ``(M, ..., n)`` with
                row ``m`` scored by model ``m``.

        Returns:
            ``(...)`` float32.
        """
        thr, r, l_, v = self._params(x, model)
        h = torch.where(x >= thr, r, l_)
        return (h * v).sum(-1)

    def confidence(self, x: torch.Tensor, model: torch.Tensor | None = None) -> torch.Tensor:
        """``C = (F - F_min) / (F_max - F_min)`` in [0, 1] (0 for a model without stumps);
        arguments as in :meth:`margin`."""
        f = self.margin(x, model)
        lo, hi = self.range()
        if model is not None:
            lo, hi = lo[model], hi[model]
        else:
            shape = (-1,) + (1,) * (f.ndim - 1)
            lo, hi = lo.view(shape), hi.view(shape)
        span = hi - lo
        c = (f - lo) / span.clamp_min(_EPS)
        return torch.where(span > _EPS, c.clamp(0.0, 1.0), torch.zeros_like(c))

    def range(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(F_min, F_max)``, each ``(M,)``."""
        v = self.valid.to(self.right.dtype)
        hi = (torch.maximum(self.right, self.left) * v).sum(1)
        lo = (torch.minimum(self.right, self.left) * v).sum(1)
        return lo, hi

    def _params(self, x: torch.Tensor, model: torch.Tensor | None):
        if x.shape[-1] != self.n_slots:
            raise ShapeError(
                f"x must have {self.n_slots} feature values per row, got {x.shape[-1]}"
            )
        ps = (self.threshold, self.right, self.left, self.valid.to(self.right.dtype))
        if model is not None:
            return tuple(p[model] for p in ps)
        if x.shape[0] != self.n_models:
            raise ShapeError(f"x must be (M={self.n_models}, ..., n), got {tuple(x.shape)}")
        shape = (self.n_models,) + (1,) * (x.ndim - 2) + (self.n_slots,)
        return tuple(p.view(shape) for p in ps)

    def features_of(self, x_pool: torch.Tensor) -> torch.Tensor:
        """Pick the stumps' features out of full pool rows ``x_pool (M, S, F)`` -> ``(M, S, n)``."""
        m, s, _ = x_pool.shape
        return x_pool.gather(2, self.feature.unsqueeze(1).expand(m, s, self.n_slots))

    def pool_confidence(self, x_pool: torch.Tensor) -> torch.Tensor:
        """Confidence of model ``m`` on its pool rows ``x_pool (M, S, F)`` -> ``(M, S)``."""
        return self.confidence(self.features_of(x_pool))


@dataclass
class TrainingSet:
    """Training sets of ``M`` models, fixed capacity ``P = pos_max`` positives (slot 0: the first
    positive, always kept) followed by ``Q = neg_max`` negatives.

    Attributes:
        x: ``(M, P + Q, F)`` float32 pool feature values.
        valid: ``(M, P + Q)`` bool, slot holds an example.
        age: ``(M, P + Q)`` int64 frame index the example was added at.
        n_pos: ``P``.
    """

    x: torch.Tensor
    valid: torch.Tensor
    age: torch.Tensor
    n_pos: int

    @property
    def labels(self) -> torch.Tensor:
        """``(P + Q,)`` float32, +1 for positive slots, -1 for negative slots."""
        s = self.x.shape[1]
        y = torch.full((s,), -1.0, device=self.x.device)
        y[: self.n_pos] = 1.0
        return y

    @classmethod
    def create(
        cls,
        x_pos: torch.Tensor,
        x_neg: torch.Tensor,
        pos_max: int = 20,
        neg_max: int = 100,
        frame: int = 0,
    ) -> TrainingSet:
        """Start from one positive ``x_pos (M, F)`` and up to ``neg_max`` negatives
        ``x_neg (M, R, F)`` per model."""
        if x_pos.ndim != 2 or x_neg.ndim != 3 or x_neg.shape[0] != x_pos.shape[0]:
            raise ShapeError(
                f"x_pos must be (M, F) and x_neg (M, R, F), got {tuple(x_pos.shape)} and "
                f"{tuple(x_neg.shape)}"
            )
        if pos_max < 1 or neg_max < 1:
            raise ConfigError(f"pos_max and neg_max must be >= 1, got {pos_max}, {neg_max}")
        m, f = x_pos.shape
        r = min(x_neg.shape[1], neg_max)
        x = torch.zeros((m, pos_max + neg_max, f), dtype=torch.float32, device=x_pos.device)
        valid = torch.zeros((m, pos_max + neg_max), dtype=torch.bool, device=x_pos.device)
        x[:, 0] = x_pos
        valid[:, 0] = True
        x[:, pos_max : pos_max + r] = x_neg[:, :r]
        valid[:, pos_max : pos_max + r] = True
        age = torch.full((m, pos_max + neg_max), frame, dtype=torch.int64, device=x_pos.device)
        return cls(x, valid, age, pos_max)

    def select(self, rows: torch.Tensor) -> TrainingSet:
        return TrainingSet(
            self.x.index_select(0, rows),
            self.valid.index_select(0, rows),
            self.age.index_select(0, rows),
            self.n_pos,
        )

    @staticmethod
    def cat(parts: list[TrainingSet]) -> TrainingSet:
        return TrainingSet(
            torch.cat([p.x for p in parts]),
            torch.cat([p.valid for p in parts]),
            torch.cat([p.age for p in parts]),
            parts[0].n_pos,
        )


def sample_weights(ts: TrainingSet, first_weight: float = 5.0) -> torch.Tensor:
    """Initial boosting weights ``(M, P + Q)``: positives 1/2 in total (the first positive
    ``first_weight`` times an ordinary one), negatives 1/2, empty slots 0."""
    p = ts.n_pos
    w = ts.valid.to(torch.float32)
    w[:, 0] = w[:, 0] * float(first_weight)
    pos = w[:, :p]
    neg = w[:, p:]
    pos = pos / pos.sum(1, keepdim=True).clamp_min(_EPS) * 0.5
    neg = neg / neg.sum(1, keepdim=True).clamp_min(_EPS) * 0.5
    return torch.cat([pos, neg], 1)


def _update_weights(w, y, h):
    """Gentle AdaBoost: ``w *= exp(-y h)``, renormalised per model; ``w, h (M, S)``."""
    w = w * torch.exp(-y * h)
    return w / w.sum(1, keepdim=True).clamp_min(_EPS)


def reselect_stumps(
    ens: StumpEnsemble,
    x: torch.Tensor,
    y: torch.Tensor,
    w: torch.Tensor,
    n_keep: int,
) -> tuple[StumpEnsemble, torch.Tensor]:
    """Simplified boosting over the old stumps (thresholds fixed): pick the best ``n_keep``
    meaningful ones one at a time and refit their outputs (sec. III-B, after Avidan).

    Args:
        ens: the previous classifiers (M models, n slots).
        x: ``(M, S, F)`` pool features of the updated training sets.
        y: ``(S,)`` or ``(M, S)`` labels in {-1, +1}.
        w: ``(M, S)`` initial sample weights (0 for empty slots).
        n_keep: number of stumps to keep (``n - k``).

    Returns:
        ``(kept, w)``: an ensemble with the kept stumps in slots ``0..`` (fewer where fewer are
        meaningful) and the sample weights after them.
    """
    m, n = ens.feature.shape
    dev, wdtype = w.device, w.dtype
    n_keep = min(n_keep, n)
    y = y.expand(m, -1) if y.ndim == 1 else y
    # The selection is sequential and tiny (M x S x n, S = pos_max + neg_max, n = 32): on the
    # host in float64 numpy each of its ~n rounds costs microseconds, where the same loop in
    # torch ops pays the per-op dispatch ~40 times a round (a 10x difference measured).
    right = (ens.features_of(x) >= ens.threshold.unsqueeze(1)).cpu().numpy()  # (M, S, n)
    rf = right.astype(np.float64)
    y_np = y.detach().cpu().numpy().astype(np.float64)
    w_np = w.detach().cpu().numpy().astype(np.float64)
    taken = ~ens.valid.cpu().numpy()
    k = max(n_keep, 1)
    pick = np.zeros((m, k), dtype=np.int64)
    out_r = np.zeros((m, k))
    out_l = np.zeros((m, k))
    found_all = np.zeros((m, k), dtype=bool)
    rows = np.arange(m)
    for r in range(n_keep):
        wy = w_np * y_np
        wr = np.einsum("ms,msn->mn", w_np, rf)  # weight right of each stump's threshold
        sr = np.einsum("ms,msn->mn", wy, rf)  # label sum right
        wl = w_np.sum(1, keepdims=True) - wr
        sl = wy.sum(1, keepdims=True) - sr
        a_r = sr / np.maximum(wr, _EPS)
        a_l = sl / np.maximum(wl, _EPS)
        ok = (a_r * a_l < 0) & (wr > _EPS) & (wl > _EPS) & ~taken
        score = np.where(ok, sr * a_r + sl * a_l, -np.inf)
        best = score.argmax(1)  # (M,)
        found = ok[rows, best]
        if not found.any():
            break
        ar, al = a_r[rows, best], a_l[rows, best]
        pick[:, r], out_r[:, r], out_l[:, r], found_all[:, r] = best, ar, al, found
        taken[rows, best] |= found
        h = al[:, None] + (ar - al)[:, None] * rf[rows, :, best]  # (M, S)
        w_new = w_np * np.exp(-y_np * h)
        w_new /= np.maximum(w_new.sum(1, keepdims=True), _EPS)
        w_np = np.where(found[:, None], w_new, w_np)
    out = StumpEnsemble.empty(m, n, device=dev)
    if n_keep > 0:
        pk = torch.from_numpy(pick[:, :n_keep]).to(dev)
        out.feature[:, :n_keep] = ens.feature.gather(1, pk)
        out.threshold[:, :n_keep] = ens.threshold.gather(1, pk)
        out.quarter[:, :n_keep] = ens.quarter.gather(1, pk)
        out.right[:, :n_keep] = torch.from_numpy(out_r[:, :n_keep]).to(dev, out.right.dtype)
        out.left[:, :n_keep] = torch.from_numpy(out_l[:, :n_keep]).to(dev, out.left.dtype)
        out.valid[:, :n_keep] = torch.from_numpy(found_all[:, :n_keep]).to(dev)
    return _compact(out), torch.from_numpy(w_np).to(dev, wdtype)


def _compact(ens: StumpEnsemble) -> StumpEnsemble:
    """Move valid slots to the front of each model (stable)."""
    if bool(ens.valid.all()):
        return ens
    order = torch.argsort((~ens.valid).to(torch.int8), dim=1, stable=True)
    return StumpEnsemble(*(t.gather(1, order) for t in ens._fields()))


def _sorted_splits(x: torch.Tensor, valid: torch.Tensor):
    """Sort every feature column once: ``x (M, S, F)`` -> ``order (M, F, S)``, candidate
    thresholds ``thr (M, F, S - 1)`` between consecutive distinct values of valid samples and
    ``ok (M, F, S - 1)`` where such a split exists."""
    xv = x.masked_fill(~valid.unsqueeze(2), math.inf).transpose(1, 2).contiguous()
    if xv.device.type == "cpu":
        # numpy's introsort of these short rows (S ~ 120 samples, F ~ 1000 features) is about
        # 6x faster than torch.sort on CPU (one thread: 0.6 against 3.8 ms per frame). The
        # order of ties does not matter: empty slots (+inf) weigh 0 and equal values are never
        # split, so only float rounding of the running sums can differ.
        order = torch.from_numpy(np.argsort(xv.numpy(), axis=2, kind="quicksort"))
        xs = xv.gather(2, order)
    else:
        xs, order = xv.sort(dim=2)
    a, b = xs[:, :, :-1], xs[:, :, 1:]
    ok = (b > a) & torch.isfinite(b)
    mid = (a.double() + b.double()).mul_(0.5).to(x.dtype)
    # Float rounding can put the midpoint on `a`; then `b` itself splits the two.
    thr = torch.where(mid > a, mid, b)
    # Margin of each split: the gap it sits in, in units of the feature's spread over the
    # valid samples (used to break ties between splits of equal weighted error).
    v = valid.unsqueeze(1).to(x.dtype)  # (M, 1, S)
    xt = torch.where(v > 0, x.transpose(1, 2), torch.zeros((), dtype=x.dtype, device=x.device))
    cnt = v.sum(2).clamp_min(1)
    mean = xt.sum(2) / cnt
    var = ((xt - mean.unsqueeze(2)) ** 2 * v).sum(2) / cnt
    spread = var.sqrt().clamp_min(1e-6).unsqueeze(2)
    gap = torch.where(ok, (b - a) / spread, torch.zeros((), dtype=x.dtype, device=x.device))
    return order, thr, ok, gap.clamp_(max=_MAX_GAP)


def fit_gentle(
    x: torch.Tensor,
    y: torch.Tensor,
    w: torch.Tensor,
    valid: torch.Tensor,
    n_stumps: int,
    quarters: torch.Tensor | None = None,
    start: StumpEnsemble | None = None,
) -> tuple[StumpEnsemble, torch.Tensor]:
    """Constrained Gentle AdaBoost over the whole pool, batched over M models.

    Args:
        x: ``(M, S, F)`` pool features of the training samples.
        y: ``(S,)`` or ``(M, S)`` labels in {-1, +1}.
        w: ``(M, S)`` sample weights (0 for empty slots).
        valid: ``(M, S)`` bool, slot holds a sample.
        n_stumps: slots of the result (``n``); with ``quarters`` a multiple of 4.
        quarters: ``(F, 4)`` bool quarter membership of the features (None: no constraint).
        start: stumps already chosen (kept ones, valid slots first); their features are not
            repeated and they count towards the quarter quotas.

    Returns:
        ``(ensemble, w)``: ``n_stumps`` slots (the ``start`` stumps first, then new ones; fewer
        valid ones where no meaningful split is left) and the final sample weights.

    Raises:
        ShapeError: inconsistent shapes. ConfigError: ``n_stumps`` not a multiple of 4 with
        the quarter constraint.
    """
    if x.ndim != 3 or w.shape != x.shape[:2] or valid.shape != x.shape[:2]:
        raise ShapeError(
            f"x must be (M, S, F) with w and valid (M, S), got {tuple(x.shape)}, "
            f"{tuple(w.shape)}, {tuple(valid.shape)}"
        )
    m, s, f = x.shape
    dev = x.device
    if quarters is not None:
        if quarters.shape != (f, 4):
            raise ShapeError(f"quarters must be (F, 4) = ({f}, 4), got {tuple(quarters.shape)}")
        if n_stumps % 4:
            raise ConfigError(f"the quarter constraint needs n divisible by 4, got n={n_stumps}")
        quarters = quarters.to(dev)
    y = (y.expand(m, -1) if y.ndim == 1 else y).to(x.dtype)
    ens = StumpEnsemble.empty(m, n_stumps, device=dev)
    if start is not None:
        k = min(start.n_slots, n_stumps)
        for t_out, t_in in zip(ens._fields(), start._fields(), strict=True):
            t_out[:, :k] = t_in[:, :k]
        ens = _compact(ens)
    # features in use and quarter counts of the start stumps (vectorised bookkeeping)
    feat = torch.where(ens.valid, ens.feature, torch.full_like(ens.feature, f))
    used = torch.zeros((m, f + 1), dtype=torch.bool, device=dev).scatter_(1, feat, True)[:, :f]
    qv = torch.where(ens.valid & (ens.quarter >= 0), ens.quarter, torch.full_like(ens.quarter, 4))
    count = torch.zeros((m, 5), dtype=torch.int64, device=dev).scatter_add_(
        1, qv, torch.ones_like(qv)
    )[:, :4]
    slot = ens.valid.sum(1)  # (M,) next free slot of each model
    n_rounds = n_stumps - int(slot.min()) if m else 0
    if n_rounds <= 0:
        return ens, w
    order, thr, ok, gap = _sorted_splits(x, valid)
    quota = n_stumps // 4
    rows = torch.arange(m, device=dev)
    neg_inf = torch.tensor(-math.inf, dtype=x.dtype, device=dev)
    for _ in range(n_rounds):
        todo = slot < n_stumps
        allowed = ~used
        if quarters is not None:
            room = count < quota  # (M, 4)
            allowed = allowed & (quarters.unsqueeze(0) & room.unsqueeze(1)).any(2)
        wy = w * y
        ws = w.unsqueeze(1).expand(m, f, s).gather(2, order)
        wys = wy.unsqueeze(1).expand(m, f, s).gather(2, order)
        wl = ws.cumsum(2)[:, :, :-1]  # (M, F, S-1): weight left of the split
        sl = wys.cumsum(2)[:, :, :-1]
        wr = w.sum(1).view(m, 1, 1) - wl
        sr = wy.sum(1).view(m, 1, 1) - sl
        a_l = sl / wl.clamp_min(_EPS)
        a_r = sr / wr.clamp_min(_EPS)
        cand = ok & allowed.unsqueeze(2) & (a_l * a_r < 0) & (wl > _EPS) & (wr > _EPS)
        score = torch.where(cand, sl * a_l + sr * a_r + _TIE * gap, neg_inf).view(m, -1)
        best = score.argmax(1)
        found = cand.view(m, -1)[rows, best] & todo
        if not bool(found.any()):
            break
        fi, si = best // (s - 1), best % (s - 1)
        t_best = thr[rows, fi, si]
        ar, al = a_r[rows, fi, si], a_l[rows, fi, si]
        if quarters is not None:
            q = (quarters[fi] & (count < quota)).to(torch.int8).argmax(1)
        else:
            q = torch.zeros(m, dtype=torch.int64, device=dev)
        fr, fs = rows[found], slot[found]
        ens.feature[fr, fs] = fi[found]
        ens.threshold[fr, fs] = t_best[found].to(ens.threshold.dtype)
        ens.right[fr, fs] = ar[found].to(ens.right.dtype)
        ens.left[fr, fs] = al[found].to(ens.left.dtype)
        ens.quarter[fr, fs] = q[found]
        ens.valid[fr, fs] = True
        used[fr, fi[found]] = True
        if quarters is not None:
            count[fr, q[found]] += 1
        slot = slot + found.to(slot.dtype)
        xf = x[rows, :, fi]  # (M, S)
        h = torch.where(xf >= t_best.unsqueeze(1), ar.unsqueeze(1), al.unsqueeze(1))
        w = torch.where(found.unsqueeze(1), _update_weights(w, y, h), w)
    return ens, w


def add_positives(
    ts: TrainingSet, ens: StumpEnsemble, x_pos: torch.Tensor, frame: int, rows: torch.Tensor
) -> TrainingSet:
    """Add one positive per model ``rows (R,)`` (in place): ``x_pos (R, F)``.

    While fewer than ``pos_max`` are held it goes to a free slot; afterwards it replaces the
    positive that ``ens`` (the classifier of t-1) is most certain about; slot 0 (the first
    positive) is never replaced.
    """
    if rows.numel() == 0:
        return ts
    p = ts.n_pos
    sub_valid = ts.valid[rows, 1:p]  # (R, P-1)
    free = ~sub_valid
    has_free = free.any(1)
    first_free = free.to(torch.int8).argmax(1)
    conf = ens.select(rows).pool_confidence(ts.x[rows, 1:p])  # (R, P-1)
    conf = conf.masked_fill(~sub_valid, -math.inf)
    most_certain = conf.argmax(1)
    slot = 1 + torch.where(has_free, first_free, most_certain)
    ts.x[rows, slot] = x_pos.to(ts.x.dtype)
    ts.valid[rows, slot] = True
    ts.age[rows, slot] = frame
    return ts


def replace_negatives(
    ts: TrainingSet, x_neg: torch.Tensor, frame: int, rows: torch.Tensor
) -> TrainingSet:
    """Replace the oldest negatives of models ``rows (R,)`` (empty slots first) by
    ``x_neg (R, r, F)``, in place."""
    if rows.numel() == 0 or x_neg.shape[1] == 0:
        return ts
    p = ts.n_pos
    r = x_neg.shape[1]
    age = ts.age[rows, p:].clone()
    age = age.masked_fill(~ts.valid[rows, p:], -1)  # empty slots are "oldest"
    # oldest first; ties broken by slot index (stable) so replacement is deterministic
    oldest = torch.argsort(age, dim=1, stable=True)[:, :r] + p  # (R, r)
    rr = rows.unsqueeze(1).expand(-1, r)
    ts.x[rr, oldest] = x_neg.to(ts.x.dtype)
    ts.valid[rr, oldest] = True
    ts.age[rr, oldest] = frame
    return ts


def adapt(
    ts: TrainingSet,
    ens: StumpEnsemble,
    x_pos: torch.Tensor,
    x_neg_candidates: torch.Tensor,
    frame: int,
    *,
    quarters: torch.Tensor | None,
    k_new: int = 1,
    n_strong: int | None = None,
    first_weight: float = 5.0,
) -> tuple[TrainingSet, StumpEnsemble]:
    """One adaptation step of ``M`` models (sec. III-B), returning new objects.

    Args:
        ts: training sets of the models (copied, not modified).
        ens: their classifiers from t-1.
        x_pos: ``(M, F)`` the new positive example of each model.
        x_neg_candidates: ``(M, R, F)`` random background examples; the ``n_strong`` the
            previous classifier scores highest become the new negatives.
        frame: current frame index (ages of the new examples).
        quarters: ``(F, 4)`` quarter membership (None: no constraint).
        k_new: stumps re-selected from the whole pool (paper: 1).
        n_strong: negatives replaced per step; default ``ceil(neg_max / 50)``.
        first_weight: relative weight of the first positive.

    Returns:
        ``(training sets, ensemble)`` after the step.
    """
    m = ens.n_models
    neg_max = ts.x.shape[1] - ts.n_pos
    if n_strong is None:
        n_strong = math.ceil(neg_max / 50)
    ts = TrainingSet(ts.x.clone(), ts.valid.clone(), ts.age.clone(), ts.n_pos)
    rows = torch.arange(m, device=ts.x.device)
    add_positives(ts, ens, x_pos, frame, rows)
    if n_strong > 0 and x_neg_candidates.shape[1] > 0:
        conf = ens.pool_confidence(x_neg_candidates)  # (M, R)
        top = conf.topk(min(n_strong, conf.shape[1]), dim=1).indices
        strong = x_neg_candidates.gather(
            1, top.unsqueeze(2).expand(-1, -1, x_neg_candidates.shape[2])
        )
        replace_negatives(ts, strong, frame, rows)
    n = ens.n_slots
    y = ts.labels
    w = sample_weights(ts, first_weight)
    kept, w = reselect_stumps(ens, ts.x, y, w, n - k_new)
    new, _ = fit_gentle(ts.x, y, w, ts.valid, n, quarters, start=kept)
    return ts, new


def replace_rows(ens: StumpEnsemble, rows: torch.Tensor, new: StumpEnsemble) -> StumpEnsemble:
    """A copy of ``ens`` with models ``rows`` replaced by ``new``."""
    out = replace(ens, **{k: getattr(ens, k).clone() for k in ens.__dataclass_fields__})
    for t_out, t_new in zip(out._fields(), new._fields(), strict=True):
        t_out[rows] = t_new
    return out
