"""Ground plane learnt online: height against foot row, robust, and silent until it is sure."""

import math

import numpy as np
import pytest
import torch

from torchtrack.errors import ConfigError, ShapeError
from torchtrack.track.ground import GroundPlane


def on_line(n, a=0.3, b=5.0, noise=0.05, seed=0, rows=(80.0, 300.0)):
    """n boxes whose foot row is uniform in ``rows`` and height ``(a y + b) * exp(noise z)``."""
    g = torch.Generator().manual_seed(seed)
    y = rows[0] + (rows[1] - rows[0]) * torch.rand(n, generator=g, dtype=torch.float64)
    h = (a * y + b) * torch.exp(noise * torch.randn(n, generator=g, dtype=torch.float64))
    w = 0.4 * h
    return torch.stack([100.0 + 0 * y, y - h, w, h], 1)


def test_fits_the_line_of_noisy_boxes_and_gates_the_wrong_sizes():
    gp = GroundPlane()
    gp.add(on_line(60))
    assert gp.fitted
    a, b = gp.line_.a, gp.line_.b
    assert abs(a - 0.3) < 0.02 and abs(b - 5.0) < 4.0, gp
    assert 0.03 < gp.line_.sd < 0.07
    # a person-sized box where a person is that size, twice as tall, and a third as tall
    y = 250.0
    h = 0.3 * y + 5.0
    boxes = torch.tensor(
        [
            [10.0, y - h, 0.4 * h, h],
            [10.0, y - 2 * h, 0.8 * h, 2 * h],
            [10.0, y - h / 3, 10.0, h / 3],
        ],
        dtype=torch.float64,
    )
    assert gp.consistent(boxes, 0.4).tolist() == [True, False, False]
    r, se = gp.log_ratio(boxes)
    assert abs(float(r[1]) - math.log(2)) < 0.05 and bool((se < 0.02).all())


def test_robust_to_a_third_of_outliers():
    g = torch.Generator().manual_seed(1)
    good = on_line(80, seed=2)
    bad = good[:40].clone()
    bad[:, 3] *= torch.exp(torch.empty(40, dtype=torch.float64).uniform_(-1.5, 1.5, generator=g))
    gp = GroundPlane()
    gp.add(torch.cat([good, bad])[torch.randperm(120, generator=g)])
    assert gp.fitted
    a, b = gp.line_.a, gp.line_.b
    assert abs(a - 0.3) < 0.03 and abs(b - 5.0) < 6.0, gp
    assert bool(gp.consistent(on_line(50, seed=3), 0.4).all())


def test_matches_least_squares_without_noise():
    y = torch.linspace(100, 300, 30, dtype=torch.float64)
    h = 0.25 * y + 10
    gp = GroundPlane()
    gp.add(torch.stack([0 * y, y - h, 0.4 * h, h], 1))
    a, b = gp.line_.a, gp.line_.b
    assert a == pytest.approx(0.25, abs=1e-9) and b == pytest.approx(10.0, abs=1e-6)
    ref = np.polyfit(y.numpy(), h.numpy(), 1)
    assert a == pytest.approx(ref[0], abs=1e-9)


@pytest.mark.parametrize(
    "boxes",
    [
        on_line(10),  # too few
        on_line(60, rows=(200.0, 201.0)),  # every foot on one row: no slope
        on_line(60, a=-0.3, b=120.0),  # lower is smaller: not a ground plane seen from above
        on_line(60, noise=0.5),  # heights all over the place (a moving camera, mixed objects)
    ],
    ids=["few", "one-row", "negative-slope", "scattered"],
)
def test_makes_no_claim_without_evidence(boxes):
    gp = GroundPlane()
    gp.add(boxes)
    assert not gp.fitted
    wild = torch.tensor([[0.0, 0.0, 5.0, 300.0], [0.0, 200.0, 2.0, 4.0]], dtype=torch.float64)
    assert bool(gp.consistent(wild, 0.1).all())
    r, se = gp.log_ratio(wild)
    assert bool(torch.isnan(r).all() and torch.isnan(se).all())


def test_extrapolation_is_allowed_more_slack():
    gp = GroundPlane()
    gp.add(on_line(40, rows=(200.0, 260.0)))
    near = torch.tensor([[0.0, 230.0 - 74.0, 30.0, 74.0]], dtype=torch.float64)
    far = torch.tensor([[0.0, 20.0 - 11.0, 5.0, 11.0]], dtype=torch.float64)
    assert float(gp.log_ratio(far)[1]) > 5 * float(gp.log_ratio(near)[1])


def test_bounded_memory_follows_a_new_scene_and_reset_forgets():
    gp = GroundPlane(capacity=64)
    gp.add(on_line(200, a=0.3, b=5.0))
    gp.add(on_line(64, a=0.5, b=-20.0, seed=4))  # the camera moved: only the new boxes remain
    assert gp._foot.shape[0] == 64
    assert abs(gp.line_.a - 0.5) < 0.03
    gp.add(torch.tensor([[0.0, 0.0, 1.0, float("nan")], [0.0, 0.0, 1.0, -3.0]]))  # ignored
    assert gp._foot.shape[0] == 64
    gp.reset()
    assert not gp.fitted and gp._foot.shape[0] == 0


def test_the_ground_truth_of_both_mot_sequences_lies_on_a_learnt_line_real_data(data_dir):
    """Fitted on the first 50 frames' boxes, the line holds for the rest of the sequence."""
    from torchtrack.io.mot import load_mot_sequence

    for seq in (
        load_mot_sequence(
            data_dir / "videos" / "pets2009_s2l1_vtest" / "vtest.avi",
            gt=data_dir / "mot" / "PETS09-S2L1" / "gt" / "gt.txt",
        ),
        load_mot_sequence(data_dir / "mot" / "TUD-Stadtmitte"),
    ):
        gt = seq.gt.select(seq.gt.conf != 0)
        boxes = torch.from_numpy(np.asarray(gt.boxes, dtype=np.float64))
        first = torch.from_numpy(np.asarray(gt.frames) < 50)
        gp = GroundPlane(capacity=1024)
        gp.add(boxes[first])
        assert gp.fitted and gp.line_.sd < 0.08, (seq.name, gp)
        rest = boxes[~first]
        assert float(gp.consistent(rest, 0.4).double().mean()) > 0.99, seq.name
        # the lower half of each box (a person's legs, at the same foot row) is off the line
        half = rest.clone()
        half[:, 1] += half[:, 3] / 2
        half[:, 3] /= 2
        assert float(gp.consistent(half, 0.4).double().mean()) < 0.05, seq.name


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"capacity": 10, "min_samples": 20}, "min_samples"),
        ({"min_samples": 1}, "min_samples"),
        ({"max_sd": 0.0}, "max_sd"),
        ({"min_inliers": 1.5}, "min_inliers"),
        ({"min_spread": float("nan")}, "min_spread"),
    ],
)
def test_bad_settings(kw, match):
    with pytest.raises(ConfigError, match=match):
        GroundPlane(**kw)


def test_two_things_seen_on_many_frames_draw_no_line():
    """Two static boxes (false detections of the background, say) repeated over 30 frames fit
    a line perfectly; the line needs boxes of three targets."""
    a = torch.tensor([[10.0, 100.0, 16.0, 40.0]], dtype=torch.float64)
    b = torch.tensor([[200.0, 150.0, 30.0, 80.0]], dtype=torch.float64)
    gp = GroundPlane()
    for _ in range(30):
        gp.add(torch.cat([a, b]), torch.tensor([1, 2]))
    assert not gp.fitted
    walker = on_line(10, a=40.0 / 140.0, b=0.0, noise=0.0, seed=5)  # on the same line
    gp.add(walker, torch.full((10,), 3))
    assert gp.fitted
    with pytest.raises(ShapeError, match="3 ids"):
        gp.add(on_line(2), torch.tensor([1, 2, 3]))
