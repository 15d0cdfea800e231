import pytest
import torch

from torchtrack.errors import ConfigError, ShapeError
from torchtrack.features.centre_surround import (
    centre_surround_features,
    channel_integrals,
    klein_pool,
)
from torchtrack.learn.online_gentle import StumpEnsemble
from torchtrack.observe.adaptive_haar import AdaptiveHaarObservation, classifier_confidence


def _ensembles(m, n=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    ens = StumpEnsemble.empty(m, n)
    ens.feature[:] = torch.randint(0, 539, (m, n), generator=g)
    ens.threshold[:] = torch.randn((m, n), generator=g) * 5
    ens.right[:] = torch.rand((m, n), generator=g)
    ens.left[:] = -torch.rand((m, n), generator=g)
    ens.valid[:] = True
    return ens


def test_confidence_paths_agree_with_manual_scoring_and_eq3():
    g = torch.Generator().manual_seed(1)
    frame = torch.randint(0, 256, (1, 3, 40, 60), dtype=torch.uint8, generator=g)
    ints = channel_integrals(frame)
    pool = klein_pool()
    boxes = torch.rand((2, 6, 4), generator=g) * torch.tensor([30.0, 15.0, 20.0, 20.0]) + 2
    ens = _ensembles(3)
    model = torch.randint(0, 3, (2, 6), generator=g)
    got = classifier_confidence(ints, boxes, pool, ens, model)
    full = centre_surround_features(ints, boxes.reshape(1, 12, 4), pool)[0]  # (12, F)
    ref = torch.stack(
        [
            ens.confidence(full[i, ens.feature[m]].view(1, 1, -1)[0], torch.tensor([m]))[0]
            for i, m in enumerate(model.flatten().tolist())
        ]
    ).view(2, 6)
    torch.testing.assert_close(got, ref, atol=1e-4, rtol=0)
    # one classifier for all boxes of one target: the shared-index fast path
    one = torch.zeros((1, 6), dtype=torch.int64)
    fast = classifier_confidence(ints, boxes[:1], pool, ens, one)
    slow = classifier_confidence(ints, boxes[:1].expand(2, 6, 4), pool, ens, one.expand(2, 6))
    torch.testing.assert_close(fast[0], slow[0], atol=1e-5, rtol=0)
    obs = AdaptiveHaarObservation(pool)
    torch.testing.assert_close(obs.log_likelihood(got), 20.0 * got)  # eq. (3): lambda = 20


def test_errors():
    pool = klein_pool()
    ints2 = channel_integrals(torch.zeros((2, 3, 8, 8), dtype=torch.uint8))
    ens = _ensembles(1)
    with pytest.raises(ShapeError, match="one frame"):
        classifier_confidence(ints2, torch.ones((1, 1, 4)), pool, ens, torch.zeros((1, 1)).long())
    ints = channel_integrals(torch.zeros((1, 3, 8, 8), dtype=torch.uint8))
    with pytest.raises(ShapeError, match=r"model \(B, N\)"):
        classifier_confidence(ints, torch.ones((1, 2, 4)), pool, ens, torch.zeros((1, 3)).long())
    with pytest.raises(ConfigError, match="lambda must be > 0"):
        AdaptiveHaarObservation(pool, lam=0.0)


def test_boxes_mostly_outside_the_frame_have_no_evidence():
    """Features of a box outside the frame read the integral image's zero padding; the
    observation gives such boxes confidence 0 (issue 12: a lost track kept confidence 0.85
    outside the frame)."""
    g = torch.Generator().manual_seed(1)
    frame = torch.randint(0, 256, (1, 3, 40, 60), dtype=torch.uint8, generator=g)
    ints = channel_integrals(frame)
    ens = _ensembles(1)
    obs = AdaptiveHaarObservation(klein_pool())
    boxes = torch.tensor(
        [
            [
                [10.0, 10.0, 20.0, 20.0],
                [50.0, 10.0, 20.0, 20.0],
                [55.0, 10.0, 20.0, 20.0],
                [500.0, 10.0, 20.0, 20.0],
                [-19.0, -19.0, 20.0, 20.0],
            ]
        ]
    )
    model = torch.zeros((1, 5), dtype=torch.int64)
    conf = obs.confidence(ints, boxes, ens, model)
    raw = classifier_confidence(ints, boxes, obs.pool, ens, model)
    assert bool((raw > 0).all())  # the classifier alone gives every box some confidence
    torch.testing.assert_close(conf[0, :2], raw[0, :2])  # inside; exactly half inside
    assert conf[0, 2:].tolist() == [0.0, 0.0, 0.0]
