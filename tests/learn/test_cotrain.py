"""Online co-training (Jin et al. Algorithm 2) on a synthetic scene."""

import pytest
import torch

from torchtrack.errors import ConfigError, NotFittedError, ShapeError
from torchtrack.learn.cotrain import CoTrainer, fuse_confidences, region_around


def scene(cx: int, cy: int, gray: bool = False, seed: int = 0, target: bool = True):
    """A 20x20 red checkered target centred on (cx, cy) over green-blue noise, (C, 80, 100)."""
    g = torch.Generator().manual_seed(seed)
    f = torch.zeros(3, 80, 100)
    f[1] = 90 + 30 * torch.rand(80, 100, generator=g)
    f[2] = 140 + 30 * torch.rand(80, 100, generator=g)
    f[0] = 40 + 10 * torch.rand(80, 100, generator=g)
    if target:
        yy, xx = torch.meshgrid(torch.arange(20), torch.arange(20), indexing="ij")
        checker = ((yy // 2 + xx // 2) % 2).float()
        sl = (slice(cy - 10, cy + 10), slice(cx - 10, cx + 10))
        f[0][sl] = 200 + 40 * checker
        f[1][sl] = 30 + 20 * checker
        f[2][sl] = 30
    f = f.round().to(torch.uint8)
    if gray:
        f = (0.299 * f[0] + 0.587 * f[1] + 0.114 * f[2]).round().to(torch.uint8)[None]
    return f


def fitted(mode="cotrain", gray=False):
    ct = CoTrainer(mode=mode, n_selectors=6, max_samples=400)
    region = region_around((40, 40), (20, 20), 2.0, (80, 100))
    ct.init(scene(40, 40, gray), (30, 30, 20, 20), region, torch.Generator().manual_seed(0))
    return ct


def test_fuse_is_signed_min_with_max_magnitude():
    conf = torch.tensor([[2.0, -1.0, 3.0, 0.0], [1.0, 4.0, -0.5, 0.0]])
    torch.testing.assert_close(fuse_confidences(conf), torch.tensor([2.0, -4.0, -3.0, 0.0]))


def test_region_around_clips_and_reports_leaving_the_frame():
    assert region_around((5, 5), (20, 10), 2.0, (80, 100)) == (0, 0, 25, 15)
    assert region_around((-30, 40), (20, 20), 2.0, (80, 100)) is None


@pytest.mark.parametrize("mode,gray", [("cotrain", False), ("self", False), ("cotrain", True)])
def test_locates_the_moved_target_and_classifies_pixels(mode, gray):
    ct = fitted(mode, gray)
    assert len(ct.classifiers) == (2 if mode == "cotrain" else 1)
    n_feat = [c.n_features_in_ for c in ct.classifiers]
    if gray:  # documented fallback: colour on Y, texture on the Y-Y pair
        assert n_feat == [1, 2]
    g = torch.Generator().manual_seed(1)
    for step in range(1, 4):  # the target moves 3 px per frame
        cx, cy = 40 + 3 * step, 40 + 2 * step
        region = region_around((cx - 3, cy - 2), (20, 20), 2.0, (80, 100))
        maps = ct.score(scene(cx, cy, gray, seed=step), region)
        blob = ct.locate(maps)
        assert blob is not None
        assert abs(blob.centre[0] - cx) < 3 and abs(blob.centre[1] - cy) < 3
        x0, y0, x1, y1 = region
        inside = torch.zeros(y1 - y0, x1 - x0, dtype=torch.bool)
        inside[cy - 10 - y0 : cy + 10 - y0, cx - 10 - x0 : cx + 10 - x0] = True
        # gray: one colour feature and two texture codes, a harder problem
        assert float(((maps.fused > 0) != inside).float().mean()) < (0.2 if gray else 0.1)
        accepted = ct.update(maps, blob, g)
        if not gray:  # a confident blob: positives added
            assert accepted


def test_no_blob_means_no_update():
    ct = fitted()
    region = region_around((40, 40), (20, 20), 2.0, (80, 100))
    maps = ct.score(scene(40, 40, target=False, seed=5), region)
    assert ct.locate(maps) is None
    before = [c.hist_.clone() for c in ct.classifiers]
    assert ct.update(maps, None) is False
    for b, c in zip(before, ct.classifiers, strict=True):
        torch.testing.assert_close(c.hist_, b)


def test_weak_blob_adds_negatives_only():
    ct = fitted()
    region = region_around((40, 40), (20, 20), 2.0, (80, 100))
    maps = ct.score(scene(40, 40, seed=2), region)
    blob = ct.locate(maps)
    ct.reference_ = blob.score * 10  # pretend an occlusion: far below the reference
    pos_before = [float(c.hist_[..., 1].sum()) for c in ct.classifiers]
    assert ct.update(maps, blob) is False
    assert [float(c.hist_[..., 1].sum()) for c in ct.classifiers] == pos_before


def test_labelled_pool_keeps_first_frame_and_accepted_positives_only():
    ct = CoTrainer(n_selectors=6, max_samples=400, replay=100, pool_size=600)
    region = region_around((40, 40), (20, 20), 2.0, (80, 100))
    ct.init(scene(40, 40), (30, 30, 20, 20), region, torch.Generator().manual_seed(0))
    (anchor, recent), _ = ct.pool_
    # the ellipse inscribed in the 20x20 box holds more than 300 pixels: capped at pool_size / 2
    assert anchor.shape == (300, 4) and recent.shape == (0, 4)
    g = torch.Generator().manual_seed(1)
    maps = ct.score(scene(40, 40, seed=1), region)
    blob = ct.locate(maps)
    assert ct.update(maps, blob, g)
    n_recent = ct.pool_[0][1].shape[0]
    assert 0 < n_recent <= 300
    # every pooled colour code is one the texture classifier called object in that frame
    ell_codes = maps.codes[0][(blob.ellipse.flatten() & (maps.conf[1].flatten() > 0))]
    assert {tuple(r) for r in ct.pool_[0][1].tolist()} <= {tuple(r) for r in ell_codes.tolist()}
    # a weak blob adds nothing to the pool, but its update still replays pooled positives
    maps = ct.score(scene(40, 40, seed=2), region)
    blob = ct.locate(maps)
    ct.reference_ = blob.score * 10
    pos_before = [float(c.hist_[..., 1].sum()) for c in ct.classifiers]
    assert ct.update(maps, blob, g) is False
    assert ct.pool_[0][1].shape[0] == n_recent
    assert all(
        float(c.hist_[..., 1].sum()) > b for c, b in zip(ct.classifiers, pos_before, strict=True)
    )


def test_positives_can_be_restricted_to_a_box():
    ct = CoTrainer(n_selectors=6, max_samples=10_000, replay=0)
    region = region_around((40, 40), (20, 20), 2.0, (80, 100))
    ct.init(scene(40, 40), (30, 30, 20, 20), region, torch.Generator().manual_seed(0))
    ct.pool_ = [[a[:0], r[:0]] for a, r in ct.pool_]  # empty pool: only this frame's positives
    maps = ct.score(scene(40, 40, seed=1), region)
    blob = ct.locate(maps)
    # keep only the target's left half (frame x in 30..40)
    assert ct.update(maps, blob, torch.Generator().manual_seed(1), within=(30, 30, 10, 20))
    x0 = region[0]
    xs = torch.arange(region[0], region[2]).repeat(region[3] - region[1]) + 0.5
    codes_left = maps.codes[0][(xs < 40) & (xs >= 30)]
    pooled = {tuple(r) for r in ct.pool_[0][1].tolist()}
    assert pooled and pooled <= {tuple(r) for r in codes_left.tolist()}
    assert x0 < 30


def test_errors():
    with pytest.raises(ConfigError, match="replay"):
        CoTrainer(replay=-1)
    with pytest.raises(ConfigError, match="pool_size"):
        CoTrainer(pool_size=1)
    with pytest.raises(ConfigError, match="unknown co-training mode"):
        CoTrainer(mode="tri")
    with pytest.raises(ConfigError, match="opening_size"):
        CoTrainer(opening_size=0)
    with pytest.raises(ConfigError, match="texture_blocks"):
        CoTrainer(texture_blocks="lbp")
    ct = CoTrainer()
    with pytest.raises(NotFittedError):
        ct.score(scene(40, 40), (20, 20, 60, 60))
    with pytest.raises(ShapeError, match="C in"):
        ct.init(torch.zeros(2, 10, 10, dtype=torch.uint8), (1, 1, 3, 3), (0, 0, 10, 10))
    with pytest.raises(ConfigError, match="holds no pixel"):
        ct.init(scene(40, 40), (0, 0, 20, 20), (50, 50, 90, 70))
