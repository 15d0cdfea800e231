import math

import numpy as np
import pytest
import torch

from torchtrack.boxes import box_iou_matrix
from torchtrack.detect.bundled import load_model
from torchtrack.detect.scan import box_vote, nms, scan, sliding_windows
from torchtrack.errors import ConfigError, ShapeError


def test_sliding_windows_inside_frame_and_scales():
    boxes = sliding_windows((100, 80), (40, 20), scale_step=1.5, stride=0.25)
    x, y, w, h = boxes.unbind(1)
    assert bool(
        (x >= 0).all()
        and (y >= 0).all()
        and (x + w <= 80 + 1e-4).all()
        and (y + h <= 100 + 1e-4).all()
    )
    # scales 1, 1.5, 2.25 fit (2.25 x 40 = 90 <= 100); 3.375 does not
    assert sorted(set(w.tolist())) == pytest.approx([20.0, 30.0, 45.0])
    # scale 1: steps of 5 px in x over 0..60, 10 px in y over 0..60
    assert int((w == 20).sum()) == 13 * 7
    assert sliding_windows((10, 10), (40, 20)).shape == (0, 4)
    # pad: windows reach a quarter of their size over each edge
    padded = sliding_windows((100, 80), (40, 20), scale_step=1.5, stride=0.25, pad=0.25)
    x, y, w, h = padded.unbind(1)
    assert x[w == 20].min().item() == pytest.approx(-5.0)
    assert y[w == 20].min().item() == pytest.approx(-10.0)
    assert x.min().item() == pytest.approx(-0.25 * 45)
    assert bool((x + w <= 80 + 0.25 * w + 1e-4).all() and (y + h <= 100 + 0.25 * h + 1e-4).all())
    assert padded.shape[0] > boxes.shape[0]
    with pytest.raises(ConfigError, match="pad"):
        sliding_windows((100, 80), (40, 20), pad=0.6)


def reference_nms(boxes, scores, thr):
    order = sorted(range(len(scores)), key=lambda i: -float(scores[i]))
    keep = []
    for i in order:
        if all(
            float(box_iou_matrix(boxes[i : i + 1], boxes[j : j + 1])[0, 0]) <= thr for j in keep
        ):
            keep.append(i)
    return keep


def test_nms_matches_reference():
    g = torch.Generator().manual_seed(0)
    boxes = torch.rand((60, 4), generator=g) * torch.tensor(
        [50.0, 50.0, 20.0, 20.0]
    ) + torch.tensor([0, 0, 5.0, 5.0])
    scores = torch.rand(60, generator=g)
    assert nms(boxes, scores, 0.3).tolist() == reference_nms(boxes, scores, 0.3)


def test_bad_scan_args():
    with pytest.raises(ConfigError, match="scale_step"):
        sliding_windows((10, 10), (4, 4), scale_step=1.0)
    with pytest.raises(ConfigError, match="stride"):
        sliding_windows((10, 10), (4, 4), stride=0)
    with pytest.raises(ShapeError, match="nms needs"):
        nms(torch.zeros(3, 4), torch.zeros(2))


def test_box_vote_is_the_weighted_mean_of_overlapping_boxes_in_centre_and_log_size():
    kept = torch.tensor([[10.0, 20.0, 40.0, 16.0]])
    big = [10.0 - 4.0, 20.0 - 1.6, 48.0, 19.2]  # the same centre, x 1.2
    shifted = [14.0, 20.0, 40.0, 16.0]  # 4 px right: IoU 36 / 44
    far = [200.0, 200.0, 40.0, 16.0]  # no overlap: no vote
    boxes = torch.tensor([kept[0].tolist(), big, shifted, far])
    weights = torch.tensor([1.0, 1.0, 2.0, 5.0])
    out = box_vote(kept, boxes, weights, 0.5)
    cx = (30.0 * 1 + 30.0 * 1 + 34.0 * 2) / 4
    w = math.exp((math.log(40) + math.log(48) + 2 * math.log(40)) / 4)
    h = w * 0.4
    assert out[0].tolist() == pytest.approx([cx - w / 2, 28.0 - h / 2, w, h], rel=1e-6)
    # a higher threshold leaves the shifted box (IoU 0.82) in and the bigger one (0.69) out
    out = box_vote(kept, boxes, weights, 0.75)
    assert out[0].tolist() == pytest.approx([10 + 8 / 3, 20.0, 40.0, 16.0], rel=1e-6)
    # no weight at all: the kept box as it was
    assert box_vote(kept, boxes, torch.zeros(4), 0.5).tolist() == kept.tolist()
    # overlaps decided on other boxes (object boxes inside windows): the far box now overlaps
    ref = boxes.clone()
    ref[3] = ref[0]
    out = box_vote(kept, boxes, torch.tensor([1.0, 0, 0, 1.0]), 0.5, reference=(ref[:1], ref))
    assert out[0, 0].item() == pytest.approx((10 + 200) / 2)


def test_box_vote_bad_input():
    k, b, w = torch.zeros(1, 4), torch.zeros(3, 4), torch.ones(3)
    with pytest.raises(ConfigError, match="vote_iou"):
        box_vote(k, b, w, 0.0)
    with pytest.raises(ShapeError, match="box_vote needs"):
        box_vote(k, b, torch.ones(2), 0.5)
    with pytest.raises(ShapeError, match="box_vote needs"):
        box_vote(k, b, w, 0.5, reference=(k, torch.zeros(2, 4)))
    assert box_vote(torch.zeros(0, 4), b, w, 0.5).shape == (0, 4)


def test_scan_vote_needs_nms():
    det = load_model("vehicle")
    frame = torch.zeros(1, 64, 128)
    with pytest.raises(ConfigError, match="give nms_iou"):
        scan(det, frame, nms_iou=None, vote_iou=0.5)
    with pytest.raises(ConfigError, match="vote_iou must be"):
        scan(det, frame, vote_iou=1.5)


def test_padded_frames_keep_their_dtype_and_continue_the_edges():
    """8-bit frames stay 8-bit through the scan's padding (their colour channels then come from
    the 8-bit table), with the values of a replicate pad of the float frame."""
    from torch.nn import functional as F

    from torchtrack.detect.scan import _pad_frames

    g = torch.Generator().manual_seed(0)
    x = torch.randint(0, 256, (2, 3, 7, 9), dtype=torch.uint8, generator=g)
    got = _pad_frames(x, 3, 5)
    assert got.dtype == torch.uint8 and got.shape == (2, 3, 13, 19)
    ref = F.pad(x.float(), (5, 5, 3, 3), mode="replicate")
    assert torch.equal(got.float(), ref)
    assert _pad_frames(x, 0, 0) is x


def test_box_corners_combine_as_the_weighted_sum():
    """The scan's shortcut for one-rectangle features: with weights of 1 the values of the
    general ``(v * coef).sum(-1)`` to the last bit; with a box mean's weight ``w`` (applied
    after the sum, among the per-feature factors) the same values up to rounding."""
    from torchtrack.detect.scan import _combine_corners, _rectangle_weights

    g = torch.Generator().manual_seed(1)
    v = torch.rand(5000, 3, 4, dtype=torch.float64, generator=g) * 1e6
    coef = torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64).expand(3, 4)
    assert torch.equal(_rectangle_weights(coef), torch.ones(3, dtype=torch.float64))
    assert torch.equal(_combine_corners(v, None), (v * coef).sum(-1))
    w = torch.tensor([0.25, 1 / 3, 0.0123], dtype=torch.float64)
    scaled = w[:, None] * coef
    assert torch.equal(_rectangle_weights(scaled), w)
    torch.testing.assert_close(_combine_corners(v, None) * w, (v * scaled).sum(-1))
    assert _rectangle_weights(torch.tensor([[1.0, -1.0, -1.0, 1.0, 0.0, 0.0]])) is None
    assert _rectangle_weights(torch.tensor([[1.0, -1.0, 1.0, -1.0]])) is None
    assert _rectangle_weights(torch.tensor([[0.5, -0.5, -0.5, 1.0]])) is None
    other = torch.tensor([[0.5, -2.0, 1.0, 1.0]], dtype=torch.float64)
    assert torch.equal(_combine_corners(v[:, :1], other), (v[:, :1] * other).sum(-1))


def test_bundled_model_scan_is_the_same_with_and_without_the_box_shortcut(data_dir, monkeypatch):
    """Both bundled models' features are box means (one rectangle, weight 1 / area): the scan
    takes the shortcut, and the general path gives the same windows, margins equal up to
    rounding (float32), and the same detections, with and without the cascade."""
    from torchtrack.detect import scan as scan_module
    from torchtrack.io.video import open_source

    with open_source(data_dir / "videos" / "pets2009_s2l1_vtest" / "vtest.avi") as src:
        frame = next(f for _, f in src.items() if f is not None)
    det = load_model("pedestrian")
    for name in ("pedestrian", "vehicle"):
        m = load_model(name)
        coef = m.bank.padded_points(m.feature_index, torch.device("cpu"))[3]
        assert scan_module._rectangle_weights(coef) is not None, name
    raw = {"min_scale": 0.5, "max_scale": 0.9, "stride": 0.1, "pad": 0.1, "threshold": None,
           "margin": True, "nms_iou": None}  # fmt: skip
    final = {"min_scale": 0.35, "threshold": 0.1, "nms_iou": 0.3, "nms_on": "object",
             "vote_iou": 0.5, "cascade_threshold": -3.0}  # fmt: skip
    runs = {}
    for shortcut in (True, False):
        if not shortcut:
            monkeypatch.setattr(scan_module, "_rectangle_weights", lambda coef: None)
        runs[shortcut] = [
            scan_module.scan_batch(det, frame[None], cascade=c, cascade_threshold=t, **raw)[0]
            for c, t in ((False, None), (True, None), (True, -3.0))
        ] + [scan_module.scan(det, frame, **final)]
    assert runs[True][0][0].shape[0] > 5000  # every window, no cascade
    assert runs[True][3][0].shape[0] > 0  # people detected
    for (wa, ma), (wb, mb) in zip(runs[True], runs[False], strict=True):
        assert torch.equal(wa, wb)
        torch.testing.assert_close(ma, mb, rtol=1e-5, atol=1e-6)


def test_a_scale_step_just_above_one_is_refused():
    """1.0000001 would ask for millions of scales: a scan that never ends."""
    from torchtrack.detect.scan import scan_scales

    with pytest.raises(ConfigError, match=r">= 1\.01"):
        scan_scales((480, 640), (128, 64), scale_step=1.0000001, min_scale=0.3)
    with pytest.raises(ConfigError, match=r">= 1\.01"):
        scan_scales((480, 640), (128, 64), scale_step=float("inf"))
    assert len(scan_scales((480, 640), (128, 64), scale_step=1.01, min_scale=0.3)) < 300


def test_a_scale_under_one_sixteenth_is_refused():
    """min_scale 0.01 on the 128 px model asked for a 15 GB lattice, 1e-308 overflowed the count
    of scales; frames are upsampled at most 16x (MIN_SCALE)."""
    from torchtrack.detect.scan import scan_scales

    assert scan_scales((480, 640), (128, 64), min_scale=0.0625)[0] == 0.0625
    assert scan_scales((48, 64), (16, 8), min_scale=0.0625)[0] == 0.0625  # 1 px: allowed
    for s in (0.06, 0.01, 1e-308):
        with pytest.raises(ConfigError, match=r"min_scale must be >= 0.0625 .* 16x"):
            scan_scales((480, 640), (128, 64), min_scale=s)


def test_a_keep_function_per_frame_gives_each_frame_its_own_scan():
    """``scan_batch(keep_windows=[k_0, ..., k_B-1])`` (the multi-target tracker's batched scans,
    each frame with its own ground line): every frame gets exactly what :func:`scan` with its
    own function gives, raw windows and margins as well as the NMS'd and voted detections."""
    import itertools

    from torchtrack.data import demo_clip_path
    from torchtrack.detect.scan import scan_batch
    from torchtrack.io.video import open_source

    with open_source(demo_clip_path()) as src:
        got = [f for _, f in itertools.islice(src.items(), 12)]
    frames = torch.stack([got[0], got[11], got[5]])
    det = load_model("pedestrian")

    def band(lo, hi):  # window bottoms in a band, as a ground line keeps them
        return lambda w: ((w[:, 1] + w[:, 3]) > lo) & ((w[:, 1] + w[:, 3]) < hi)

    keeps = [band(150, 300), None, band(200, 360)]
    raw = {"threshold": None, "margin": True, "nms_iou": None, "min_scale": 0.5, "pad": 0.1}
    # the multi-target tracker's scan (its people are small)
    final = {"threshold": 0.1, "nms_iou": 0.3, "nms_on": "object", "vote_iou": 0.5}
    final |= {"min_scale": 0.35, "stride": 0.08, "scale_step": 1.15, "cascade_threshold": -3.0}
    for kw in (raw, final):
        batched = scan_batch(det, frames, keep_windows=keeps, **kw)
        for b, (wb, sb) in enumerate(batched):
            wa, sa = scan(det, frames[b], keep_windows=keeps[b], **kw)
            assert wa.shape[0] > 0
            if kw is raw:  # order windows the same way before comparing
                oa, ob = (torch.argsort(w[:, 0] * 1e6 + w[:, 1] * 1e3 + w[:, 2]) for w in (wa, wb))
                wa, sa, wb, sb = wa[oa], sa[oa], wb[ob], sb[ob]
            assert torch.equal(wa, wb) and torch.equal(sa, sb)
    with pytest.raises(ConfigError, match="one per frame"):
        scan_batch(det, frames, keep_windows=keeps[:2])


def test_scan_thresholds_nms_and_max_scale_out_of_range_are_refused():
    """threshold=NaN kept no window and nms_iou=NaN suppressed none (the comparisons are false),
    a threshold of 2 or an nms_iou of 1.5 ran as given, and max_scale=NaN was ignored: all
    silently. Margins (margin=True) take any threshold but NaN."""
    from torchtrack.detect.scan import scan_scales

    det = load_model("vehicle")
    frame = torch.zeros(3, 60, 120, dtype=torch.uint8)
    for bad in (math.nan, 2.0, -0.1):
        with pytest.raises(ConfigError, match=r"threshold must be None or a probability"):
            scan(det, frame, threshold=bad)
    with pytest.raises(
        ConfigError, match=r"threshold must be None or a margin \(a number, not NaN\)"
    ):
        scan(det, frame, threshold=math.nan, margin=True)
    scan(det, frame, threshold=-5.0, margin=True)
    for bad in (math.nan, 1.5, -0.1):
        with pytest.raises(ConfigError, match=r"nms_iou must be None or in \[0, 1\]"):
            scan(det, frame, nms_iou=bad)
    # a string was TypeError "'<=' not supported between instances of 'float' and 'str'"
    for bad in ("0.5", True):
        with pytest.raises(ConfigError, match=r"threshold must be None or a probability .* got"):
            det.scan(frame, threshold=bad)
        with pytest.raises(ConfigError, match=r"threshold must be None or a margin"):
            scan(det, frame, threshold=bad, margin=True)
        with pytest.raises(ConfigError, match=r"nms_iou must be None or in \[0, 1\], got"):
            det.scan(frame, nms_iou=bad)
    det.scan(frame, threshold=np.float32(0.5), nms_iou=np.float64(0.3))
    for bad in (math.nan, 0.5):
        with pytest.raises(ConfigError, match=r"max_scale must be None or a number >= min_scale"):
            scan_scales((480, 640), (128, 64), min_scale=0.6, max_scale=bad)
    assert scan_scales((480, 640), (128, 64), max_scale=math.inf) == scan_scales(
        (480, 640), (128, 64)
    )


def test_frames_scaled_to_one_warn_that_they_are_read_as_0_255():
    """A float frame in [0, 1] (torchvision's convention) was scanned as a nearly black 0..255
    frame: no detection and no word. It cannot be refused (a dark 0..255 frame looks the
    same), so Detector.scan and scan warn; 0..255 frames, 8-bit frames and an all-black float
    frame do not."""
    import warnings

    det = load_model("vehicle")
    g = torch.Generator().manual_seed(0)
    frame = torch.randint(0, 256, (3, 60, 120), generator=g).float()
    unit = frame / 255
    with pytest.warns(UserWarning, match=r"every value in \[0, 1\]: .* read as 0\.\.255 levels"):
        det.scan(unit)
    with pytest.warns(UserWarning, match=r"multiply by 255"):
        det.scan(unit[None])
    with pytest.warns(UserWarning, match=r"read as 0\.\.255 levels"):
        scan(det, unit)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        det.scan(frame)
        det.scan(frame.to(torch.uint8))
        det.scan(torch.zeros(3, 60, 120))
        scan(det, frame)


def test_window_and_frame_sizes_that_are_not_two_sizes_are_refused():
    """sliding_windows took a window (True, 8) as 1 x 8 (13,802 windows), a frame (True, 64)
    as 1 x 64 (no window), a NaN frame side raised a bare ValueError and a zero window side a
    ZeroDivisionError; scan_scales alike."""
    from torchtrack.detect.scan import scan_scales

    for fn in (sliding_windows, scan_scales):
        for frame, window, what in (
            ((True, 64), (16, 8), "frame_size"),
            ((float("nan"), 64), (16, 8), "frame_size"),
            ((48, 64), (True, 8), "window"),
            ((48, 64), (0, 8), "window"),
            ((48, 64), (16, float("inf")), "window"),
            ((48, 64), (16,), "window"),
        ):
            with pytest.raises(ShapeError, match=rf"{what} must be \(H, W\)"):
                fn(frame, window)
    assert sliding_windows((48, 64), (16, 8)).shape[0] > 0


def test_an_hwc_frame_is_named_as_such_not_as_too_small():
    # (H, W, C) frames passed the size check only where C happened to be large: (100, 200, 3)
    # was reported as a 200x3 frame smaller than the window
    det = load_model("vehicle")
    frame = torch.zeros(100, 200, 3, dtype=torch.uint8)
    with pytest.raises(ShapeError, match=r"C = 1 \(gray\) or 3 \(RGB\).*permute\(2, 0, 1\)"):
        det.scan(frame)
    with pytest.raises(ShapeError, match=r"C=100"):
        det.scan(frame[None])


def test_an_empty_batch_of_frames_gives_an_empty_list():
    # B = 0 asked for 0 windows per call: ConfigError 'batch must be >= 1, got 0', an argument
    # the caller never gave
    det = load_model("vehicle")
    assert det.scan(torch.zeros(0, 1, 100, 200, dtype=torch.uint8)) == []
    with pytest.raises(ConfigError, match="nms_iou"):  # the arguments are still checked
        det.scan(torch.zeros(0, 1, 100, 200, dtype=torch.uint8), nms_iou=2.0)
