"""Selection, boosting, SVM and Platt calibration on real UIUC car crops (a small subset)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from sklearn.calibration import _sigmoid_calibration

from torchtrack.detect.config import read_name_list
from torchtrack.features.haar import haar_bank, haar_features_dense
from torchtrack.io.crops import load_crops
from torchtrack.learn import (
    BoostedStumps,
    PlattCalibrator,
    SVMClassifier,
    calibration_metrics,
    select_features,
)

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_real_car_crops_select_boost_calibrate(data_dir):
    folder = data_dir / "detection_crops" / "uiuc_car" / "CarData" / "TrainImages"
    test_names = read_name_list(REPO / "configs" / "splits" / "uiuc_car_test.txt")
    window = (40, 100)
    pos = load_crops(folder, window, pattern="pos-*", exclude=test_names)
    neg = load_crops(folder, window, pattern="neg-*", exclude=test_names)
    g = torch.Generator().manual_seed(0)
    pi = torch.randperm(len(pos), generator=g)[:300]
    ni = torch.randperm(len(neg), generator=g)[:300]
    crops = torch.cat((pos.images[pi], neg.images[ni]))
    y = torch.cat((torch.ones(300), torch.zeros(300))).long()
    perm = torch.randperm(600, generator=g)
    crops, y = crops[perm], y[perm]
    bank = haar_bank(window, stride=2)  # a sparser bank keeps the test fast
    X = haar_features_dense(crops, bank)
    tr, ca, te = slice(0, 300), slice(300, 450), slice(450, 600)
    sel = select_features(X[tr], y[tr], 20)
    assert len(set(sel.tolist())) == 20
    Xs = X[:, sel]
    for clf in (BoostedStumps(20), BoostedStumps(20, variant="gentle"), SVMClassifier()):
        clf.fit(Xs[tr], y[tr])
        acc = (clf.decision_function(Xs[te]) > 0).long().eq(y[te]).float().mean()
        assert acc > 0.85, (clf, acc)  # chance is 0.5
    s_ca = clf.decision_function(Xs[ca]).double()
    cal = PlattCalibrator().fit(s_ca, y[ca])
    a, b = _sigmoid_calibration(s_ca.numpy(), y[ca].numpy())
    assert abs(cal.a_ - a) < 1e-3 and abs(cal.b_ - b) < 1e-3
    p = cal.predict_proba(clf.decision_function(Xs[te]).double())
    raw = torch.sigmoid(clf.decision_function(Xs[te]).double())
    assert calibration_metrics(p, y[te])["nll"] < calibration_metrics(raw, y[te])["nll"]
    assert np.isfinite(calibration_metrics(p, y[te])["ece"])
