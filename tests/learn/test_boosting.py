"""Boosted stumps and AdaBoost feature selection against slow loop references."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from sklearn.base import clone
from sklearn.exceptions import NotFittedError as SkNotFitted

from torchtrack import errors
from torchtrack.learn import BoostedStumps, classifier_from_state, select_features


def _data(n=80, F=5, seed=0, integer=False):
    rng = np.random.default_rng(seed)
    if integer:
        X = rng.integers(0, 8, size=(n, F)).astype(np.float32)
    else:
        X = rng.normal(size=(n, F)).astype(np.float32)
    y = ((X[:, 0] + 0.7 * X[:, 1] + rng.normal(scale=0.8, size=n)) > 0.2).astype(np.int64)
    if integer:
        y = ((X[:, 0] + X[:, 2] + rng.integers(0, 6, size=n)) > 9).astype(np.int64)
    return X, y


def _reference_boost(X, y, rounds, variant):
    """Plain loop AdaBoost: every feature, every midpoint threshold, float64 (slow, obvious)."""
    n, F = X.shape
    w = np.full(n, 1.0 / n)
    ys = 2.0 * y - 1.0
    stumps = []
    eps = 1.0 / n
    for _ in range(rounds):
        best = None
        for f in range(F):
            v = np.unique(X[:, f])
            for a, b in itertools.pairwise(v):
                t = np.float32((np.float64(a) + np.float64(b)) / 2)
                if not t > a:
                    t = b
                right = X[:, f] >= t
                Lp, Ln = w[~right & (y == 1)].sum(), w[~right & (y == 0)].sum()
                Rp, Rn = w[right & (y == 1)].sum(), w[right & (y == 0)].sum()
                if variant == "discrete":
                    e1, e2 = Lp + Rn, Ln + Rp
                    obj, pol = (e1, 1) if e1 <= e2 else (e2, -1)
                    e = min(max(obj, 1e-10), 1 - 1e-10)
                    al = 0.5 * math.log((1 - e) / e)
                    vals = (-pol * al, pol * al)
                elif variant == "real":
                    obj = math.sqrt(Lp * Ln) + math.sqrt(Rp * Rn)
                    vals = (
                        0.5 * math.log((Lp + eps) / (Ln + eps)),
                        0.5 * math.log((Rp + eps) / (Rn + eps)),
                    )
                else:
                    L, R = Lp + Ln, Rp + Rn
                    obj = -((Lp - Ln) ** 2 / L + (Rp - Rn) ** 2 / R)
                    vals = ((Lp - Ln) / L, (Rp - Rn) / R)
                if best is None or obj < best[0] - 1e-12:
                    best = (obj, f, t, vals)
        _, f, t, (lv, rv) = best
        out = np.where(X[:, f] >= t, rv, lv)
        stumps.append((f, t, lv, rv))
        w = w * np.exp(-ys * out)
        w /= w.sum()
    return stumps


@pytest.mark.parametrize("variant", ["discrete", "real", "gentle"])
def test_boosted_stumps_match_loop_reference(variant):
    X, y = _data()
    ref = _reference_boost(X.astype(np.float64), y, 6, variant)
    clf = BoostedStumps(n_estimators=6, variant=variant).fit(X, y)
    assert clf.feature_.tolist() == [s[0] for s in ref]
    np.testing.assert_allclose(clf.threshold_.numpy(), [s[1] for s in ref], rtol=1e-6)
    np.testing.assert_allclose(clf.left_.numpy(), [s[2] for s in ref], rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(clf.right_.numpy(), [s[3] for s in ref], rtol=1e-4, atol=1e-6)
    margin = sum(np.where(X[:, f] >= t, r, lv) for f, t, lv, r in ref)
    np.testing.assert_allclose(clf.decision_function(X), margin, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("variant", ["discrete", "real", "gentle"])
def test_boosting_learns_held_out(variant):
    X, y = _data(n=600, F=6, seed=1)
    clf = BoostedStumps(n_estimators=30, variant=variant).fit(X[:400], y[:400])
    acc = (clf.predict(X[400:]) == y[400:]).mean()
    assert acc > 0.75  # chance is ~0.5; Bayes rate of this problem is ~0.8


def test_binned_mode_and_inputs_agree():
    X, y = _data(n=300, F=4, integer=True)
    exact = BoostedStumps(10).fit(X, y)
    binned = BoostedStumps(10, max_bins=256).fit(torch.from_numpy(X), torch.from_numpy(y))
    # integer data with 8 values: 256 quantile bins can split between every pair of values
    assert exact.feature_.tolist() == binned.feature_.tolist()
    np.testing.assert_allclose(
        exact.decision_function(X), binned.decision_function(X), rtol=1e-5, atol=1e-5
    )


def test_decision_function_batched_and_devices():
    X, y = _data(n=200)
    clf = BoostedStumps(10).fit(X, y)
    Xt = torch.from_numpy(X).reshape(4, 50, 5)
    out = clf.decision_function(Xt)
    assert out.shape == (4, 50) and out.dtype == torch.float32
    np.testing.assert_allclose(out.reshape(-1).numpy(), clf.decision_function(X), rtol=1e-6)
    assert set(np.unique(clf.predict(X))) <= {0, 1}


def test_labels_minus_one_plus_one_and_classes():
    X, y = _data(n=200)
    clf = BoostedStumps(5).fit(X, 2 * y - 1)
    assert clf.classes_.tolist() == [-1, 1]
    assert set(np.unique(clf.predict(X))) <= {-1, 1}


def test_sklearn_contract():
    est = BoostedStumps(n_estimators=7, variant="gentle")
    assert est.get_params()["n_estimators"] == 7
    est.set_params(variant="real")
    assert clone(est).variant == "real"
    X, y = _data()
    with pytest.raises(errors.NotFittedError, match="not fitted"):
        est.decision_function(X)
    with pytest.raises(SkNotFitted):
        est.to_state()
    assert est.fit(X, y) is est
    assert est.score(X, y) > 0.6


def test_state_roundtrip_and_validation():
    X, y = _data()
    clf = BoostedStumps(8, variant="real").fit(X, y)
    tensors, meta = clf.to_state()
    back = classifier_from_state(tensors, meta)
    np.testing.assert_array_equal(back.decision_function(X), clf.decision_function(X))
    bad = dict(tensors, threshold=tensors["threshold"][:-1])
    with pytest.raises(errors.ModelFormatError, match=r"boosted_stumps\.threshold"):
        classifier_from_state(bad, meta)
    bad = dict(tensors, left=tensors["left"].clone().fill_(float("nan")))
    with pytest.raises(errors.ModelFormatError, match=r"boosted_stumps\.left: contains NaN"):
        classifier_from_state(bad, meta)
    bad = dict(tensors, feature=tensors["feature"] + 100)
    with pytest.raises(errors.ModelFormatError, match=r"boosted_stumps\.feature"):
        classifier_from_state(bad, meta)
    with pytest.raises(errors.ModelFormatError, match=r"boosted_stumps\.variant"):
        classifier_from_state(tensors, dict(meta, variant="lazy"))
    with pytest.raises(errors.ModelFormatError, match="unknown classifier kind 'forest'"):
        classifier_from_state(tensors, dict(meta, kind="forest"))
    with pytest.raises(errors.ModelFormatError, match="missing tensor"):
        classifier_from_state({k: v for k, v in tensors.items() if k != "right"}, meta)


def test_bad_input():
    X, y = _data()
    Xn = X.copy()
    Xn[7, 2] = np.nan
    with pytest.raises(errors.DataError, match=r"index \(7, 2\)"):
        BoostedStumps().fit(Xn, y)
    with pytest.raises(errors.DataError, match="exactly two classes"):
        BoostedStumps().fit(X, np.zeros(len(y)))
    with pytest.raises(errors.ShapeError, match="must have shape"):
        BoostedStumps().fit(X, y[:-1])
    with pytest.raises(errors.ConfigError, match="variant must be one of"):
        BoostedStumps(variant="lazy").fit(X, y)
    clf = BoostedStumps(3).fit(X, y)
    with pytest.raises(errors.ShapeError, match="5 columns"):
        clf.decision_function(X[:, :3])


@pytest.mark.parametrize(
    ("params", "match"),
    [
        ({"n_estimators": 2.5}, r"n_estimators must be a positive integer, got 2\.5"),
        ({"n_estimators": True}, r"n_estimators must be a positive integer, got True"),
        ({"n_estimators": "40"}, r"n_estimators must be a positive integer, got '40'"),
        ({"n_estimators": 0}, r"n_estimators must be a positive integer, got 0"),
        ({"max_bins": 2.5}, r"max_bins must be None or an integer in \[2, 256\], got 2\.5"),
        ({"max_bins": 257}, r"max_bins must be None or an integer in \[2, 256\], got 257"),
        ({"chunk_size": 0}, r"chunk_size must be None or a positive integer, got 0"),
    ],
)
def test_parameters_are_validated_in_fit(params, match):
    # n_estimators=2.5 fitted 2 rounds without complaint (int() of the parameter)
    X, y = _data()
    clf = BoostedStumps(**params)  # __init__ only stores (scikit-learn's contract)
    with pytest.raises(errors.ConfigError, match=match):
        clf.fit(X, y)
    assert len(BoostedStumps(np.int64(2), max_bins=np.int32(16)).fit(X, y).feature_) <= 2


def test_perfect_stump_stops_early():
    X = np.array([[0.0], [1.0], [2.0], [3.0]], dtype=np.float32)
    y = np.array([0, 0, 1, 1])
    clf = BoostedStumps(10).fit(X, y)
    assert len(clf.feature_) == 1 and clf.threshold_.item() == pytest.approx(1.5)
    assert (clf.predict(X) == y).all()


# ------------------------------------------------------------------------ selection


def _reference_selection(X, y, n_features):
    """Loop discrete AdaBoost on integer data, balanced initial weights, all thresholds."""
    _n, F = X.shape
    w = np.where(y == 1, 0.5 / (y == 1).sum(), 0.5 / (y == 0).sum())
    ys = 2.0 * y - 1
    picked = []
    while len(picked) < n_features:
        best = None
        for f in range(F):
            for t in np.unique(X[:, f])[1:]:
                right = X[:, f] >= t
                e = w[(right & (y == 0)) | (~right & (y == 1))].sum()
                for err, pol in ((e, 1), (1 - e, -1)):
                    if best is None or err < best[0] - 1e-12:
                        best = (err, f, t, pol)
        err, f, t, pol = best
        if f not in picked:
            picked.append(f)
        h = np.where(X[:, f] >= t, pol, -pol)
        e = min(max(err, 1e-10), 1 - 1e-10)
        w = w * np.exp(-0.5 * math.log((1 - e) / e) * ys * h)
        w /= w.sum()
    return picked


def test_select_features_matches_loop_reference():
    X, y = _data(n=400, F=12, seed=3, integer=True)
    ref = _reference_selection(X, y, 6)
    got = select_features(X, y, 6)
    assert got.dtype == torch.int64
    assert got.tolist() == ref
    # chunking and input type do not change the result
    assert select_features(torch.from_numpy(X), y, 6, chunk_size=5).tolist() == ref


def test_select_features_finds_informative_columns():
    g = torch.Generator().manual_seed(0)
    X = torch.randn(1000, 300, generator=g)
    y = ((X[:, 11] - X[:, 222] + 0.3 * torch.randn(1000, generator=g)) > 0).long()
    sel = select_features(X, y, 5)
    assert set(sel[:2].tolist()) == {11, 222}
    assert len(set(sel.tolist())) == 5


def test_select_features_after_perfect_stump_still_returns_distinct():
    X = np.zeros((20, 4), dtype=np.float32)
    X[:, 0] = np.arange(20)
    X[:, 1:] = np.random.default_rng(0).normal(size=(20, 3))
    y = (X[:, 0] >= 10).astype(int)
    sel = select_features(X, y, 4)
    assert sel[0] == 0 and sorted(sel.tolist()) == [0, 1, 2, 3]


def test_select_features_bad_input():
    X, y = _data()
    with pytest.raises(errors.ConfigError, match="n_features must be in"):
        select_features(X, y, 6)
    Xn = X.copy()
    Xn[3, 4] = np.inf
    with pytest.raises(errors.DataError, match="row 3, column 4"):
        select_features(Xn, y, 2)
    with pytest.raises(errors.DataError, match="exactly two classes"):
        select_features(X, np.ones(len(y)), 2)
    with pytest.raises(errors.ShapeError, match="2-D"):
        select_features(X[0], y, 2)


def test_weights_on_one_class_only_are_refused():
    """Sample weights of 0 on every negative boosted a constant classifier (the same margin for
    every sample) without a word, in BoostedStumps, BoostedTrees and select_features alike, as
    SVMClassifier and the calibrators refuse them."""
    from torchtrack.learn.trees import BoostedTrees

    g = torch.Generator().manual_seed(0)
    X = torch.randn(60, 3, generator=g)
    y = (X[:, 0] > 0).long()
    w = y.double()  # positives only
    for fit in (
        lambda: BoostedStumps(n_estimators=3).fit(X, y, sample_weight=w),
        lambda: BoostedTrees(n_estimators=3).fit(X, y, sample_weight=w),
        lambda: select_features(X, y, 2, sample_weight=w),
    ):
        with pytest.raises(errors.DataError, match="positive weights for class 'positive' only"):
            fit()
