import cv2
import numpy as np
import pytest
import torch

from torchtrack.errors import ConfigError, DataError
from torchtrack.io.crops import (
    CropSet,
    crops_from_boxes,
    load_crops,
    load_images,
    mirror,
    sample_windows,
)


@pytest.fixture
def folder(tmp_path):
    rng = np.random.default_rng(0)
    cv2.imwrite(str(tmp_path / "a.png"), rng.integers(0, 256, (20, 10), dtype=np.uint8))
    cv2.imwrite(
        str(tmp_path / "b.png"), rng.integers(0, 256, (20, 10, 3), dtype=np.uint8)
    )  # colour
    cv2.imwrite(str(tmp_path / "c.pgm"), rng.integers(0, 256, (40, 20), dtype=np.uint8))  # 2x size
    (tmp_path / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    (tmp_path / "notes.bin").write_bytes(b"\x00\x01")
    (tmp_path / "README.md").write_text("ignored")
    return tmp_path


def test_load_mixed_folder(folder):
    cs = load_crops(folder, (20, 10))
    assert cs.images.shape == (3, 1, 20, 10) and cs.images.dtype == torch.uint8
    assert [s.rsplit("/", 1)[1] for s in cs.sources] == ["a.png", "b.png", "c.pgm"]
    assert cs.resized == 1  # c.pgm was 40x20
    reasons = dict((p.rsplit("/", 1)[1], why) for p, why in cs.skipped)
    assert set(reasons) == {"broken.png", "notes.bin"}
    assert "decoded" in reasons["broken.png"] and "extension" in reasons["notes.bin"]
    # colour crop -> BT.601 luma, as cv2 computes it
    b = cv2.imread(str(folder / "b.png"), cv2.IMREAD_GRAYSCALE)
    assert np.array_equal(cs.images[1, 0].numpy(), b)


def test_a_crop_far_smaller_than_the_window_is_skipped_with_its_size(folder):
    """A 1x1 image (or anything under a quarter of the window on a side) is not blown up into
    a training example; one just above a quarter is resized as before."""
    cv2.imwrite(str(folder / "dot.png"), np.zeros((1, 1), np.uint8))
    cv2.imwrite(str(folder / "d.png"), np.zeros((5, 3), np.uint8))  # 5 >= 20 / 4, 3 >= 10 / 4
    cs = load_crops(folder, (20, 10))
    reasons = dict((p.rsplit("/", 1)[1], why) for p, why in cs.skipped)
    assert "1x1 px, under a quarter of the 20x10 crop" in reasons["dot.png"]
    assert "d.png" not in reasons and cs.images.shape[0] == 4
    with pytest.raises(DataError, match=r"dot\.png"):
        load_crops(folder, (20, 10), strict=True)


def test_strict_names_every_bad_path(folder):
    with pytest.raises(DataError, match=r"2 unusable file\(s\)(.|\n)*broken.png(.|\n)*notes.bin"):
        load_crops(folder, (20, 10), strict=True)


def test_empty_and_missing_folders(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="no usable image"):
        load_crops(tmp_path / "empty", (20, 10))
    with pytest.raises(DataError, match="does not exist"):
        load_crops(tmp_path / "nope", (20, 10))
    # every file unusable: the error named one file but not why (the warnings that give the
    # reasons are printed only after a load that succeeds)
    cv2.imwrite(str(tmp_path / "empty" / "dot.png"), np.zeros((1, 1), np.uint8))
    with pytest.raises(
        DataError, match=r"no usable image \(1 unusable file\(s\), e.g. .*dot\.png: 1x1 px, under"
    ):
        load_crops(tmp_path / "empty", (20, 10))


def test_region_and_exclude(folder):
    cs = load_crops(folder, (10, 5), region=(0, 0, 10, 20), crop_size=(20, 10), exclude={"a.png"})
    assert len(cs) == 2 and cs.images.shape[-2:] == (10, 5)
    with pytest.raises(ConfigError, match="crop_size"):
        load_crops(folder, (10, 5), region=(0, 0, 10, 20))
    with pytest.raises(ConfigError, match="inside crop_size"):
        load_crops(folder, (10, 5), region=(5, 0, 10, 20), crop_size=(20, 10))
    with pytest.raises(ConfigError, match=r"region must be \(x, y, w, h\), got \[0, 0, 10\]"):
        load_crops(folder, (10, 5), region=(0, 0, 10), crop_size=(20, 10))
    with pytest.raises(ConfigError, match=r"crop_size must be \(H, W\), got \[20\]"):
        load_crops(folder, (10, 5), region=(0, 0, 10, 20), crop_size=(20,))


def test_mirror_and_subset(folder):
    cs = mirror(load_crops(folder, (20, 10)))
    assert len(cs) == 6 and cs.sources[3].endswith("a.png#flip")
    assert torch.equal(cs.images[3], cs.images[0].flip(-1))
    sub = cs.subset([0, 3])
    assert len(sub) == 2
    assert len(CropSet.concat([sub, sub])) == 4


def test_sample_windows_reproducible():
    rng = np.random.default_rng(1)
    imgs = [
        rng.integers(0, 256, (50, 60), dtype=np.uint8),
        rng.integers(0, 256, (10, 10), dtype=np.uint8),
    ]
    a = sample_windows(imgs, ["x", "y"], (20, 10), 30, generator=torch.Generator().manual_seed(3))
    b = sample_windows(imgs, ["x", "y"], (20, 10), 30, generator=torch.Generator().manual_seed(3))
    assert torch.equal(a.images, b.images) and a.sources == b.sources
    assert all(s.startswith("x@") for s in a.sources)  # the 10x10 image is too small
    with pytest.raises(DataError, match="no negative image"):
        sample_windows(imgs[1:], ["y"], (20, 10), 3)


def test_crops_from_boxes_identity():
    img = np.arange(200, dtype=np.uint8).reshape(10, 20)
    out = crops_from_boxes(img, np.array([[2, 3, 5, 4]]), (4, 5))
    assert np.array_equal(out[0], img[3:7, 2:7])


def test_load_images_reports(tmp_path):
    (tmp_path / "bad.jpg").write_bytes(b"nope")
    with pytest.raises(DataError, match="none of the 1"):
        load_images([tmp_path / "bad.jpg"])


def test_real_inria_crops(data_dir):
    folder = data_dir / "detection_crops" / "inria_person_96x160" / "pos"
    only = {"crop001001a.png", "crop001001c.png", "person_001a.png"}
    cs = load_crops(folder, (128, 64), region=(16, 16, 64, 128), crop_size=(160, 96), only=only)
    assert cs.images.shape == (len(cs), 1, 128, 64) and cs.resized == 0 and len(cs) >= 2


def test_a_broken_symbolic_link_is_an_unusable_crop(folder):
    """A link whose target is gone is skipped with its reason (and refused under strict),
    as an unreadable crop is; it was left out of the listing unseen, even with strict."""
    (folder / "gone.png").symlink_to(folder / "nowhere.png")
    cs = load_crops(folder, (20, 10))
    reasons = dict((p.rsplit("/", 1)[1], why) for p, why in cs.skipped)
    assert "broken symbolic link" in reasons["gone.png"]
    with pytest.raises(DataError, match=r"gone\.png"):
        load_crops(folder, (20, 10), strict=True)
