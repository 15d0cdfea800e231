import numpy as np
import pytest
import torch

from torchtrack.errors import BoxError, ConfigError, DataError, ShapeError
from torchtrack.features.haar import (
    KINDS,
    HaarBank,
    HaarFeatures,
    haar_bank,
    haar_features,
    haar_features_at,
    haar_features_dense,
    integrals,
    paper_pedestrian_count,
)


def mask(kind: str, t: int) -> np.ndarray:
    """The filter as a T x T weight image, written out by hand."""
    m = np.zeros((t, t))
    h, q = t // 2, t // 4
    if kind == "edge_x":
        m[:, :h], m[:, h:] = 1, -1
    elif kind == "edge_y":
        m[:h], m[h:] = 1, -1
    elif kind == "diagonal":
        m[:h, :h], m[h:, h:], m[:h, h:], m[h:, :h] = 1, 1, -1, -1
    elif kind == "line_x":
        m[:], m[:, q : t - q] = -1, 1
    elif kind == "line_y":
        m[:], m[q : t - q] = -1, 1
    return m


def reference_feature(crop: np.ndarray, kind: str, t: int, y: int, x: int, min_std=1.0) -> float:
    crop = crop.astype(np.float64)
    std = max(crop.std(), min_std)
    return float((crop[y : y + t, x : x + t] * mask(kind, t)).sum() / (t * t * std))


def area_sum(img: np.ndarray, y0: float, x0: float, y1: float, x1: float) -> float:
    """Integral of the piecewise-constant image over a fractional rectangle, by pixel overlaps."""
    total = 0.0
    for i in range(img.shape[0]):
        oy = max(0.0, min(y1, i + 1) - max(y0, i))
        if oy == 0:
            continue
        for j in range(img.shape[1]):
            ox = max(0.0, min(x1, j + 1) - max(x0, j))
            total += oy * ox * float(img[i, j])
    return total


def test_paper_counts():
    assert len(haar_bank((64, 64))) == 17455  # paper section 4.1, vehicles: reproduced exactly
    assert len(haar_bank((128, 64))) == 5 * (65 * 1 + 97 * 33 + 113 * 49) == 44015
    assert paper_pedestrian_count((128, 64)) == 42560  # the paper's own formula
    assert haar_bank((128, 64)).sizes == (64, 32, 16)
    assert haar_bank((40, 100)).sizes == (32, 16, 8)


def test_filters_are_zero_mean():
    for kind in KINDS:
        assert mask(kind, 8).sum() == 0
    flat = torch.full((2, 1, 16, 16), 77, dtype=torch.uint8)
    assert haar_features_dense(flat, haar_bank((16, 16))).abs().max() == 0


def test_dense_matches_slow_reference():
    g = torch.Generator().manual_seed(0)
    bank = haar_bank((24, 16), sizes=(16, 8, 4), stride=2)
    crops = torch.randint(0, 256, (3, 1, 24, 16), dtype=torch.uint8, generator=g)
    feats = haar_features_dense(crops, bank, chunk=2)
    assert feats.shape == (3, len(bank)) and feats.dtype == torch.float32
    rng = np.random.default_rng(0)
    for i in rng.choice(len(bank), size=60, replace=False):
        d = bank.describe(int(i))
        for n in range(3):
            ref = reference_feature(crops[n, 0].numpy(), d["kind"], d["size"], d["y"], d["x"])
            assert feats[n, i].item() == pytest.approx(ref, rel=1e-5, abs=1e-6)


def test_box_path_at_scale_one_equals_dense_path():
    g = torch.Generator().manual_seed(1)
    bank = haar_bank((16, 8), sizes=(8, 4))
    crops = torch.randint(0, 256, (4, 3, 16, 8), dtype=torch.uint8, generator=g)
    dense = haar_features_dense(crops, bank)
    boxes = torch.tensor([0.0, 0.0, 8.0, 16.0]).expand(4, 1, 4)
    torch.testing.assert_close(haar_features(crops, boxes, bank)[:, 0], dense, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("factor", [2, 3])
def test_integer_upscaled_box_gives_same_features(factor):
    # Nearest-neighbour upscaling by k and a box k times the window: every rectangle sum is
    # k^2 times the original and the normalisation divides it out exactly.
    g = torch.Generator().manual_seed(2)
    bank = haar_bank((16, 8), sizes=(8, 4))
    crops = torch.randint(0, 256, (2, 1, 16, 8), dtype=torch.uint8, generator=g)
    big = crops.repeat_interleave(factor, 2).repeat_interleave(factor, 3)
    frame = torch.randint(0, 256, (2, 1, 80, 70), dtype=torch.uint8, generator=g)
    frame[:, :, 5 : 5 + 16 * factor, 9 : 9 + 8 * factor] = big
    boxes = torch.tensor([9.0, 5.0, 8.0 * factor, 16.0 * factor]).expand(2, 1, 4)
    torch.testing.assert_close(
        haar_features(frame, boxes, bank)[:, 0],
        haar_features_dense(crops, bank),
        rtol=1e-5,
        atol=1e-5,
    )


def test_fractional_box_matches_area_integral_reference():
    g = torch.Generator().manual_seed(3)
    bank = haar_bank((8, 8), sizes=(8, 4))
    frame = torch.randint(0, 256, (1, 1, 20, 20), dtype=torch.uint8, generator=g)
    box = (2.3, 1.7, 9.4, 11.1)  # x, y, w, h: non-integer position and scale
    x, y, w, h = box
    sx, sy = w / 8, h / 8
    img = frame[0, 0].numpy().astype(np.float64)
    s1 = area_sum(img, y, x, y + h, x + w)
    s2 = area_sum(img**2, y, x, y + h, x + w)
    mean = s1 / (w * h)
    std = max(np.sqrt(s2 / (w * h) - mean**2), 1.0)
    from torchtrack.features.haar import _RECTS

    idx = torch.tensor([0, 3, 9, 11, 30, 52, len(bank) - 1])
    got = haar_features(frame, torch.tensor([[box]]), bank, idx)[0, 0]
    for j, i in enumerate(idx.tolist()):
        d = bank.describe(i)
        t = d["size"]
        raw = 0.0
        for ry0, rx0, ry1, rx1, wt in _RECTS[d["kind"]]:
            raw += wt * area_sum(
                img,
                y + (d["y"] + ry0 * t) * sy,
                x + (d["x"] + rx0 * t) * sx,
                y + (d["y"] + ry1 * t) * sy,
                x + (d["x"] + rx1 * t) * sx,
            )
        ref = raw / (t * t * sx * sy * std)
        assert got[j].item() == pytest.approx(ref, rel=1e-5, abs=1e-5)


def test_batch_equals_single_and_module_agrees():
    g = torch.Generator().manual_seed(4)
    bank = haar_bank((16, 8), sizes=(8, 4))
    frames = torch.randint(0, 256, (3, 1, 40, 50), dtype=torch.uint8, generator=g)
    boxes = torch.rand((3, 5, 4), generator=g) * torch.tensor(
        [30.0, 20.0, 10.0, 15.0]
    ) + torch.tensor([0.0, 0.0, 4.0, 8.0])
    idx = torch.tensor([1, 5, 100, 300])
    whole = haar_features(frames, boxes, bank, idx)
    for b in range(3):
        torch.testing.assert_close(
            whole[b : b + 1], haar_features(frames[b : b + 1], boxes[b : b + 1], bank, idx)
        )
    torch.testing.assert_close(HaarFeatures(bank, idx)(frames, boxes), whole)
    ints = integrals(frames)
    torch.testing.assert_close(haar_features_at(ints, boxes, bank, idx), whole)


def test_bank_round_trips_through_dict():
    bank = haar_bank((40, 100), stride=2, min_std=2.0)
    again = HaarBank.from_dict(bank.to_dict())
    assert again == bank and torch.equal(again.table, bank.table)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"window": (16, 8), "sizes": (6,)}, "multiples of 4"),
        ({"window": (16, 8), "sizes": (16,)}, "does not fit"),
        ({"window": (16, 0), "sizes": (4,)}, "window width"),
        ({"window": (16, 8), "sizes": (4,), "stride": 0}, "stride"),
        ({"window": (16, 8), "sizes": (4,), "min_std": 0.0}, "min_std"),
        ({"window": (16, 8), "sizes": (4, 4)}, "distinct"),
    ],
)
def test_bad_bank(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        HaarBank(**kwargs)


def test_n_scales_bounded_by_the_window():
    # a huge n_scales built a list of that many sizes and printed it in the error
    assert haar_bank((64, 40), n_scales=4).sizes == (32, 16, 8, 4)
    for bad in (0, 5, 2**62):
        with pytest.raises(
            ConfigError, match=r"n_scales must be an integer in \[1, 4\] for a 64x40"
        ):
            haar_bank((64, 40), n_scales=bad)


def test_bank_from_bad_dict():
    with pytest.raises(ConfigError, match="unknown Haar bank key"):
        HaarBank.from_dict({"window": [8, 8], "sizes": [4], "colour": 1})
    with pytest.raises(ConfigError, match="lacks"):
        HaarBank.from_dict({"window": [8, 8]})
    with pytest.raises(ConfigError, match="kinds"):
        HaarBank.from_dict({"window": [8, 8], "sizes": [4], "kinds": ["edge_x"]})


def test_bad_boxes_and_shapes():
    bank = haar_bank((8, 8), sizes=(4,))
    frame = torch.zeros(1, 1, 20, 20)
    with pytest.raises(BoxError, match="size below"):
        haar_features(frame, torch.tensor([[[1.0, 1.0, 0.0, 5.0]]]), bank)
    with pytest.raises(BoxError, match="size below"):
        haar_features(frame, torch.tensor([[[1.0, 1.0, -3.0, 5.0]]]), bank)
    with pytest.raises(BoxError, match="outside"):
        haar_features(frame, torch.tensor([[[30.0, 1.0, 5.0, 5.0]]]), bank)
    with pytest.raises(BoxError, match="not finite"):
        haar_features(frame, torch.tensor([[[float("nan"), 1.0, 5.0, 5.0]]]), bank)
    with pytest.raises(ShapeError, match=r"\(B, N, 4\)"):
        haar_features(frame, torch.zeros(1, 4), bank)
    with pytest.raises(ShapeError, match="2 frame"):
        haar_features(frame, torch.ones(2, 1, 4), bank)
    with pytest.raises(ShapeError, match="out of range"):
        haar_features(frame, torch.ones(1, 1, 4) * 4, bank, torch.tensor([len(bank)]))
    with pytest.raises(ShapeError, match="window-sized"):
        haar_features_dense(torch.zeros(1, 1, 9, 8), bank)


@pytest.mark.parametrize("chunk", [0, -1, 2.5, True])
def test_dense_refuses_a_bad_chunk(chunk):
    # 0 and -1 failed inside torch ('cannot reshape tensor of 0 elements')
    with pytest.raises(ConfigError, match="chunk must be an integer >= 1"):
        haar_features_dense(torch.zeros(2, 1, 8, 8), haar_bank((8, 8), sizes=(4,)), chunk=chunk)


def test_dense_refuses_an_integer_out():
    # an int64 out truncated every feature to an integer, silently
    bank = haar_bank((8, 8), sizes=(4,))
    crops = torch.randint(0, 256, (2, 1, 8, 8), dtype=torch.uint8)
    with pytest.raises(ShapeError, match="floating-point"):
        haar_features_dense(crops, bank, out=torch.zeros(2, len(bank), dtype=torch.int64))
    out = torch.zeros(2, len(bank), dtype=torch.float64)
    assert haar_features_dense(crops, bank, out=out) is out


@pytest.mark.parametrize("value", [float("nan"), 300.0, -1.0])
def test_dense_checks_pixel_values_like_the_box_path(value):
    # NaN crops gave NaN features and 16-bit levels were read as 8-bit ones, silently
    bank = haar_bank((8, 8), sizes=(4,))
    crops = torch.zeros(2, 1, 8, 8)
    crops[1, 0, 3, 3] = value
    with pytest.raises(DataError, match="crops hold"):
        haar_features_dense(crops, bank)


def test_box_partly_outside_frame_is_handled():
    bank = haar_bank((8, 8), sizes=(4,))
    g = torch.Generator().manual_seed(5)
    frame = torch.randint(0, 256, (1, 1, 20, 20), dtype=torch.uint8, generator=g)
    out = haar_features(frame, torch.tensor([[[-4.0, 15.0, 10.0, 10.0]]]), bank)
    assert torch.isfinite(out).all()


def gather_reference(frames, boxes, bank, index):
    """The previous implementation (explicit gathers, padded 9-point tables), a slow reference
    of the grid_sample path: every corner point read with ``haar._bilinear``."""
    from torchtrack.features import haar as hm

    ints = integrals(frames)
    b, n = boxes.shape[:2]
    fh, fw = ints.frame_size
    table = bank.table[index]
    bx = boxes.to(torch.float64)
    x, y, w, h = bx.unbind(-1)
    sy, sx = h / bank.window[0], w / bank.window[1]
    out = torch.zeros((b, n, index.numel()), dtype=torch.float64)
    x0, x1 = x.clamp(0, fw), (x + w).clamp(0, fw)
    y0, y1 = y.clamp(0, fh), (y + h).clamp(0, fh)

    def rect(ii, ya, xa, yb, xb):
        ys = torch.stack((yb, ya, yb, ya), -1).reshape(b, -1)
        xs = torch.stack((xb, xb, xa, xa), -1).reshape(b, -1)
        v = hm._bilinear(ii, ys, xs).reshape(b, n, 4)
        return v[..., 0] - v[..., 1] - v[..., 2] + v[..., 3]

    vis = (x1 - x0) * (y1 - y0)
    mean = rect(ints.ii, y0, x0, y1, x1) / vis
    std = (rect(ints.ii2, y0, x0, y1, x1) / vis - mean**2).clamp(min=0).sqrt()
    std = std.clamp(min=bank.min_std)
    for j, (k, t, fy, fx) in enumerate(table.tolist()):
        raw = torch.zeros((b, n), dtype=torch.float64)
        for py, px, c in hm._POINTS[KINDS[k]]:
            ys = (y + (fy + py * t) * sy).reshape(b, -1)
            xs = (x + (fx + px * t) * sx).reshape(b, -1)
            raw += c * hm._bilinear(ints.ii, ys, xs).reshape(b, n)
        out[..., j] = raw / (t * t * sx * sy * std)
    return out.to(torch.float32)


@pytest.mark.parametrize("dense_max", [0, 1 << 20])
def test_grid_sample_path_matches_gather_reference(monkeypatch, dense_max):
    # Both ways of combining corner values (one dense matrix product; per-group sums) agree
    # with the explicit-gather reference, for boxes inside, across and partly outside the frame.
    from torchtrack.features import haar as hm

    monkeypatch.setattr(hm, "_DENSE_MAX", dense_max)
    g = torch.Generator().manual_seed(6)
    bank = haar_bank((16, 8), sizes=(8, 4))
    frames = torch.randint(0, 256, (2, 3, 37, 51), dtype=torch.uint8, generator=g)
    boxes = torch.rand((2, 7, 4), generator=g, dtype=torch.float64) * torch.tensor(
        [50.0, 30.0, 30.0, 40.0], dtype=torch.float64
    ) + torch.tensor([-8.0, -8.0, 9.0, 9.0], dtype=torch.float64)
    idx = torch.randperm(len(bank), generator=g)[:25]
    got = haar_features_at(integrals(frames), boxes, bank, idx)
    torch.testing.assert_close(got, gather_reference(frames, boxes, bank, idx))
    # The cached point table is reused (same object) and gives the same values again.
    assert hm._point_table(bank, idx, torch.device("cpu")) is hm._point_table(
        bank, idx.clone(), torch.device("cpu")
    )
    torch.testing.assert_close(haar_features_at(integrals(frames), boxes, bank, idx), got)


def test_integrals_equal_integral_images_of_luma():
    from torchtrack.features.integral import integral_image, rgb_to_gray

    g = torch.Generator().manual_seed(7)
    for c in (1, 3):
        frames = torch.randint(0, 256, (2, c, 13, 17), dtype=torch.uint8, generator=g)
        ints = integrals(frames)
        gray = rgb_to_gray(frames)
        assert torch.equal(ints.ii, integral_image(gray)[:, 0])
        assert torch.equal(ints.ii2, integral_image(gray, squared=True)[:, 0])
        assert ints.frame_size == (13, 17)
