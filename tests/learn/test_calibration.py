"""Platt / isotonic calibration against scikit-learn, plus properties and bad input."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from sklearn.base import BaseEstimator, ClassifierMixin
from sklearn.calibration import CalibratedClassifierCV, _sigmoid_calibration
from sklearn.frozen import FrozenEstimator
from sklearn.isotonic import IsotonicRegression
from sklearn.metrics import brier_score_loss, log_loss

from torchtrack import errors
from torchtrack.learn import (
    BoostedStumps,
    IsotonicCalibrator,
    PlattCalibrator,
    SVMClassifier,
    calibration_metrics,
    calibrator_from_dict,
    calibrator_from_state,
    fit_calibrated,
    prior_weights,
    reliability_bins,
    reliability_diagram,
    with_prior,
)


def _scores(n=500, seed=0, scale=1.0, pos_rate=0.3):
    rng = np.random.default_rng(seed)
    y = (rng.random(n) < pos_rate).astype(np.int64)
    s = (rng.normal(size=n) + 1.7 * y - 0.4) * scale
    return s, y


class _Identity(ClassifierMixin, BaseEstimator):
    """A 'classifier' whose decision_function is its single input column (precomputed scores)."""

    def fit(self, X, y):
        self.classes_ = np.unique(y)
        return self

    def decision_function(self, X):
        return np.asarray(X)[:, 0]

    def predict(self, X):
        return self.classes_[(self.decision_function(X) > 0).astype(int)]


@pytest.mark.parametrize(
    ("n", "seed", "scale", "pos_rate"),
    [(500, 0, 1.0, 0.3), (200, 1, 80.0, 0.5), (1000, 2, 0.02, 0.1), (60, 3, 5.0, 0.8)],
)
def test_platt_matches_sklearn_sigmoid(n, seed, scale, pos_rate):
    s, y = _scores(n, seed, scale, pos_rate)
    cal = PlattCalibrator().fit(s, y)
    a, b = _sigmoid_calibration(s, y)
    # sklearn's sign convention: P = expit(-(a s + b)) = 1 / (1 + exp(a s + b)), same as ours
    assert abs(cal.a_ - a) < 1e-3 * max(1.0, abs(a)) and abs(cal.b_ - b) < 1e-3
    # the public route: CalibratedClassifierCV around a frozen score "classifier"
    ccv = CalibratedClassifierCV(FrozenEstimator(_Identity().fit(s[:, None], y)), method="sigmoid")
    ccv.fit(s[:, None], y)
    sk = ccv.calibrated_classifiers_[0].calibrators[0]
    assert abs(cal.a_ - sk.a_) < 1e-3 * max(1.0, abs(sk.a_)) and abs(cal.b_ - sk.b_) < 1e-3
    np.testing.assert_allclose(cal.predict_proba(s), ccv.predict_proba(s[:, None])[:, 1], atol=1e-4)


def test_platt_sample_weight_matches_sklearn():
    s, y = _scores(300, 5)
    sw = np.random.default_rng(5).uniform(0.2, 3.0, size=s.size)
    cal = PlattCalibrator().fit(s, y, sample_weight=sw)
    a, b = _sigmoid_calibration(s, y, sample_weight=sw)
    assert abs(cal.a_ - a) < 1e-3 and abs(cal.b_ - b) < 1e-3


@pytest.mark.parametrize("cls", [PlattCalibrator, IsotonicCalibrator])
def test_bad_sample_weights_are_refused_by_both_calibrators(cls):
    """The isotonic fit passed its weights to scikit-learn unchecked: one weight short raised
    sklearn's ValueError 'inconsistent numbers of samples', negative weights 'Found array with
    0 sample(s)'; it now refuses them as the Platt fit does."""
    s, y = _scores(100, 3)
    with pytest.raises(errors.ShapeError, match=r"sample_weight must have shape \(100,\)"):
        cls().fit(s, y, sample_weight=np.ones(99))
    with pytest.raises(errors.DataError, match="sample_weight must be non-negative"):
        cls().fit(s, y, sample_weight=-np.ones(100))
    with pytest.raises(errors.DataError, match="with a positive sum"):
        cls().fit(s, y, sample_weight=np.zeros(100))
    cls().fit(s, y, sample_weight=np.ones(100))


@pytest.mark.parametrize("cls", [PlattCalibrator, IsotonicCalibrator])
def test_weights_that_zero_one_class_out_are_refused(cls):
    """Weights 0 on every negative fitted a one-class map without a word (isotonic: 1 for
    every score; Platt: A = 0 with only a warning), as SVMClassifier already refused."""
    s, y = _scores(100, 3)
    with pytest.raises(errors.DataError, match="positive weight to samples of both classes"):
        cls().fit(s, y, sample_weight=np.asarray(y, dtype=np.float64))


@pytest.mark.parametrize("cls", [PlattCalibrator, IsotonicCalibrator])
def test_complex_scores_are_refused(cls):
    """Complex scores lost their imaginary part with only torch's UserWarning."""
    s, y = _scores(100, 3)
    with pytest.raises(errors.ShapeError, match="scores must hold real numbers"):
        cls().fit(torch.as_tensor(s).to(torch.complex64), y)


def test_flipping_labels_gives_one_minus_p():
    s, y = _scores(400, 7)
    p = PlattCalibrator().fit(s, y).predict_proba(s)
    q = PlattCalibrator().fit(s, 1 - y).predict_proba(s)
    np.testing.assert_allclose(q, 1 - p, atol=1e-6)


def test_scaling_scores_keeps_probabilities():
    s, y = _scores(400, 8)
    p = PlattCalibrator().fit(s, y).predict_proba(s)
    q = PlattCalibrator().fit(s * 1000.0, y).predict_proba(s * 1000.0)
    np.testing.assert_allclose(q, p, atol=1e-7)


def test_torch_input_and_shapes():
    s, y = _scores()
    cal = PlattCalibrator().fit(torch.from_numpy(s), torch.from_numpy(y))
    grid = torch.linspace(-3, 3, 12, dtype=torch.float32).reshape(3, 4)
    p = cal.predict_proba(grid)
    assert p.shape == (3, 4) and p.dtype == torch.float32
    assert cal.a_ < 0 and bool((p.flatten().diff() > 0).all())  # higher score, higher P


def test_all_identical_scores_give_base_rate():
    y = np.array([1, 0, 0, 0, 1, 0, 0, 0, 0, 0])
    with pytest.warns(UserWarning, match="identical"):
        cal = PlattCalibrator().fit(np.full(10, 2.5), y)
    n1, n0 = 2, 8
    expected = (n1 * (n1 + 1) / (n1 + 2) + n0 / (n0 + 2)) / 10
    assert cal.a_ == 0.0
    np.testing.assert_allclose(cal.predict_proba(np.array([-5.0, 2.5, 9.0])), expected)


def test_platt_fit_that_cannot_leave_zero_warns():
    # the same ranking as a good fit, at magnitudes whose squares overflow: Newton cannot
    # take a step from A = 0 (was silent: every probability the base rate)
    rng = np.random.default_rng(0)
    y = (rng.random(100) < 0.4).astype(int)
    s = rng.normal(size=100) + 2.0 * y
    with pytest.warns(UserWarning, match="did not move from A = 0.*isotonic"):
        cal = PlattCalibrator().fit(s * 1e300, y)
    assert cal.a_ == 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert PlattCalibrator().fit(s * 1e150, y).a_ < 0  # large but fine: no warning
    # magnitudes whose squares underflow: the fit stopped at A ~ 1e-287, as blind to the scores
    # (was silent; the message said "overflows" where A stayed exactly 0)
    with pytest.warns(UserWarning, match="is too small for .*underflow.* the fit"):
        cal = PlattCalibrator().fit(s * 1e-300, y)
    assert abs(cal.a_) * 1e-300 < 1e-9


@pytest.mark.parametrize(
    ("params", "match"),
    [
        ({"tol": -1}, r"tol must be a finite number >= 0 \(gradient tolerance\), got -1"),
        ({"tol": float("nan")}, r"tol must be a finite number >= 0 .*got nan"),
        ({"tol": "1e-10"}, r"tol must be a finite number >= 0 .*got '1e-10'"),
        ({"max_iter": 0}, r"max_iter must be a positive integer \(Newton iterations\), got 0"),
        ({"max_iter": 2.5}, r"max_iter must be a positive integer .*got 2\.5"),
        ({"max_iter": True}, r"max_iter must be a positive integer .*got True"),
    ],
)
def test_platt_parameters_are_validated_in_fit(params, match):
    # tol=-1 was accepted and max_iter=0 only warned that A stayed 0
    s, y = _scores()
    cal = PlattCalibrator(**params)  # __init__ only stores (scikit-learn's contract)
    with pytest.raises(errors.ConfigError, match=match):
        cal.fit(s, y)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert PlattCalibrator(max_iter=np.int64(50), tol=0).fit(s, y).a_ < 0


def test_isotonic_scores_whose_range_overflows_are_refused():
    # +-1.8e308: the fit's interpolation gave NaN probabilities ("p contains 99 non-finite")
    y = np.array([0, 1] * 10)
    s = np.where(y == 1, 1.7e308, -1.7e308)
    with pytest.raises(errors.DataError, match="a range beyond the float range: rescale them"):
        IsotonicCalibrator().fit(s, y)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("cls", [PlattCalibrator, IsotonicCalibrator])
def test_non_finite_scores_rejected_with_index(bad, cls):
    s, y = _scores(50)
    s[13] = bad
    with pytest.raises(errors.DataError, match="index 13"):
        cls().fit(s, y)


@pytest.mark.parametrize("cls", [PlattCalibrator, IsotonicCalibrator])
def test_single_class_and_bad_shapes_rejected(cls):
    s, _ = _scores(50)
    with pytest.raises(errors.DataError, match="exactly two classes"):
        cls().fit(s, np.ones(50))
    with pytest.raises(errors.ShapeError, match="must have shape"):
        cls().fit(s, np.ones(49))
    with pytest.raises(errors.NotFittedError, match="not fitted"):
        cls().predict_proba(s)
    # scores that are not numbers: numpy's ValueError / TypeError escaped from predict_proba
    cal = cls().fit(s, (s > 0).astype(int))
    for bad in (["a", "b"], [[1.0], [2.0, 3.0]], {"s": 1.0}):
        with pytest.raises(errors.DataError, match="scores must be numbers, got"):
            cal.predict_proba(bad)


def test_isotonic_matches_sklearn_and_roundtrips():
    s, y = _scores(400, 9)
    cal = IsotonicCalibrator().fit(s, y)
    ref = IsotonicRegression(y_min=0, y_max=1, out_of_bounds="clip").fit(s, y)
    grid = np.linspace(s.min() - 2, s.max() + 2, 2001)
    np.testing.assert_allclose(cal.predict_proba(grid), ref.predict(grid), atol=1e-12)
    back = calibrator_from_state(*cal.to_state())
    np.testing.assert_allclose(
        back.predict_proba(torch.from_numpy(grid)).numpy(), ref.predict(grid)
    )


def test_calibrator_state_validation():
    s, y = _scores()
    t, m = PlattCalibrator().fit(s, y).to_state()
    back = calibrator_from_state(t, m)
    assert back.predict_proba(np.array([0.3]))[0] == pytest.approx(
        PlattCalibrator().fit(s, y).predict_proba(np.array([0.3]))[0]
    )
    with pytest.raises(errors.ModelFormatError, match=r"platt\.a: missing"):
        calibrator_from_state(t, {"kind": "platt", "b": 1.0})
    with pytest.raises(errors.ModelFormatError, match=r"platt\.b: not finite"):
        calibrator_from_state(t, {"kind": "platt", "a": 1.0, "b": float("nan")})
    with pytest.raises(errors.ModelFormatError, match="unknown calibrator kind 'beta'"):
        calibrator_from_state(t, {"kind": "beta"})
    # a JSON integer beyond the float range (json reads 1e400 as inf, 10**400 as an int):
    # float() of it escaped as an OverflowError, from the metadata and from a tensor
    with pytest.raises(errors.ModelFormatError, match=r"platt\.a: not finite \(an integer beyond"):
        calibrator_from_dict({"calibrator": {"kind": "platt", "a": -(10**400), "b": 0}})
    big = {"dtype": "float64", "data": [0.0, 10**400]}
    with pytest.raises(errors.ModelFormatError, match="tensor 'x': int too large"):
        calibrator_from_dict({"calibrator": {"kind": "isotonic"}, "tensors": {"x": big}})
    ti, mi = IsotonicCalibrator().fit(s, y).to_state()
    with pytest.raises(errors.ModelFormatError, match=r"isotonic\.x: thresholds not sorted"):
        calibrator_from_state({"x": ti["x"].flip(0), "y": ti["y"]}, mi)
    with pytest.raises(errors.ModelFormatError, match=r"isotonic\.y"):
        calibrator_from_state({"x": ti["x"], "y": ti["y"][:-1]}, mi)


def _ece_loop(p, y, n_bins):
    total = 0.0
    for b in range(n_bins):
        lo, hi = b / n_bins, (b + 1) / n_bins
        m = [
            (pi, yi)
            for pi, yi in zip(p, y, strict=True)
            if lo <= pi < hi or (b == n_bins - 1 and pi == 1.0)
        ]
        if m:
            total += len(m) / len(p) * abs(np.mean([a for a, _ in m]) - np.mean([c for _, c in m]))
    return total


def test_metrics_against_references():
    s, y = _scores(300, 11)
    p = PlattCalibrator().fit(s, y).predict_proba(s)
    p[0] = 1.0
    met = calibration_metrics(p, y)
    assert met["nll"] == pytest.approx(log_loss(y, np.clip(p, 1e-15, 1 - 1e-15)), rel=1e-9)
    assert met["brier"] == pytest.approx(brier_score_loss(y, p), rel=1e-9)
    assert met["ece"] == pytest.approx(_ece_loop(p, y, 15), abs=1e-12)
    assert calibration_metrics(p, y, n_bins=7)["ece"] == pytest.approx(
        _ece_loop(p, y, 7), abs=1e-12
    )
    with pytest.raises(errors.DataError, match=r"p\[4\]"):
        calibration_metrics(np.where(np.arange(300) == 4, 1.5, p), y)
    with pytest.raises(errors.DataError, match="only 0 and 1"):
        calibration_metrics(p, y * 2)


def test_reliability_bins_against_a_loop():
    s, y = _scores(300, 11)
    p = PlattCalibrator().fit(s, y).predict_proba(s)
    p[0] = 1.0
    rows = reliability_bins(p, y, n_bins=7)
    assert sum(r["count"] for r in rows) == 300
    assert sum(r["ece_share"] for r in rows) == pytest.approx(_ece_loop(p, y, 7), abs=1e-12)
    for r in rows:
        b = round(r["lo"] * 7)
        m = (p >= r["lo"]) & (p < r["hi"]) | ((b == 6) & (p == 1.0))
        assert r["count"] == int(m.sum()) > 0
        assert r["mean_p"] == pytest.approx(p[m].mean(), rel=1e-12)
        assert r["frequency"] == pytest.approx(y[m].mean(), rel=1e-12)
    with pytest.raises(errors.DataError, match="only 0 and 1"):
        reliability_bins(p, y * 2)


def test_bin_counts_are_bounded(tmp_path):
    """2e9 bins tried a 16 GB allocation (RuntimeError), 1e20 overflowed (OverflowError)."""
    s, y = _scores(50, 3)
    p = 1 / (1 + np.exp(-s))
    assert set(calibration_metrics(p, y, n_bins=1000)) == {"nll", "brier", "ece"}
    # not integers: 15.0, '15', True, None were TypeErrors from torch.bincount or int(), NaN a
    # ValueError; reliability_diagram sized np.linspace by n_bins before any check (16 GB)
    for n in (0, 1001, 2_000_000_000, 10**20, 15.0, "15", True, None, float("nan")):
        with pytest.raises(errors.ConfigError, match=r"n_bins must be an integer in \[1, 1000\]"):
            calibration_metrics(p, y, n_bins=n)
        with pytest.raises(errors.ConfigError, match="n_bins must be"):
            reliability_bins(p, y, n_bins=n)
        with pytest.raises(errors.ConfigError, match="n_bins must be"):
            reliability_diagram(p, y, tmp_path / "r.png", n_bins=n)
    assert not (tmp_path / "r.png").exists()


def test_reliability_diagram_writes_png(tmp_path):
    s, y = _scores(300)
    raw = 1 / (1 + np.exp(-s))
    p = PlattCalibrator().fit(s, y).predict_proba(s)
    out = reliability_diagram({"raw": raw, "platt": p}, y, tmp_path / "rel.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [f.name for f in tmp_path.iterdir()] == ["rel.png"]


def test_fit_calibrated_holdout_and_cv():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(300, 4)).astype(np.float32)
    y = (X[:, 0] + 0.5 * rng.normal(size=300) > 0).astype(int)
    g = torch.Generator().manual_seed(0)
    fit = fit_calibrated(BoostedStumps(10), X, y, generator=g)
    assert len(set(fit.train_index.tolist()) & set(fit.calib_index.tolist())) == 0
    assert len(fit.calib_index) == round(0.3 * (y == 1).sum()) + round(0.3 * (y == 0).sum())
    np.testing.assert_array_equal(fit.labels.numpy(), y[fit.calib_index.numpy()])
    assert fit.calibrator.a_ < 0  # higher margin -> higher probability
    again = fit_calibrated(BoostedStumps(10), X, y, generator=torch.Generator().manual_seed(0))
    assert torch.equal(again.calib_index, fit.calib_index)
    cv = fit_calibrated(SVMClassifier(kernel="linear"), X, y, cv=3, method="isotonic")
    assert isinstance(cv.calibrator, IsotonicCalibrator) and cv.scores.shape == (300,)
    with pytest.raises(errors.ConfigError, match="holdout must be in"):
        fit_calibrated(BoostedStumps(3), X, y, holdout=1.2)
    with pytest.raises(errors.ConfigError, match="cv must be >= 2"):
        fit_calibrated(BoostedStumps(3), X, y, cv=1)
    # cv=2.5 ran 2 folds without a word, cv 'x' / inf escaped as ValueError / OverflowError,
    # holdout 'x' / None as ValueError / TypeError
    for cv in (2.5, "x", float("inf"), True):
        with pytest.raises(errors.ConfigError, match=r"cv must be >= 2 folds \(an integer\)"):
            fit_calibrated(BoostedStumps(3), X, y, cv=cv)
    # X as nested lists: X.shape was an AttributeError; ragged ones are a DataError
    fit = fit_calibrated(
        BoostedStumps(3), X.tolist(), y, generator=torch.Generator().manual_seed(0)
    )
    assert fit.scores.shape == (len(fit.calib_index),)
    with pytest.raises(errors.DataError, match="X must be array-like"):
        fit_calibrated(BoostedStumps(3), [[1.0, 2.0], [3.0]] * 50, y[:100])
    for holdout in ("x", None, float("nan")):
        with pytest.raises(errors.ConfigError, match="holdout must be in"):
            fit_calibrated(BoostedStumps(3), X, y, holdout=holdout)
    with pytest.raises(errors.ConfigError, match="calibration method must be one of"):
        fit_calibrated(BoostedStumps(3), X, y, method="beta")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit_calibrated(BoostedStumps(3), X, y, cv=2)


def _two_gaussians(n_pos, n_neg, seed):
    rng = np.random.default_rng(seed)
    s = np.concatenate([rng.normal(1.5, 1.0, n_pos), rng.normal(-1.5, 1.0, n_neg)])
    return s, np.r_[np.ones(n_pos), np.zeros(n_neg)].astype(int)


@pytest.mark.parametrize("cls", [PlattCalibrator, IsotonicCalibrator])
def test_with_prior_calibrates_at_the_new_share(cls):
    """Fitted on balanced scores, moved to 3%: calibrated on a test set of 3% positives from
    the same two score distributions, where the unmoved map is not; the ranking stays."""
    s, y = _two_gaussians(3000, 3000, 0)
    cal = cls().fit(s, y)
    moved = with_prior(cal, 0.03, 0.5)
    ts, ty = _two_gaussians(300, 9700, 1)
    before = calibration_metrics(cal.predict_proba(ts), ty)["ece"]
    after = calibration_metrics(moved.predict_proba(ts), ty)["ece"]
    assert before > 0.05 and after < 0.01
    p0, p1 = cal.predict_proba(ts), moved.predict_proba(ts)
    assert np.all(np.diff(p1[np.argsort(ts)]) >= -1e-12)  # still monotone in the score
    assert np.all(p1 <= p0 + 1e-12)  # a lower share lowers every probability
    # estimated from the balanced data alone, weighted to the new share: close to the test's
    w = prior_weights(y, 0.03)
    est = calibration_metrics(moved.predict_proba(s), y, sample_weight=w)["ece"]
    assert est == pytest.approx(after, abs=0.01)
    same = with_prior(cal, 0.5, 0.5).predict_proba(ts)
    np.testing.assert_allclose(same, p0, rtol=0, atol=1e-12)  # no change of share: the same


def test_with_prior_platt_moves_b_and_isotonic_keeps_0_and_1():
    s, y = _two_gaussians(200, 600, 2)
    cal = PlattCalibrator().fit(s, y)
    a0, b0 = cal.a_, cal.b_
    moved = with_prior(cal, 0.1, 0.25)
    shift = np.log(0.1 / 0.9) - np.log(0.25 / 0.75)
    assert moved is not cal and (cal.a_, cal.b_) == (a0, b0)  # the original is untouched
    assert moved.a_ == a0 and moved.b_ == pytest.approx(b0 - shift, abs=1e-12)
    iso = IsotonicCalibrator().fit(s, y)
    mi = with_prior(iso, 0.1, 0.25)
    y0, y1 = iso.y_thresholds_, mi.y_thresholds_
    ends = (y0 == 0) | (y0 == 1)
    assert bool(ends.any()) and torch.equal(y1[ends], y0[ends])
    inner = ~ends
    expect = torch.sigmoid(torch.logit(y0[inner]) + shift)
    torch.testing.assert_close(y1[inner], expect, rtol=0, atol=1e-12)
    assert torch.equal(mi.x_thresholds_, iso.x_thresholds_)
    state, meta = mi.to_state()
    assert torch.equal(calibrator_from_state(state, meta).y_thresholds_, y1)


@pytest.mark.parametrize("bad", [0, 1, 0.0, 1.5, -0.2, float("nan"), "0.1", None, True])
def test_with_prior_and_weights_refuse_bad_shares(bad):
    s, y = _two_gaussians(50, 50, 3)
    cal = PlattCalibrator().fit(s, y)
    with pytest.raises(errors.ConfigError, match=r"prior must be a share of positives in \(0, 1\)"):
        with_prior(cal, bad, 0.5)
    with pytest.raises(errors.ConfigError, match=r"base_prior must be a share"):
        with_prior(cal, 0.5, bad)
    with pytest.raises(errors.ConfigError, match=r"prior must be a share"):
        prior_weights(y, bad)


def test_with_prior_needs_a_fitted_calibrator_and_weights_both_classes():
    with pytest.raises(errors.NotFittedError):
        with_prior(PlattCalibrator(), 0.1, 0.5)
    with pytest.raises(errors.NotFittedError):
        with_prior(IsotonicCalibrator(), 0.1, 0.5)
    with pytest.raises(errors.ConfigError, match="PlattCalibrator or an IsotonicCalibrator"):
        with_prior(object(), 0.1, 0.5)
    with pytest.raises(errors.DataError, match="both classes"):
        prior_weights(np.ones(10), 0.1)
    with pytest.raises(errors.DataError, match="only 0 and 1"):
        prior_weights(np.array([0, 1, 2]), 0.1)


def test_weighted_metrics_equal_repeated_samples(tmp_path):
    """Integer weights give the metrics of the data with each sample repeated that often;
    prior weights average 1 and give positives the asked share."""
    s, y = _scores(120, 5)
    p = PlattCalibrator().fit(s, y).predict_proba(s)
    w = np.random.default_rng(0).integers(0, 4, size=120).astype(float)
    w[0] = 1.0
    rep = np.repeat(np.arange(120), w.astype(int))
    got = calibration_metrics(p, y, 9, sample_weight=w)
    ref = calibration_metrics(p[rep], y[rep], 9)
    for k in ("nll", "brier", "ece"):
        assert got[k] == pytest.approx(ref[k], rel=1e-9, abs=1e-12)
    pw = prior_weights(y, 0.05)
    assert float(pw.mean()) == pytest.approx(1.0, rel=1e-12)
    assert float(pw[torch.as_tensor(y) == 1].sum() / pw.sum()) == pytest.approx(0.05, rel=1e-12)
    with pytest.raises(errors.DataError, match="non-negative"):
        calibration_metrics(p, y, sample_weight=-np.ones(120))
    with pytest.raises(errors.ShapeError, match="sample_weight must have shape"):
        calibration_metrics(p, y, sample_weight=np.ones(3))
    out = reliability_diagram(p, y, tmp_path / "w.png", sample_weight=pw)
    assert out.read_bytes()[:4] == b"\x89PNG"


def test_platt_fit_checks_its_inputs():
    """The public low-level ``platt_fit`` took NaN scores, labels other than 0 / 1 and negative
    weights and returned numbers without a word; now the calibrators' own errors."""
    from torchtrack.errors import DataError, ShapeError
    from torchtrack.learn.calibration import platt_fit

    s = torch.linspace(-2, 2, 20, dtype=torch.float64)
    y = (s > 0).long()
    a, b, _ = platt_fit(s, y)
    assert a < 0 and (a, b) == platt_fit(s, y.bool())[:2]  # bool labels: the same fit
    with pytest.raises(DataError, match="non-finite"):
        platt_fit(torch.where(s > 1, float("nan"), s), y)
    with pytest.raises(DataError, match="y01 must contain only 0 and 1"):
        platt_fit(s, y * 2)
    with pytest.raises(DataError, match="non-negative"):
        platt_fit(s, y, -torch.ones(20))
    with pytest.raises(ShapeError, match="y01 must have shape"):
        platt_fit(s, y[:5])
