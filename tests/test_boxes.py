import pytest
import torch

from torchtrack.boxes import (
    box_iou,
    box_iou_matrix,
    check_boxes,
    clip_boxes,
    cxcywh_to_xywh,
    inside_fraction,
    xywh_to_cxcywh,
    xywh_to_xyxy,
    xyxy_to_xywh,
)
from torchtrack.errors import BoxError, ShapeError


def test_round_trips():
    b = torch.tensor([[1.0, 2.0, 3.0, 4.0], [0.5, 0.0, 10.0, 2.0]])
    torch.testing.assert_close(xyxy_to_xywh(xywh_to_xyxy(b)), b)
    torch.testing.assert_close(cxcywh_to_xywh(xywh_to_cxcywh(b)), b)
    assert xywh_to_xyxy(b)[0].tolist() == [1.0, 2.0, 4.0, 6.0]


def test_iou_hand_computed():
    a = torch.tensor([0.0, 0.0, 10.0, 10.0])
    b = torch.tensor([5.0, 0.0, 10.0, 10.0])  # overlap 50, union 150
    assert box_iou(a, b).item() == pytest.approx(1 / 3)
    assert box_iou(a, a).item() == pytest.approx(1.0)
    assert box_iou(a, torch.tensor([20.0, 20.0, 1.0, 1.0])).item() == 0.0
    m = box_iou_matrix(torch.stack([a, b]), torch.stack([a, b, a]))
    assert m.shape == (2, 3)
    assert m[1, 0].item() == pytest.approx(1 / 3)


def test_iou_of_boxes_that_do_not_pair_is_a_shape_error():
    """box_iou of 3 and 5 boxes raised torch's RuntimeError; box_iou_matrix of one box (4,)
    an IndexError, and of a (2, 3, 4) batch against (5, 4) a RuntimeError."""
    a, b = torch.ones(3, 4), torch.ones(5, 4)
    with pytest.raises(ShapeError, match=r"broadcastable boxes, got a \(3, 4\) and b \(5, 4\)"):
        box_iou(a, b)
    assert box_iou(a, b[:1]).shape == (3,) and box_iou(a[:, None], b).shape == (3, 5)
    for bad in (torch.ones(4), torch.ones(2, 3, 4)):
        with pytest.raises(ShapeError, match=r"box_iou_matrix needs a \(N, 4\) and b \(M, 4\)"):
            box_iou_matrix(bad, b)
        with pytest.raises(ShapeError, match=r"box_iou_matrix needs"):
            box_iou_matrix(b, bad)


def test_check_boxes_errors():
    with pytest.raises(BoxError, match=r"boxes\[1\].*size below"):
        check_boxes(torch.tensor([[0.0, 0, 5, 5], [1.0, 1, 0, 5]]))
    with pytest.raises(BoxError, match="not finite"):
        check_boxes(torch.tensor([[float("nan"), 0, 5, 5]]))
    with pytest.raises(BoxError, match="outside the 20x10 frame"):
        check_boxes(torch.tensor([[30.0, 0, 5, 5]]), frame_size=(10, 20))
    with pytest.raises(ShapeError, match=r"\(\.\.\., 4\)"):
        check_boxes(torch.zeros(3, 5))
    check_boxes(torch.tensor([[-2.0, -2, 5, 5]]), frame_size=(10, 20))  # partly inside is fine


def test_clip_boxes():
    b = torch.tensor([[-5.0, 2.0, 10.0, 20.0]])
    assert clip_boxes(b, (10, 8)).tolist() == [[0.0, 2.0, 5.0, 8.0]]


@pytest.mark.parametrize("size", [(-10, 8), (10, -1), (float("nan"), 8), (10, float("inf")), (10,)])
def test_a_frame_size_that_is_not_two_sizes_is_refused(size):
    # a negative size clipped boxes to a mirrored frame and gave negative inside fractions
    b = torch.tensor([[1.0, 2.0, 3.0, 4.0]])
    with pytest.raises(ShapeError, match="frame_size must be"):
        clip_boxes(b, size)
    with pytest.raises(ShapeError, match="frame_size must be"):
        inside_fraction(b, size)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_boxes_of_ordinary_size(dtype):
    """A 300 x 300 box's area (90000) is beyond float16: its IoU with itself came out 0 and
    its inside fraction NaN. The areas are taken in float32; the results keep the dtype."""
    a = torch.tensor([[0.0, 0.0, 300.0, 300.0]], dtype=dtype)
    b = torch.tensor([[10.0, 10.0, 300.0, 300.0]], dtype=dtype)
    want = box_iou(a.float(), b.float())
    assert box_iou(a, a).dtype == dtype and box_iou(a, a).item() == 1.0
    assert box_iou(a, b).float().item() == pytest.approx(want.item(), abs=5e-3)
    assert box_iou_matrix(a, b).float().item() == pytest.approx(want.item(), abs=5e-3)
    frac = inside_fraction(a, (150, 1000))
    assert frac.dtype == dtype and frac.float().item() == pytest.approx(0.5, abs=5e-3)
