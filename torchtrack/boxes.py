"""Box formats, IoU and validation.

The one convention of the package: a box is ``x, y, w, h`` in pixels, ``(x, y)`` the top-left
corner, 0-based, in the pixel grid of the frame it belongs to (pixel ``(i, j)`` covers
``[j, j+1) x [i, i+1)``). Other formats exist only at the edges: ``xyxy`` (x1, y1, x2, y2,
exclusive right/bottom) and ``cxcywh`` (centre, size). OTB files are 1-based; their loader
subtracts 1.
"""

from __future__ import annotations

import math

import torch

from torchtrack.errors import BoxError, ConfigError, ShapeError, is_number

__all__ = [
    "box_area",
    "box_iou",
    "box_iou_matrix",
    "check_boxes",
    "clip_boxes",
    "cxcywh_to_xywh",
    "inside_fraction",
    "xywh_to_cxcywh",
    "xywh_to_xyxy",
    "xyxy_to_xywh",
]


def _check_last4(boxes: torch.Tensor, name: str = "boxes") -> None:
    if not isinstance(boxes, torch.Tensor):
        raise ShapeError(f"{name} must be a torch.Tensor, got {type(boxes).__name__}")
    if boxes.ndim == 0 or boxes.shape[-1] != 4:
        raise ShapeError(f"{name} must have shape (..., 4), got {tuple(boxes.shape)}")
    if boxes.dtype == torch.bool or boxes.is_complex():  # areas of 0 / 1, or a RuntimeError
        raise ShapeError(f"{name} must hold real numbers, got {boxes.dtype}")


#: integer dtypes whose box areas (and corners) wrap: a uint8 20 x 20 box's area was 144
_NARROW_INTS = (torch.uint8, torch.int8, torch.int16, torch.int32)


def _wide(boxes: torch.Tensor) -> torch.Tensor:
    """``boxes`` in int64 when they are a narrower integer dtype, else as they are."""
    return boxes.long() if boxes.dtype in _NARROW_INTS else boxes


def _check_frame_size(frame_size, name: str = "frame_size", positive: bool = False) -> tuple:
    """``(H, W)`` of a frame (or a window, ``name``), as given, once checked to be two finite
    numbers >= 0 (> 0 with ``positive``).

    Raises:
        ShapeError: anything else (a negative size clipped every box to a mirrored frame; a
            bool, ``(True, 64)``, was a 1-pixel side).
    """
    try:
        h, w = (float(v) for v in frame_size)
    except (TypeError, ValueError, RuntimeError):  # RuntimeError: a tensor of several values
        raise ShapeError(f"{name} must be (H, W), got {frame_size!r}") from None
    if any(_is_bool(v) for v in frame_size):
        raise ShapeError(f"{name} must be (H, W) as numbers, not bool, got {frame_size!r}")
    least = "> 0" if positive else ">= 0"
    if not (math.isfinite(h) and math.isfinite(w) and h >= 0 and w >= 0) or (
        positive and not (h > 0 and w > 0)
    ):
        raise ShapeError(f"{name} must be (H, W) with H, W {least} and finite, got {frame_size!r}")
    return frame_size[0], frame_size[1]


def _is_bool(v) -> bool:
    """A Python, NumPy or torch boolean (``float()`` takes each as 0 or 1)."""
    if isinstance(v, torch.Tensor):
        return v.dtype == torch.bool
    return isinstance(v, bool) or type(v).__name__ in ("bool", "bool_")  # numpy 2 and 1


def xywh_to_xyxy(boxes: torch.Tensor) -> torch.Tensor:
    """``(..., 4)`` x, y, w, h -> x1, y1, x2, y2 (uint8 / int8 / int16 / int32 boxes give
    int64 corners: a uint8 box at x 200 of width 100 ended at 44)."""
    _check_last4(boxes)
    x, y, w, h = _wide(boxes).unbind(-1)
    return torch.stack((x, y, x + w, y + h), dim=-1)


def xyxy_to_xywh(boxes: torch.Tensor) -> torch.Tensor:
    """``(..., 4)`` x1, y1, x2, y2 -> x, y, w, h (narrow integer corners give int64 sizes, as
    :func:`xywh_to_xyxy`: a reversed uint8 box had a size of 255 rather than -1)."""
    _check_last4(boxes)
    x1, y1, x2, y2 = _wide(boxes).unbind(-1)
    return torch.stack((x1, y1, x2 - x1, y2 - y1), dim=-1)


def xywh_to_cxcywh(boxes: torch.Tensor) -> torch.Tensor:
    """``(..., 4)`` x, y, w, h -> centre x, centre y, w, h."""
    _check_last4(boxes)
    x, y, w, h = boxes.unbind(-1)
    return torch.stack((x + w / 2, y + h / 2, w, h), dim=-1)


def cxcywh_to_xywh(boxes: torch.Tensor) -> torch.Tensor:
    """``(..., 4)`` centre x, centre y, w, h -> x, y, w, h."""
    _check_last4(boxes)
    cx, cy, w, h = boxes.unbind(-1)
    return torch.stack((cx - w / 2, cy - h / 2, w, h), dim=-1)


def box_area(boxes: torch.Tensor) -> torch.Tensor:
    """Area ``(...)`` of ``(..., 4)`` xywh boxes; negative sizes count as zero.

    float16 / bfloat16 boxes give float32 areas (a 256 x 256 box's area is beyond float16's
    65504: it came out inf) and integer boxes int64 areas (a uint8 20 x 20 box's was 144);
    other dtypes keep theirs.
    """
    _check_last4(boxes)
    if _half_dtype(boxes) is not None:
        boxes = boxes.float()
    boxes = _wide(boxes)
    return boxes[..., 2].clamp(min=0) * boxes[..., 3].clamp(min=0)


def _broadcastable(s: tuple[int, ...], t: tuple[int, ...]) -> bool:
    """Whether shapes ``s`` and ``t`` broadcast (torch's rule, on the sizes alone: a tenth of
    the time of ``torch.broadcast_shapes``, which the trackers paid thousands of times a
    second)."""
    return all(x == y or x == 1 or y == 1 for x, y in zip(reversed(s), reversed(t), strict=False))


def box_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Element-wise IoU of broadcastable xywh boxes ``a (..., 4)`` and ``b (..., 4)``.

    Returns ``(...)``; 0 where the union is empty. NaN boxes give NaN (callers treat NaN as
    "target absent").
    """
    _check_last4(a, "a")
    _check_last4(b, "b")
    if a.shape[:-1] != b.shape[:-1] and not _broadcastable(a.shape[:-1], b.shape[:-1]):
        # torch's RuntimeError otherwise
        raise ShapeError(
            f"box_iou needs broadcastable boxes, got a {tuple(a.shape)} and b {tuple(b.shape)}"
        )
    half = _half_dtype(a, b)
    if half is not None:  # areas of boxes from 256 px overflow float16: IoU 0 for one box twice
        return box_iou(a.float(), b.float()).to(half)
    a, b = _wide(a), _wide(b)  # narrow integers: areas that wrap
    # the corners and areas of xywh_to_xyxy and box_area, without their checks and stacks
    ax1, ay1, aw, ah = a.unbind(-1)
    bx1, by1, bw, bh = b.unbind(-1)
    iw = (torch.minimum(ax1 + aw, bx1 + bw) - torch.maximum(ax1, bx1)).clamp(min=0)
    ih = (torch.minimum(ay1 + ah, by1 + bh) - torch.maximum(ay1, by1)).clamp(min=0)
    inter = iw * ih
    union = aw.clamp(min=0) * ah.clamp(min=0) + bw.clamp(min=0) * bh.clamp(min=0) - inter
    iou = inter / union.clamp(min=torch.finfo(inter.dtype).tiny if inter.is_floating_point() else 1)
    return torch.where(union > 0, iou, torch.zeros_like(iou))


def box_iou_matrix(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Pairwise IoU: ``a (N, 4)``, ``b (M, 4)`` xywh -> ``(N, M)``."""
    _check_last4(a, "a")
    _check_last4(b, "b")
    if a.ndim != 2 or b.ndim != 2:  # one box (4,) was an IndexError, (B, N, 4) broadcast
        raise ShapeError(
            f"box_iou_matrix needs a (N, 4) and b (M, 4), got {tuple(a.shape)} and {tuple(b.shape)}"
        )
    return box_iou(a[:, None, :], b[None, :, :])


def check_boxes(
    boxes: torch.Tensor,
    frame_size: tuple[int, int] | None = None,
    *,
    name: str = "boxes",
    min_size: float = 1.0,
) -> None:
    """Raise :class:`BoxError` unless every xywh box is finite, at least ``min_size`` pixels wide
    and high, and (when ``frame_size = (H, W)`` is given) overlaps the frame.

    The message names the first offending box by index. Use :func:`clip_boxes` to bring boxes
    that only stick out of the frame back inside.

    Raises:
        BoxError: a box as above.
        ShapeError: ``boxes`` not ``(..., 4)``, or ``frame_size`` not two finite sizes >= 0
            (a bool among them included).
        ConfigError: ``min_size`` not a finite number (a bool included).
    """
    _check_last4(boxes, name)
    if frame_size is not None:
        _check_frame_size(frame_size)
    # True was a minimum of 1 pixel, '1' a TypeError, NaN a 'size below nan pixel(s)' BoxError
    if not is_number(min_size) or not math.isfinite(min_size):
        raise ConfigError(f"check_boxes: min_size must be a finite number, got {min_size!r}")
    if boxes.numel() == 0:
        return
    finite = torch.isfinite(boxes).all(-1)
    if not bool(finite.all()):
        i = _first_false(finite)
        raise BoxError(f"{name}[{i}] is not finite: {boxes.reshape(-1, 4)[i].tolist()}")
    small = (boxes[..., 2] >= min_size) & (boxes[..., 3] >= min_size)
    if not bool(small.all()):
        i = _first_false(small)
        raise BoxError(
            f"{name}[{i}] = {boxes.reshape(-1, 4)[i].tolist()} (x, y, w, h) has a size below "
            f"{min_size} pixel(s), the smallest {name} accepted"
        )
    if frame_size is not None:
        h_img, w_img = frame_size
        x, y, w, h = boxes.unbind(-1)
        inside = (x < w_img) & (y < h_img) & (x + w > 0) & (y + h > 0)
        if not bool(inside.all()):
            i = _first_false(inside)
            raise BoxError(
                f"{name}[{i}] = {boxes.reshape(-1, 4)[i].tolist()} (x, y, w, h) lies entirely "
                f"outside the {w_img}x{h_img} frame"
            )


def clip_boxes(boxes: torch.Tensor, frame_size: tuple[int, int]) -> torch.Tensor:
    """Clip xywh boxes ``(..., 4)`` to a frame of size ``(H, W)``; boxes fully outside get
    zero size at the nearest border. Boxes already inside come back exactly as they are (the
    corners' round trip would change a fractional box in its last bits). NaN boxes (a target
    absent) stay NaN.

    Raises:
        BoxError: a box of negative width or height, named by its (flattened) index: it is
            no box to clip (one inside the frame came back with its negative size, one
            outside it as a zero-size box).
        ShapeError: ``boxes`` not ``(..., 4)``, or ``frame_size`` not two finite sizes >= 0.
    """
    _check_last4(boxes)
    h_img, w_img = _check_frame_size(frame_size)
    if boxes.dtype in _NARROW_INTS:  # the corners x + w wrap: clipped in int64
        return clip_boxes(boxes.long(), frame_size).to(boxes.dtype)
    negative = (boxes[..., 2] < 0) | (boxes[..., 3] < 0)  # NaN compares false: passes
    if bool(negative.any()):
        i = int(negative.reshape(-1).nonzero()[0, 0])
        row = boxes.reshape(-1, 4)[i]
        side = "width" if float(row[2]) < 0 else "height"
        raise BoxError(
            f"boxes[{i}] = {row.tolist()} (x, y, w, h) has a negative {side}: clip_boxes clips "
            "boxes to the frame, it does not repair them"
        )
    return _clip(boxes, h_img, w_img)


def _clip(boxes: torch.Tensor, h_img, w_img) -> torch.Tensor:
    """:func:`clip_boxes` without its checks (negative sizes come back as they are)."""
    xyxy = xywh_to_xyxy(boxes)
    x1 = xyxy[..., 0].clamp(0, w_img)
    y1 = xyxy[..., 1].clamp(0, h_img)
    x2 = xyxy[..., 2].clamp(0, w_img)
    y2 = xyxy[..., 3].clamp(0, h_img)
    clipped = xyxy_to_xywh(torch.stack((x1, y1, x2, y2), dim=-1))
    inside = (xyxy[..., 0] >= 0) & (xyxy[..., 1] >= 0)
    inside &= (xyxy[..., 2] <= w_img) & (xyxy[..., 3] <= h_img)
    return torch.where(inside[..., None], boxes, clipped)


def inside_fraction(boxes: torch.Tensor, frame_size: tuple[int, int]) -> torch.Tensor:
    """The fraction ``(...)`` of each xywh box's area ``(..., 4)`` that lies inside a frame of
    size ``(H, W)``: 1 inside, 0 entirely outside; NaN for a box that is not finite or has no
    area, a negative width or height included (compare with ``>=`` and such boxes fail)."""
    _check_last4(boxes)
    half = _half_dtype(boxes)
    if half is not None:  # as box_iou: the areas in float32, the fractions in the half dtype
        return inside_fraction(boxes.float(), frame_size).to(half)
    h_img, w_img = _check_frame_size(frame_size)
    boxes = _wide(boxes)  # narrow integers: corners and areas that wrap
    area = box_area(boxes)  # negative sizes: 0 (w * h of two negative sizes was > 0)
    inside = box_area(_clip(boxes, h_img, w_img))
    return torch.where(area > 0, inside / torch.where(area > 0, area, 1), float("nan"))


def _half_dtype(*boxes: torch.Tensor) -> torch.dtype | None:
    """The 16-bit float dtype of ``boxes`` (their promoted dtype), else ``None``: box areas
    are computed in float32, since a 256 x 256 box's area is beyond float16's 65504 (and
    bfloat16 keeps 8 bits of it)."""
    dtype = boxes[0].dtype
    for b in boxes[1:]:
        dtype = torch.promote_types(dtype, b.dtype)
    return dtype if dtype in (torch.float16, torch.bfloat16) else None


def _check_box_values(boxes: torch.Tensor) -> None:
    """``boxes (B, N, 4)`` of real numbers, finite, with widths and heights >= 0 (boxes
    outside the frame and empty ones allowed): ShapeError / BoxError naming ``boxes[b, n]``.
    One reduction and, for a bad box, one read: cheap enough for a tracker's hot path (a NaN
    box had read features of 0, a negative size sums of the frame taken backwards)."""
    _check_last4(boxes)  # bools were 0 / 1 pixel boxes
    bad = ~(torch.isfinite(boxes).all(-1) & (boxes[..., 2:] >= 0).all(-1))
    if boxes.numel() and bool(bad.any()):
        i = int(bad.reshape(-1).nonzero()[0, 0])
        raise BoxError(
            f"boxes[{i // boxes.shape[1]}, {i % boxes.shape[1]}] = "
            f"{boxes.reshape(-1, 4)[i].tolist()} (x, y, w, h) must be finite with a width and "
            "height >= 0"
        )


def _first_false(mask: torch.Tensor) -> int:
    return int((~mask.reshape(-1)).nonzero()[0, 0])
