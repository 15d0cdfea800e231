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
