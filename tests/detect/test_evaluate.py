import numpy as np
import pytest
import torch
from sklearn.metrics import roc_auc_score

from torchtrack.detect.evaluate import detection_rate_at_fpr, roc_auc
from torchtrack.errors import DataError


def test_roc_auc_matches_sklearn_with_ties():
    rng = np.random.default_rng(0)
    s = np.round(rng.normal(size=400), 1)  # many ties
    y = (s + rng.normal(size=400) > 0).astype(int)
    assert roc_auc(torch.from_numpy(s), torch.from_numpy(y)) == pytest.approx(
        roc_auc_score(y, s), abs=1e-12
    )


def test_detection_rate_at_fpr_brute_force():
    rng = np.random.default_rng(1)
    neg = rng.normal(size=1000)
    pos = rng.normal(loc=2.5, size=300)
    s = torch.from_numpy(np.concatenate((pos, neg)))
    y = torch.cat((torch.ones(300), torch.zeros(1000)))
    dr, fpr, thr = detection_rate_at_fpr(s, y, 0.01)
    # brute force: the lowest threshold among the negative scores with at most 1% of negatives above
    best = None
    for t in sorted(neg):
        if (neg > t).mean() <= 0.01:
            best = t
            break
    assert thr == best and fpr <= 0.01
    assert dr == pytest.approx((pos > best).mean())


def test_bad_inputs():
    with pytest.raises(DataError, match="both classes"):
        roc_auc(torch.ones(3), torch.ones(3))
    with pytest.raises(DataError, match="NaN"):
        detection_rate_at_fpr(torch.tensor([0.0, float("nan")]), torch.tensor([0, 1]))
    with pytest.raises(DataError, match="labels"):
        roc_auc(torch.ones(3), torch.ones(2))
