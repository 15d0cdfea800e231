"""``tools/loso_multi.py``'s argument checks (the grid itself runs for minutes: not a test)."""

import importlib.util
import math
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("loso_multi", REPO / "tools" / "loso_multi.py")
loso = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(loso)


def test_set_holds_other_keys_typed_like_the_config():
    assert loso.parse_fixed("", "motion_noise") == {}
    fixed = loso.parse_fixed("detection_proposal=0.1,confirm_hits=3", "motion_noise")
    assert fixed == {"detection_proposal": 0.1, "confirm_hits": 3}


@pytest.mark.parametrize(
    "spec, grid_key, message",
    [
        ("motion_noise=0.5", "motion_noise", "grid's key"),
        ("no_such_key=1", "motion_noise", "no_such_key"),
        ("detection_proposal=2", "motion_noise", "detection_proposal"),
    ],
)
def test_set_refuses_the_grid_key_unknown_keys_and_bad_values(spec, grid_key, message):
    with pytest.raises(SystemExit, match=message):
        loso.parse_fixed(spec, grid_key)


def test_pan_copies_move_the_boxes_with_the_view_and_drop_those_left_outside():
    import numpy as np

    from torchtrack.io.mot import MotRows

    rows = MotRows(
        np.array([0, 1, 1, 2]),
        np.array([1, 1, 2, 1]),
        np.array([[50.0, 5, 20, 40], [50, 5, 20, 40], [95, 5, 20, 40], [2, 5, 20, 40]]),
        np.ones(4),
    )
    out = loso._copied_rows(
        rows, 1.0, 1, (lambda i: (3 * i, 0), 100, 100)
    )  # the view slides 3 px a frame
    np.testing.assert_array_equal(out.frames, [0, 1, 2])  # 95 - 3 = 92: 8 of 20 px inside, dropped
    np.testing.assert_allclose(out.boxes[:, 0], [50, 47, -4])  # -4: 16 of 20 px inside, kept
    out = loso._copied_rows(rows, 1.0, 1, (lambda i: (15 * i, 0), 100, 100))
    np.testing.assert_array_equal(out.frames, [0, 1, 1])  # 2 - 30 = -28: outside, dropped
    np.testing.assert_allclose(out.boxes[:, 0], [50, 35, 80])


def test_shake_copies_move_the_boxes_on_both_axes():
    import numpy as np

    from torchtrack.io.mot import MotRows

    rows = MotRows(
        np.array([0, 0]), np.array([1, 2]), np.array([[50.0, 50, 20, 40], [50, 85, 20, 40]]),
        np.ones(2),
    )  # fmt: skip
    out = loso._copied_rows(rows, 1.0, 1, (lambda i: (4, 3), 100, 100))
    np.testing.assert_allclose(out.boxes, [[46, 47, 20, 40]])  # 82..122: 18 of 40 px inside
    out = loso._copied_rows(rows, 1.0, 1, (lambda i: (4, 9), 100, 100))
    np.testing.assert_allclose(out.boxes, [[46, 41, 20, 40], [46, 76, 20, 40]])  # 24 of 40


def test_zoom_copies_scale_the_boxes_as_the_frames_are_magnified():
    """The frame and its boxes go through the same zoom: a bright box drawn on a frame is found
    in the zoomed frame where the zoomed box says (to a pixel), and boxes pushed out of the view
    are dropped."""
    import numpy as np

    from torchtrack.io.mot import MotRows

    transform = loso.zoom_transform(50.0, 10.0, 0.02, 1.5)
    assert transform(0) == (0.0, 0.0, 1.0)
    half = math.log(1.5) / math.log1p(0.02)  # frames from 1x to 1.5x
    assert transform(round(half))[2] == pytest.approx(1.5, rel=0.02)
    assert transform(round(2 * half))[2] == pytest.approx(1.0, rel=0.02)  # and back
    i = 15
    x0, y0, z = transform(i)
    img = np.zeros((80, 100, 3), dtype=np.uint8)
    img[30:50, 60:70] = 255  # the box (60, 30, 10, 20)
    seen = loso.zoom_warp(img, x0, y0, z)[..., 0] >= 128
    ys, xs = np.nonzero(seen)
    rows = MotRows(
        np.array([i, i]), np.array([1, 2]), np.array([[60.0, 30, 10, 20], [95, 70, 10, 20]]),
        np.ones(2),
    )  # fmt: skip
    out = loso._copied_rows(rows, 1.0, 1, (transform, 100, 80))
    assert out.ids.tolist() == [1]  # the box near the corner left the view
    x, y, w, h = out.boxes[0]
    assert w == pytest.approx(10 * z) and h == pytest.approx(20 * z)
    assert abs(xs.min() - x) <= 1 and abs(xs.max() + 1 - (x + w)) <= 1
    assert abs(ys.min() - y) <= 1 and abs(ys.max() + 1 - (y + h)) <= 1


def test_pan_must_move():
    with pytest.raises(SystemExit, match="--pan"):
        loso.panned(None, 0.0, None)
    with pytest.raises(SystemExit, match="--shake"):
        loso.shaken(None, 0, None)
    with pytest.raises(SystemExit, match="--zoom"):
        loso.zoomed(None, 0.0, None)


def test_degrade_gain_follows_the_sine_and_leaves_the_default_unchanged():
    import numpy as np

    frame = np.full((4, 6, 3), 100, dtype=np.uint8)
    frame[0, 0] = (250, 10, 0)
    same = loso.degrade(frame, 1.0, 0.0, 7)
    assert np.array_equal(same, frame)  # no change asked for, none made
    peak = loso.degrade(frame, 1.0, 0.0, 25, gain=0.5, period=100)  # sin = 1: x1.5
    trough = loso.degrade(frame, 1.0, 0.0, 75, gain=0.5, period=100)  # sin = -1: x0.5
    assert peak[1, 1, 0] == 150 and trough[1, 1, 0] == 50
    assert tuple(peak[0, 0]) == (255, 15, 0)  # clipped at white
    assert np.array_equal(loso.degrade(frame, 1.0, 0.0, 0, gain=0.5), frame)  # sin 0 = 0


def test_degrade_blur_softens_and_jpeg_compresses():
    import numpy as np

    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, (32, 48, 3), dtype=np.uint8)
    soft = loso.degrade(frame, 1.0, 0.0, 0, blur=1.5)
    # a blurred frame keeps its mean and loses most of its pixel-to-pixel differences
    assert abs(float(soft.mean()) - float(frame.mean())) < 2.0
    assert (
        np.abs(np.diff(soft.astype(float), axis=1)).mean()
        < 0.5 * np.abs(np.diff(frame.astype(float), axis=1)).mean()
    )
    packed = loso.degrade(frame, 1.0, 0.0, 0, jpeg=20)
    assert packed.shape == frame.shape and packed.dtype == np.uint8
    assert 0 < np.abs(packed.astype(int) - frame.astype(int)).mean() < 60
    assert np.array_equal(loso.degrade(frame, 1.0, 0.0, 0, blur=0.0, jpeg=0), frame)


@pytest.mark.parametrize(
    "spec",
    ["gain=1", "gain=-0.1", "gain=0.5,period=0", "gain=x", "blur=-1", "blur=30", "jpeg=101",
     "jpeg=2.5"],
)  # fmt: skip
def test_degrade_refuses_a_bad_gain(spec, tmp_path):
    with pytest.raises(SystemExit, match="--degrade: expected"):
        loso.degraded(None, spec, tmp_path)


def test_live_runs_score_what_the_command_writes(data_dir, tmp_path, one_thread, trackeval):
    """``--live``: the own-detection run scans every frame itself, as ``torchtrack track`` does;
    on the first 30 TUD-Stadtmitte frames it scores exactly what the command's MOT file scores
    (the cached scans are close to the command, not the same: docs/multi_target.md)."""
    import dataclasses

    import numpy as np

    from torchtrack.cli import main
    from torchtrack.eval.mot import score_mot
    from torchtrack.io.mot import read_mot

    seq = loso.load(data_dir, "TUD-Stadtmitte")
    n = 30
    keep = seq.gt.frames < n
    gt = dataclasses.replace(seq.gt, **{f.name: getattr(seq.gt, f.name)[keep]
                                        for f in dataclasses.fields(seq.gt)
                                        if isinstance(getattr(seq.gt, f.name), np.ndarray)})  # fmt: skip
    short = dataclasses.replace(seq, gt=gt, n_frames=n)
    live = loso.run_one(short, None, {}, seed=1, own=True, scan_workers=0)
    out = tmp_path / "tud.txt"
    argv = ["track", str(data_dir / "mot" / "TUD-Stadtmitte" / "img1"), "--seed", "1",
            "--max-frames", str(n), "--scan-workers", "0", "--no-progress", "-q", "--mot", str(out)]  # fmt: skip
    assert main(argv) == 0
    m = score_mot(gt, read_mot(out, 1.0, n), n)
    assert live["hota"] == pytest.approx(100 * m.hota) and live["mota"] == pytest.approx(
        100 * m.mota
    )
    assert live["hota"] > 20  # people were found and followed


def test_scans_of_a_model_file_are_cached_by_its_name_beside_the_others(
    data_dir, tmp_path, one_thread
):
    """A model given as a path (``--grid model=PATH``) caches its scans as one file directly
    under ``--cache``, named by the file's stem and its content's digest (a path's folders
    made folders in the cache), and a second call reads them back."""
    import dataclasses
    import shutil

    from torchtrack.detect.bundled import resolve_model

    model = tmp_path / "deep" / "folder" / "candidate.safetensors"
    model.parent.mkdir(parents=True)
    shutil.copy(resolve_model("pedestrian"), model)
    seq = dataclasses.replace(loso.load(data_dir, "TUD-Stadtmitte"), n_frames=2)
    cache = tmp_path / "cache"
    rows = loso.own_detections(seq, cache, {"model": str(model)})
    files = list(cache.iterdir())
    assert len(files) == 1 and files[0].is_file() and "_candidate_" in files[0].name
    again = loso.own_detections(seq, cache, {"model": str(model)})
    assert (again.frames == rows.frames).all() and len(rows.frames) > 0
