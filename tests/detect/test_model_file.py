import json
import struct

import pytest
import torch

from torchtrack.detect import Detector, load_detector, save_detector
from torchtrack.detect.model_file import FORMAT_VERSION, read_model_metadata
from torchtrack.errors import BoxError, ModelFormatError, NotFittedError
from torchtrack.features.haar import haar_bank
from torchtrack.learn import BoostedStumps, IsotonicCalibrator, PlattCalibrator, SVMClassifier


def toy_data():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(80, 4, generator=g)
    y = (x[:, 0] - x[:, 2] + 0.5 * torch.randn(80, generator=g) > 0).long()
    return x, y


def make_detector(cal=True, svm=False) -> Detector:
    bank = haar_bank((16, 8), sizes=(8, 4))
    idx = torch.tensor([3, 50, 200, 360])
    x, y = toy_data()
    clf = SVMClassifier(kernel="rbf") if svm else BoostedStumps(n_estimators=5)
    clf.fit(x, y)
    calib = PlattCalibrator().fit(clf.decision_function(x).double(), y) if cal else None
    return Detector(bank, idx, clf, calib, name="toy", summary={"n_pos": 10, "split": ["a.png"]})


def frames_boxes():
    g = torch.Generator().manual_seed(1)
    frames = torch.randint(0, 256, (2, 3, 60, 80), dtype=torch.uint8, generator=g)
    boxes = torch.tensor(
        [
            [[1.0, 2.0, 8.0, 16.0], [20.5, 10.2, 13.0, 27.0]],
            [[50.0, 3.0, 24.0, 48.0], [0.0, 0.0, 80.0, 60.0]],
        ]
    )
    return frames, boxes


@pytest.mark.parametrize("svm", [False, True])
def test_round_trip_scores_identically(tmp_path, svm):
    det = make_detector(svm=svm)
    frames, boxes = frames_boxes()
    p = det.score(frames, boxes)
    assert p.shape == (2, 2) and bool(((p > 0) & (p < 1)).all())
    path = save_detector(tmp_path / "m.safetensors", det)
    again = load_detector(path)
    torch.testing.assert_close(again.score(frames, boxes), p, rtol=0, atol=0)
    assert again.summary == det.summary and again.name == "toy"
    meta = read_model_metadata(path)
    assert meta["format_version"] == FORMAT_VERSION and meta["window"] == [16, 8]
    assert meta["selected_features"][0] == det.bank.describe(3)


def test_isotonic_round_trip(tmp_path):
    x, y = toy_data()
    det = make_detector()
    det = det.with_calibrator(
        IsotonicCalibrator().fit(det.classifier.decision_function(x).double(), y)
    )
    frames, boxes = frames_boxes()
    again = load_detector(save_detector(tmp_path / "m.safetensors", det))
    torch.testing.assert_close(again.score(frames, boxes), det.score(frames, boxes))


def test_score_is_calibrated_margin():
    det = make_detector()
    frames, boxes = frames_boxes()
    m = det.decision_function(frames, boxes)
    a, b = det.calibrator.a_, det.calibrator.b_
    assert a < 0  # a useful classifier: probability rises with the margin
    torch.testing.assert_close(det.score(frames, boxes), 1 / (1 + torch.exp(a * m + b)))


def test_uncalibrated_detector_refuses_to_score():
    det = make_detector(cal=False)
    frames, boxes = frames_boxes()
    det.decision_function(frames, boxes)
    with pytest.raises(NotFittedError, match="torchtrack calibrate"):
        det.score(frames, boxes)


def test_bad_boxes_rejected():
    det = make_detector()
    frames, _ = frames_boxes()
    with pytest.raises(BoxError, match="size below"):
        det.score(frames, torch.tensor([[[1.0, 1.0, 0.0, 4.0]], [[1.0, 1.0, 4.0, 4.0]]]))
    with pytest.raises(BoxError, match="outside"):
        det.score(frames, torch.tensor([[[100.0, 1.0, 5.0, 4.0]], [[1.0, 1.0, 4.0, 4.0]]]))


def test_truncated_file(tmp_path):
    path = save_detector(tmp_path / "m.safetensors", make_detector())
    data = path.read_bytes()
    for cut in (4, 20, len(data) - 3):
        bad = tmp_path / f"cut{cut}.safetensors"
        bad.write_bytes(data[:cut])
        with pytest.raises(ModelFormatError, match=r"truncated|only"):
            load_detector(bad)


def test_edited_tensor_fails_checksum(tmp_path):
    path = save_detector(tmp_path / "m.safetensors", make_detector())
    data = bytearray(path.read_bytes())
    data[-1] ^= 0x40  # flip a bit in the last tensor's bytes
    path.write_bytes(bytes(data))
    with pytest.raises(ModelFormatError, match="checksum"):
        load_detector(path)


def rewrite_meta(path, edit):
    data = path.read_bytes()
    (n,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8 : 8 + n])
    meta = json.loads(header["__metadata__"]["torchtrack"])
    edit(meta)
    header["__metadata__"]["torchtrack"] = json.dumps(meta)
    h = json.dumps(header).encode()
    h += b" " * (-len(h) % 8)
    path.write_bytes(struct.pack("<Q", len(h)) + h + data[8 + n :])


def test_edited_metadata_fails_checksum(tmp_path):
    path = save_detector(tmp_path / "m.safetensors", make_detector())
    rewrite_meta(path, lambda m: m["calibration"].update(A=-30.0))
    with pytest.raises(ModelFormatError, match="checksum"):
        load_detector(path)


def test_future_version_rejected(tmp_path):
    path = save_detector(tmp_path / "m.safetensors", make_detector())
    rewrite_meta(path, lambda m: m.update(format_version=FORMAT_VERSION + 1))
    with pytest.raises(ModelFormatError, match="newer than this torchtrack"):
        load_detector(path)


def test_not_a_model(tmp_path):
    from safetensors.torch import save_file

    other = tmp_path / "other.safetensors"
    save_file({"w": torch.zeros(3)}, str(other))
    with pytest.raises(ModelFormatError, match="not a torchtrack detector"):
        load_detector(other)
    with pytest.raises(ModelFormatError, match="does not exist"):
        load_detector(tmp_path / "missing.safetensors")
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"\x00" * 3)
    with pytest.raises(ModelFormatError, match="not a torchtrack model"):
        load_detector(junk)


def test_no_pickle_in_file(tmp_path):
    path = save_detector(tmp_path / "m.safetensors", make_detector())
    data = path.read_bytes()
    assert b"\x80\x04\x95" not in data and b"torch._utils" not in data


def test_detector_validation():
    bank = haar_bank((16, 8), sizes=(8, 4))
    clf = BoostedStumps(n_estimators=3).fit(*toy_data())
    with pytest.raises(ModelFormatError, match="reads 4 features but 2"):
        Detector(bank, torch.tensor([1, 2]), clf)
    with pytest.raises(ModelFormatError, match="lie in"):
        Detector(bank, torch.tensor([0, 1, 2, len(bank)]), clf)
    with pytest.raises(NotFittedError, match="not fitted"):
        Detector(bank, torch.tensor([0, 1, 2, 3]), BoostedStumps())


def test_object_box_round_trip_and_conversion(tmp_path):
    from dataclasses import replace

    det = replace(make_detector(), object_box=(0.25, 0.125, 0.5, 0.75))
    again = load_detector(save_detector(tmp_path / "m.safetensors", det))
    assert again.object_box == (0.25, 0.125, 0.5, 0.75)
    win = torch.tensor([[10.0, 20.0, 8.0, 16.0], [0.0, 0.0, 64.0, 128.0]])
    obj = again.window_to_object(win)
    torch.testing.assert_close(obj[1], torch.tensor([16.0, 16.0, 32.0, 96.0]))
    torch.testing.assert_close(again.object_to_window(obj), win)
    plain = make_detector()  # no object box: windows are the objects
    assert plain.object_box is None and torch.equal(plain.window_to_object(win), win)
    assert "object_box" not in read_model_metadata(save_detector(tmp_path / "p.st", plain))


@pytest.mark.parametrize(
    "box", [(0.5, 0.0, 0.6, 1.0), (0.0, 0.0, 0.0, 1.0), (0.1, 0.1, float("nan"), 0.5), (1, 2, 3)]
)
def test_object_box_outside_window_rejected(box):
    from dataclasses import replace

    with pytest.raises(ModelFormatError, match="object_box"):
        replace(make_detector(), object_box=box)


def test_bundled_pedestrian_reports_the_person_not_the_window():
    from torchtrack.detect.bundled import load_model

    det = load_model("pedestrian")
    # Dalal & Triggs: the INRIA person is 96 px tall with 16 px of margin in the 64x128 window.
    assert det.object_box == (0.25, 0.125, 0.5, 0.75)
