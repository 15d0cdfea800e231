"""SVMClassifier: torch scoring equals scikit-learn's SVC decision_function."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from sklearn.base import clone
from sklearn.svm import SVC

from torchtrack import errors
from torchtrack.learn import SVMClassifier, classifier_from_state


def _data(n=400, T=10, seed=0):
    rng = np.random.default_rng(seed)
    X = (rng.normal(size=(n, T)) * rng.uniform(0.1, 20, size=T) + rng.normal(size=T) * 5).astype(
        np.float32
    )
    z = (X - X.mean(0)) / X.std(0)
    y = ((z[:, 0] + z[:, 1] ** 2 - z[:, 2] + 0.3 * rng.normal(size=n)) > 0.8).astype(np.int64)
    return X, y


@pytest.mark.parametrize(
    ("kernel", "gamma", "C"), [("rbf", "scale", 1.0), ("rbf", 0.05, 10.0), ("linear", "scale", 0.5)]
)
def test_torch_decision_function_equals_sklearn(kernel, gamma, C):
    X, y = _data()
    clf = SVMClassifier(kernel=kernel, gamma=gamma, C=C).fit(X, y)
    # an independent SVC trained on the same standardised data
    Xd = X.astype(np.float64)
    Z = (Xd - Xd.mean(0)) / Xd.std(0)
    ref = SVC(kernel=kernel, gamma=gamma, C=C).fit(Z, y)
    Xtest, _ = _data(n=300, seed=1)
    Ztest = (Xtest.astype(np.float64) - Xd.mean(0)) / Xd.std(0)
    expected = ref.decision_function(Ztest)
    np.testing.assert_allclose(clf.decision_function(Xtest), expected, atol=1e-5)
    out = clf.decision_function(torch.from_numpy(Xtest).reshape(3, 100, 10))
    assert out.shape == (3, 100) and out.dtype == torch.float32
    np.testing.assert_allclose(out.reshape(-1).numpy(), expected, atol=1e-5, rtol=1e-5)
    # chunked kernel blocks give the same margins
    np.testing.assert_allclose(clf.decision_function(Xtest, chunk_size=7), expected, atol=1e-5)
    np.testing.assert_array_equal(clf.predict(Xtest), ref.predict(Ztest))


def test_state_roundtrip_and_validation():
    X, y = _data()
    clf = SVMClassifier().fit(X, y)
    tensors, meta = clf.to_state()
    back = classifier_from_state(tensors, meta)
    np.testing.assert_allclose(back.decision_function(X), clf.decision_function(X), atol=1e-12)
    with pytest.raises(errors.ModelFormatError, match=r"svm\.dual_coef"):
        classifier_from_state(dict(tensors, dual_coef=tensors["dual_coef"][:-1]), meta)
    with pytest.raises(errors.ModelFormatError, match=r"svm\.support_vectors"):
        classifier_from_state(
            dict(tensors, support_vectors=tensors["support_vectors"].float()), meta
        )
    with pytest.raises(errors.ModelFormatError, match=r"svm\.gamma"):
        classifier_from_state(tensors, dict(meta, gamma=-1.0))
    with pytest.raises(errors.ModelFormatError, match=r"svm\.kernel"):
        classifier_from_state(tensors, dict(meta, kernel="poly"))


def test_contract_and_bad_input():
    X, y = _data(n=100)
    est = SVMClassifier(kernel="linear", C=2.0)
    assert clone(est).get_params()["C"] == 2.0
    with pytest.raises(errors.NotFittedError, match="not fitted"):
        est.decision_function(X)
    with pytest.raises(errors.ConfigError, match="kernel must be one of"):
        SVMClassifier(kernel="poly").fit(X, y)
    Xn = X.copy()
    Xn[5, 1] = np.nan
    with pytest.raises(errors.DataError, match=r"index \(5, 1\)"):
        est.fit(Xn, y)
    assert est.fit(X, y) is est
    with pytest.raises(errors.ShapeError, match="10 columns"):
        est.decision_function(X[:, :4])


def test_bad_sample_weights_are_typed_errors():
    # a wrong length, negative, all-zero or one-class weights reached scikit-learn's ValueError
    X, y = _data(n=60)
    est = SVMClassifier(kernel="linear")
    with pytest.raises(errors.ShapeError, match=r"sample_weight must have shape \(60,\)"):
        est.fit(X, y, sample_weight=np.ones(59))
    with pytest.raises(errors.DataError, match="non-negative with a positive sum"):
        est.fit(X, y, sample_weight=-np.ones(60))
    with pytest.raises(errors.DataError, match="non-negative with a positive sum"):
        est.fit(X, y, sample_weight=np.zeros(60))
    with pytest.raises(errors.DataError, match="both classes"):
        est.fit(X, y, sample_weight=(y == 1).astype(float))
    assert est.fit(X, y, sample_weight=np.ones(60)) is est
