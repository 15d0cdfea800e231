import math

import numpy as np
import pytest
import torch

from torchtrack.errors import ConfigError, ShapeError
from torchtrack.track.association import association_cost, expected_iou, linear_assignment


def test_expected_iou_is_the_weighted_mean_of_particle_ious():
    parts = torch.tensor(
        [[[0.0, 0.0, 10.0, 10.0], [5.0, 0.0, 10.0, 10.0]], [[50.0, 50.0, 4.0, 4.0]] * 2]
    )
    lw = torch.log(torch.tensor([[0.25, 0.75], [0.5, 0.5]]))
    dets = torch.tensor([[0.0, 0.0, 10.0, 10.0], [100.0, 100.0, 5.0, 5.0]])
    ov = expected_iou(parts, lw, dets)
    # particle 2 overlaps the first detection by 50 / 150
    assert ov[0, 0].item() == pytest.approx(0.25 * 1.0 + 0.75 * 50 / 150)
    assert ov[1].abs().max().item() == 0.0 and ov[0, 1].item() == 0.0
    assert expected_iou(parts[:0], lw[:0], dets).shape == (0, 2)
    with pytest.raises(ShapeError):
        expected_iou(parts[0], lw, dets)


def test_cost_gates_and_blends_cues():
    ov = torch.tensor([[0.9, 0.05], [0.5, 0.6]])
    app = torch.tensor([[0.5, 1.0], [1.0, 0.0]])
    c = association_cost(ov, app, w_overlap=1.0, w_appearance=1.0, gate=0.1)
    assert math.isinf(c[0, 1].item())
    assert c[0, 0].item() == pytest.approx(1 - 0.7)
    assert c[1, 1].item() == pytest.approx(1 - 0.3)
    only = association_cost(ov, None, gate=0.0)
    torch.testing.assert_close(only, 1 - ov.double())


def test_assignment_is_optimal_and_drops_forbidden_pairs():
    # greedy would pair (0, 0) at 0.1 and leave row 1 with 0.95; optimal pairs crosswise
    cost = torch.tensor([[0.1, 0.2], [0.3, 0.95]], dtype=torch.float64)
    res = linear_assignment(cost, max_cost=1.0)
    assert sorted(res.pairs.tolist()) == [[0, 1], [1, 0]]
    res = linear_assignment(torch.tensor([[0.1, math.inf], [math.inf, 0.99]]), max_cost=0.9)
    assert res.pairs.tolist() == [[0, 0]]
    assert res.unmatched_targets.tolist() == [1] and res.unmatched_detections.tolist() == [1]
    empty = linear_assignment(torch.zeros((3, 0)))
    assert len(empty) == 0 and empty.unmatched_targets.tolist() == [0, 1, 2]


def test_assignment_matches_brute_force_on_random_costs():
    from itertools import permutations

    rng = np.random.default_rng(0)
    for _ in range(20):
        c = torch.from_numpy(rng.random((4, 4)))
        res = linear_assignment(c, max_cost=2.0)
        best = min(sum(c[i, p[i]].item() for i in range(4)) for p in permutations(range(4)))
        got = sum(c[r, k].item() for r, k in res.pairs.tolist())
        assert got == pytest.approx(best)


def test_bad_weights_gates_and_log_weights_are_refused():
    """A (T, 1) log_weights broadcast over the particles (each overlap summed N times, clamped
    to 1); bool boxes were 0 / 1 pixels; a negative cue weight gave costs above 1, a NaN one
    NaN costs; max_cost NaN forbade every pair; all without a word."""
    parts = torch.tensor([[[0.0, 0.0, 10.0, 10.0], [5.0, 0.0, 10.0, 10.0]]])
    dets = torch.tensor([[0.0, 0.0, 10.0, 10.0]])
    with pytest.raises(ShapeError, match=r"log_weights must be \(T, N\) = \(1, 2\)"):
        expected_iou(parts, torch.zeros(1, 1), dets)
    with pytest.raises(ShapeError, match="detections must hold real numbers"):
        expected_iou(parts, torch.zeros(1, 2), dets.bool())
    ov, app = torch.tensor([[0.9]]), torch.tensor([[0.5]])
    for kw in ({"w_overlap": -1.0}, {"w_appearance": math.nan}, {"gate": math.nan}, {"gate": True}):
        with pytest.raises(ConfigError, match=r"association_cost: .* must be a finite number"):
            association_cost(ov, app, **kw)
    torch.testing.assert_close(  # w_appearance 0: the overlap alone, as before
        association_cost(ov, app, w_overlap=0.0, w_appearance=0.0), 1 - ov.double()
    )
    with pytest.raises(ConfigError, match="max_cost must be a number"):
        linear_assignment(torch.zeros(1, 1), max_cost=math.nan)
    assert len(linear_assignment(torch.zeros(1, 1), max_cost=math.inf)) == 1
