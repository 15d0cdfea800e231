"""Bundled models: names, resolution, loading, recorded splits, and batched scans."""

import shutil

import pytest
import torch

from torchtrack.detect import Detector, load_detector
from torchtrack.detect.bundled import MODELS_DIR, bundled_models, load_model, resolve_model
from torchtrack.detect.model_file import read_model_metadata
from torchtrack.detect.scan import scan, scan_batch
from torchtrack.errors import ConfigError, ModelFormatError, ShapeError


def test_bundled_names():
    assert bundled_models() == ["pedestrian", "vehicle"]
    assert resolve_model("vehicle") == MODELS_DIR / "vehicle.safetensors"


@pytest.mark.parametrize(("name", "window"), [("pedestrian", (128, 64)), ("vehicle", (40, 100))])
def test_load_by_name(name, window):
    det = load_model(name)
    assert isinstance(det, Detector)
    assert det.name == name and det.window == window and det.calibrator is not None
    # every bundled model is a small file with its training record
    assert resolve_model(name).stat().st_size < 1_000_000
    summ = det.summary
    assert summ["counts"]["positives_train"] > 0 and summ["counts"]["positives_calibration"] > 0
    assert 0.9 < summ["held_out"]["auc"] <= 1.0
    assert summ["calibration_sources"]  # the calibration hold-out is listed by file


def test_held_out_split_recorded_and_benchmark_images_never_read():
    meta = read_model_metadata(resolve_model("vehicle"))
    train = meta["training"]
    assert "uiuc_car_test.txt" in train["excluded_lists"]
    data = train["config"]["data"]
    used = data["positives"] + data["negatives"] + data["negative_images"]
    assert used and all("TrainImages" in p or "scene_negatives" in p for p in used)
    # the UIUC benchmark images (TestImages, TestImages_Scale) are never training data
    assert not any("TestImages" in p for p in used)
    ped = read_model_metadata(resolve_model("pedestrian"))["training"]
    assert "inria_person_test.txt" in ped["excluded_lists"]


def test_unknown_name_lists_bundled():
    with pytest.raises(ConfigError, match=r"unknown model 'bike'.*pedestrian, vehicle"):
        resolve_model("bike")
    with pytest.raises(ModelFormatError, match="does not exist"):
        resolve_model("missing/model.safetensors")


@pytest.mark.parametrize(("bad", "got"), [(None, "NoneType"), (5, "int"), ("", "''")])
def test_a_model_that_is_no_path_or_name_is_named(bad, got):
    # None and 5 were Path's TypeError; "" (Path(".")) was "model '' is a folder"
    with pytest.raises(
        ConfigError,
        match=rf"model must be a model file's path or a bundled model's name, got {got}; "
        r"bundled models: pedestrian, vehicle",
    ):
        load_model(bad)


def test_a_file_wins_over_a_name(tmp_path, monkeypatch):
    shutil.copy(resolve_model("vehicle"), tmp_path / "pedestrian")
    monkeypatch.chdir(tmp_path)
    assert load_model("pedestrian").name == "vehicle"  # the local file, not the bundled model
    assert load_detector(resolve_model("pedestrian")).name == "vehicle"


def test_scan_batch_equals_single_frames():
    """A batch of B frames scanned at once gives the B single-frame results."""
    det = load_model("vehicle")
    g = torch.Generator().manual_seed(0)
    frames = (torch.rand((3, 1, 60, 140), generator=g) * 255).to(torch.uint8)
    frames[1] = frames[1].flip(-1)
    # every window scored (no cascade: random frames would lose most windows to it)
    kw = {"threshold": None, "stride": 0.2, "scale_step": 1.3, "nms_iou": 0.3, "cascade": False}
    batch = scan_batch(det, frames, **kw)
    assert len(batch) == 3 and all(b[0].shape[0] > 0 for b in batch)
    for f in range(3):
        boxes, scores = scan(det, frames[f], **kw)
        torch.testing.assert_close(batch[f][0], boxes)
        torch.testing.assert_close(batch[f][1], scores)
    # Detector.scan dispatches on the input's rank (the vehicle's object box is its window)
    torch.testing.assert_close(det.scan(frames[0], **kw)[1], batch[0][1])
    with_cascade = dict(kw, cascade=True)
    for f, (_b, s) in enumerate(scan_batch(det, frames, **with_cascade)):
        torch.testing.assert_close(scan(det, frames[f], **with_cascade)[1], s)
    assert len(det.scan(frames, **kw)) == 3


def test_scan_below_training_scale_and_small_frames():
    det = load_model("pedestrian")
    frame = torch.full((1, 100, 60), 100, dtype=torch.uint8)
    with pytest.raises(ShapeError, match=r"smaller than the detector window 128x64"):
        scan(det, frame)
    boxes, _ = scan(
        det, frame, threshold=None, nms_iou=None, min_scale=0.5, max_scale=0.5, cascade=False
    )
    assert boxes.shape[0] > 0
    assert torch.allclose(boxes[:, 2:], torch.tensor([32.0, 64.0]))
