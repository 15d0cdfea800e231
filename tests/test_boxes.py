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


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_box_area_is_float32(dtype):
    """box_area of a float16 300 x 300 box overflowed to inf (box_iou and inside_fraction
    already took their areas in float32): the areas of 16-bit boxes come back in float32,
    which holds them, exactly for whole-pixel sizes."""
    from torchtrack.boxes import box_area

    b = torch.tensor([[0.0, 0.0, 300.0, 300.0], [1.0, 1.0, 2.0, -3.0]], dtype=dtype)
    area = box_area(b)
    assert area.dtype == torch.float32 and area.tolist() == [90000.0, 0.0]
    assert box_area(b.float()).dtype == torch.float32
    assert box_area(b.double()).dtype == torch.float64


def test_clip_boxes_refuses_negative_sizes_naming_the_row():
    """A box of negative width or height is not a box: one inside the frame came back as it
    was (negative size), one outside it as a zero-size box, silently. clip_boxes refuses it,
    naming the row; NaN boxes (a target absent) still pass through; inside_fraction gives such
    a box NaN like any box without area (it gave 0 or NaN by the signs)."""
    ok = torch.tensor([[1.0, 1.0, 4.0, 4.0]])
    bad = torch.tensor([[1.0, 1.0, 4.0, 4.0], [10.0, 10.0, -5.0, 5.0]])
    with pytest.raises(BoxError, match=r"boxes\[1\] = \[10.0, 10.0, -5.0, 5.0\] .* negative width"):
        clip_boxes(bad, (48, 64))
    with pytest.raises(BoxError, match=r"boxes\[3\] = \[9.0, 9.0, 2.0, -1.0\] .* negative height"):
        clip_boxes(
            torch.tensor([[[1.0, 1, 4, 4], [2, 2, 3, 3]], [[0, 0, 1, 1], [9, 9, 2, -1]]]), (48, 64)
        )
    nan = torch.tensor([[float("nan"), 1.0, 4.0, 4.0]])
    assert torch.isnan(clip_boxes(nan, (48, 64))).any()
    assert clip_boxes(torch.tensor([[70.0, 1.0, 0.0, 4.0]]), (48, 64)).tolist() == [
        [64.0, 1.0, 0.0, 4.0]
    ]
    frac = inside_fraction(
        torch.tensor([[10.0, 10.0, -5.0, -5.0], [10, 10, -5, 5], [1, 1, 4, 4]]), (48, 64)
    )
    assert torch.isnan(frac[:2]).all() and frac[2].item() == 1.0
    assert clip_boxes(ok, (48, 64)).tolist() == ok.tolist()


@pytest.mark.parametrize("size", [(True, 64), (48, False), (torch.tensor(True), 64)])
def test_a_frame_size_of_bools_is_refused(size):
    """(True, 64) was a 1 x 64 frame: clip_boxes clipped to it and check_boxes (which did not
    check its frame_size: (48,) was a bare ValueError) measured boxes against it."""
    import numpy as np

    b = torch.tensor([[1.0, 2.0, 3.0, 4.0]])
    for fn in (clip_boxes, inside_fraction, lambda b, s: check_boxes(b, s)):
        with pytest.raises(ShapeError, match=r"frame_size must be \(H, W\) .*not bool"):
            fn(b, size)
    with pytest.raises(ShapeError, match="not bool"):
        clip_boxes(b, (np.bool_(True), 64))
    for bad in ((48,), "ab", (48, 64, 3), (float("nan"), 64)):
        with pytest.raises(ShapeError, match="frame_size must be"):
            check_boxes(b, bad)


@pytest.mark.parametrize("dtype", [torch.uint8, torch.int8, torch.int16, torch.int32])
def test_areas_and_iou_of_narrow_integer_boxes_do_not_wrap(dtype):
    """box_area of a uint8 20 x 20 box was 144 (400 mod 256) and of an int16 300 x 300 box
    24464, silently; their IoUs were computed from the wrapped areas. Narrow integer boxes are
    measured in int64 (areas) and float64 (IoU); int64 and float boxes are unchanged."""
    side = 20 if dtype in (torch.uint8, torch.int8) else 300
    if dtype == torch.int32:
        side = 50_000  # 2.5e9: beyond int32
    a = torch.tensor([[0, 0, side, side]], dtype=dtype)
    b = torch.tensor([[side // 2, 0, side // 2, side]], dtype=dtype)
    from torchtrack.boxes import box_area

    assert box_area(a).tolist() == [side * side] and box_area(a).dtype == torch.int64
    assert box_iou(a, b).item() == pytest.approx(0.5)
    assert box_iou_matrix(a, b).item() == pytest.approx(0.5)
    assert inside_fraction(a, (side // 2, side)).item() == pytest.approx(0.5)


def test_bool_and_complex_boxes_are_refused():
    """bool boxes were areas of 0 / 1 in box_area and a RuntimeError in box_iou; complex ones a
    RuntimeError: boxes are real numbers."""
    from torchtrack.boxes import box_area

    b = torch.tensor([[1.0, 2.0, 3.0, 4.0]])
    for bad in (b.bool(), b.to(torch.complex64)):
        for fn in (box_area, lambda x: box_iou(x, x), lambda x: clip_boxes(x, (10, 10))):
            with pytest.raises(ShapeError, match=r"(boxes|a) must hold real numbers, got torch\."):
                fn(bad)


@pytest.mark.parametrize(
    ("dtype", "x", "w"),
    [(torch.uint8, 200, 100), (torch.int8, 100, 100), (torch.int16, 30000, 9000)],
)
def test_corner_conversions_of_narrow_integer_boxes_do_not_wrap(dtype, x, w):
    """xywh_to_xyxy of a uint8 box at x 200 of width 100 ended at 44 (int8 at 100 + 100: -56),
    and xyxy_to_xywh of reversed uint8 corners gave a size of 255 rather than -1; box_area and
    box_iou already widened such boxes."""
    b = torch.tensor([[x, 20, w, 10]], dtype=dtype)
    out = xywh_to_xyxy(b)
    assert out.tolist() == [[x, 20, x + w, 30]] and out.dtype == torch.int64
    r = torch.tensor([[5, 5, 4, 4]], dtype=dtype)
    assert xyxy_to_xywh(r).tolist() == [[5, 5, -1, -1]]
    assert xywh_to_xyxy(b.float()).dtype == torch.float32  # other dtypes keep theirs


@pytest.mark.parametrize("bad", [True, "1", float("nan"), None])
def test_check_boxes_min_size_must_be_a_number(bad):
    """min_size=True was a 1-pixel minimum, '1' a TypeError, NaN a 'size below nan' BoxError."""
    from torchtrack.errors import ConfigError

    with pytest.raises(ConfigError, match="check_boxes: min_size must be a finite number"):
        check_boxes(torch.tensor([[1.0, 2, 3, 4]]), min_size=bad)
