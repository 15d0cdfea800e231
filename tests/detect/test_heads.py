import numpy as np
import pytest
import torch
from sklearn.calibration import _SigmoidCalibration
from sklearn.ensemble import AdaBoostClassifier
from sklearn.isotonic import IsotonicRegression
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler
from sklearn.svm import SVC, LinearSVC
from sklearn.tree import DecisionTreeClassifier

from torchtrack.detect.heads import (
    IsotonicCalibrator,
    KernelScorer,
    SigmoidCalibrator,
    StumpScorer,
    calibrator_from_estimator,
    scorer_from_estimator,
)
from torchtrack.errors import ModelFormatError, ShapeError


@pytest.fixture(scope="module")
def xy():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(300, 6)).astype(np.float32)
    y = (x[:, 0] + 0.5 * x[:, 3] ** 2 - x[:, 5] + 0.3 * rng.normal(size=300) > 0.4).astype(int)
    return x, y


def test_sklearn_adaboost_stumps_exported_exactly(xy):
    x, y = xy
    ada = AdaBoostClassifier(
        DecisionTreeClassifier(max_depth=1), n_estimators=25, random_state=0
    ).fit(x, y)
    head = scorer_from_estimator(ada)
    ours = head.decision_function(torch.from_numpy(x)).numpy()
    np.testing.assert_allclose(ours, ada.decision_function(x), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("kernel", ["rbf", "linear"])
def test_svm_exported(xy, kernel):
    x, y = xy
    clf = make_pipeline(StandardScaler(), SVC(kernel=kernel, C=2.0, gamma="scale")).fit(x, y)
    head = scorer_from_estimator(clf)
    assert isinstance(head, KernelScorer) and head.kernel == kernel
    np.testing.assert_allclose(
        head.decision_function(torch.from_numpy(x)).numpy(),
        clf.decision_function(x),
        rtol=1e-4,
        atol=1e-4,
    )


def test_linear_svc_exported(xy):
    x, y = xy
    clf = LinearSVC(C=0.5).fit(x, y)
    head = scorer_from_estimator(clf)
    np.testing.assert_allclose(
        head.decision_function(torch.from_numpy(x)).numpy(),
        clf.decision_function(x),
        rtol=1e-4,
        atol=1e-4,
    )


def test_sigmoid_calibrator_matches_sklearn_convention(xy):
    rng = np.random.default_rng(1)
    m = rng.normal(size=200)
    y = (m + rng.normal(size=200) > 0).astype(int)
    sk = _SigmoidCalibration().fit(m, y)
    head = calibrator_from_estimator(sk)
    np.testing.assert_allclose(
        head(torch.from_numpy(m)).numpy(), sk.predict(m), rtol=1e-6, atol=1e-9
    )


def test_isotonic_calibrator_matches_sklearn():
    rng = np.random.default_rng(2)
    m = rng.normal(size=200)
    y = (m + rng.normal(size=200) > 0).astype(float)
    iso = IsotonicRegression(out_of_bounds="clip").fit(m, y)
    head = calibrator_from_estimator(iso)
    q = np.linspace(-4, 4, 97)
    np.testing.assert_allclose(head(torch.from_numpy(q)).numpy(), iso.predict(q), atol=1e-9)


def test_stump_semantics_paper_eq9():
    # m(f) = sum alpha_i h_i(f) with h in {0, 1}: left = 0, right = alpha.
    head = StumpScorer([0, 1], [0.5, -1.0], [0.0, 0.0], [2.0, 3.0])
    x = torch.tensor([[1.0, 0.0], [0.0, -2.0], [0.5, -0.5]])
    assert head.decision_function(x).tolist() == [5.0, 0.0, 3.0]


def test_bad_heads():
    with pytest.raises(ModelFormatError, match="kernel"):
        KernelScorer(np.zeros((1, 2)), [1.0], 0.0, "poly", 1.0, np.zeros(2), np.ones(2))
    with pytest.raises(ModelFormatError, match="disagree"):
        KernelScorer(np.zeros((2, 2)), [1.0], 0.0, "rbf", 1.0, np.zeros(2), np.ones(2))
    with pytest.raises(ModelFormatError, match="finite"):
        SigmoidCalibrator(float("nan"), 0.0)
    with pytest.raises(ModelFormatError, match="non-decreasing"):
        IsotonicCalibrator([0.0, 1.0], [0.9, 0.1])
    with pytest.raises(ModelFormatError, match="shape"):
        StumpScorer([0, 1], [0.0], [0.0, 0.0], [1.0, 1.0])
    head = KernelScorer(np.zeros((1, 2)), [1.0], 0.0, "rbf", 1.0, np.zeros(2), np.ones(2))
    with pytest.raises(ShapeError, match=r"\(M, 2\)"):
        head.decision_function(torch.zeros(3, 5))
    with pytest.raises(TypeError, match="cannot export"):
        scorer_from_estimator(object())
