"""Colour histograms (Pérez et al.): HSV binning, sampled box histograms, Bhattacharyya."""

from __future__ import annotations

import colorsys

import pytest
import torch

from torchtrack.errors import ConfigError, ShapeError
from torchtrack.io.video import read_image
from torchtrack.observe.histogram import (
    FrameBins,
    HSVBins,
    bhattacharyya,
    box_histograms,
    hsv_bin_map,
    region_histograms,
)


@pytest.fixture(scope="module")
def frame(data_dir):
    return read_image(data_dir / "tracking" / "bobot_pedestrian" / "frames" / "img0002.jpg")


def reference_bin(rgb, bins: HSVBins) -> int:
    """Pérez et al.'s rule with colorsys' exact HSV (floats)."""
    h, s, v = colorsys.rgb_to_hsv(*(c / 255.0 for c in rgb))
    if s > bins.s_min and v > bins.v_min:
        return min(int(h * bins.n_h), bins.n_h - 1) * bins.n_s + min(
            int(s * bins.n_s), bins.n_s - 1
        )
    return bins.n_h * bins.n_s + min(int(v * bins.n_v), bins.n_v - 1)


def test_bin_map_matches_colorsys_reference(frame):
    bins = HSVBins()
    patch = frame[:, 40:80, 100:150]
    m = hsv_bin_map(patch[None], bins)[0]
    ref = torch.tensor(
        [[reference_bin(patch[:, y, x].tolist(), bins) for x in range(50)] for y in range(40)]
    )
    # OpenCV rounds 8-bit S and H (2-degree steps): pixels on a bin border may move one bin.
    assert float((m == ref).float().mean()) > 0.95
    assert int(m.min()) >= 0 and int(m.max()) < bins.n_bins


def test_gray_frames_use_value_bins_only(frame):
    bins = HSVBins()
    gray = frame[:1]
    m = hsv_bin_map(gray[None], bins)[0]
    assert bool((m >= 100).all())
    assert torch.equal(m, 100 + (gray[0].long() * 10 // 256))


def test_grid_histogram_equals_exact_histogram_when_one_sample_per_pixel(frame):
    bins = HSVBins()
    m = hsv_bin_map(frame[None], bins)
    boxes = torch.tensor([[[10.0, 20.0, 16.0, 16.0], [200.0, 100.0, 16.0, 16.0]]])
    fast = box_histograms(m, boxes, bins.n_bins, grid=16)
    torch.testing.assert_close(fast, region_histograms(m, boxes, bins.n_bins))
    assert torch.allclose(fast.sum(-1), torch.ones(1, 2))


def test_boxes_outside_the_frame(frame):
    bins = HSVBins()
    m = hsv_bin_map(frame[None], bins)
    w = frame.shape[-1]
    boxes = torch.tensor([[[w + 5.0, 0.0, 20.0, 20.0], [-8.0, 0.0, 16.0, 16.0]]])
    hist = box_histograms(m, boxes, bins.n_bins, grid=16)
    assert float(hist[0, 0].sum()) == 0.0  # no sample inside
    # Half the box is inside: its histogram is that of the inside half.
    inside = region_histograms(m, torch.tensor([[[0.0, 0.0, 8.0, 16.0]]]), bins.n_bins)
    torch.testing.assert_close(hist[0, 1], inside[0, 0])


def test_bhattacharyya_against_loop():
    g = torch.Generator().manual_seed(0)
    p = torch.rand(4, 7, generator=g)
    p /= p.sum(-1, keepdim=True)
    q = torch.rand(7, generator=g)
    q /= q.sum()
    ref = torch.tensor([sum((p[i, k] * q[k]).sqrt() for k in range(7)) for i in range(4)])
    torch.testing.assert_close(bhattacharyya(p, q), ref)
    assert float(bhattacharyya(q, q)) == pytest.approx(1.0)
    a = torch.tensor([0.5, 0.5, 0.0, 0.0])
    assert float(bhattacharyya(a, a.flip(0))) == 0.0


@pytest.mark.parametrize("bins", [HSVBins(), HSVBins(n_h=18, n_s=16, n_v=8, s_min=0.3)])
def test_frame_bins_bin_only_the_samples_the_same_as_the_whole_map(frame, bins):
    """What the multi-target tracker reads: FrameBins gives the histograms and pixel bins of
    hsv_bin_map, bit for bit, in colour, in gray, and with boxes over the frame's edges."""
    g = torch.Generator().manual_seed(0)
    h, w = frame.shape[-2:]
    boxes = torch.rand((2, 9, 4), generator=g) * torch.tensor([w, h, 80.0, 160.0])
    boxes[..., :2] -= 40  # some boxes over the top and left edges
    frames = torch.stack((frame, frame.flip(-1)))  # (2, 3, H, W): two frames
    for f in (frames, frames[:, :1].contiguous()):
        whole, lazy = hsv_bin_map(f, bins), FrameBins(f, bins)
        assert lazy.shape == tuple(whole.shape)
        flat = torch.randint(0, h * w, (2, 5000), generator=g)
        assert torch.equal(lazy.take(flat), whole.reshape(2, -1).gather(1, flat).long())
        for grid in (4, 8, 16):
            assert torch.equal(
                box_histograms(lazy, boxes, bins.n_bins, grid),
                box_histograms(whole, boxes, bins.n_bins, grid),
            )
    with pytest.raises(ShapeError, match="uint8"):
        FrameBins(frames.float(), bins)


def test_errors(frame):
    with pytest.raises(ConfigError, match="n_h"):
        HSVBins(n_h=0)
    with pytest.raises(ConfigError, match="s_min"):
        HSVBins(s_min=1.5)
    with pytest.raises(ShapeError, match="uint8"):
        hsv_bin_map(frame[None].float(), HSVBins())
    m = hsv_bin_map(frame[None], HSVBins())
    with pytest.raises(ShapeError, match=r"\(B, N, 4\)"):
        box_histograms(m, torch.zeros(3, 4), 110)
    with pytest.raises(ConfigError, match="grid"):
        box_histograms(m, torch.zeros(1, 3, 4), 110, grid=0)
    with pytest.raises(ShapeError, match="bins"):
        bhattacharyya(torch.ones(3), torch.ones(4))


def test_box_histograms_refuse_bad_boxes_bins_and_grids():
    """A bin past n_bins was counted in the next box's histogram (the last box's was an
    IndexError); a NaN box gave the empty histogram of a box outside the frame and a negative
    size one of pixels sampled backwards; float bins were truncated; grid=2.5 was reshape's
    TypeError; all without a word (or a traceback)."""
    from torchtrack.errors import BoxError

    bm = torch.tensor([[[3, 1], [2, 0]]])  # box 0 samples bin 3, box 1 bin 0
    bx = torch.tensor([[[0.0, 0, 1, 1], [1.0, 1, 1, 1]]])
    assert box_histograms(bm, bx, 4, grid=1)[0, :, :].argmax(-1).tolist() == [3, 0]
    with pytest.raises(ShapeError, match=r"bin_map holds bins 0..3, outside \[0, 2\)"):
        box_histograms(bm, bx, 2, grid=1)  # box 0's bin 3 landed in box 1's bin 1
    with pytest.raises(ShapeError, match="bin_map must hold integer bin indices"):
        box_histograms(bm.float(), bx, 4, grid=1)
    for bad in ([float("nan"), 0, 1, 1], [1.0, 1, -1, -1]):
        with pytest.raises(BoxError, match=r"boxes\[0, 0\] = .* must be finite"):
            box_histograms(bm, torch.tensor([[bad]]), 4, grid=1)
    for kw in ({"grid": 2.5}, {"grid": True}, {"n_bins": 0}):
        with pytest.raises(ConfigError, match=r"box_histograms: \w+ must be an integer >= 1"):
            box_histograms(bm, bx, **({"n_bins": 4, "grid": 1} | kw))
    frame = torch.randint(0, 256, (1, 3, 4, 4), dtype=torch.uint8)
    with pytest.raises(ConfigError, match="n_bins = 10 but the frames are binned into 110"):
        box_histograms(FrameBins(frame, HSVBins()), torch.tensor([[[0.0, 0, 4, 4]]]), 10)


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"n_h": "10"}, r"n_h must be an integer in \[1, 256\], got '10'"),
        ({"n_s": True}, r"n_s must be an integer in \[1, 256\], got True"),
        ({"n_v": 2.5}, r"n_v must be an integer in \[1, 256\]"),
        ({"n_h": 10**6}, r"n_h must be an integer in \[1, 256\]"),
        ({"n_h": None}, r"n_h must be an integer"),
        ({"s_min": "0.1"}, r"s_min must be a number in \[0, 1\)"),
    ],
)
def test_hsv_bins_refuse_what_is_not_a_bin_count(kw, match):
    """'10' and 2.5 went through int(), True was one bin, 10**6 x 10**6 bins sized every
    histogram by 10**12 and None was int()'s TypeError."""
    with pytest.raises(ConfigError, match=match):
        HSVBins(**kw)
