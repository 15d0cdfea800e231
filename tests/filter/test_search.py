import math

import pytest
import torch

from torchtrack.errors import ConfigError, ShapeError
from torchtrack.filter.search import draw_around, search_grid, search_log_weights, top_cells


def _t(*rows):
    return torch.tensor(rows, dtype=torch.float64)


def test_search_grid_covers_the_radius_inside_the_frame():
    centre, size = _t([50.0, 40.0], [5.0, 5.0]), _t([10.0, 20.0], [10.0, 20.0])
    radius, stride = _t([20.0, 10.0], [20.0, 10.0]), _t([5.0, 5.0], [5.0, 5.0])
    g = search_grid(centre, size, radius, stride, (100, 200), scales=(1.0, 2.0))
    nx, ny = 9, 5  # 40 / 5 + 1, 20 / 5 + 1
    assert g.shape == (2, 2 * nx * ny, 4)
    c = g[..., :2] + g[..., 2:] / 2
    # row 0: the full window around its centre, both scales
    assert c[0, :, 0].min() == 30 and c[0, :, 0].max() == 70
    assert c[0, :, 1].min() == 30 and c[0, :, 1].max() == 50
    torch.testing.assert_close(g[0, nx * ny :, 2:], _t([20.0, 40.0]).expand(nx * ny, 2))
    # row 1: cut to the frame (centres in [0, W] x [0, H]), same number of points
    assert c[1, :, 0].min() == 0 and c[1, :, 0].max() == 25 and c[1, :, 1].min() == 0
    small = search_grid(centre, size, radius, stride, (100, 200), max_boxes=10)
    assert small.shape[1] <= 10
    with pytest.raises(ShapeError, match="radius must be"):
        search_grid(centre, size, radius[:, :1], stride, (100, 200))
    with pytest.raises(ConfigError, match="at least one scale"):
        search_grid(centre, size, radius, stride, (100, 200), scales=())


def test_top_cells_and_draw_around():
    boxes = torch.tensor([[[0.0, 0, 10, 10], [100, 0, 10, 10], [50, 50, 10, 10]]])
    scores = torch.tensor([[math.log(1.0), math.log(3.0), -50.0]])
    cells, log_pi = top_cells(boxes, scores, 2)
    torch.testing.assert_close(cells[0, 0], boxes[0, 1])
    torch.testing.assert_close(log_pi.exp(), torch.tensor([[0.75, 0.25]], dtype=torch.float64))
    c, comp = draw_around(cells, log_pi, 40_000, _t([2.0, 1.0]), torch.Generator().manual_seed(0))
    assert c.shape == (1, 40_000, 2)
    share = (comp == 0).double().mean().item()
    assert abs(share - 0.75) < 0.01
    near = c[0, comp[0] == 0] - torch.tensor([105.0, 5.0], dtype=torch.float64)
    assert abs(near[:, 0].std().item() - 2.0) < 0.05 and abs(near[:, 1].std().item() - 1.0) < 0.03


def test_search_log_weights_are_prior_over_proposal():
    # one cell at (5, 5), sd 1: d(x) = N(x; (5, 5), I); the jump density u = 1 / 400
    cells = torch.tensor([[[0.0, 0.0, 10.0, 10.0]]], dtype=torch.float64)
    log_pi = torch.zeros(1, 1, dtype=torch.float64)
    x = torch.tensor([[[5.0, 5.0], [7.0, 5.0]]], dtype=torch.float64)
    log_u = torch.tensor([-math.log(400.0)], dtype=torch.float64)
    pred, srch = search_log_weights(x, cells, log_pi, _t([1.0, 1.0]), log_u, 0.1, 98)
    torch.testing.assert_close(pred, torch.tensor([math.log(0.9 / 98)], dtype=torch.float64))
    log_d = torch.tensor([0.0, -2.0], dtype=torch.float64) - math.log(2 * math.pi)
    ref = math.log(0.1) - math.log(400.0) - math.log(2) - log_d
    torch.testing.assert_close(srch[0], ref)
    with pytest.raises(ConfigError, match="0 < eps < 1"):
        search_log_weights(x, cells, log_pi, _t([1.0, 1.0]), log_u, 0.0, 98)
