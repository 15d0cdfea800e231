"""Integral channel features: channels against kornia and hand-made images, features against a
pixel-loop reference, the scanning lattice and the training path against the any-box reader,
octave levels, validation of channel sets and banks."""

from __future__ import annotations

import pytest
import torch
from torch.nn import functional as F

from torchtrack.errors import ConfigError, ShapeError
from torchtrack.features.channels import (
    CHANNEL_NAMES,
    ChannelBank,
    ChannelFeatures,
    ChannelSet,
    _integral,
    box_levels,
    channel_bank,
    channel_features_at,
    compute_channels,
    scale_lattice,
    window_features,
)


def frames(b=2, h=70, w=90, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (b, 3, h, w), dtype=torch.uint8, generator=g)


def small_bank(**kw):
    return channel_bank((32, 16), ChannelSet(), boxes=60, haar=60, **kw)


def reference(ch: torch.Tensor, bank: ChannelBank, x: int, y: int) -> torch.Tensor:
    """Pixel-loop reference: every feature of a window at (x, y), scale 1, from ``ch (C, H, W)``."""
    win = ch[:, y : y + bank.window[0], x : x + bank.window[1]].double()
    c = bank.cell
    out = torch.zeros(len(bank), dtype=torch.float64)
    for f in range(len(bank)):
        k = int(bank.channel[f])
        for i0, j0, i1, j1, wt in bank.rects[f].tolist():
            if wt:
                out[f] += wt * win[k, i0 * c : i1 * c, j0 * c : j1 * c].mean()
    return out


def test_luv_is_kornias_for_uint8_and_float_frames():
    from kornia.color import rgb_to_luv

    x = frames(1)
    ours = compute_channels(x, ChannelSet(names=("L", "U", "V")))
    ref = rgb_to_luv(x.float() / 255.0) / 100.0
    torch.testing.assert_close(ours, ref, atol=2e-5, rtol=0)
    ours_f = compute_channels(x.float(), ChannelSet(names=("L", "U", "V")))
    torch.testing.assert_close(ours_f, ref, atol=2e-5, rtol=0)


def test_gray_frame_on_a_colour_set_has_neutral_colour():
    """Documented: a colour model given a grayscale image sees R = G = B, so U = V = 0."""
    g = frames(1)[:, :1]
    cs = ChannelSet()
    a = compute_channels(g, cs)
    b = compute_channels(g.expand(-1, 3, -1, -1), cs)
    torch.testing.assert_close(a, b)
    assert a[:, 1:3].abs().max() < 1e-3  # U, V


def test_orientation_channels_follow_the_edge_direction():
    img = torch.zeros(1, 1, 40, 40)
    img[..., :, 20:] = 255.0  # a vertical edge: the gradient points along x (orientation 0)
    cs = ChannelSet(names=("gray", "grad", "orient"), orientations=6, norm_radius=0)
    ch = compute_channels(img, cs)
    o = ch[0, 2:, 20, 19:21].sum(-1)  # the six orientation channels at the edge
    assert int(o.argmax()) == 0 and float(o[0]) > 0.99 * float(o.sum())
    torch.testing.assert_close(ch[0, 2:].sum(0), ch[0, 1])  # the bins split the magnitude
    rot = compute_channels(img.transpose(-1, -2), cs)  # a horizontal edge: orientation 3 (pi/2)
    assert int(rot[0, 2:, 19:21, 20].sum(-1).argmax()) == 3


def test_local_normalisation_makes_gradients_contrast_invariant():
    img = torch.zeros(1, 1, 40, 40)
    img[..., :, 20:] = 200.0
    cs = ChannelSet(names=("gray", "grad"), norm_radius=5)
    a = compute_channels(img, cs)[0, 1]
    b = compute_channels(img * 0.5, cs)[0, 1]
    assert float((a - b).abs().max()) < 0.05 * float(a.max())


def test_integral_cv2_path_equals_cumsum():
    ch = torch.rand(2, 5, 33, 41)
    got = _integral(list(ch.unbind(1)))
    ref = torch.zeros((2, 34, 42, 5), dtype=torch.float64)
    ref[:, 1:, 1:] = ch.double().permute(0, 2, 3, 1).cumsum(1).cumsum(2)
    torch.testing.assert_close(got, ref, rtol=0, atol=1e-9)
    assert got.is_contiguous()


def test_integral_of_planes_is_the_interleaved_integral_to_the_bit():
    """One ``cv2.integral`` per plane, interleaved afterwards, gives the table of one
    ``cv2.integral`` of the interleaved channels (the path before) bit for bit; one plane too."""
    import cv2

    g = torch.Generator().manual_seed(3)
    for c in (1, 10):
        ch = torch.rand(1, c, 57, 73, generator=g) * torch.logspace(-6, 2, c).view(1, c, 1, 1)
        got = _integral(list(ch.unbind(1)))
        hwc = ch[0].permute(1, 2, 0).contiguous().numpy()
        ref = torch.from_numpy(cv2.integral(hwc, sdepth=cv2.CV_64F)).reshape(1, 58, 74, c)
        assert torch.equal(got, ref)


def test_features_at_scale_one_equal_a_pixel_loop():
    x = frames()
    bank = small_bank()
    ch = compute_channels(x, bank.channels)
    boxes = torch.tensor([[[3.0, 5.0, 16.0, 32.0]], [[40.0, 30.0, 16.0, 32.0]]])
    got = channel_features_at(bank.integrals(x), boxes, bank)
    for b, (bx, by) in enumerate(((3, 5), (40, 30))):
        torch.testing.assert_close(
            got[b, 0].double(), reference(ch[b], bank, bx, by), atol=2e-5, rtol=0
        )


def test_fractional_box_reads_area_integrals():
    """A box at scale 0.5 and a fractional position reads the exact area integral: equal to the
    scale-1 box on the frame upsampled by 2 (nearest neighbour), with its channels computed on
    the original frame (channels are computed once per octave, not per box)."""
    x = frames(1)
    bank = small_bank()
    ch = compute_channels(x, bank.channels)
    up = ch.repeat_interleave(2, -1).repeat_interleave(2, -2)
    box = torch.tensor([[[10.5, 7.5, 8.0, 16.0]]])
    got = channel_features_at(bank.integrals(x), box, bank)[0, 0].double()
    ref = reference(up[0], bank, 21, 15)
    lam = torch.tensor(bank.channels.lambdas, dtype=torch.float64)[bank.channel]
    torch.testing.assert_close(got, ref * 0.5**lam, atol=2e-5, rtol=0)  # the power law r ** lambda


def test_octave_levels():
    assert box_levels(torch.tensor([0.3, 1.0, 1.4, 1.5, 2.9, 3.0, 100.0]), 3).tolist() == [
        0,
        0,
        0,
        1,
        2,
        2,
        3,
    ]
    # a box at scale 2 is read at level 1: the scale-1 box on the 2x2-averaged frame
    x = frames(1, 80, 96)
    bank = small_bank()
    got = channel_features_at(bank.integrals(x), torch.tensor([[[8.0, 4.0, 32.0, 64.0]]]), bank)
    half = F.avg_pool2d(x.float(), 2)
    ref = channel_features_at(bank.integrals(half), torch.tensor([[[4.0, 2.0, 16.0, 32.0]]]), bank)
    torch.testing.assert_close(got, ref, atol=1e-5, rtol=0)


@pytest.mark.parametrize("size", [(80, 96), (81, 97), (45, 70)])
def test_octave_levels_of_8_bit_frames_are_avg_pool2d_bit_for_bit(size):
    """Levels 1-3 of integer frames come from exact 2 x 2 block sums (faster than avg_pool2d);
    their tables equal those of avg_pool2d's means, bit for bit, odd sizes included."""
    from torchtrack.features.channels import ChannelIntegrals, _block_means

    bank = small_bank()
    x = torch.randint(0, 256, (2, 3, *size), generator=torch.Generator().manual_seed(0))
    x = x.to(torch.uint8)
    ints = bank.integrals(x)
    for k in (1, 2, 3):
        ref = F.avg_pool2d(x.float(), 1 << k)
        assert torch.equal(_block_means(x, k), ref)
        want = ChannelIntegrals(ref, bank.channels).level(0)
        assert torch.equal(ints.level(k), want)


@pytest.mark.parametrize("scale", [0.5, 0.77, 1.0, 1.3, 1.6, 2.5])
def test_scan_lattice_equals_the_any_box_reader(scale):
    x = frames(2, 120, 160)
    bank = small_bank()
    ints = bank.integrals(x)
    lat = scale_lattice(ints, bank, scale, step=(1, 2))
    boxes = lat.boxes.float()[None].expand(2, -1, -1)
    ref = channel_features_at(ints, boxes, bank)
    c, i, j, coef, lam = bank.padded_points(None, torch.device("cpu"))
    li, lj = lat.shape
    for b in range(2):
        base = ((b * li + lat.origins[:, 0]) * lj + lat.origins[:, 1]) * lat.channels
        idx = base[:, None, None] + ((i * lj + j) * lat.channels + c)[None]
        got = (lat.values[idx] * coef).sum(-1) * lat.norm * torch.exp(lat.logr * lam)
        torch.testing.assert_close(got.float(), ref[b], atol=2e-5, rtol=0)
    # windows lie inside the frame on the step grid
    assert bool((lat.boxes[:, 0] + lat.boxes[:, 2] <= 160 + 1e-6).all())
    assert bool((lat.boxes[:, 1] + lat.boxes[:, 3] <= 120 + 1e-6).all())


@pytest.mark.parametrize("scale", [0.5, 1.0, 1.6])
def test_scan_lattice_over_the_edges_reads_the_padded_frame(scale):
    """Windows up to ``outside`` cells over the edges, on frames padded by ``frame_pad`` px:
    the features of the any-box reader on the padded frames at the shifted boxes."""
    x = frames(1, 120, 160)
    bank = small_bank()
    py, px = 20, 13
    padded = F.pad(x.float(), (px, px, py, py), mode="replicate")
    ints = bank.integrals(padded)
    lat = scale_lattice(ints, bank, scale, step=(1, 2), outside=(2, 1), frame_pad=(py, px))
    cs = bank.cell * scale
    assert lat.boxes[:, 0].min().item() == pytest.approx(-cs)
    assert lat.boxes[:, 1].min().item() == pytest.approx(-2 * cs)
    assert bool((lat.boxes[:, 0] + lat.boxes[:, 2] <= 160 + cs + 1e-6).all())
    assert bool((lat.boxes[:, 1] + lat.boxes[:, 3] <= 120 + 2 * cs + 1e-6).all())
    assert (lat.boxes[:, 1] + lat.boxes[:, 3]).max().item() > 120  # some hang over the bottom
    shifted = (lat.boxes + torch.tensor([px, py, 0.0, 0.0], dtype=torch.float64)).float()
    ref = channel_features_at(ints, shifted[None], bank)[0]
    c, i, j, coef, lam = bank.padded_points(None, torch.device("cpu"))
    lj = lat.shape[1]
    base = (lat.origins[:, 0] * lj + lat.origins[:, 1]) * lat.channels
    idx = base[:, None, None] + ((i * lj + j) * lat.channels + c)[None]
    got = (lat.values[idx] * coef).sum(-1) * lat.norm * torch.exp(lat.logr * lam)
    torch.testing.assert_close(got.float(), ref, atol=2e-5, rtol=0)
    with pytest.raises(ConfigError, match="frame_pad"):
        scale_lattice(ints, bank, 8.0, outside=(2, 1), frame_pad=(py, px))
    with pytest.raises(ConfigError, match="outside"):
        scale_lattice(ints, bank, scale, outside=(-1, 0))


def test_window_features_equal_the_any_box_reader():
    x = frames(3, 40, 24)
    bank = small_bank()
    got = window_features(x, bank, (4, 4, 16, 32))
    ref = channel_features_at(
        bank.integrals(x), torch.tensor([4.0, 4, 16, 32]).expand(3, 1, 4), bank
    )
    torch.testing.assert_close(got, ref[:, 0], atol=2e-5, rtol=0)
    half = F.avg_pool2d(x.float(), 2)  # a window at scale 0.5 with 2-px cells
    got = window_features(half, bank, (2, 2, 8, 16))
    ref = channel_features_at(
        bank.integrals(half), torch.tensor([2.0, 2, 8, 16]).expand(3, 1, 4), bank
    )
    torch.testing.assert_close(got, ref[:, 0], atol=2e-5, rtol=0)
    with pytest.raises(ShapeError, match="whole-pixel cells"):
        window_features(x, bank, (0, 0, 12, 24))  # scale 0.75: 3-px cells are fine ...
        window_features(x, bank, (0, 0, 10, 20))  # ... 2.5-px cells are not


def test_batch_equals_single_frames_and_the_module_wrapper():
    x = frames(2)
    bank = small_bank()
    boxes = torch.tensor([[[1.0, 2.0, 16.0, 32.0], [10.2, 3.3, 25.0, 50.0]]] * 2)
    both = channel_features_at(bank.integrals(x), boxes, bank)
    for b in range(2):
        one = channel_features_at(bank.integrals(x[b : b + 1]), boxes[b : b + 1], bank)
        torch.testing.assert_close(both[b], one[0])
    idx = torch.tensor([3, 0, 7])
    torch.testing.assert_close(ChannelFeatures(bank, idx)(x, boxes), both[..., idx])


def test_channel_set_validation():
    with pytest.raises(
        ConfigError, match="unknown channel name 'XYZ'.*" + ", ".join(CHANNEL_NAMES)
    ):
        ChannelSet(names=("L", "XYZ"))
    with pytest.raises(ConfigError, match="distinct"):
        ChannelSet(names=("L", "L"))
    with pytest.raises(ConfigError, match="orientations"):
        ChannelSet(orientations=0)
    with pytest.raises(ConfigError, match="norm_const"):
        ChannelSet(norm_const=-1.0)
    cs = ChannelSet(names=("gray", "grad", "orient"), orientations=4)
    assert cs.channels == ("gray", "grad", "orient0", "orient1", "orient2", "orient3")
    assert ChannelSet.from_dict(cs.to_dict()) == cs
    with pytest.raises(ConfigError, match="unknown channel-set key"):
        ChannelSet.from_dict({**cs.to_dict(), "gamma": 2})
    with pytest.raises(ConfigError, match="list of strings"):
        ChannelSet.from_dict({"names": "L"})
    with pytest.raises(ConfigError, match="norm_radius"):
        ChannelSet.from_dict({"names": ["L"], "norm_radius": 2.5})


def test_bank_validation_and_round_trip():
    bank = small_bank()
    again = ChannelBank.from_dict(bank.to_dict(), bank.tensors())
    assert torch.equal(again.rects, bank.rects) and again.channels == bank.channels
    sub = bank.subset(torch.tensor([5, 1]))
    assert sub.describe(0) == bank.describe(5) and len(sub) == 2
    bad = bank.rects.clone()
    bad[0, 0, 2] = 99  # a rectangle past the window
    with pytest.raises(ConfigError, match="inside the 8x4-cell window"):
        ChannelBank(bank.window, bank.channels, bad, bank.channel)
    with pytest.raises(ConfigError, match="channels must lie"):
        ChannelBank(bank.window, bank.channels, bank.rects, bank.channel + 100)
    d = bank.to_dict()
    with pytest.raises(ConfigError, match="unknown channel name"):
        ChannelBank.check_header({**d, "channels": {**d["channels"], "names": ["L", "Q"]}})
    with pytest.raises(ConfigError, match="unknown channel bank key"):
        ChannelBank.check_header({**d, "extra": 1})
    with pytest.raises(ConfigError, match="multiples of the cell"):
        ChannelBank.check_header({**d, "window": [30, 16]})
    with pytest.raises(ConfigError, match="n_features"):
        ChannelBank.check_header({**d, "n_features": 10**9})
    with pytest.raises(ConfigError, match="shape"):
        ChannelBank.from_dict(d, {"rects": bank.rects[:3], "channel": bank.channel})


def test_errors():
    bank = small_bank()
    ints = bank.integrals(frames(1))
    with pytest.raises(ShapeError, match=r"\(B, N, 4\)"):
        channel_features_at(ints, torch.zeros(3, 4), bank)
    with pytest.raises(ShapeError, match="1 \\(gray\\) or 3 \\(RGB\\)"):
        compute_channels(torch.zeros(1, 2, 8, 8))
    other = channel_bank((32, 16), ChannelSet(names=("gray",)), boxes=5, haar=0)
    with pytest.raises(ShapeError, match="integrals of channels"):
        channel_features_at(ints, torch.zeros(1, 1, 4) + 4, other)


@pytest.mark.parametrize("chunk", [256, 5])
def test_many_boxes_of_mixed_levels_equal_one_box_at_a_time(chunk, monkeypatch):
    """The lattice-major reads of many boxes at once (boxes on the innermost axis, in blocks
    of ``_BOX_CHUNK``) give exactly the values of each box read alone."""
    import torchtrack.features.channels as channels_mod

    monkeypatch.setattr(channels_mod, "_BOX_CHUNK", chunk)
    x = frames(1, h=90, w=120)
    bank = small_bank()
    g = torch.Generator().manual_seed(2)
    n = 37
    scale = torch.rand(n, generator=g, dtype=torch.float64) * 2.5 + 0.4  # levels 0 and 1
    wh = torch.stack((16 * scale, 32 * scale), 1)
    xy = torch.rand(n, 2, generator=g, dtype=torch.float64) * torch.tensor([100.0, 70.0]) - 5
    boxes = torch.cat((xy, wh), 1)[None]
    ints = bank.integrals(x)
    many = channel_features_at(ints, boxes, bank)
    for j in range(n):
        one = channel_features_at(ints, boxes[:, j : j + 1], bank)
        assert torch.equal(many[0, j], one[0, 0])


def test_a_few_features_read_only_their_lattice_points_with_the_same_values(monkeypatch):
    """A feature subset that reads a small share of the cell lattice (a tracking head) samples
    only those points, channel by channel: the values equal the whole lattice's read bit for
    bit, on two frames, boxes of three octave levels, partly outside the frame."""
    import torchtrack.features.channels as channels_mod

    x = frames(2, h=90, w=120)
    bank = small_bank()
    index = torch.tensor([3, 17, 40, 41, 77, 90, 101, 118])
    g = torch.Generator().manual_seed(3)
    n = 300
    scale = torch.rand(2, n, generator=g, dtype=torch.float64) * 4.0 + 0.4
    wh = torch.stack((16 * scale, 32 * scale), -1)
    xy = torch.rand(2, n, 2, generator=g, dtype=torch.float64) * torch.tensor([110.0, 80.0]) - 8
    boxes = torch.cat((xy, wh), -1)
    ints = bank.integrals(x)
    hc, wc = bank.grid
    compact = channels_mod._compact_lattice(
        bank.points(index, torch.device("cpu")),
        len(index),
        wc + 1,
        (hc + 1) * (wc + 1),
        len(bank.channels.channels),
        torch.device("cpu"),
    )
    assert compact is not None and compact[1].numel() < 0.1 * 10 * (hc + 1) * (wc + 1)
    few = channel_features_at(ints, boxes, bank, index, check=False)
    monkeypatch.setattr(channels_mod, "_COMPACT_SHARE", 0.0)
    monkeypatch.setattr(channels_mod, "_COMPACT", {})
    whole = channel_features_at(ints, boxes, bank, index, check=False)
    assert torch.equal(few, whole)
    assert torch.equal(whole, channel_features_at(ints, boxes, bank, check=False)[..., index])


def test_gpu_arithmetic_of_the_channels_equals_kornias_cpu_path():
    """On CUDA the channels avoid kornia's cuDNN convolutions (TF32 rounding by default): the
    central differences and the RGB -> XYZ product they use instead give kornia's CPU values."""
    from kornia.color import rgb_to_xyz
    from kornia.filters import spatial_gradient

    from torchtrack.features import channels as C

    g = torch.Generator().manual_seed(0)
    img = torch.randint(0, 256, (2, 3, 23, 31), generator=g, dtype=torch.uint8)
    lin = C._linear_rgb(img)
    k = torch.tensor(C._XYZ, dtype=lin.dtype)
    assert torch.equal(torch.einsum("oi, ...ihw -> ...ohw", k, lin), rgb_to_xyz(lin))
    lum = C._luv(img)[:, :1] / 100
    assert torch.equal(
        C._central_differences(lum), spatial_gradient(lum, mode="diff", normalized=False)
    )


@pytest.mark.parametrize("band_bytes", [1, 700, 1 << 30])
def test_lattice_reads_in_bands_of_rows_are_the_bilinear_reads(monkeypatch, band_bytes):
    """The lattice's bilinear reads, done a band of rows at a time over the columns they need
    (one row per band, a few rows, the whole table at once): each value is the bilinear
    interpolation of the table's four neighbours, clamped at its edges, bit for bit the same
    whatever the band."""
    from torchtrack.features import channels as C

    monkeypatch.setattr(C, "_SAMPLE_CHUNK_BYTES", band_bytes)
    g = torch.Generator().manual_seed(3)
    tab = torch.rand((2, 23, 31, 3), generator=g, dtype=torch.float64).cumsum(1).cumsum(2)
    ys = torch.tensor([-0.5, 0.0, 2.3, 7.75, 21.9, 22.0, 25.0], dtype=torch.float64)
    xs = torch.tensor([4.2, 5.0, 11.6, 19.99, 29.5], dtype=torch.float64)  # columns 4-30 only
    got = C._sample_product(tab, ys, xs)
    y = ys.clamp(0, 22)
    x = xs.clamp(0, 30)
    y0, x0 = y.floor().clamp(max=21).long(), x.floor().clamp(max=29).long()
    fy, fx = (y - y0)[:, None, None], (x - x0)[None, :, None]
    for b in range(2):
        t = tab[b]
        top = t[y0][:, x0] * (1 - fx) + t[y0][:, x0 + 1] * fx
        bot = t[y0 + 1][:, x0] * (1 - fx) + t[y0 + 1][:, x0 + 1] * fx
        torch.testing.assert_close(got[b], top * (1 - fy) + bot * fy, atol=1e-9, rtol=0)
    monkeypatch.setattr(C, "_SAMPLE_CHUNK_BYTES", 1 << 30)
    assert torch.equal(got, C._sample_product(tab, ys, xs))
    assert C._sample_product(tab, ys[:0], xs).shape == (2, 0, 5, 3)


def test_a_lattice_with_no_kept_window_computes_no_channels():
    """``keep_windows`` is asked before the octave's channels are computed: a scale none of whose
    windows is kept costs nothing (the ground plane's sizes skip whole octaves)."""
    x = frames(1, 120, 160)
    bank = small_bank()
    ints = bank.integrals(x)
    assert scale_lattice(ints, bank, 2.0, keep_windows=lambda b: b[:, 0] < -1) is None
    assert ints._levels == {}
    lat = scale_lattice(ints, bank, 2.0, keep_windows=lambda b: b[:, 0] < 20)
    assert lat is not None and set(ints._levels) == {1}


def test_a_keep_function_by_row_is_asked_one_window_a_row():
    """``keep_windows.by_row`` (an answer that depends on a window's y and height only, as a
    ground plane's): asked about the first window of each lattice row, it gives the lattice of
    the same function asked about every window, windows and values alike."""
    x = frames(2, 150, 170)
    bank = small_bank()
    ints = bank.integrals(x)

    def band(b):  # window bottoms in a band
        return ((b[:, 1] + b[:, 3]) > 60) & ((b[:, 1] + b[:, 3]) < 120)

    asked = []

    def by_row(b):
        asked.append(b.shape[0])
        return band(b)

    by_row.by_row = True
    for scale in (1.0, 1.5):
        whole = scale_lattice(ints, bank, scale, 2, keep_windows=band)
        rows = scale_lattice(ints, bank, scale, 2, keep_windows=by_row)
        assert torch.equal(whole.boxes, rows.boxes) and torch.equal(whole.origins, rows.origins)
        assert torch.equal(whole.values, rows.values) and whole.shape == rows.shape
        n_i = len(scale_lattice(ints, bank, scale, 2).boxes[:, 1].unique())
        assert asked[-1] == n_i < whole.boxes.shape[0]


@pytest.mark.parametrize(
    "cs",
    [
        ChannelSet(),
        ChannelSet(names=("gray", "grad", "orient")),
        ChannelSet(names=("gray", "grad", "orient"), orientations=4),
    ],
)
@pytest.mark.parametrize("size", [(2, 70, 90), (2, 33, 47)])
def test_channels_last_layout_holds_the_same_values(cs, size):
    """``memory_format=torch.channels_last`` lays the same channels out with the channel
    innermost."""
    x = frames(*size)
    planar = compute_channels(x, cs)
    last = compute_channels(x, cs, memory_format=torch.channels_last)
    assert last.shape == planar.shape and torch.equal(last, planar)
    assert last.permute(0, 2, 3, 1).is_contiguous()
