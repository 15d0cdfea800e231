"""Batched integral images (summed-area tables), exact for 8-bit frames.

``ii[b, c, y, x]`` is the sum of ``image[b, c, :y, :x]``: the table has one extra leading row and
column of zeros, like ``cv2.integral``, so the sum over pixel rows ``y0..y1-1`` and columns
``x0..x1-1`` is ``ii[y1, x1] - ii[y0, x1] - ii[y1, x0] + ii[y0, x0]``.

Precision: a VGA 8-bit frame sums to ~7.8e7 and its squares to ~2e10, beyond float32's 24-bit
mantissa, so the default result dtype is float64. Integer inputs are accumulated in int64 (exact)
and converted once; float inputs are accumulated in float64.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from torchtrack.errors import ConfigError, DataError, ShapeError

__all__ = ["IntegralImage", "check_pixel_values", "integral_image", "rgb_to_gray"]

#: unsigned integer dtypes torch offers no ``aminmax`` for (uint16 frames from 16-bit PNGs)
_NO_MINMAX = tuple(getattr(torch, n) for n in ("uint16", "uint32", "uint64") if hasattr(torch, n))

# ITU-R BT.601 luma, the weights cv2.cvtColor(..., COLOR_RGB2GRAY) uses.
_LUMA = (0.299, 0.587, 0.114)


def _check_images(images: torch.Tensor, name: str = "images") -> None:
    if not isinstance(images, torch.Tensor):
        raise ShapeError(f"{name} must be a torch.Tensor, got {type(images).__name__}")
    if images.ndim != 4:
        raise ShapeError(f"{name} must have shape (B, C, H, W), got {tuple(images.shape)}")
    if images.dtype == torch.bool or images.is_complex():
        raise ShapeError(f"{name} must be an integer or floating tensor, got {images.dtype}")


def check_pixel_values(images: torch.Tensor, name: str = "frames") -> None:
    """Raise DataError unless every value of ``images`` is an 8-bit level: finite, in
    ``[0, 255]`` (uint8 images need no pass over the pixels).

    Features read from NaN or infinite pixels are NaN, which the classifiers turn into an
    ordinary-looking score; 16-bit levels (up to 65535) or floats in [0, 1] are read on the
    8-bit scale the models were trained on. The second of those cannot be told from a dark
    frame; values beyond 255, below 0 or not finite can.
    """
    if images.dtype == torch.uint8 or images.numel() == 0:
        return
    if images.dtype in _NO_MINMAX:  # torch has no min/max for them ('aminmax_cpu' error)
        images = images.to(torch.float64)
    lo, hi = (float(v) for v in torch.aminmax(images))
    if not (lo >= 0 and hi <= 255):  # also false for NaN
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise DataError(
                f"{name} hold NaN or infinite values: pixels must be finite levels in [0, 255]"
            )
        raise DataError(
            f"{name} hold values in [{lo:g}, {hi:g}]: pixels must be 8-bit levels in [0, 255] "
            "(16-bit images: divide by 257)"
        )


def integral_image(
    images: torch.Tensor, *, squared: bool = False, dtype: torch.dtype = torch.float64
) -> torch.Tensor:
    """Integral image of a batch of images.

    Args:
        images: ``(B, C, H, W)``, any integer or floating dtype (8-bit frames as uint8 or float
            in 0..255), on any device.
        squared: integrate ``images ** 2`` instead (for window variances).
        dtype: result dtype, a floating torch dtype; float64 (default) is exact for 8-bit VGA
            frames and their squares.

    Returns:
        ``(B, C, H + 1, W + 1)`` on the input's device; row 0 and column 0 are zeros.

    Raises:
        ShapeError: ``images`` is not a 4-D real tensor.
        ConfigError: ``dtype`` is not a floating torch dtype.

    Example:
        >>> ii = integral_image(torch.ones(1, 1, 2, 3, dtype=torch.uint8))
        >>> ii[0, 0].tolist()
        [[0.0, 0.0, 0.0, 0.0], [0.0, 1.0, 2.0, 3.0], [0.0, 2.0, 4.0, 6.0]]
    """
    _check_images(images)
    # "float32" was torch's RuntimeError 'Invalid device string', torch.bool a table of bools
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise ConfigError(
            "integral_image: dtype must be a floating torch dtype (e.g. torch.float64, "
            f"torch.float32), got {dtype!r}"
        )
    if images.is_floating_point():
        acc = images.to(torch.float64)
    else:
        acc = images.to(torch.int64)
    if squared:
        acc = acc * acc
    b, c, h, w = acc.shape
    out = torch.zeros((b, c, h + 1, w + 1), dtype=acc.dtype, device=acc.device)
    out[:, :, 1:, 1:] = acc.cumsum(2).cumsum(3)
    return out.to(dtype)


def rgb_to_gray(images: torch.Tensor) -> torch.Tensor:
    """``(B, C, H, W)`` with C = 1 (returned as is) or 3 (RGB) -> ``(B, 1, H, W)`` float luma.

    Integer input keeps its 0..255 scale (as float32); BGR frames from OpenCV must be flipped
    to RGB first (``frames.flip(1)``).

    Raises:
        ShapeError: C is neither 1 nor 3.
    """
    _check_images(images)
    c = images.shape[1]
    if c == 1:
        return images
    if c != 3:
        raise ShapeError(f"images must have 1 (gray) or 3 (RGB) channels, got C={c}")
    x = images if images.is_floating_point() else images.to(torch.float32)
    wts = torch.tensor(_LUMA, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    return (x * wts).sum(1, keepdim=True)


class IntegralImage(nn.Module):
    """Module wrapper of :func:`integral_image`; stores the arguments only."""

    def __init__(self, squared: bool = False, dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        self.squared = squared
        self.dtype = dtype

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """``(B, C, H, W)`` -> ``(B, C, H + 1, W + 1)``."""
        return integral_image(images, squared=self.squared, dtype=self.dtype)
