import itertools
import math

import numpy as np
import pytest
import torch

from torchtrack.errors import ConfigError, ShapeError
from torchtrack.features.centre_surround import klein_pool
from torchtrack.learn.online_gentle import (
    StumpEnsemble,
    TrainingSet,
    adapt,
    add_positives,
    fit_gentle,
    replace_negatives,
    reselect_stumps,
    sample_weights,
)


# ------------------------------------------------------------------ slow loop references
def loop_gentle(x, y, w, n, quarters=None):
    """Constrained Gentle AdaBoost, one model, every feature and split in Python loops; ties
    in the weighted error go to the split in the widest gap (in feature standard deviations,
    capped at 10)."""
    _s, f = x.shape
    w = w.copy()
    std = np.maximum(x.astype(np.float64).std(0), 1e-6)
    used, count, stumps = set(), [0, 0, 0, 0], []
    for _ in range(n):
        best = None
        for j in range(f):
            if j in used:
                continue
            qs = [q for q in range(4) if quarters is None or (quarters[j, q] and count[q] < n // 4)]
            if not qs:
                continue
            vals = sorted(set(x[:, j].tolist()))
            for a, b in itertools.pairwise(vals):
                t = np.float32((np.float64(a) + np.float64(b)) / 2)
                t = t if t > a else np.float32(b)
                r = x[:, j] >= t
                wr, wl = w[r].sum(), w[~r].sum()
                ar, al = (w[r] * y[r]).sum() / wr, (w[~r] * y[~r]).sum() / wl
                if ar * al >= 0:
                    continue
                gap = min((np.float64(b) - np.float64(a)) / std[j], 10.0)
                err = (w * (y - np.where(r, ar, al)) ** 2).sum() - 1e-6 * gap
                if best is None or err < best[0] - 1e-12:
                    best = (err, j, t, ar, al, qs[0])
        if best is None:
            break
        _, j, t, ar, al, q = best
        stumps.append((j, float(t), ar, al))
        used.add(j)
        count[q] += 1
        h = np.where(x[:, j] >= t, ar, al)
        w = w * np.exp(-y * h)
        w /= w.sum()
    return stumps


def loop_reselect(x, y, w, old, n_keep):
    """Simplified boosting over old stumps (fixed features and thresholds), loop reference."""
    w = w.copy()
    left = list(range(len(old)))
    kept = []
    for _ in range(n_keep):
        best = None
        for i in left:
            j, t = old[i]
            r = x[:, j] >= t
            wr, wl = w[r].sum(), w[~r].sum()
            if wr <= 0 or wl <= 0:
                continue
            ar, al = (w[r] * y[r]).sum() / wr, (w[~r] * y[~r]).sum() / wl
            if ar * al >= 0:
                continue
            err = (w * (y - np.where(r, ar, al)) ** 2).sum()
            if best is None or err < best[0] - 1e-12:
                best = (err, i, ar, al)
        if best is None:
            break
        _, i, ar, al = best
        left.remove(i)
        j, t = old[i]
        kept.append((j, t, ar, al))
        w = w * np.exp(-y * np.where(x[:, j] >= t, ar, al))
        w /= w.sum()
    return kept


def random_problem(seed, m=2, s=24, f=16):
    g = torch.Generator().manual_seed(seed)
    y = torch.ones(s)
    y[s // 3 :] = -1
    x = torch.randn((m, s, f), generator=g) + 0.8 * y[None, :, None] * torch.rand(
        (m, 1, f), generator=g
    )
    w = torch.rand((m, s), generator=g) + 0.1
    w = w / w.sum(1, keepdim=True)
    q = torch.zeros((f, 4), dtype=torch.bool)
    q[torch.arange(f), torch.arange(f) % 4] = True
    q[0] = True  # a feature on the dividing lines: in every quarter
    return x, y, w, q


def as_list(ens, m):
    v = ens.valid[m]
    return list(
        zip(
            ens.feature[m][v].tolist(),
            ens.threshold[m][v].tolist(),
            ens.right[m][v].tolist(),
            ens.left[m][v].tolist(),
            strict=True,
        )
    )


# ------------------------------------------------------------------ tests
@pytest.mark.parametrize("constrained", [False, True])
def test_fit_gentle_matches_loop_reference(constrained):
    x, y, w, q = random_problem(0)
    n = 8
    ens, _ = fit_gentle(
        x, y, w, torch.ones_like(w, dtype=torch.bool), n, q if constrained else None
    )
    for m in range(2):
        ref = loop_gentle(
            x[m].numpy(), y.numpy(), w[m].double().numpy(), n, q.numpy() if constrained else None
        )
        got = as_list(ens, m)
        assert [r[0] for r in got] == [r[0] for r in ref]
        np.testing.assert_allclose([r[1:] for r in got], [r[1:] for r in ref], rtol=1e-4, atol=1e-5)


def test_ties_go_to_the_widest_margin():
    # one positive; features 0, 1 and 2 all separate it perfectly, feature 2 by the widest gap
    x = torch.tensor([[[1.0, 1.0, 5.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.5, 0.6, 0.2, 0.9]]])
    y = torch.tensor([1.0, -1.0, -1.0])
    w = torch.tensor([[0.5, 0.25, 0.25]])
    ens, _ = fit_gentle(x, y, w, torch.ones_like(w, dtype=torch.bool), 1)
    assert ens.feature[0, 0].item() == 2
    assert ens.threshold[0, 0].item() == pytest.approx(2.6)


def test_quarter_constraint_and_no_repeat_on_the_real_pool():
    pool = klein_pool()
    g = torch.Generator().manual_seed(1)
    x = torch.randn((3, 60, len(pool)), generator=g)
    y = torch.ones(60)
    y[20:] = -1
    x[:, :20] += torch.rand((3, 1, len(pool)), generator=g)
    w = torch.full((3, 60), 1 / 60)
    ens, _ = fit_gentle(x, y, w, torch.ones((3, 60), dtype=torch.bool), 32, pool.quarters())
    quarters = pool.quarters()
    for m in range(3):
        assert bool(ens.valid[m].all())
        feats = ens.feature[m].tolist()
        assert len(set(feats)) == 32  # no repeated feature
        counts = torch.bincount(ens.quarter[m], minlength=4)
        assert counts.tolist() == [8, 8, 8, 8]
        # each stump's assigned quarter contains its feature's centre
        assert bool(quarters[ens.feature[m], ens.quarter[m]].all())
        assert bool((ens.right[m] * ens.left[m] < 0).all())  # meaningful thresholds only


def test_reselect_matches_loop_reference():
    x, y, w, _q = random_problem(2, f=16)
    n = 8
    ens, _ = fit_gentle(x, y, w, torch.ones_like(w, dtype=torch.bool), n, None)
    # change the training data, then keep the best n - 1 of the old stumps
    g = torch.Generator().manual_seed(5)
    x2 = x + 0.5 * torch.randn(x.shape, generator=g)
    kept, _ = reselect_stumps(ens, x2, y, w, n - 1)
    for m in range(2):
        old = [(j, t) for j, t, _, _ in as_list(ens, m)]
        ref = loop_reselect(x2[m].numpy(), y.numpy(), w[m].double().numpy(), old, n - 1)
        got = as_list(kept, m)
        assert [r[0] for r in got] == [r[0] for r in ref]
        np.testing.assert_allclose([r[1:] for r in got], [r[1:] for r in ref], rtol=1e-4, atol=1e-5)


def test_confidence_range_and_extremes():
    ens = StumpEnsemble.empty(1, 4)
    ens.feature[0] = torch.tensor([0, 1, 2, 3])
    ens.threshold[0] = 0.0
    ens.right[0] = torch.tensor([0.9, 0.5, -0.2, 1.0])
    ens.left[0] = torch.tensor([-1.0, -0.5, 0.7, -1.0])
    ens.valid[0] = True
    best = torch.tensor([[[1.0, 1.0, -1.0, 1.0]]])  # every stump votes its larger output
    worst = -best
    assert float(ens.confidence(best)) == pytest.approx(1.0)
    assert float(ens.confidence(worst)) == pytest.approx(0.0)
    mid = ens.confidence(torch.randn((1, 50, 4)))
    assert bool(((mid >= 0) & (mid <= 1)).all())
    assert float(StumpEnsemble.empty(1, 4).confidence(best)) == 0.0  # no stumps: 0
    model = torch.zeros((2, 3), dtype=torch.int64)
    xs = torch.randn((2, 3, 4))
    torch.testing.assert_close(
        ens.confidence(xs, model), ens.confidence(xs.view(1, 6, 4)).view(2, 3)
    )


def test_sample_weights_balance_classes_and_favour_first_positive():
    x_pos = torch.zeros((1, 5))
    ts = TrainingSet.create(x_pos, torch.zeros((1, 7, 5)), pos_max=4, neg_max=10)
    ts.valid[0, 1:3] = True
    w = sample_weights(ts, first_weight=5.0)
    assert float(w[0, :4].sum()) == pytest.approx(0.5)
    assert float(w[0, 4:].sum()) == pytest.approx(0.5)
    assert float(w[0, 0]) == pytest.approx(5 * float(w[0, 1]))
    assert float(w[0, 3]) == 0.0 and float(w[0, 4 + 7]) == 0.0  # empty slots


def _toy_set(pos_max=3, neg_max=4, f=6):
    return TrainingSet.create(torch.zeros((1, f)), torch.ones((1, neg_max, f)), pos_max, neg_max)


def test_positives_fill_then_replace_most_certain_but_never_the_first():
    ts = _toy_set()
    ens = StumpEnsemble.empty(1, 4)
    ens.feature[0, 0] = 0
    ens.threshold[0, 0] = 0.5
    ens.right[0, 0], ens.left[0, 0] = 1.0, -1.0
    ens.valid[0, 0] = True
    rows = torch.tensor([0])
    add_positives(ts, ens, torch.full((1, 6), 0.7), 1, rows)  # slot 1 (free)
    add_positives(ts, ens, torch.full((1, 6), 0.2), 2, rows)  # slot 2 (free)
    assert ts.valid[0, :3].tolist() == [True, True, True]
    # full: the classifier is most certain about slot 1 (0.7 >= 0.5): it is replaced
    add_positives(ts, ens, torch.full((1, 6), 0.1), 3, rows)
    assert ts.x[0, 1, 0].item() == pytest.approx(0.1)
    assert ts.x[0, 2, 0].item() == pytest.approx(0.2)
    assert ts.x[0, 0, 0].item() == 0.0  # the first positive is kept
    assert ts.age[0, 1].item() == 3


def test_oldest_negatives_are_replaced():
    ts = _toy_set(neg_max=4)
    ts.age[0, 3:] = torch.tensor([5, 1, 3, 2])
    replace_negatives(ts, torch.full((1, 2, 6), 9.0), 7, torch.tensor([0]))
    assert ts.age[0, 3:].tolist() == [5, 7, 3, 7]
    assert ts.x[0, 4, 0].item() == 9.0 and ts.x[0, 6, 0].item() == 9.0


def test_adapt_keeps_n_minus_k_old_stumps_and_updates_the_sets():
    pool = klein_pool()
    g = torch.Generator().manual_seed(3)
    f = len(pool)
    x_pos = torch.randn((1, f), generator=g) + 2.0
    x_neg = torch.randn((1, 100, f), generator=g)
    ts = TrainingSet.create(x_pos, x_neg, 20, 100)
    ens, _ = fit_gentle(ts.x, ts.labels, sample_weights(ts), ts.valid, 32, pool.quarters())
    new_pos = x_pos + 0.1 * torch.randn((1, f), generator=g)
    cands = torch.randn((1, 10, f), generator=g)
    ts2, ens2 = adapt(ts, ens, new_pos, cands, 1, quarters=pool.quarters(), k_new=1)
    assert int(ens2.valid.sum()) == 32
    assert len(set(ens2.feature[0].tolist())) == 32
    assert len(set(ens2.feature[0].tolist()) & set(ens.feature[0].tolist())) >= 31
    assert torch.bincount(ens2.quarter[0], minlength=4).tolist() == [8, 8, 8, 8]
    assert int(ts2.valid[0, :20].sum()) == 2  # the new positive was added
    assert int((ts2.age[0, 20:] == 1).sum()) == math.ceil(100 / 50)  # two strong negatives
    # the strong negatives are the candidates the old classifier liked most
    conf = ens.pool_confidence(cands)[0]
    top = set(conf.topk(2).indices.tolist())
    new_rows = ts2.x[0, 20:][ts2.age[0, 20:] == 1]
    chosen = {int((cands[0] - r).abs().sum(1).argmin()) for r in new_rows}
    assert chosen == top
    assert ts.valid[0, :20].sum() == 1  # the input sets are not modified


def test_errors():
    x, y, w, q = random_problem(0)
    valid = torch.ones_like(w, dtype=torch.bool)
    with pytest.raises(ConfigError, match="divisible by 4"):
        fit_gentle(x, y, w, valid, 6, q)
    with pytest.raises(ShapeError, match=r"x must be \(M, S, F\)"):
        fit_gentle(x[0], y, w, valid, 4)
    with pytest.raises(ShapeError, match=r"quarters must be \(F, 4\)"):
        fit_gentle(x, y, w, valid, 4, q[:3])
    with pytest.raises(ShapeError, match="feature values per row"):
        StumpEnsemble.empty(1, 4).confidence(torch.zeros((1, 3)))
    with pytest.raises(ShapeError, match=r"x_pos must be \(M, F\)"):
        TrainingSet.create(torch.zeros(5), torch.zeros((1, 2, 5)))
    with pytest.raises(ConfigError, match="pos_max and neg_max"):
        TrainingSet.create(torch.zeros((1, 5)), torch.zeros((1, 2, 5)), pos_max=0)
