import pytest
import torch

from torchtrack.boxes import box_iou_matrix
from torchtrack.detect.scan import nms, sliding_windows
from torchtrack.errors import ConfigError, ShapeError


def test_sliding_windows_inside_frame_and_scales():
    boxes = sliding_windows((100, 80), (40, 20), scale_step=1.5, stride=0.25)
    x, y, w, h = boxes.unbind(1)
    assert bool(
        (x >= 0).all()
        and (y >= 0).all()
        and (x + w <= 80 + 1e-4).all()
        and (y + h <= 100 + 1e-4).all()
    )
    # scales 1, 1.5, 2.25 fit (2.25 x 40 = 90 <= 100); 3.375 does not
    assert sorted(set(w.tolist())) == pytest.approx([20.0, 30.0, 45.0])
    # scale 1: steps of 5 px in x over 0..60, 10 px in y over 0..60
    assert int((w == 20).sum()) == 13 * 7
    assert sliding_windows((10, 10), (40, 20)).shape == (0, 4)


def reference_nms(boxes, scores, thr):
    order = sorted(range(len(scores)), key=lambda i: -float(scores[i]))
    keep = []
    for i in order:
        if all(
            float(box_iou_matrix(boxes[i : i + 1], boxes[j : j + 1])[0, 0]) <= thr for j in keep
        ):
            keep.append(i)
    return keep


def test_nms_matches_reference():
    g = torch.Generator().manual_seed(0)
    boxes = torch.rand((60, 4), generator=g) * torch.tensor(
        [50.0, 50.0, 20.0, 20.0]
    ) + torch.tensor([0, 0, 5.0, 5.0])
    scores = torch.rand(60, generator=g)
    assert nms(boxes, scores, 0.3).tolist() == reference_nms(boxes, scores, 0.3)


def test_bad_scan_args():
    with pytest.raises(ConfigError, match="scale_step"):
        sliding_windows((10, 10), (4, 4), scale_step=1.0)
    with pytest.raises(ConfigError, match="stride"):
        sliding_windows((10, 10), (4, 4), stride=0)
    with pytest.raises(ShapeError, match="nms needs"):
        nms(torch.zeros(3, 4), torch.zeros(2))
