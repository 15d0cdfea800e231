"""Pixel colour + LTP features (Jin et al. sec. 2) against loop references and scikit-image."""

import numpy as np
import pytest
import torch
from skimage.feature import local_binary_pattern

from torchtrack.errors import ConfigError, ShapeError
from torchtrack.features.pixels import (
    CHANNEL_PAIRS,
    RIU2_TABLE,
    TEXTURE_NAMES,
    PixelFeatures,
    ltp_codes,
    pixel_features,
    quantize_colour,
    region_features,
    texture_blocks,
)

# (dy, dx) of neighbour u, counter-clockwise from "right" (scikit-image's order).
OFFS = [(0, 1), (-1, 1), (-1, 0), (-1, -1), (0, -1), (1, -1), (1, 0), (1, 1)]


def loop_ltp(c: np.ndarray, n: np.ndarray, t: float):
    """Eq. (2)-(3) pixel by pixel, 3x3 square mask, replicated border."""
    h, w = c.shape
    up = np.zeros((h, w), np.int64)
    lo = np.zeros((h, w), np.int64)
    for i in range(h):
        for j in range(w):
            for u, (dy, dx) in enumerate(OFFS):
                ii, jj = min(max(i + dy, 0), h - 1), min(max(j + dx, 0), w - 1)
                d = float(n[ii, jj]) - float(c[i, j])
                up[i, j] += (d >= t) << u
                lo[i, j] += (d <= -t) << u
    return up, lo


@pytest.fixture
def image():
    g = torch.Generator().manual_seed(3)
    img = torch.randint(0, 256, (1, 3, 13, 17), generator=g, dtype=torch.uint8)
    img[:, :, 3:8, 4:9] = 120  # flat patch: ties at the threshold
    img[:, 1, 5, 6] = 125  # a +5 step: exactly at t
    return img


def test_ltp_matches_loop_reference_for_every_pair(image):
    colour, texture = pixel_features(image, threshold=5.0)
    assert colour.shape == (1, 4, 13, 17) and texture.shape == (1, 18, 13, 17)
    x = image[0].numpy()
    for k, (a, b) in enumerate(CHANNEL_PAIRS):
        up, lo = loop_ltp(x[a], x[b], 5.0)
        np.testing.assert_array_equal(texture[0, 2 * k].numpy(), up, err_msg=TEXTURE_NAMES[2 * k])
        np.testing.assert_array_equal(texture[0, 2 * k + 1].numpy(), lo)


def test_colour_features_are_rgb_and_bt601_luma(image):
    colour, _ = pixel_features(image)
    x = image[0].double()
    y = 0.299 * x[0] + 0.587 * x[1] + 0.114 * x[2]
    torch.testing.assert_close(colour[0, :3].double(), x)
    torch.testing.assert_close(colour[0, 3].double(), y, atol=1e-4, rtol=0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_upper_pattern_with_zero_threshold_is_skimage_lbp(seed):
    g = torch.Generator().manual_seed(seed)
    img = torch.randint(0, 256, (40, 50), generator=g, dtype=torch.uint8)
    img[10:20, 10:25] = 77  # flat area: equal neighbours must count as >= 0
    ref = local_binary_pattern(img.numpy(), 8, 1, method="default")
    up, _ = ltp_codes(img[None, None], img[None, None], 0.0, circular=True)
    # scikit-image pads with zeros, we replicate: compare the interior.
    np.testing.assert_array_equal(up[0, 0, 1:-1, 1:-1].numpy(), ref[1:-1, 1:-1].astype(np.int64))


def test_riu2_blocks_match_skimage_uniform():
    g = torch.Generator().manual_seed(5)
    img = torch.randint(0, 256, (30, 30), generator=g, dtype=torch.uint8)
    ref = local_binary_pattern(img.numpy(), 8, 1, method="uniform")
    up, _ = ltp_codes(img[None, None], img[None, None], 0.0, circular=True)
    got = texture_blocks(up, "riu2")
    np.testing.assert_array_equal(got[0, 0, 1:-1, 1:-1].numpy(), ref[1:-1, 1:-1].astype(np.int64))
    assert RIU2_TABLE.max() == 9 and texture_blocks(up, "full") is up


def test_gray_fallback_is_y_and_yy_patterns():
    g = torch.Generator().manual_seed(1)
    img = torch.randint(0, 256, (2, 1, 9, 11), generator=g, dtype=torch.uint8)
    colour, texture = pixel_features(img)
    assert colour.shape == (2, 1, 9, 11) and texture.shape == (2, 2, 9, 11)
    up, lo = loop_ltp(img[1, 0].numpy(), img[1, 0].numpy(), 5.0)
    np.testing.assert_array_equal(texture[1, 0].numpy(), up)
    np.testing.assert_array_equal(texture[1, 1].numpy(), lo)


def test_batch_equals_single_and_module_equals_function(image):
    batch = torch.cat([image, image.flip(-1)])
    c2, t2 = PixelFeatures(threshold=3.0)(batch)
    c1, t1 = pixel_features(image.flip(-1), 3.0)
    torch.testing.assert_close(c2[1:], c1)
    torch.testing.assert_close(t2[1:], t1)


def test_region_features_see_true_neighbours(image):
    frame = image[0]
    colour, texture = pixel_features(image)
    cc, tc = region_features(frame, (3, 2, 12, 10), colour_bins=16)
    assert cc.shape == (8 * 9, 4) and tc.shape == (8 * 9, 18)
    assert cc.dtype == torch.uint8 and tc.dtype == torch.uint8
    want_t = texture[0, :, 2:10, 3:12].flatten(1).T
    torch.testing.assert_close(tc.long(), want_t)
    want_c = quantize_colour(colour[0, :, 2:10, 3:12], 16).flatten(1).T
    torch.testing.assert_close(cc.long(), want_c)
    # the float path (same values as floats) and the riu2 blocks agree with the reference
    cf, tf = region_features(frame.float(), (3, 2, 12, 10), colour_bins=16)
    torch.testing.assert_close(tf, tc)
    torch.testing.assert_close(cf, cc)
    _, tr = region_features(frame, (3, 2, 12, 10), blocks="riu2")
    torch.testing.assert_close(tr.long(), texture_blocks(want_t, "riu2"))
    assert int(cc.max()) < 16


@pytest.mark.parametrize("t", [0.0, 4.5, 5.0, 300.0])
def test_integer_path_equals_float_path(image, t):
    c, n = image[:, :2], image[:, 1:]
    up_i, lo_i = ltp_codes(c, n, t)
    up_f, lo_f = ltp_codes(c.float(), n.float(), t)
    torch.testing.assert_close(up_i, up_f)
    torch.testing.assert_close(lo_i, lo_f)
    assert up_i.dtype == torch.int64


def test_errors():
    with pytest.raises(ShapeError, match="1 \\(gray\\) or 3"):
        pixel_features(torch.zeros(1, 2, 4, 4))
    with pytest.raises(ShapeError, match="\\(B, C, H, W\\)"):
        pixel_features(torch.zeros(4, 4))
    with pytest.raises(ConfigError, match="threshold must be >= 0"):
        ltp_codes(torch.zeros(1, 1, 3, 3), torch.zeros(1, 1, 3, 3), -1.0)
    with pytest.raises(ShapeError, match="equal"):
        ltp_codes(torch.zeros(1, 1, 3, 3), torch.zeros(1, 1, 3, 4))
    with pytest.raises(ConfigError, match="outside"):
        region_features(torch.zeros(3, 10, 10, dtype=torch.uint8), (5, 5, 12, 8))
    with pytest.raises(ConfigError, match="colour bins"):
        quantize_colour(torch.zeros(3), 0)
    frame = torch.zeros(3, 10, 10, dtype=torch.uint8)
    with pytest.raises(ConfigError, match="colour bins"):
        region_features(frame, (0, 0, 5, 5), colour_bins=300)
    with pytest.raises(ConfigError, match="texture blocks"):
        region_features(frame, (0, 0, 5, 5), blocks="lbp")
    with pytest.raises(ConfigError, match="threshold must be >= 0"):
        region_features(frame, (0, 0, 5, 5), threshold=-1.0)
    with pytest.raises(ShapeError, match="1 \\(gray\\) or 3"):
        region_features(torch.zeros(2, 10, 10, dtype=torch.uint8), (0, 0, 5, 5))
    with pytest.raises(ConfigError, match="texture blocks"):
        texture_blocks(torch.zeros(3, dtype=torch.long), "lbp")


def test_bad_pixels_thresholds_bins_regions_and_codes_are_refused():
    """NaN pixels gave NaN colour features (and texture codes of 0); threshold=True was 1 and
    '5' a TypeError; colour bins 2.5 / True went through int(); a NaN region was int()'s
    ValueError, True a bound of 1, 5.5 cut to 5; float texture codes or codes past 255 were
    IndexErrors; NaN colour was quantised to bin 0."""
    from torchtrack.errors import DataError

    frame = torch.randint(0, 256, (3, 20, 20), dtype=torch.uint8)
    with pytest.raises(DataError, match="images hold NaN"):
        pixel_features(torch.full((1, 3, 4, 4), float("nan")))
    for bad in (True, "5", float("inf")):
        with pytest.raises(ConfigError, match=r"LTP threshold must be >= 0 \(a finite number\)"):
            pixel_features(frame[None], threshold=bad)
    for bad in (2.5, True):
        with pytest.raises(ConfigError, match=r"colour bins must be in 1\.\.256 \(an integer\)"):
            region_features(frame, (2, 2, 10, 10), colour_bins=bad)
        with pytest.raises(ConfigError, match=r"colour bins must be in 1\.\.256"):
            quantize_colour(torch.zeros(1, 4, 2, 2), bad)
    for bad in ((float("nan"), 2, 10, 10), (True, 2, 10, 10), (2.5, 2, 10, 10)):
        with pytest.raises(ConfigError, match="region must be 4 integer pixel bounds"):
            region_features(frame, bad)
    a = region_features(frame, (2, 2, 10, 10))
    b = region_features(frame, torch.tensor([2, 2, 10, 10]))  # tensors of integers: as before
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))
    with pytest.raises(ShapeError, match="codes must be an integer tensor"):
        texture_blocks(torch.zeros(1, 4, 4))
    with pytest.raises(ShapeError, match=r"codes must be in 0\.\.255, got 0\.\.300"):
        texture_blocks(torch.tensor([0, 300]))
    torch.testing.assert_close(  # uint8 codes were read as a mask (IndexError)
        texture_blocks(torch.tensor([0, 255], dtype=torch.uint8)),
        texture_blocks(torch.tensor([0, 255])),
    )
    with pytest.raises(DataError, match="colour holds NaN"):
        quantize_colour(torch.full((1, 4, 2, 2), float("nan")))
