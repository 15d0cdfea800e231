"""BoostedTrees: depth-2 trees learn what stumps cannot, against scikit-learn's AdaBoost over
depth-2 trees; the histogram search (with subtraction, trimming and feature sampling) against
a brute-force split search; the soft cascade; serialisation and errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchtrack.errors import ConfigError, ModelFormatError, ShapeError
from torchtrack.learn import BoostedStumps, BoostedTrees, classifier_from_state
from torchtrack.learn.trees import _best_splits, _hist, code_features, quantile_edges


def xor_data(n=1200, seed=0):
    """An exclusive or, off-centre in x1 so that a greedy root split on x0 has some signal
    (a symmetric XOR gives every single split zero gain). Stumps cannot represent it."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 5, generator=g) * 2 - 1
    y = ((x[:, 0] > 0) ^ (x[:, 1] > 0.4)).long()
    return x, y


@pytest.mark.parametrize("variant", ["discrete", "real", "gentle"])
def test_depth_two_trees_learn_xor_like_sklearn(variant):
    from sklearn.ensemble import AdaBoostClassifier
    from sklearn.tree import DecisionTreeClassifier

    x, y = xor_data()
    xt, yt = xor_data(600, seed=1)
    trees = BoostedTrees(n_estimators=30, variant=variant).fit(x, y)
    acc = float((trees.predict(xt) == yt.numpy()).mean())
    sk = AdaBoostClassifier(DecisionTreeClassifier(max_depth=2), n_estimators=30, random_state=0)
    sk_acc = sk.fit(x.numpy(), y.numpy()).score(xt.numpy(), yt.numpy())
    stumps = BoostedStumps(n_estimators=30, variant=variant).fit(x, y)
    st_acc = float((stumps.predict(xt) == yt.numpy()).mean())
    assert acc > 0.95 and acc >= sk_acc - 0.03
    assert st_acc < 0.8  # XOR needs the interaction a depth-2 tree can express


def test_histogram_search_matches_brute_force():
    """The root split of the first tree, and the histograms (also over row subsets), against
    a direct search over every feature and threshold."""
    g = torch.Generator().manual_seed(2)
    x = torch.randn(300, 7, generator=g)
    y = (x[:, 3] + 0.3 * torch.randn(300, generator=g) > 0.2).long()
    edges = quantile_edges(x, 16)
    codes = code_features(x, edges)
    w = torch.rand(300, generator=g, dtype=torch.float64)
    rows = torch.arange(0, 300, 3)
    h = _hist(codes, None, rows, w[rows], 16, chunk=4)
    ref = torch.zeros(7, 16, dtype=torch.float64)
    for f in range(7):
        for i in rows.tolist():
            ref[f, int(codes[f, i])] += w[i]
    torch.testing.assert_close(h, ref)
    H = torch.stack(
        [_hist(codes, None, torch.nonzero(y == c).flatten(), w[y == c], 16, 3) for c in (0, 1)], 1
    )
    f, b = _best_splits(H[:, None], "gentle")
    best, arg = -1.0, None
    for ff in range(7):
        for bb in range(15):
            right = codes[ff].long() > bb
            s = 0.0
            for side in (right, ~right):
                wp = float(w[side & (y == 1)].sum())
                wn = float(w[side & (y == 0)].sum())
                s += (wp - wn) ** 2 / (wp + wn) if wp + wn > 0 else 0.0
            if s > best + 1e-9:
                best, arg = s, (ff, bb)
    assert (int(f[0]), int(b[0])) == arg


def test_trimming_and_feature_fraction_still_learn():
    x, y = xor_data()
    xt, yt = xor_data(600, seed=1)
    clf = BoostedTrees(n_estimators=40, feature_fraction=0.6, weight_trimming=0.05)
    clf.fit_codes(*_codes(x), y, generator=torch.Generator().manual_seed(0))
    assert float((clf.predict(xt) == yt.numpy()).mean()) > 0.93


def _codes(x):
    edges = quantile_edges(x, 64)
    return code_features(x, edges), edges


def test_staged_margins_and_numpy_in_numpy_out():
    x, y = xor_data(400)
    clf = BoostedTrees(n_estimators=12, variant="real").fit(x, y)
    staged = clf.staged_decision_function(x)
    assert staged.shape == (400, 12)
    torch.testing.assert_close(staged[:, -1], clf.decision_function(x), atol=1e-5, rtol=0)
    m = clf.decision_function(x.numpy())
    assert isinstance(m, np.ndarray) and m.shape == (400,)
    lo, hi = clf.margin_range()
    assert lo <= float(staged[:, -1].min()) and float(staged[:, -1].max()) <= hi


@pytest.mark.parametrize("depth", [1, 2, 3])
def test_soft_cascade_keeps_every_positive_above_the_cut_and_scores_passers_fully(depth):
    x, y = xor_data(800)
    clf = BoostedTrees(n_estimators=40, variant="real", max_depth=depth).fit(x, y)
    pos = x[y == 1]
    cut = float(clf.decision_function(pos).quantile(0.2))
    clf.fit_cascade(pos, cut)
    xt, _ = xor_data(2000, seed=3)
    full = clf.decision_function(xt)

    def read(rows, f):
        return xt[rows[:, None], f]

    rows, m = clf.cascade(read, xt.shape[0], stages=(2, 5))
    # passers: the full margin (a running sum against a sum: float32 rounding of margins ~50)
    torch.testing.assert_close(m, full[rows], atol=1e-5, rtol=1e-6)
    kept = set(rows.tolist())
    staged = clf.staged_decision_function(pos)
    # every training positive at or above the cut passes (direct backward pruning) ...
    p_rows, _ = clf.cascade(lambda r, f: pos[r[:, None], f], pos.shape[0])
    assert set(torch.nonzero(staged[:, -1] >= cut).flatten().tolist()) <= set(p_rows.tolist())
    # ... and the cascade rejects windows (most of the negatives here)
    assert len(kept) < xt.shape[0]
    rows_all, m_all = clf.cascade(read, xt.shape[0], reject=False)
    assert rows_all.numel() == xt.shape[0]
    torch.testing.assert_close(m_all, full, atol=1e-5, rtol=1e-6)


@pytest.mark.parametrize("depth", [1, 2, 3])
def test_cascade_reads_in_bounded_runs_of_windows(depth, monkeypatch):
    """Each ``read`` call asks for at most ``_READ_VALUES`` window-features (a step of many
    trees on many windows is read in runs of windows), with the same passers and margins."""
    from torchtrack.learn import trees

    x, y = xor_data(600)
    clf = BoostedTrees(n_estimators=30, variant="real", max_depth=depth).fit(x, y)
    clf.fit_cascade(x[y == 1], float(clf.decision_function(x[y == 1]).quantile(0.2)))
    xt, _ = xor_data(1500, seed=4)
    sizes = []

    def read(rows, f):
        sizes.append(rows.shape[0] * f.shape[-1])
        return xt[rows[:, None], f]

    want = clf.cascade(read, xt.shape[0], stages=(2, 8))
    assert max(sizes) > 40
    monkeypatch.setattr(trees, "_READ_VALUES", 40)
    sizes.clear()
    got = clf.cascade(read, xt.shape[0], stages=(2, 8))
    assert max(sizes) <= 40
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])


@pytest.mark.parametrize("depth", [1, 2, 3])
def test_cascade_steps_that_cannot_reject_share_one_read(depth):
    """A step whose rejection thresholds lie below the lowest running margin any window can
    have (the sum of its trees' smallest leaves) is read together with the next step: fewer
    read calls, the same passers and margins as every step read alone."""
    x, y = xor_data(600)
    clf = BoostedTrees(n_estimators=30, variant="real", max_depth=depth).fit(x, y)
    clf.fit_cascade(x[y == 1], float(clf.decision_function(x[y == 1]).quantile(0.2)))
    xt, _ = xor_data(1500, seed=5)
    calls, widths = [], []

    def read(rows, f):
        calls.append(rows.shape[0])
        widths.append(f.shape[-1])
        return xt[rows[:, None], f] if f.ndim == 2 else xt[rows][:, f]

    # no threshold can reject: every step in one read group, margins of reject=False exactly
    rows, m = clf.cascade(read, xt.shape[0], stages=(1, 4, 8), reject_at_most=-1e6)
    merged = len(calls)
    calls.clear()
    rows_all, m_all = clf.cascade(read, xt.shape[0], stages=(1, 4, 8), reject=False)
    assert merged == max(1, depth - 1)  # one read group: depth 3 reads its third level after
    assert len(calls) > merged
    assert torch.equal(rows, rows_all) and torch.equal(m, m_all)
    # the first trees cannot reject, later ones can: the passers of the running margins
    low = torch.cumsum(clf.leaf_.min(1).values.double(), 0)
    k = 6
    clf.reject_ = clf.reject_.clone()
    clf.reject_[:k] = (low[:k] - 1.0).float()
    calls.clear()
    widths.clear()
    rows, m = clf.cascade(read, xt.shape[0], stages=(1, 4, 8))
    staged = clf.staged_decision_function(xt)
    want = torch.nonzero((staged >= clf.reject_[None]).all(1)).flatten()
    assert torch.equal(rows, want)
    torch.testing.assert_close(m, clf.decision_function(xt)[rows], atol=1e-5, rtol=1e-6)
    # steps of trees [0, 1), [1, 5), [5, 13), [13, 21), [21, 29), [29, 30): the first two
    # cannot reject, so the first read covers 13 trees and there are 4 read groups, not 6
    per_tree = 1 if depth == 1 else 3
    assert calls[0] == xt.shape[0] and widths[0] == 13 * per_tree
    assert len(calls) <= 4 * max(1, depth - 1)


def test_state_round_trip_and_validation():
    x, y = xor_data(300)
    clf = BoostedTrees(n_estimators=6, max_depth=3, variant="gentle").fit(x, y)
    t, meta = clf.to_state()
    again = classifier_from_state(t, meta)
    torch.testing.assert_close(again.decision_function(x), clf.decision_function(x))
    bad = dict(t)
    bad["leaf"] = bad["leaf"][:, :3]
    with pytest.raises(ModelFormatError, match="leaf"):
        classifier_from_state(bad, meta)
    bad = dict(t)
    bad["feature"] = bad["feature"] + 100
    with pytest.raises(ModelFormatError, match="indices outside"):
        classifier_from_state(bad, meta)
    with pytest.raises(ModelFormatError, match="max_depth"):
        classifier_from_state(t, {**meta, "max_depth": 9})


def test_errors():
    x, y = xor_data(100)
    with pytest.raises(ConfigError, match="variant"):
        BoostedTrees(variant="lazy").fit(x, y)
    with pytest.raises(ConfigError, match="max_depth"):
        BoostedTrees(max_depth=0).fit(x, y)
    with pytest.raises(ConfigError, match="feature_fraction"):
        BoostedTrees(feature_fraction=0.0).fit(x, y)
    with pytest.raises(ShapeError, match="uint8"):
        BoostedTrees().fit_codes(torch.zeros(3, 100), torch.zeros(3, 4), y)
    clf = BoostedTrees(n_estimators=3).fit(x, y)
    with pytest.raises(ShapeError, match="5 columns"):
        clf.decision_function(torch.zeros(2, 4))


def test_edges_stay_clear_of_clusters_of_nearly_equal_values():
    """A feature that is 0 on most windows, read as 0, 4e-13 or -1e-15 by different exact
    paths: no edge may fall inside that cluster, so rounding never decides a split."""
    g = torch.Generator().manual_seed(0)
    zeros = torch.randn(800, generator=g) * 1e-12  # the cluster around 0
    rest = torch.rand(200, generator=g) + 0.5
    x = torch.cat((zeros, rest))[:, None]
    edges = quantile_edges(x, 64)[0]
    finite = edges[torch.isfinite(edges)]
    assert bool((finite.abs() > 1e-6).all()), finite[finite.abs() <= 1e-6]
    codes = code_features(x, edges[None])[0]
    assert codes[:800].unique().numel() == 1  # the whole cluster in one bin
    # continuous columns still get fine edges
    y = torch.linspace(0, 1, 1000)[:, None]
    assert int(torch.isfinite(quantile_edges(y, 64)).sum()) == 63


def test_truncated_trees_are_the_running_margin():
    x, y = xor_data(400)
    clf = BoostedTrees(n_estimators=12, variant="real").fit(x, y)
    head = clf.truncated(5)
    torch.testing.assert_close(
        head.decision_function(x), clf.staged_decision_function(x)[:, 4], atol=1e-5, rtol=0
    )
    assert head.n_estimators == 5 and clf.feature_.shape[0] == 12
    for bad in (0, 13, 2.5, True):
        with pytest.raises(ConfigError):
            clf.truncated(bad)


@pytest.mark.parametrize("depth", [1, 2, 3])
def test_tree_outputs_equal_a_node_by_node_descent_in_row_blocks(depth, monkeypatch):
    """The batched descent (rows in blocks, all split tests at once) gives exactly the leaves
    of a per-sample walk down each tree, ties (value == threshold goes right) included."""
    import torchtrack.learn.trees as trees_mod

    g = torch.Generator().manual_seed(0)
    x = torch.randint(0, 5, (300, 6), generator=g).to(torch.float32)
    y = (x[:, 0] + x[:, 3] > 4).long()
    clf = BoostedTrees(n_estimators=7, max_depth=depth).fit(x, y)
    monkeypatch.setattr(trees_mod, "_ROW_CHUNK", 64)  # several blocks and a ragged last one
    got = clf._tree_outputs(x.view(3, 100, 6))
    r, n_int = clf.feature_.shape
    want = torch.empty(300, r)
    for s in range(300):
        for t in range(r):
            node = 0
            while node < n_int:
                go_right = bool(x[s, clf.feature_[t, node]] >= clf.threshold_[t, node])
                node = 2 * node + 1 + int(go_right)
            want[s, t] = clf.leaf_[t, node - n_int]
    assert torch.equal(got.reshape(300, r), want)
    assert torch.equal(clf.decision_function(x), want.sum(-1))
