import shutil

import pytest
import torch

from torchtrack.detect import load_detector, save_detector
from torchtrack.detect.config import TrainConfig
from torchtrack.detect.evaluate import crop_scores
from torchtrack.detect.training import group_split, portable_config, train_detector
from torchtrack.errors import DataError
from torchtrack.io.crops import load_crops


@pytest.fixture(scope="module")
def car_folders(data_dir, tmp_path_factory):
    """A small real subset: 40 car and 40 non-car UIUC crops in two folders."""
    src = data_dir / "detection_crops" / "uiuc_car" / "CarData" / "TrainImages"
    root = tmp_path_factory.mktemp("cars")
    for kind in ("pos", "neg"):
        (root / kind).mkdir()
        for i in range(40):
            shutil.copy(src / f"{kind}-{i}.pgm", root / kind / f"{kind}-{i}.pgm")
    return root


def small_config(root) -> TrainConfig:
    cfg = TrainConfig(name="car-test", window=[40, 100])
    cfg.data.positives = [str(root / "pos")]
    cfg.data.negatives = [str(root / "neg")]
    cfg.data.mirror_positives = True
    cfg.data.mirror_negatives = True
    cfg.features.stride = 4
    cfg.learn.n_features = 6
    return cfg


def test_group_split_keeps_mirror_pairs_together():
    sources = [f"a{i}.png" for i in range(10)] + [f"a{i}.png#flip" for i in range(10)]
    keep, out = group_split(sources, 0.3, torch.Generator().manual_seed(0))
    held = {sources[i].split("#")[0] for i in out.tolist()}
    kept = {sources[i].split("#")[0] for i in keep.tolist()}
    assert len(held) == 3 and not held & kept and len(out) == 6


def test_train_small_real_detector(car_folders, tmp_path):
    cfg = small_config(car_folders)
    det = train_detector(cfg)
    s = det.summary
    assert s["counts"]["positives_train"] + s["counts"]["positives_calibration"] == 80
    assert s["counts"]["positives_calibration"] == 24  # 30% of 40 source files, with mirrors
    assert det.feature_index.numel() == 6
    # cars vs non-cars are separable enough that even 6 features rank well on held-out crops
    assert s["held_out"]["auc"] > 0.8
    # the recorded config names data relative to the data root, no absolute path of this machine
    data = s["config"]["data"]
    assert data["positives"] == ["pos"] and data["negatives"] == ["neg"]
    assert data["root"] == car_folders.name
    assert str(car_folders) not in repr(s)
    # the model file reproduces the scores exactly
    path = save_detector(tmp_path / "car.safetensors", det)
    again = load_detector(path)
    crops = load_crops(car_folders / "pos", (40, 100)).images[:10]
    torch.testing.assert_close(
        crop_scores(again, crops, margin=False), crop_scores(det, crops, margin=False)
    )
    # same seed, same detector
    det2 = train_detector(small_config(car_folders))
    assert torch.equal(det2.feature_index, det.feature_index)


def test_empty_positive_folder(tmp_path, car_folders):
    (tmp_path / "empty").mkdir()
    cfg = small_config(car_folders)
    cfg.data.positives = [str(tmp_path / "empty")]
    with pytest.raises(DataError, match="no usable image"):
        train_detector(cfg)


def test_portable_config_paths_relative_to_the_data_root(tmp_path):
    cfg = TrainConfig(name="p", window=[128, 64])
    root = tmp_path / "data" / "detection_crops"
    cfg.data.positives = [str(root / "inria" / "pos")]
    cfg.data.negatives = [str(root / "uiuc" / "TrainImages" / "neg-*.pgm")]
    cfg.data.negative_images = [str(root / "scenes"), str(root / "scenes" / "a.jpg")]
    cfg.data.exclude = [str(tmp_path / "configs" / "splits" / "test.txt")]
    d = portable_config(cfg)["data"]
    assert d["root"] == "detection_crops"
    assert d["positives"] == ["inria/pos"]
    assert d["negatives"] == ["uiuc/TrainImages/neg-*.pgm"]
    assert d["negative_images"] == ["scenes", "scenes/a.jpg"]
    assert d["exclude"] == ["test.txt"]
    assert str(tmp_path) not in repr(d)
    assert cfg.data.positives == [str(root / "inria" / "pos")]  # the config itself is unchanged


# ------------------------------------------------------------------- too little data (issue 12)
def _subset(root, tmp_path, n_pos, n_neg):
    out = tmp_path / f"sub{n_pos}_{n_neg}"
    for kind, n in (("pos", n_pos), ("neg", n_neg)):
        (out / kind).mkdir(parents=True)
        for i in range(n):
            shutil.copy(root / kind / f"{kind}-{i}.pgm", out / kind)
    return out


@pytest.mark.parametrize(
    "n_pos, n_neg, holdout, match",
    [
        (3, 3, 0.3, "4 positive training crops, fewer than the minimum 20"),
        (40, 40, 0.99, "positive training crops, fewer than"),
        (40, 40, 0.01, "2 positive calibration crops, fewer than the minimum 10"),
        (40, 5, 0.3, "negative training crops"),
    ],
)
def test_too_little_data_is_refused_before_training(
    car_folders, tmp_path, n_pos, n_neg, holdout, match
):
    cfg = small_config(_subset(car_folders, tmp_path, n_pos, n_neg))
    cfg.learn.calibration_fraction = holdout
    with pytest.raises(DataError, match=f"too little data.*{match}.*--force"):
        train_detector(cfg)


def test_flat_positives_are_refused(tmp_path):
    import cv2
    import numpy as np

    rng = np.random.default_rng(0)
    for kind in ("pos", "neg"):
        (tmp_path / kind).mkdir()
        for i in range(40):
            img = np.full((40, 100), 128, np.uint8)
            if kind == "neg":
                img = rng.integers(0, 255, (40, 100), np.uint8)
            cv2.imwrite(str(tmp_path / kind / f"{i}.png"), img)
    cfg = small_config(tmp_path)
    with pytest.raises(DataError, match="80 of 80 positive crops are flat"):
        train_detector(cfg)


def test_force_trains_anyway_and_says_so(car_folders, tmp_path):
    cfg = small_config(_subset(car_folders, tmp_path, 12, 12))
    lines = []
    det = train_detector(cfg, force=True, log=lines.append)
    assert any("warning (forced)" in ln for ln in lines)
    assert det.summary["forced"] and "fewer than the minimum 20" in det.summary["forced"][0]


def test_minimums_are_config_keys():
    cfg = TrainConfig()
    cfg.data.positives = ["p"]
    cfg.data.negatives = ["n"]
    cfg.learn.min_train_per_class = 0
    with pytest.raises(Exception, match="min_train_per_class"):
        cfg.validate()


def test_haar_detector_scan_with_pad_scores_the_continued_frame(car_folders):
    """The sliding-window path (Chateau's Haar bank) with windows over the edges: every window
    of ``sliding_windows(pad=...)`` is scored on the frame with its border pixels continued."""
    from torchtrack.detect.scan import scan_batch, scan_window_count, sliding_windows

    det = train_detector(small_config(car_folders))
    g = torch.Generator().manual_seed(0)
    frame = torch.randint(0, 256, (1, 1, 60, 130), generator=g, dtype=torch.uint8)
    kw = {"min_scale": 1.0, "max_scale": 1.2, "scale_step": 1.2, "stride": 0.2, "pad": 0.25}
    wins, m = scan_batch(det, frame, threshold=None, margin=True, nms_iou=None, **kw)[0]
    ref_boxes = sliding_windows((60, 130), det.window, **kw)
    assert wins.shape[0] == ref_boxes.shape[0] == scan_window_count(det, (60, 130), **kw)
    assert float(wins[:, 0].min()) < 0 and float(wins[:, 1].min()) < 0
    p = 40
    padded = torch.nn.functional.pad(frame.float(), (p, p, p, p), mode="replicate")
    ref = det.decision_function(padded, (wins + torch.tensor([p, p, 0.0, 0.0]))[None])[0]
    torch.testing.assert_close(m, ref, atol=1e-4, rtol=1e-5)


@pytest.mark.parametrize(
    "edit, match",
    [
        # the config's check names the key (the model file's bounds)
        ({"stride": 101}, r"features\.stride must be an integer in \[1, 100\], got 101"),
        (
            {"min_std": 1e-4},
            r"features\.min_std must be a finite number in \[0.001, 255.0\], got 0.0001",
        ),
    ],
)
def test_a_haar_bank_no_model_file_holds_is_refused_before_any_data_is_read(
    tmp_path, monkeypatch, edit, match
):
    """A stride beyond the window or a min_std under 1e-3 passed the config's checks, trained
    to the end and was refused when the model was written ('not writing ...'): the config's
    check now runs the model file's own bank check, naming the key, before the crops are
    read."""
    import torchtrack.detect.training as training
    from torchtrack.errors import ConfigError

    (tmp_path / "pos").mkdir()
    (tmp_path / "neg").mkdir()
    cfg = small_config(tmp_path)
    for k, v in edit.items():
        setattr(cfg.features, k, v)

    def read_nothing(*a, **k):
        raise AssertionError("the crops were read before the bank was checked")

    monkeypatch.setattr(training, "load_training_data", read_nothing)
    with pytest.raises(ConfigError, match=match):
        train_detector(cfg)


def test_more_selected_features_than_the_bank_holds_is_refused_before_any_data_is_read(
    tmp_path, monkeypatch
):
    """n_features above the bank's size was refused by the feature selection, after every
    crop had been read and its features computed ('n_features must be in [1, F] (columns of
    X)'); it is now a config error naming the key, before the crops are read."""
    import torchtrack.detect.training as training
    from torchtrack.errors import ConfigError

    (tmp_path / "pos").mkdir()
    (tmp_path / "neg").mkdir()
    cfg = small_config(tmp_path)
    cfg.learn.n_features = 10**6

    def read_nothing(*a, **k):
        raise AssertionError("the crops were read before n_features was checked")

    monkeypatch.setattr(training, "load_training_data", read_nothing)
    with pytest.raises(ConfigError, match=r"learn\.n_features \(--features\) is 1000000, more th"):
        train_detector(cfg)
