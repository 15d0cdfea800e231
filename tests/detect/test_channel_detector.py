"""Channel-feature detectors end to end on a small real subset (seconds): training with mining
rounds, the model file (version 2, version 1 still loading, forged channel descriptions), the
cascade scan against box scoring, object boxes, the tracker's cropped scoring, and the bad
inputs of issue 16."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from torchtrack.detect import load_detector, save_detector
from torchtrack.detect.config import TrainConfig
from torchtrack.detect.model_file import read_model_metadata
from torchtrack.detect.scan import scan_batch, scan_window_count
from torchtrack.detect.train_channels import held_out_cascade_threshold
from torchtrack.detect.training import train_detector
from torchtrack.errors import ConfigError, DataError, ModelFormatError, TrainingWarning
from torchtrack.io.video import read_image

pytestmark = pytest.mark.usefixtures("one_thread")


def close_share(a: torch.Tensor, b: torch.Tensor, atol: float = 2e-3) -> float:
    """Share of entries equal within ``atol``."""
    return float(((a - b).abs() <= atol).double().mean())


def small_config(root) -> TrainConfig:
    cfg = TrainConfig(name="person-test", window=[128, 64])
    cfg.data.positives = [str(root / "pos")]
    cfg.data.crop_size, cfg.data.region = [160, 96], [16, 16, 64, 128]
    cfg.data.object = [32, 32, 32, 96]
    cfg.data.negative_images = [str(root / "neg")]
    cfg.data.random_negatives = 300
    cfg.data.negative_min_scale = 0.7
    cfg.data.gray_copies = True
    cfg.data.positive_jitter = 2
    cfg.features.kind = "channels"
    cfg.features.cells = False
    cfg.features.boxes = 300
    cfg.features.haar = 100
    cfg.learn.n_trees = 24
    cfg.mining.rounds = 1
    cfg.mining.per_round = 200
    cfg.mining.scale_step = 1.3
    cfg.mining.stride = 0.125
    cfg.mining.target_fpr = 0.5
    cfg.learn.cascade = "held-out"
    cfg.learn.box_regression = True
    return cfg.validate()


@pytest.fixture(scope="module")
def folders(data_dir, tmp_path_factory):
    """40 INRIA person crops and 4 person-free images."""
    crops = data_dir / "detection_crops"
    root = tmp_path_factory.mktemp("persons")
    (root / "pos").mkdir()
    (root / "neg").mkdir()
    for p in sorted((crops / "inria_person_96x160" / "pos").glob("*.png"))[:40]:
        shutil.copy(p, root / "pos" / p.name)
    for p in sorted((crops / "inria_negatives" / "train").iterdir())[:4]:
        shutil.copy(p, root / "neg" / p.name)
    return root


@pytest.fixture(scope="module")
def trained(folders, tmp_path_factory):
    det = train_detector(small_config(folders))
    path = save_detector(tmp_path_factory.mktemp("m") / "person.safetensors", det)
    return det, path


@pytest.fixture(scope="module")
def frame(data_dir):
    return read_image(data_dir / "tracking" / "otb" / "Crossing" / "img" / "0001.jpg")


def test_training_summary_and_model_file(trained, frame):
    det, path = trained
    s = det.summary
    assert [r["round"] for r in s["rounds"]] == [0, 1]
    assert s["rounds"][0]["trees"] == 32 and s["rounds"][1]["trees"] == 24  # max(32, ...), final
    assert s["held_out"]["auc"] > 0.9
    assert s["features"]["used"] == len(det.bank) <= s["features"]["pool"] == 400
    c = s["cascade"]
    assert c["method"] == "held-out" and c["upper"] == -1.0 and c["threshold"] <= -1.0
    assert bool((det.classifier.reject_ == torch.tensor(c["threshold"], dtype=torch.float32)).all())
    assert c.get("held_out_confident_positives_rejected", 0.0) <= 0.01
    assert det.object_box == (0.25, 0.125, 0.5, 0.75)
    meta = read_model_metadata(path)
    assert meta["format_version"] == 2 and meta["features"]["kind"] == "channels"
    assert "selected_features" not in meta
    again = load_detector(path)
    boxes = torch.tensor([[[100.0, 40.0, 40.0, 80.0], [10.5, 3.2, 64.0, 128.0], [200, 10, 30, 60]]])
    torch.testing.assert_close(again.score(frame[None], boxes), det.score(frame[None], boxes))
    # learn.box_regression: a regressor on the selected features, fitted on the 40 crops and
    # their mirrors, saved and loaded with the model
    reg = det.box_regressor
    assert reg is not None and reg.n_features == det.feature_index.numel()
    assert reg.summary["crops"] == 80 and reg.summary["windows"] == 80 * 16
    assert torch.equal(again.box_regressor.weight, reg.weight)
    torch.testing.assert_close(
        again.refine_windows(frame[None], boxes), det.refine_windows(frame[None], boxes)
    )


def test_scan_with_pad_scores_windows_over_the_edges_on_the_continued_frame(trained, frame):
    det, _ = trained
    kw = {"min_scale": 0.5, "max_scale": 0.9, "scale_step": 1.25, "stride": 0.125, "pad": 0.2}
    wins, m = scan_batch(
        det, frame[None], threshold=None, margin=True, nms_iou=None, cascade=False, **kw
    )[0]
    assert wins.shape[0] == scan_window_count(det, tuple(frame.shape[-2:]), **kw)
    fh, fw = frame.shape[-2:]
    far = wins[:, :2] + wins[:, 2:] > torch.tensor([fw, fh])
    over = (wins[:, :2] < 0).any(1) | far.any(1)
    assert 0 < int(over.sum()) < wins.shape[0]
    # at most 0.2 of the window (rounded to whole cells) over any edge
    hc, wc = det.bank.grid
    cs = det.bank.cell * wins[:, 2] / det.window[1]
    assert bool((-wins[:, 0] <= round(0.2 * wc) * cs + 1e-4).all())
    assert bool((-wins[:, 1] <= round(0.2 * hc) * cs + 1e-4).all())
    # the scores are those of the frame with its edge pixels continued
    p = 64
    padded = torch.nn.functional.pad(frame[None].float(), (p, p, p, p), mode="replicate")
    ref = det.decision_function(padded, (wins + torch.tensor([p, p, 0.0, 0.0]))[None])[0]
    torch.testing.assert_close(m, ref, atol=2e-4, rtol=1e-5)


def test_scan_cascade_threshold_overrides_the_models(trained, frame):
    det, _ = trained
    kw = {"min_scale": 0.5, "max_scale": 0.9, "scale_step": 1.25, "stride": 0.125}
    kw |= {"threshold": None, "margin": True, "nms_iou": None}
    full, _ = scan_batch(det, frame[None], cascade=False, **kw)[0]
    own, _ = scan_batch(det, frame[None], **kw)[0]
    never, _ = scan_batch(det, frame[None], cascade_threshold=-1e9, **kw)[0]
    assert never.shape == full.shape  # a threshold nothing falls below rejects nothing
    own_max = float(det.classifier.reject_.max())
    loose, m = scan_batch(det, frame[None], cascade_threshold=own_max - 2.0, **kw)[0]
    assert own.shape[0] < loose.shape[0] <= full.shape[0]
    last = min(float(det.classifier.reject_[-1]), own_max - 2.0)
    assert bool((m >= last - 1e-4).all())  # no survivor ends below its last tree's bar
    # never stricter than the model's own: a higher value changes nothing
    same, _ = scan_batch(det, frame[None], cascade_threshold=own_max + 5.0, **kw)[0]
    assert torch.equal(same, own)
    with pytest.raises(ConfigError, match="cascade_threshold"):
        scan_batch(det, frame[None], cascade_threshold=float("-inf"), **kw)


def test_scales_scored_together_equal_one_call_per_scale(trained, frame, monkeypatch):
    """The scan scores the windows of several scales in one cascade call; capping the group at
    one scale (one call per scale, as before) gives the same windows and margins, bit for bit,
    with and without the cascade, on two frames at once and with windows over the edges."""
    import torchtrack.detect.scan as scan_module

    det, _ = trained
    frames = torch.stack([frame, frame.flip(-1)])
    kw = {"min_scale": 0.5, "max_scale": 1.2, "scale_step": 1.15, "stride": 0.125, "pad": 0.1}
    kw |= {"threshold": None, "margin": True, "nms_iou": None}
    runs, big = {}, scan_module._GROUP_VALUES
    assert big > 10_000  # several scales of this frame fit one group
    for group in (big, 1):
        monkeypatch.setattr(scan_module, "_GROUP_VALUES", group)
        runs[group] = [scan_batch(det, frames, cascade_threshold=c, **kw) for c in (None, -1e9)] + [
            scan_batch(det, frames, cascade=False, **kw)
        ]
    assert runs[1][0][0][0].shape[0] > 0
    for together, alone in zip(runs[big], runs[1], strict=True):
        for (wa, ma), (wb, mb) in zip(together, alone, strict=True):
            assert torch.equal(wa, wb) and torch.equal(ma, mb)


@pytest.mark.parametrize("pad", [0.0, 0.1])
def test_kept_windows_are_scored_as_in_the_whole_scan(trained, frame, pad):
    """``keep_windows`` (a band of window bottoms, as a ground plane gives, and a column
    range): the lattice covers only the rows and columns those windows read, and each kept
    window gets the margin of the whole scan, bit for bit; the rest are not scored."""
    det, _ = trained
    frames = torch.stack([frame, frame.flip(-1)])
    kw = {"min_scale": 0.5, "max_scale": 1.2, "scale_step": 1.15, "stride": 0.125, "pad": pad}
    kw |= {"threshold": None, "margin": True, "nms_iou": None}

    def keep(w):
        bottom = w[:, 1] + w[:, 3]
        return (bottom > 0.6 * w[:, 3] + 40) & (bottom < 1.4 * w[:, 3] + 60) & (w[:, 0] > 10)

    calls = []

    def spy(w):
        calls.append(w.shape[0])
        return keep(w)

    for c in (None, -1e9):
        whole = scan_batch(det, frames, cascade_threshold=c, **kw)
        part = scan_batch(det, frames, cascade_threshold=c, keep_windows=spy, **kw)
        for (wa, ma), (wb, mb) in zip(whole, part, strict=True):
            k = keep(wa)
            assert 0 < int(k.sum()) < wa.shape[0]
            wa, ma = wa[k], ma[k]
            oa, ob = (torch.from_numpy(np.lexsort(w.T.numpy()[::-1].copy())) for w in (wa, wb))
            assert torch.equal(wa[oa], wb[ob]) and torch.equal(ma[oa], mb[ob])
    assert len(calls) >= 4  # once per scale
    none = scan_batch(det, frames, keep_windows=lambda w: w[:, 0] < -1e6, **kw)
    assert all(w.shape[0] == 0 for w, _ in none)


def test_scan_is_box_scoring_with_a_cascade_and_reports_object_boxes(trained, frame):
    det, _ = trained
    kw = {"min_scale": 0.5, "max_scale": 0.9, "scale_step": 1.25, "stride": 0.125}
    wins, m = scan_batch(
        det, frame[None], threshold=None, margin=True, nms_iou=None, cascade=False, **kw
    )[0]
    assert wins.shape[0] == scan_window_count(det, tuple(frame.shape[-2:]), **kw)
    ref = det.decision_function(frame[None], wins[None])[0]
    order = wins[:, 1] * 1e4 + wins[:, 0] + wins[:, 2] * 1e8
    torch.testing.assert_close(m[order.argsort()], ref[order.argsort()], atol=2e-4, rtol=1e-5)
    # the cascade keeps a subset, with their full margins
    kept, mk = scan_batch(det, frame[None], threshold=None, margin=True, nms_iou=None, **kw)[0]
    assert 0 < kept.shape[0] < wins.shape[0]
    torch.testing.assert_close(
        mk, det.decision_function(frame[None], kept[None])[0], atol=2e-4, rtol=1e-5
    )
    # Detector.scan reports object boxes (NMS on them); windows on request, and with the same
    # NMS the same detections, each object box inside its window
    obj, p = det.scan(frame, threshold=0.0, **kw)
    win, p2 = det.scan(frame, threshold=0.0, windows=True, nms_on="object", **kw)
    assert obj.shape[0] > 0
    assert torch.equal(p, p2) and torch.equal(obj, det.window_to_object(win))
    assert not torch.equal(obj, win)


def test_cropped_tracker_scoring_equals_the_whole_frame(trained, frame):
    from torchtrack.observe.detector import DetectorObservation

    det, _ = trained
    g = torch.Generator().manual_seed(0)
    wh = 20 + 60 * torch.rand(50, 2, generator=g, dtype=torch.float64)
    xy = torch.rand(50, 2, generator=g, dtype=torch.float64) * torch.tensor([300.0, 200.0])
    boxes = torch.cat([xy, wh * torch.tensor([0.5, 1.0], dtype=torch.float64)], 1)[None]
    a = DetectorObservation(det, crop=True).probabilities(frame[None], boxes)
    b = DetectorObservation(det, crop=False).probabilities(frame[None], boxes)
    assert close_share(a, b, atol=1e-4) >= 0.95  # see the scan test: rare threshold crossings


def test_colour_model_on_a_grayscale_image(trained, frame):
    """Documented: a gray image is taken as R = G = B (U = V = 0); it scores like that RGB image."""
    det, _ = trained
    assert det.colour
    gray = (
        frame.float().mul(torch.tensor([0.299, 0.587, 0.114])[:, None, None]).sum(0, keepdim=True)
    )
    gray = gray.round().to(torch.uint8)
    boxes = torch.tensor([[[100.0, 40.0, 40.0, 80.0], [10.0, 3.0, 64.0, 128.0]]])
    p1 = det.score(gray[None], boxes)
    p3 = det.score(gray.expand(3, -1, -1)[None], boxes)
    torch.testing.assert_close(p1, p3)
    assert bool(torch.isfinite(p1).all())


def _people_as_negatives(folders, tmp_path):
    """Negative 'images' that show people (INRIA positive crops): mining cannot clean them."""
    neg = tmp_path / "neg"
    neg.mkdir()
    for p in sorted((folders / "pos").iterdir())[:3]:
        shutil.copy(p, neg / p.name)
    for p in sorted((folders / "neg").iterdir())[:1]:
        shutil.copy(p, neg / p.name)
    return neg


def test_warns_when_the_false_positive_rate_is_not_reached(folders, tmp_path):
    cfg = small_config(folders)
    cfg.data.negative_images = [str(_people_as_negatives(folders, tmp_path))]
    cfg.data.negative_min_scale = 0.5
    cfg.mining.target_fpr = 0.0
    cfg.learn.n_trees = 8
    lines: list[str] = []
    with pytest.warns(
        TrainingWarning, match=r"false-positive rate .* above mining.target_fpr = 0"
    ) as rec:
        train_detector(cfg, log=lines.append)
    # warned, not logged as well: `torchtrack train` prints both, so it read twice
    assert len([w for w in rec if w.category is TrainingWarning]) == 1
    assert not [ln for ln in lines if "above mining.target_fpr" in ln]


def test_cli_prints_the_false_positive_rate_warning_once(folders, tmp_path, capsys):
    from torchtrack.cli import main

    neg = _people_as_negatives(folders, tmp_path)
    (tmp_path / "c.toml").write_text(
        f"""name = "person-test"
window = [128, 64]
[data]
positives = ["{folders / "pos"}"]
negative_images = ["{neg}"]
crop_size = [160, 96]
region = [16, 16, 64, 128]
random_negatives = 300
negative_min_scale = 0.5
[features]
kind = "channels"
cells = false
boxes = 300
haar = 100
[learn]
n_trees = 8
[mining]
rounds = 1
per_round = 200
scale_step = 1.3
stride = 0.125
target_fpr = 0.0
"""
    )
    out = tmp_path / "m.safetensors"
    with pytest.warns(TrainingWarning, match="above mining.target_fpr = 0") as rec:
        assert main(["train", "--config", str(tmp_path / "c.toml"), "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert "mining:" in err  # the log lines are printed ...
    assert "above mining.target_fpr" not in err  # ... the warning only by the warnings module
    assert len([w for w in rec if w.category is TrainingWarning]) == 1


def test_bad_inputs(folders, tmp_path):
    cfg = small_config(folders)
    cfg.features.channels = ["L", "U", "V", "depth"]
    with pytest.raises(ConfigError, match=r"unknown channel name 'depth'.*gray"):
        cfg.validate()
    empty = tmp_path / "negs"
    empty.mkdir()
    (empty / "notes.txt").write_text("no images")
    (empty / "broken.png").write_bytes(b"\x89PNG not an image")
    cfg = small_config(folders)
    cfg.data.negative_images = [str(empty)]
    with pytest.raises(DataError, match="negative image"):
        train_detector(cfg)
    cfg = small_config(folders)
    cfg.data.positive_jitter = -1
    with pytest.raises(ConfigError, match="positive_jitter"):
        cfg.validate()
    cfg = small_config(folders)
    cfg.data.positive_scales = [1.0, 0.3]  # 4-px cells x 0.3 is not whole pixels
    with pytest.raises(ConfigError, match="positive_scales"):
        cfg.validate()


def test_version_1_files_load_and_future_versions_are_named(tmp_path, forge_model):
    from torchtrack.detect import Detector
    from torchtrack.features.haar import haar_bank
    from torchtrack.learn import BoostedStumps, PlattCalibrator

    g = torch.Generator().manual_seed(0)
    x = torch.randn(80, 4, generator=g)
    y = (x[:, 0] > 0).long()
    clf = BoostedStumps(n_estimators=4).fit(x, y)
    det = Detector(
        haar_bank((16, 8), sizes=(8, 4)),
        torch.tensor([3, 50, 200, 360]),
        clf,
        PlattCalibrator().fit(clf.decision_function(x).double(), y),
        name="old",
    )
    path = save_detector(tmp_path / "v2.safetensors", det)

    def to_v1(m):
        f = m.pop("features")
        f.pop("kind")
        m["bank"] = f
        m["format_version"] = 1

    old = forge_model(path, tmp_path / "v1.safetensors", meta_edit=to_v1)
    assert read_model_metadata(old)["format_version"] == 1
    frames = torch.randint(0, 256, (1, 3, 40, 30), dtype=torch.uint8, generator=g)
    boxes = torch.tensor([[[2.0, 3.0, 8.0, 16.0]]])
    torch.testing.assert_close(load_detector(old).score(frames, boxes), det.score(frames, boxes))
    future = forge_model(
        path, tmp_path / "v3.safetensors", meta_edit=lambda m: m.update(format_version=3)
    )
    with pytest.raises(
        ModelFormatError, match="format version 3, newer than this torchtrack reads"
    ):
        load_detector(future)


def test_forged_channel_descriptions_are_refused(trained, tmp_path, forge_model):
    _, path = trained
    cases = [
        (
            lambda m: m["features"]["channels"].update(names=["L", "U", "V", "sonar"]),
            "unknown channel name 'sonar'",
        ),
        (lambda m: m["features"].update(cell=3), "multiples of the cell"),
        (lambda m: m["features"].update(n_features=10**9), "n_features"),
        (lambda m: m["features"].update(kind="wavelets"), "features.kind"),
        (lambda m: m["classifier"].update(max_depth=7), "max_depth"),
    ]
    for edit, match in cases:
        bad = forge_model(path, tmp_path / "bad.safetensors", meta_edit=edit)
        with pytest.raises(ModelFormatError, match=match):
            load_detector(bad)

    def outside(t):
        r = t["features.rects"].clone()
        r[0, 0, 2] = 1000
        t["features.rects"] = r

    bad = forge_model(path, tmp_path / "bad2.safetensors", tensor_edit=outside)
    with pytest.raises(ModelFormatError, match="inside the 32x16-cell window"):
        load_detector(bad)
    short = forge_model(
        path,
        tmp_path / "bad3.safetensors",
        tensor_edit=lambda t: t.update({"features.channel": t["features.channel"][:-1]}),
    )
    with pytest.raises(ModelFormatError, match=r"features\.channel"):
        load_detector(short)


def test_tracking_head_scores_with_its_first_trees(folders, frame, tmp_path, forge_model):
    """A model trained with ``learn.tracking_trees`` keeps a head: the first trees, reading
    only their features, with a Platt calibration of their own; saved, loaded and checked."""
    cfg = small_config(folders)
    cfg.learn.tracking_trees = 8
    det = train_detector(cfg)
    k, cal = det.tracking_head
    assert k == 8 and det.summary["tracking_head"]["trees"] == 8
    assert det.summary["tracking_head"]["held_out_by_trees"]["8"]["auc"] > 0.8
    head = det.tracking_model()
    used = torch.unique(det.classifier.feature_[:8])
    assert head.feature_index.numel() == used.numel() < det.feature_index.numel()
    boxes = torch.tensor([[[100.0, 40.0, 40.0, 80.0], [10.5, 3.2, 64.0, 128.0], [200, 10, 30, 60]]])
    staged = det.classifier.staged_decision_function(det.features(frame[None], boxes))[..., 7]
    torch.testing.assert_close(
        head.decision_function(frame[None], boxes), staged, atol=1e-4, rtol=0
    )
    torch.testing.assert_close(
        head.score(frame[None], boxes),
        cal.predict_proba(staged.double()).float(),
        atol=1e-5,
        rtol=0,
    )
    path = save_detector(tmp_path / "head.safetensors", det)
    again = load_detector(path)
    assert again.tracking_head[0] == 8
    torch.testing.assert_close(
        again.tracking_model().score(frame[None], boxes), head.score(frame[None], boxes)
    )
    # the particle filter's observation uses the head unless told otherwise
    from torchtrack.observe.detector import DetectorObservation

    assert DetectorObservation(again).detector.classifier.n_estimators == 8
    assert DetectorObservation(again, head=False).detector is again
    for edit, match in [
        (lambda m: m["tracking_head"].update(trees=10**6), "tracking_head.trees"),
        (lambda m: m["tracking_head"]["calibration"].update(a=1.0), "tracking_head"),
        (lambda m: m["tracking_head"].update(extra=1), "tracking_head"),
    ]:
        bad = forge_model(path, tmp_path / "bad.safetensors", meta_edit=edit)
        with pytest.raises(ModelFormatError, match=match):
            load_detector(bad)


def test_held_out_cascade_threshold_keeps_all_but_the_miss_share_of_confident_positives():
    g = torch.Generator().manual_seed(0)
    staged = torch.randn(500, 40, generator=g).cumsum(1)  # running margins after each tree
    prob = torch.rand(500, generator=g)
    keep = prob >= 0.5
    theta = held_out_cascade_threshold(staged, keep, miss=0.01, upper=10.0)
    low = staged[keep].min(1).values
    rejected = float((low < theta).double().mean())
    assert 0.005 < rejected <= 0.01  # at most the miss share, and not needlessly fewer
    # never above the upper bound; miss 0 keeps every confident positive
    assert held_out_cascade_threshold(staged, keep, miss=0.01, upper=-50) == -50
    t0 = held_out_cascade_threshold(staged, keep, miss=0.0, upper=10.0)
    assert bool((low >= t0).all()) and float(low.min()) - t0 < 1e-3
    # no confident positive: the upper bound
    none = torch.zeros_like(keep)
    assert held_out_cascade_threshold(staged, none, miss=0.01, upper=-1) == -1


def test_tracker_crops_come_in_few_shapes_and_hold_their_boxes():
    """Particle-scoring crops are whole multiples of CROP_QUANTUM (clipped at the frame's edge),
    start on the alignment grid and contain the boxes plus their margin: a long run meets few
    crop shapes (oneDNN compiles and caches one convolution per input shape)."""
    from torchtrack.detect.detector import CROP_QUANTUM, _crop_span

    g = torch.Generator().manual_seed(0)
    lengths = set()
    for _ in range(2000):
        size = 480
        lo = float(torch.rand(1, generator=g)) * 460
        hi = min(size, lo + 5 + float(torch.rand(1, generator=g)) * 200)
        margin, align = (
            int(torch.randint(0, 20, (1,), generator=g)),
            1 << int(torch.randint(0, 3, (1,), generator=g)),
        )
        a, b = _crop_span(lo, hi, margin, align, size)
        assert a % align == 0 and 0 <= a < b <= size
        assert a <= max(0, int(lo) - margin) and b >= min(size, int(hi) + margin)
        if b < size:
            assert (b - a) % CROP_QUANTUM == 0
        lengths.add(b - a)
    assert len(lengths) <= 40  # against ~480 for unrounded crops


def test_blur_copies_blur_both_classes_and_stay_in_their_groups(folders):
    """``data.blur_copies``: a seeded share of the positive crops and of the negative images
    get a copy blurred as OpenCV's Gaussian blurs (sd in pixels), tagged ``#blur`` so that the
    calibration split keeps each copy with its source; bad values are ConfigErrors."""
    import cv2

    from torchtrack.detect.train_channels import _group_key, load_channel_data

    cfg = small_config(folders)
    cfg.data.positive_jitter = 0
    plain = load_channel_data(cfg)
    cfg.data.blur_copies, cfg.data.blur_share = 1.0, 0.5
    data = load_channel_data(cfg.validate())
    n0, n1 = len(plain.positives[0]), len(data.positives[0])
    assert n1 == n0 + n0 // 2  # half of the crops (gray copies among them), mirrors follow
    assert len(data.images) == len(plain.images) + len(plain.images) // 2
    blur_src = [s for s in data.positives[0].sources if "#blur" in s]
    assert len(blur_src) == n0 // 2
    assert {_group_key(s) for s in blur_src} <= {_group_key(s) for s in plain.positives[0].sources}
    # the first blurred image is a blurred copy of the image it names, as cv2 blurs it
    i = data.image_sources.index(next(s for s in data.image_sources if s.endswith("#blur")))
    src = plain.image_sources.index(data.image_sources[i].removesuffix("#blur"))
    ref = cv2.GaussianBlur(
        plain.images[src].permute(1, 2, 0).numpy(), (7, 7), 1.0, borderType=cv2.BORDER_REFLECT_101
    )
    got = data.images[i].permute(1, 2, 0).numpy()
    assert np.abs(got.astype(int) - ref.astype(int)).max() <= 1
    assert not np.array_equal(got, plain.images[src].permute(1, 2, 0).numpy())
    # the same seed picks the same ones
    again = load_channel_data(cfg)
    assert again.image_sources == data.image_sources
    for key, bad in (("blur_copies", -1.0), ("blur_copies", float("nan")), ("blur_share", 0.0)):
        c = small_config(folders)
        setattr(c.data, key, bad)
        with pytest.raises(ConfigError, match=key):
            c.validate()
    c = small_config(folders)
    c.features.kind, c.data.blur_copies = "haar", 1.0
    with pytest.raises(ConfigError, match="blur_copies applies to channel models"):
        c.validate()
