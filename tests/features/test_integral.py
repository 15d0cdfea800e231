import math

import cv2
import numpy as np
import pytest
import torch

from torchtrack.errors import ConfigError, DataError, ShapeError
from torchtrack.features.integral import IntegralImage, integral_image, rgb_to_gray


def loop_integral(img: np.ndarray) -> np.ndarray:
    """Slow, obviously right reference: ii[y, x] = sum(img[:y, :x]) in float64."""
    h, w = img.shape
    out = np.zeros((h + 1, w + 1), dtype=np.float64)
    for y in range(1, h + 1):
        row = 0.0
        for x in range(1, w + 1):
            row += float(img[y - 1, x - 1])
            out[y, x] = out[y - 1, x] + row
    return out


def test_matches_loop_reference_batched():
    g = torch.Generator().manual_seed(0)
    imgs = torch.randint(0, 256, (2, 3, 7, 9), dtype=torch.uint8, generator=g)
    ii = integral_image(imgs)
    assert ii.shape == (2, 3, 8, 10) and ii.dtype == torch.float64
    for b in range(2):
        for c in range(3):
            np.testing.assert_array_equal(ii[b, c].numpy(), loop_integral(imgs[b, c].numpy()))


def test_float_input_matches_loop():
    g = torch.Generator().manual_seed(1)
    imgs = torch.rand((1, 1, 5, 6), generator=g, dtype=torch.float32) * 255
    ii = integral_image(imgs)
    np.testing.assert_allclose(
        ii[0, 0].numpy(), loop_integral(imgs[0, 0].double().numpy()), rtol=1e-12
    )


def test_exact_on_vga_against_cv2():
    rng = np.random.default_rng(0)
    # A worst case for float32: a bright VGA frame whose sums pass 2**24.
    frame = rng.integers(200, 256, size=(480, 640), dtype=np.uint8)
    ii = integral_image(torch.from_numpy(frame)[None, None])[0, 0].numpy()
    ref = cv2.integral(frame, sdepth=cv2.CV_64F)
    np.testing.assert_array_equal(ii, ref)
    assert ii[-1, -1] > 2**24  # the float32 danger zone is really reached
    ii2 = integral_image(torch.from_numpy(frame)[None, None], squared=True)[0, 0].numpy()
    np.testing.assert_array_equal(ii2, cv2.integral2(frame, sdepth=cv2.CV_64F)[1])


def test_batch_equals_single_runs():
    g = torch.Generator().manual_seed(2)
    imgs = torch.randint(0, 256, (4, 1, 11, 13), dtype=torch.uint8, generator=g)
    whole = integral_image(imgs)
    for b in range(4):
        torch.testing.assert_close(
            whole[b : b + 1], integral_image(imgs[b : b + 1]), rtol=0, atol=0
        )


def test_module_agrees_with_function():
    imgs = torch.arange(24, dtype=torch.uint8).reshape(1, 2, 3, 4)
    torch.testing.assert_close(
        IntegralImage(squared=True)(imgs), integral_image(imgs, squared=True)
    )


def test_rgb_to_gray_matches_cv2():
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, size=(6, 5, 3), dtype=np.uint8)
    ours = rgb_to_gray(torch.from_numpy(rgb).permute(2, 0, 1)[None])[0, 0].numpy()
    ref = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    np.testing.assert_allclose(ours, ref, atol=0.51)  # cv2 rounds to uint8


@pytest.mark.parametrize(
    "bad, match",
    [
        (torch.zeros(3, 4), r"\(B, C, H, W\)"),
        (np.zeros((1, 1, 2, 2)), "torch.Tensor"),
        (torch.zeros(1, 1, 2, 2, dtype=torch.bool), "integer or floating"),
    ],
)
def test_bad_input(bad, match):
    with pytest.raises(ShapeError, match=match):
        integral_image(bad)


@pytest.mark.parametrize("dtype", ["float32", torch.bool, torch.int32, torch.complex64, None])
def test_result_dtype_must_be_a_floating_torch_dtype(dtype):
    # "float32" was torch's RuntimeError 'Invalid device string', torch.bool a table of bools
    img = torch.ones(1, 1, 2, 3, dtype=torch.uint8)
    with pytest.raises(ConfigError, match=r"integral_image: dtype must be a floating torch dtype"):
        integral_image(img, dtype=dtype)
    with pytest.raises(ConfigError, match=r"dtype must be a floating torch dtype .* got"):
        IntegralImage(dtype=dtype)(img)
    assert integral_image(img, dtype=torch.float32).dtype == torch.float32


def test_gray_rejects_two_channels():
    with pytest.raises(ShapeError, match="1 \\(gray\\) or 3 \\(RGB\\)"):
        rgb_to_gray(torch.zeros(1, 2, 3, 3))


def test_feature_banks_refuse_pixels_that_are_not_8_bit_levels():
    """NaN or infinite pixels gave NaN features, which the classifiers turned into an
    ordinary-looking probability (a NaN frame scored 1e-7, like an empty window), and 16-bit
    levels were read on the 8-bit scale, silently: both are DataErrors naming the range, for
    Haar and channel banks and for the public channel function. uint8 frames, floats inside
    [0, 255] and empty batches pass as before."""
    from torchtrack.features.channels import channel_integrals, compute_channels
    from torchtrack.features.haar import integrals as haar_integrals
    from torchtrack.features.integral import check_pixel_values

    ok = torch.full((1, 3, 8, 8), 255.0, dtype=torch.float64)
    for fn in (check_pixel_values, compute_channels, channel_integrals, haar_integrals):
        fn(ok)
        fn(ok.to(torch.uint8))
        fn(ok[:0])
        for bad in (math.nan, math.inf, -math.inf):
            frame = ok.clone()
            frame[0, 1, 2, 3] = bad
            with pytest.raises(DataError, match="NaN or infinite values"):
                fn(frame)
        sixteen = (ok * 257).to(torch.int32)
        sixteen[0, 0, 0, 0] = 0
        with pytest.raises(DataError, match=r"values in \[0, 65535\].*divide by 257"):
            fn(sixteen)
        with pytest.raises(DataError, match=r"values in \[-1, 255\]"):
            fn(torch.cat([ok, -ok / 255]))


@pytest.mark.skipif(not hasattr(torch, "uint16"), reason="torch without uint16")
def test_uint16_frames_are_checked_not_a_torch_error():
    """torch has no aminmax for uint16 (16-bit PNGs): the pixel check failed with its
    NotImplementedError ('aminmax_cpu' not implemented for 'UInt16') in every feature bank.
    16-bit levels are the DataError that says to divide by 257; 8-bit levels in uint16 pass."""
    from torchtrack.features.channels import channel_integrals
    from torchtrack.features.haar import integrals as haar_integrals
    from torchtrack.features.integral import check_pixel_values

    eight = torch.full((1, 3, 8, 8), 255, dtype=torch.uint8)
    for fn in (check_pixel_values, channel_integrals, haar_integrals):
        fn(eight.to(torch.uint16))
        with pytest.raises(DataError, match=r"values in \[65535, 65535\].*divide by 257"):
            fn(eight.to(torch.uint16) * 257)
