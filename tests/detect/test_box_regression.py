"""The box regressor: where the object lies in a detection window (torchtrack.detect.box_regression)."""

from dataclasses import replace

import pytest
import torch

from torchtrack.detect import load_detector, save_detector
from torchtrack.detect.box_regression import BoxRegressor, fit_box_regressor, jitter_windows
from torchtrack.detect.bundled import load_model
from torchtrack.detect.scan import scan, scan_batch
from torchtrack.errors import ConfigError, DataError, ModelFormatError, ShapeError


def _regressor(k, w=None, b=(0.0, 0.0, 0.0), limit=(0.12, 0.06, 0.12)):
    w = torch.zeros(3, k) if w is None else w
    return BoxRegressor(w, torch.tensor(b), limit, {"note": "test"})


def test_apply_moves_and_scales_the_window_and_clips_to_its_limits():
    reg = _regressor(2, w=torch.tensor([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]]), b=(0, 0, 0.1))
    win = torch.tensor([[10.0, 20.0, 40.0, 80.0]])
    out = reg.apply(win, torch.tensor([[0.05, -0.02]]))
    s = torch.exp(torch.tensor(0.1))
    cx, cy = 30 + 0.05 * 40, 60 - 0.02 * 80
    want = torch.tensor([[cx - 20 * s, cy - 40 * s, 40 * s, 80 * s]])
    assert torch.allclose(out, want, atol=1e-4)
    # a prediction beyond the fitting jitter is clipped to it
    d = reg.predict(torch.tensor([[5.0, -5.0]]))
    assert torch.allclose(d, torch.tensor([[0.12, -0.06, 0.1]]))


def test_jitter_targets_take_each_window_back_to_the_region():
    g = torch.Generator().manual_seed(0)
    region = (16, 16, 64, 128)
    win, t = jitter_windows(region, 500, (0.12, 0.06, 0.12), g)
    reg = _regressor(3, w=torch.eye(3))
    back = reg.apply(win.float(), t.float())  # the targets as the prediction
    assert torch.allclose(
        back, torch.tensor([region], dtype=torch.float32).expand(500, 4), atol=1e-3
    )
    assert float(t[:, 0].abs().max()) <= 0.12 + 1e-9 and float(t[:, 2].abs().max()) <= 0.12 + 1e-9


@pytest.mark.parametrize(
    "kw, err, match",
    [
        ({"w": torch.zeros(2, 4)}, ShapeError, "weight must be"),
        ({"w": torch.full((3, 4), float("nan"))}, ModelFormatError, "finite"),
        ({"limit": (0.1, 0.0, 0.1)}, ConfigError, "limits"),
        ({"limit": (0.1, 2.0, 0.1)}, ConfigError, "limits"),
    ],
)
def test_bad_regressors_are_refused(kw, err, match):
    with pytest.raises(err, match=match):
        _regressor(4, **kw)


def test_fit_refuses_too_few_crops_and_bad_settings():
    det = load_model("pedestrian")
    few = torch.zeros((3, 3, 160, 96), dtype=torch.uint8)
    with pytest.raises(DataError, match="at least 8"):
        fit_box_regressor(det, few, (16, 16, 64, 128))
    crops = torch.zeros((8, 3, 160, 96), dtype=torch.uint8)
    for kw, match in (
        ({"per_crop": 0}, "per_crop"),
        ({"jitter": (0.1, 0.1)}, "jitter"),
        ({"alpha": float("nan")}, "alpha"),
        ({"held_out": 1.0}, "held_out"),
    ):
        with pytest.raises(ConfigError, match=match):
            fit_box_regressor(det, crops, (16, 16, 64, 128), **kw)


def test_a_regressor_reading_other_features_than_the_detector_is_refused():
    det = load_model("pedestrian")
    with pytest.raises(ModelFormatError, match="box regressor reads 5 features"):
        replace(det, box_regressor=_regressor(5))


def test_model_file_round_trip_and_forged_sections(tmp_path, forge_model):
    det = load_model("pedestrian")
    assert det.box_regressor is not None  # the bundled pedestrian model ships one
    path = save_detector(tmp_path / "p.safetensors", det)
    back = load_detector(path)
    assert torch.equal(back.box_regressor.weight, det.box_regressor.weight)
    assert torch.equal(back.box_regressor.bias, det.box_regressor.bias)
    assert back.box_regressor.limit == det.box_regressor.limit
    # a model without one (the vehicle model) still loads, and saves without the section
    assert load_model("vehicle").box_regressor is None
    plain = load_detector(
        save_detector(tmp_path / "n.safetensors", replace(det, box_regressor=None))
    )
    assert plain.box_regressor is None

    def tensor(name, fn):
        def edit(t):
            t[name] = fn(t[name].clone())

        return edit

    for kw, match in (
        (
            {"tensor_edit": tensor("box_regression.weight", lambda v: v[:, :-1])},
            "box_regression.weight",
        ),
        (
            {"tensor_edit": tensor("box_regression.bias", lambda v: v.double())},
            "box_regression.bias",
        ),
        (
            {"tensor_edit": tensor("box_regression.weight", lambda v: v.fill_(float("inf")))},
            "not finite",
        ),
        (
            {"tensor_edit": lambda t: t.update({"box_regression.extra": torch.zeros(1)})},
            "unexpected",
        ),
        ({"meta_edit": lambda m: m["box_regression"].update(limit=[0.1, 0.1])}, "limit"),
        ({"meta_edit": lambda m: m["box_regression"].update(limit=[0.1, 0.1, 7])}, "limit"),
        ({"meta_edit": lambda m: m["box_regression"].update(extra=1)}, "unknown key"),
        ({"meta_edit": lambda m: m.pop("box_regression")}, "unexpected tensor"),
    ):
        bad = forge_model(path, tmp_path / "bad.safetensors", **kw)
        with pytest.raises(ModelFormatError, match=match):
            load_detector(bad)


def _crops(data_dir, names):
    import cv2

    folder = data_dir / "detection_crops" / "inria_person_96x160" / "pos"
    imgs = [cv2.cvtColor(cv2.imread(str(folder / n)), cv2.COLOR_BGR2RGB) for n in names]
    return torch.from_numpy(__import__("numpy").stack(imgs)).permute(0, 3, 1, 2).contiguous()


def _test_split():
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "configs" / "splits" / "inria_person_test.txt"
    return [s.strip() for s in path.read_text().splitlines() if s.strip() and not s.startswith("#")]


@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_the_shipped_regressor_puts_held_out_people_back_in_place(data_dir, scale):
    """The held-out test crops (never used to fit it), at their own size and at half size (a
    person 48 px tall, as the detector also trains: ``data.positive_scales``): windows moved
    off each person by a known amount are moved back; the error left is far below the error
    put in."""
    from torchtrack.detect.train_channels import _scaled_images

    det = load_model("pedestrian")
    assert det.box_regressor.summary["scales"] == [1.0, 0.5]
    crops, region = _scaled_images(_crops(data_dir, _test_split()[:120]), (16, 16, 64, 128), scale)
    g = torch.Generator().manual_seed(5)
    win, t = jitter_windows(region, crops.shape[0] * 4, (0.12, 0.06, 0.12), g)
    win = win.float().view(crops.shape[0], 4, 4)
    pred = det.box_regressor.predict(det.features(crops, win, check=False)).reshape(-1, 3)
    before = t.pow(2).mean(0).sqrt()
    after = (pred.double() - t).pow(2).mean(0).sqrt()
    assert float(after[0]) < 0.75 * float(before[0])  # across: ~0.07 -> ~0.04
    assert float(after[1]) < 0.75 * float(before[1])  # up and down
    assert float(after[2]) < 0.9 * float(before[2])  # scale: the hardest
    # and refine_windows is that move
    moved = det.refine_windows(crops, win)
    assert torch.allclose(
        moved, det.box_regressor.apply(win, det.features(crops, win, check=False))
    )


def test_fit_learns_the_move_from_training_crops(data_dir):
    """Fitted on 200 training crops, scored on held-out test crops: it beats leaving the
    windows where they are, and its summary records held-out residuals below the jitter."""
    from pathlib import Path

    test = set(_test_split())
    folder = Path(data_dir) / "detection_crops" / "inria_person_96x160" / "pos"
    train = sorted(p.name for p in folder.glob("*.png") if p.name not in test)[:200]
    det = replace(load_model("pedestrian"), box_regressor=None)
    reg = fit_box_regressor(det, _crops(data_dir, train), (16, 16, 64, 128), per_crop=8, alpha=1e4)
    s = reg.summary
    assert all(
        a < b
        for a, b in zip(s["held_out_rms_after"][:2], s["held_out_rms_before"][:2], strict=True)
    )
    crops = _crops(data_dir, _test_split()[:60])
    win, t = jitter_windows(
        (16, 16, 64, 128), 60 * 4, (0.12, 0.06, 0.12), torch.Generator().manual_seed(1)
    )
    win = win.float().view(60, 4, 4)
    pred = reg.predict(det.features(crops, win, check=False)).reshape(-1, 3)
    assert float((pred.double() - t)[:, :2].pow(2).mean()) < 0.8 * float(t[:, :2].pow(2).mean())


def test_fit_reads_the_crops_at_every_scale(data_dir):
    """``scales``: every crop is also read downscaled (the region with it), its jittered
    windows join the fit, and the held-out groups hold every scale of their crops."""
    from pathlib import Path

    test = set(_test_split())
    folder = Path(data_dir) / "detection_crops" / "inria_person_96x160" / "pos"
    train = sorted(p.name for p in folder.glob("*.png") if p.name not in test)[:64]
    det = replace(load_model("pedestrian"), box_regressor=None)
    crops = _crops(data_dir, train)
    one = fit_box_regressor(det, crops, (16, 16, 64, 128), per_crop=4)
    two = fit_box_regressor(det, crops, (16, 16, 64, 128), per_crop=4, scales=(1.0, 0.5))
    assert one.summary["windows"] == 64 * 4 and one.summary["scales"] == [1.0]
    assert two.summary["windows"] == 2 * 64 * 4 and two.summary["scales"] == [1.0, 0.5]
    assert not torch.equal(one.weight, two.weight)
    for bad in [(), (1.0, 1.0), (0.0,), (1.5,)]:
        with pytest.raises(ConfigError, match="scales must be distinct"):
            fit_box_regressor(det, crops, (16, 16, 64, 128), per_crop=4, scales=bad)
    with pytest.raises(ConfigError, match=r"^scales: 0.3 x the window region .* whole pixels"):
        fit_box_regressor(det, crops, (16, 16, 64, 128), per_crop=4, scales=(1.0, 0.3))


def test_scan_refines_only_the_windows_nms_keeps():
    from torchtrack.data import demo_clip_path
    from torchtrack.io.video import open_source

    det = load_model("pedestrian")
    frame = next(iter(open_source(demo_clip_path())))
    kw = dict(threshold=0.5, min_scale=0.4, scale_step=1.15, stride=0.08, nms_iou=0.4)
    raw, p_raw = scan(det, frame, refine=False, **kw)
    ref, p_ref = scan(det, frame, **kw)
    assert raw.shape[0] > 0 and torch.equal(p_raw, p_ref)  # scores as scanned
    assert not torch.allclose(raw, ref)
    want = det.refine_windows(det.integrals(frame[None].float()), raw[None])[0]
    assert torch.allclose(ref, want, atol=0.05)  # the scan's padded tables: the same reads
    # without NMS every window comes back as scanned
    a, _ = scan(det, frame, threshold=0.99, min_scale=0.4, nms_iou=None)
    b, _ = scan(det, frame, threshold=0.99, min_scale=0.4, nms_iou=None, refine=False)
    assert torch.equal(a, b)
    # a batch of frames: each frame's windows as its own scan gives them, bit for bit
    frames = torch.stack([frame, frame.flip(-1)])
    batched = scan_batch(det, frames, **kw)
    for f in range(2):
        wa, sa = scan(det, frames[f], **kw)
        assert torch.equal(batched[f][0], wa) and torch.equal(batched[f][1], sa)


def test_the_shipped_regressor_is_what_its_recipe_fits(data_dir, monkeypatch):
    """``train/default_models.py --box-regression``: refitting the bundled pedestrian model's
    regressor from ``configs/pedestrian.toml`` (its crops, its test split left out, its seed)
    gives the shipped tensors bit for bit."""
    from pathlib import Path

    from torchtrack.detect.config import load_train_config
    from torchtrack.detect.train_channels import fit_box_regression

    cfg_path = Path(__file__).resolve().parents[2] / "configs" / "pedestrian.toml"
    cfg = load_train_config(cfg_path)
    cfg.data.positives = [str(data_dir / "detection_crops" / "inria_person_96x160" / "pos")]
    det = load_model("pedestrian")
    again = fit_box_regression(cfg, replace(det, box_regressor=None)).box_regressor
    assert torch.equal(again.weight, det.box_regressor.weight)
    assert torch.equal(again.bias, det.box_regressor.bias)
    assert again.summary == det.box_regressor.summary
