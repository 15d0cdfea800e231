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
    rewrite_meta(path, lambda m: m["calibration"].update(a=-30.0))
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


# ---------------------------------------------------------------- malformed and forged files
@pytest.fixture
def model_path(tmp_path):
    return save_detector(tmp_path / "m.safetensors", make_detector())


@pytest.mark.parametrize(
    "header_edit, match",
    [
        (lambda h: h.__setitem__("features.index", "x"), "features.index"),
        (lambda h: h["features.index"].pop("data_offsets"), "data_offsets"),
        (lambda h: h["features.index"].update(dtype="Q128"), "unknown dtype"),
        (lambda h: h["features.index"].update(shape=[2, -1]), "invalid shape"),
        (lambda h: h["features.index"].update(shape=[5]), "data_offsets .* do not match"),
        (lambda h: h["features.index"].update(data_offsets=[0, "8"]), "invalid data_offsets"),
        (lambda h: h["__metadata__"].update(torchtrack=7), "no torchtrack metadata"),
        (lambda h: h["__metadata__"].update(torchtrack="{not json"), "not valid JSON"),
        (lambda h: h["__metadata__"].update(extra=[1]), "strings to strings"),
    ],
)
def test_malformed_header_is_a_typed_error(tmp_path, model_path, forge_model, header_edit, match):
    bad = forge_model(model_path, tmp_path / "bad.safetensors", header_edit=header_edit)
    with pytest.raises(ModelFormatError, match=match):
        load_detector(bad)


@pytest.mark.parametrize("inner", [False, True])
def test_deeply_nested_header_is_a_typed_error(tmp_path, model_path, inner):
    """JSON nested 10^5 deep, in the header or in the torchtrack description: Python's decoder
    raised a RecursionError (a traceback from the CLI)."""
    data = model_path.read_bytes()
    (n,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8 : 8 + n])
    deep = "[" * 100_000 + "]" * 100_000
    if inner:
        md = header["__metadata__"]
        md["torchtrack"] = md["torchtrack"][:-1] + ', "x": ' + deep + "}"
        text = json.dumps(header)
    else:
        text = json.dumps(header)[:-1] + ', "x": ' + deep + "}"
    h = text.encode() + b" " * (-len(text) % 8)
    bad = tmp_path / "deep.safetensors"
    bad.write_bytes(struct.pack("<Q", len(h)) + h + data[8 + n :])
    what = "the torchtrack description" if inner else "its header"
    with pytest.raises(ModelFormatError, match=f"deep.safetensors'?: {what} nests JSON .* deeply"):
        load_detector(bad)


@pytest.mark.parametrize(
    "meta_edit, match",
    [
        (None, "format"),  # metadata that is a list (meta_replace below)
        (lambda m: m.update(window=[100000, 100000]), "window height"),
        (lambda m: m.update(window=[16.5, 8]), "window height"),
        (lambda m: m["features"].update(window=[100000, 100000]), "bank window"),
        (lambda m: m["features"].update(sizes=[4], stride=1, min_std=1e-9), "min_std"),
        (lambda m: m["features"].update(sizes=[6]), "multiple of 4"),
        (lambda m: m["classifier"].update(n_features_in=3), "n_features_in"),
        (lambda m: m["classifier"].update(kind="forest"), "unknown classifier kind"),
        (lambda m: m["calibration"].update(a=-m["calibration"]["a"]), "Platt slope"),
        (lambda m: m["calibration"].update(a=-1e308), "Platt slope"),
        (lambda m: m["calibration"].update(b=1e308), "calibration.b"),
        (lambda m: m["calibration"].update(b="1"), "calibration.b"),
        (lambda m: m.update(name=["x"]), "name"),
        (lambda m: m.update(format_version=True), "format_version"),
        (lambda m: m.update(surprise=1), "unknown key"),
        (lambda m: m.pop("selected_features"), "lacks"),
        (lambda m: m["selected_features"].pop(), "selected_features"),
        (lambda m: m.update(object_box=[0.5, 0.5, 0.9, 0.9]), "object_box"),
    ],
)
def test_forged_description_is_refused(tmp_path, model_path, forge_model, meta_edit, match):
    """Edits with a recomputed checksum: the range and consistency checks refuse them."""
    if meta_edit is None:
        bad = forge_model(model_path, tmp_path / "bad.safetensors", meta_replace=lambda m: [m])
    else:
        bad = forge_model(model_path, tmp_path / "bad.safetensors", meta_edit=meta_edit)
    with pytest.raises(ModelFormatError, match=match):
        load_detector(bad)


def _set(name, fn):
    def edit(t):
        t[name] = fn(t[name].clone())

    return edit


@pytest.mark.parametrize(
    "tensor_edit, match",
    [
        (_set("classifier.threshold", lambda v: v + 1000), "classifier.threshold"),
        (_set("classifier.threshold", lambda v: v.fill_(float("nan"))), "NaN"),
        (_set("classifier.left", lambda v: v * 1e30), "classifier.left"),
        (_set("features.index", lambda v: v + 10**6), "outside the bank"),
        (_set("features.index", lambda v: v - 10**6), "outside the bank"),
        (_set("classifier.feature", lambda v: v + 4), "classifier.feature"),
        (_set("classifier.threshold", lambda v: v.double()), "dtype F64"),
        (_set("classifier.threshold", lambda v: v[:-1]), "shape"),
        (lambda t: t.update(extra=torch.zeros(2)), "unexpected tensor"),
    ],
)
def test_forged_tensors_are_refused(tmp_path, model_path, forge_model, tensor_edit, match):
    bad = forge_model(model_path, tmp_path / "bad.safetensors", tensor_edit=tensor_edit)
    with pytest.raises(ModelFormatError, match=match):
        load_detector(bad)


def test_svm_and_isotonic_ranges(tmp_path, forge_model):
    x, y = toy_data()
    det = make_detector(svm=True)
    path = save_detector(tmp_path / "svm.safetensors", det)
    C = read_model_metadata(path)["classifier"]["C"]
    for edit, match in (
        (_set("classifier.dual_coef", lambda v: v * 0 + 2 * C), "dual_coef"),
        (_set("classifier.scale", lambda v: -v), "scale"),
        (_set("classifier.support_vectors", lambda v: v[:, :2]), "support_vectors"),
    ):
        bad = forge_model(path, tmp_path / "bad.safetensors", tensor_edit=edit)
        with pytest.raises(ModelFormatError, match=match):
            load_detector(bad)
    bad = forge_model(
        path, tmp_path / "bad.safetensors", meta_edit=lambda m: m["classifier"].update(gamma=0)
    )
    with pytest.raises(ModelFormatError, match="gamma"):
        load_detector(bad)
    iso = det.with_calibrator(
        IsotonicCalibrator().fit(det.classifier.decision_function(x).double(), y)
    )
    path = save_detector(tmp_path / "iso.safetensors", iso)
    bad = forge_model(
        path, tmp_path / "bad.safetensors", tensor_edit=_set("calibration.y", lambda v: 1 - v)
    )
    with pytest.raises(ModelFormatError, match=r"calibration\.y"):
        load_detector(bad)


def test_huge_window_is_refused_before_allocating(tmp_path, model_path, forge_model):
    """The issue's 100000 x 100000 window with a recomputed checksum: refused from the header
    (the bank of that window would be ~5e10 features, 1.6 TB of table)."""
    import resource

    def huge(m):
        m["window"] = [100000, 100000]
        m["features"]["window"] = [100000, 100000]
        m["features"]["sizes"] = [64, 32, 16]

    bad = forge_model(model_path, tmp_path / "bad.safetensors", meta_edit=huge)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(ModelFormatError, match="window height"):
        load_detector(bad)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 100_000  # KiB


def test_bank_too_large_for_a_model_file(tmp_path, model_path, forge_model):
    def big(m):
        m["window"] = [512, 512]
        m["features"].update(window=[512, 512], sizes=[4, 8, 12, 16, 20, 24, 28, 32])

    bad = forge_model(model_path, tmp_path / "bad.safetensors", meta_edit=big)
    with pytest.raises(ModelFormatError, match="more than a model file may ask for"):
        load_detector(bad)


def test_save_refuses_a_model_that_would_not_load(tmp_path):
    det = make_detector()
    det.calibrator.a_ = abs(det.calibrator.a_)  # probability falling with the margin
    with pytest.raises(ModelFormatError, match=r"not writing .*Platt slope"):
        save_detector(tmp_path / "m.safetensors", det)
    assert not (tmp_path / "m.safetensors").exists()
    assert list(tmp_path.iterdir()) == []


def test_a_folder_or_a_huge_file_is_not_read(tmp_path, monkeypatch):
    from torchtrack.detect import model_file

    with pytest.raises(ModelFormatError, match="is a folder"):
        load_detector(tmp_path)
    path = save_detector(tmp_path / "m.safetensors", make_detector())
    monkeypatch.setattr(model_file, "LIMITS", model_file.Limits(file_bytes=100))
    with pytest.raises(ModelFormatError, match="more than a model file may have"):
        load_detector(path)
