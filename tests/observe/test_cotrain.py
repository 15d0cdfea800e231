"""Eq. (13) likelihood of the co-training tracker against a pixel-loop reference."""

import math

import pytest
import torch

from torchtrack.errors import ConfigError, ShapeError
from torchtrack.observe.cotrain import CoTrainLikelihood, window_sums


def loop_likelihood(conf, origin, size, mean, sigma, cx, cy, beta=1.0):
    h, w = conf.shape
    x0 = round(cx - origin[0] - size[0] / 2)
    y0 = round(cy - origin[1] - size[1] / 2)
    s = 0.0
    for y in range(y0, y0 + round(size[1])):
        for x in range(x0, x0 + round(size[0])):
            if 0 <= y < h and 0 <= x < w:
                s += max(float(conf[y, x]), 0.0)
    gate = -0.5 * (((cx - mean[0]) / sigma[0]) ** 2 + ((cy - mean[1]) / sigma[1]) ** 2)
    return beta * math.log(s) + gate if s > 0 else -math.inf


def test_matches_loop_reference_inside_and_across_the_region_border():
    g = torch.Generator().manual_seed(0)
    conf = torch.randn(12, 15, generator=g, dtype=torch.float64) * 3
    lik = CoTrainLikelihood(conf, (100, 50), (6, 4), (107, 56), (5, 3), sharpness=2.0)
    states = torch.stack(
        [100 + 20 * torch.rand(2, 9, generator=g) - 2, 50 + 16 * torch.rand(2, 9, generator=g) - 2],
        -1,
    ).double()
    states[0, 0] = torch.tensor([60.0, 20.0])  # window entirely outside the region
    got = lik(states)
    assert got.shape == (2, 9)
    for b in range(2):
        for n in range(9):
            cx, cy = states[b, n].tolist()
            want = loop_likelihood(conf, (100, 50), (6, 4), (107, 56), (5, 3), cx, cy, 2.0)
            if math.isinf(want):
                assert got[b, n] == -math.inf
            else:
                assert abs(float(got[b, n]) - want) < 1e-9


def test_window_sums_of_ones_count_pixels():
    ii = torch.zeros(5, 6, dtype=torch.float64)
    ii[1:, 1:] = torch.ones(4, 5, dtype=torch.float64).cumsum(0).cumsum(1)
    x0, y0 = torch.tensor([0, -3, 4]), torch.tensor([0, 1, 2])
    out = window_sums(ii, x0, y0, x0 + 2, y0 + 2)
    assert out.tolist() == [4.0, 0.0, 2.0]


def test_errors():
    with pytest.raises(ShapeError, match="confidence map"):
        CoTrainLikelihood(torch.zeros(3), (0, 0), (2, 2), (0, 0), (1, 1))
    with pytest.raises(ConfigError, match="window size"):
        CoTrainLikelihood(torch.zeros(3, 3), (0, 0), (0, 2), (0, 0), (1, 1))
    with pytest.raises(ConfigError, match="gate_sigma"):
        CoTrainLikelihood(torch.zeros(3, 3), (0, 0), (2, 2), (0, 0), (0, 1))
    lik = CoTrainLikelihood(torch.zeros(3, 3), (0, 0), (2, 2), (0, 0), (1, 1))
    with pytest.raises(ShapeError, match="states"):
        lik(torch.zeros(4, 2))


def test_mean_positive_confidence_and_the_cue():
    from torchtrack.features.integral import integral_image
    from torchtrack.learn.cotrain import CoTrainer
    from torchtrack.observe.cotrain import CoTrainCue, mean_positive_confidence

    conf = torch.zeros(20, 30, dtype=torch.float64)
    conf[5:10, 10:20] = 0.8  # a 10 x 5 object, region origin (100, 50) in the frame
    ii = integral_image(conf[None, None])[0, 0]
    boxes = torch.tensor([[110.0, 55, 10, 5], [110.0, 55, 20, 10], [100.0, 50, 4, 4]])
    m = mean_positive_confidence(ii, (100.0, 50.0), boxes)
    torch.testing.assert_close(m, torch.tensor([0.8, 0.2, 0.0], dtype=torch.float64))
    with pytest.raises(ConfigError, match="search_scale"):
        CoTrainCue(CoTrainer(), search_scale=0.5)
    cue = CoTrainCue(CoTrainer(n_selectors=4), floor=1e-3)
    assert float(cue.log_likelihood(boxes).abs().max()) == 0  # no maps yet: no evidence
    g = torch.Generator().manual_seed(0)
    f = torch.randint(0, 60, (3, 60, 80), dtype=torch.uint8, generator=g)
    f[0, 20:40, 30:50] = 230
    cue.init(f, (30.0, 20.0, 20.0, 20.0), (60, 80), g)
    assert cue.score(f, (40.0, 30.0), (20.0, 20.0), (60, 80))
    ll = cue.log_likelihood(torch.tensor([[30.0, 20, 20, 20], [0.0, 0, 20, 20]]))
    assert ll[0] > ll[1] and ll[1] >= math.log(1e-3)
    assert cue.update(g)[0]
