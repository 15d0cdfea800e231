import numpy as np
import pytest
import torch

from torchtrack.errors import ConfigError, ShapeError
from torchtrack.features.centre_surround import (
    CHANNEL_SUBSETS,
    CentreSurroundFeatures,
    CentreSurroundPool,
    centre_surround_features,
    channel_integrals,
    klein_pool,
)
from torchtrack.features.channels import ChannelSet, compute_channels


def area_sum(img: np.ndarray, y0: float, x0: float, y1: float, x1: float) -> float:
    """Integral of the piecewise-constant image over a fractional rectangle (clipped to the
    image), from the pixel overlaps: the slow, obviously right reference."""
    h, w = img.shape
    y0, y1 = np.clip([y0, y1], 0, h)
    x0, x1 = np.clip([x0, x1], 0, w)
    ys, xs = np.arange(h), np.arange(w)
    oy = np.clip(np.minimum(y1, ys + 1) - np.maximum(y0, ys), 0, None)
    ox = np.clip(np.minimum(x1, xs + 1) - np.maximum(x0, xs), 0, None)
    return float(oy @ img @ ox)


def reference(frame: torch.Tensor, boxes: list, pool: CentreSurroundPool) -> np.ndarray:
    """Feature values by pixel sums; outside the frame counts as the mean colour."""
    img = frame.double().numpy()
    if img.shape[0] == 1:
        img = np.repeat(img, 3, 0)
    chans = [img[list(s)].mean(0) for s in CHANNEL_SUBSETS]
    if pool.gradients:
        names = ("grad", "orient") if pool.gradients > 1 else ("grad",)
        cs = ChannelSet(names=names, orientations=max(pool.gradients - 1, 1))
        chans += list(compute_channels(frame[None], cs)[0].double().numpy() * 255)
    chans = np.stack(chans)
    chans -= chans.mean(axis=(1, 2), keepdims=True)  # outside = mean = 0 after centring
    out = np.zeros((len(boxes), len(pool)))
    for n, (x, y, w, h) in enumerate(boxes):
        for i, (c, cx, cy, hc, hs) in enumerate(pool.table.tolist()):
            im = chans[int(c)]
            sc = area_sum(
                im, y + (cy - hc) * h, x + (cx - hc) * w, y + (cy + hc) * h, x + (cx + hc) * w
            )
            ss = area_sum(
                im, y + (cy - hs) * h, x + (cx - hs) * w, y + (cy + hs) * h, x + (cx + hs) * w
            )
            ac, a_s = (2 * hc) ** 2 * w * h, (2 * hs) ** 2 * w * h
            out[n, i] = sc / ac - (ss - sc) / (a_s - ac)
    return out


def test_pool_has_539_features_over_rgb_subsets():
    pool = klein_pool()
    assert len(pool) == 539 == 7 * (36 + 25 + 16)
    assert len(CHANNEL_SUBSETS) == 7
    q = pool.quarters()
    assert q.shape == (539, 4)
    assert bool(q.any(1).all())  # every feature lies in some quarter
    # centres on a dividing line (5 x 5 grid) belong to two or four quarters
    assert int(q.sum(1).max()) == 4
    d = pool.describe(538)
    assert d["channels"] == "RGB" and d["surround"] == pytest.approx(2 * d["centre"])


def test_features_match_pixel_sum_reference():
    g = torch.Generator().manual_seed(0)
    frame = torch.randint(0, 256, (3, 40, 52), dtype=torch.uint8, generator=g)
    boxes = [
        [5.3, 4.7, 20.2, 25.9],
        [0.0, 0.0, 52.0, 40.0],
        [-3.5, -2.0, 20.0, 21.0],
        [40, 30, 15, 12],
    ]
    pool = klein_pool()
    got = centre_surround_features(channel_integrals(frame[None]), torch.tensor([boxes]), pool)[
        0
    ].numpy()
    ref = reference(frame, boxes, pool)
    np.testing.assert_allclose(got, ref, atol=2e-3, rtol=1e-4)


@pytest.mark.parametrize("gradients", [1, 5])
def test_gradient_channels_match_reference_and_leave_colour_features_alone(gradients):
    g = torch.Generator().manual_seed(4)
    frame = torch.randint(0, 256, (3, 36, 44), dtype=torch.uint8, generator=g)
    boxes = [[5.3, 4.7, 20.2, 25.9], [-3.5, -2.0, 20.0, 21.0]]
    pool = CentreSurroundPool(gradients=gradients)
    assert len(pool) == 77 * (7 + gradients) and pool.n_channels == 7 + gradients
    assert pool.describe(539)["channels"] == "grad"
    assert pool.describe(len(pool) - 1)["channels"] == ("grad" if gradients == 1 else "orient3")
    ints = channel_integrals(frame[None], gradients)
    assert ints.n_subsets == 7 + gradients
    got = centre_surround_features(ints, torch.tensor([boxes]), pool)[0]
    np.testing.assert_allclose(got.numpy(), reference(frame, boxes, pool), atol=5e-3, rtol=1e-4)
    colour = centre_surround_features(channel_integrals(frame[None]), torch.tensor([boxes]),
                                      klein_pool())[0]  # fmt: skip
    torch.testing.assert_close(got[:, :539], colour, atol=2e-3, rtol=1e-4)  # taller stack: rounding
    # a gray frame: the same gradients as the RGB frame of equal channels
    gray = frame[:1]
    a = centre_surround_features(channel_integrals(gray[None], gradients), torch.tensor([boxes]),
                                 pool)  # fmt: skip
    b = centre_surround_features(
        channel_integrals(gray.expand(3, -1, -1)[None], gradients), torch.tensor([boxes]), pool
    )
    torch.testing.assert_close(a, b, atol=1e-3, rtol=1e-4)  # luma of gray vs of RGB: rounding


def test_float32_tables_precise_on_full_size_frame():
    g = torch.Generator().manual_seed(1)
    frame = torch.randint(0, 256, (3, 240, 320), dtype=torch.uint8, generator=g)
    pool = klein_pool()
    boxes = [[250.25, 60.5, 56.0, 150.0], [3.0, 2.0, 60.0, 170.0]]
    idx = torch.arange(0, 539, 7)
    got = centre_surround_features(channel_integrals(frame[None]), torch.tensor([boxes]), pool, idx)
    ref = reference(frame, boxes, pool)[:, idx.numpy()]
    np.testing.assert_allclose(got[0].numpy(), ref, atol=5e-3)


def test_per_box_index_equals_gather_of_all():
    g = torch.Generator().manual_seed(2)
    frames = torch.randint(0, 256, (2, 3, 30, 40), dtype=torch.uint8, generator=g)
    boxes = torch.rand((2, 5, 4), generator=g) * torch.tensor([20.0, 10.0, 15.0, 15.0]) + 3
    ints = channel_integrals(frames)
    pool = klein_pool()
    full = centre_surround_features(ints, boxes, pool)
    idx = torch.randint(0, 539, (2, 5, 32), generator=g)
    np.testing.assert_allclose(
        centre_surround_features(ints, boxes, pool, idx).numpy(),
        full.gather(2, idx).numpy(),
        atol=1e-3,
    )
    shared = torch.tensor([3, 100, 538])
    np.testing.assert_allclose(
        centre_surround_features(ints, boxes, pool, shared).numpy(),
        full[..., shared].numpy(),
        atol=1e-3,
    )


def test_gray_frame_equals_rgb_with_equal_channels_and_module_agrees():
    g = torch.Generator().manual_seed(3)
    gray = torch.randint(0, 256, (1, 1, 20, 30), dtype=torch.uint8, generator=g)
    rgb = gray.expand(1, 3, 20, 30).contiguous()
    boxes = torch.tensor([[[2.0, 3.0, 12.5, 10.0]]])
    pool = klein_pool()
    a = centre_surround_features(channel_integrals(gray), boxes, pool)
    b = centre_surround_features(channel_integrals(rgb), boxes, pool)
    torch.testing.assert_close(a, b)
    torch.testing.assert_close(CentreSurroundFeatures(pool)(rgb, boxes), b)


def test_constant_image_gives_zero():
    frame = torch.full((1, 3, 20, 20), 77, dtype=torch.uint8)
    f = centre_surround_features(
        channel_integrals(frame), torch.tensor([[[1.0, 2.0, 9.0, 11.0]]]), klein_pool()
    )
    assert float(f.abs().max()) < 1e-4


def test_pool_config_roundtrip_and_errors():
    pool = CentreSurroundPool(grids=(2,), sizes=(0.4,), surround=1.5)
    assert len(pool) == 7 * 4
    assert CentreSurroundPool.from_dict(pool.to_dict()).to_dict() == pool.to_dict()
    with pytest.raises(ConfigError, match="unknown centre-surround pool key"):
        CentreSurroundPool.from_dict({"grid": [3]})
    with pytest.raises(ConfigError, match="equal length"):
        CentreSurroundPool(grids=(3, 4), sizes=(0.2,))
    for bad in (1.0, 1e308):  # 1e308 overflowed the surround's area to inf
        with pytest.raises(ConfigError, match=r"surround must be in \(1, 10\]"):
            CentreSurroundPool(surround=bad)
    with pytest.raises(ConfigError, match=r"centre sizes must be in \(0, 1\]"):
        CentreSurroundPool(grids=(3,), sizes=(1.5,))
    with pytest.raises(ConfigError, match=r"gradients must be an integer in \[0, 19\]"):
        CentreSurroundPool(gradients=20)
    with pytest.raises(ConfigError, match="gradients must be an integer"):
        channel_integrals(torch.zeros((1, 3, 8, 8)), gradients=-1)
    grad = CentreSurroundPool(gradients=3)
    assert CentreSurroundPool.from_dict(grad.to_dict()) == grad
    assert CentreSurroundPool.from_dict({"grids": [2], "sizes": [0.4]}).gradients == 0


def test_shape_errors():
    pool = klein_pool()
    ints = channel_integrals(torch.zeros((1, 3, 10, 10), dtype=torch.uint8))
    with pytest.raises(ShapeError, match="C = 1 or 3"):
        channel_integrals(torch.zeros((1, 2, 10, 10)))
    with pytest.raises(ShapeError, match=r"boxes must have shape \(B, N, 4\)"):
        centre_surround_features(ints, torch.zeros((1, 4)), pool)
    with pytest.raises(ShapeError, match="frame"):
        centre_surround_features(ints, torch.zeros((2, 1, 4)), pool)
    with pytest.raises(ShapeError, match="out of range"):
        centre_surround_features(ints, torch.ones((1, 1, 4)), pool, torch.tensor([539]))
    with pytest.raises(ShapeError, match=r"reads 8 channels but the integrals hold 7.*gradients=1"):
        centre_surround_features(ints, torch.ones((1, 1, 4)), CentreSurroundPool(gradients=1))
    with pytest.raises(ShapeError, match=r"\(B, N, K\)"):
        centre_surround_features(
            ints, torch.ones((1, 2, 4)), pool, torch.zeros((1, 3, 2), dtype=torch.int64)
        )


def test_bad_boxes_and_pixel_values_are_refused():
    """A NaN box read features of 0 and a negative width sums of the frame taken backwards
    (-1.6e10), bool boxes were 0 / 1 pixel boxes, and NaN or 16-bit frames were integrated
    as they were (NaN features, levels read on the 8-bit scale); all without a word."""
    from torchtrack.errors import BoxError, DataError

    frames = torch.randint(0, 256, (1, 3, 40, 50), dtype=torch.uint8)
    ints, pool = channel_integrals(frames), klein_pool()
    for bad in ([float("nan"), 5, 20, 20], [5, 5, -20, 20]):
        with pytest.raises(BoxError, match=r"boxes\[0, 0\] = .* must be finite with a width"):
            centre_surround_features(ints, torch.tensor([[bad]], dtype=torch.float32), pool)
    with pytest.raises(ShapeError, match=r"boxes must hold real numbers, got torch\.bool"):
        centre_surround_features(ints, torch.ones(1, 1, 4, dtype=torch.bool), pool)
    out = torch.tensor([[[500.0, 500, 20, 20], [5, 5, 0, 0]]])  # outside / empty: allowed
    assert centre_surround_features(ints, out, pool).shape == (1, 2, len(pool))
    for bad in (torch.full((1, 3, 8, 8), float("nan")), torch.full((1, 3, 8, 8), 300.0)):
        with pytest.raises(DataError, match="frames hold"):
            channel_integrals(bad)
    with pytest.raises(ShapeError, match=r"integer or floating tensor, got torch\.bool"):
        channel_integrals(torch.ones(1, 3, 8, 8, dtype=torch.bool))
