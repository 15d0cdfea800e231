"""``torchtrack detect`` on real images and the demo clip: JSON lines, annotated output, bad
input (unreadable images, unopenable video, frames smaller than the window, unknown model),
luma handling of grayscale vs colour input."""

import json
import re
import shutil

import cv2
import numpy as np
import pytest
import torch

from torchtrack.cli import main
from torchtrack.data import demo_clip_path
from torchtrack.detect.bundled import load_model
from torchtrack.detect.scan import scan
from torchtrack.io.video import open_source, read_image
from torchtrack.track.scan_ahead import fork_available


def records(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines() if line.strip()]


@pytest.fixture(scope="module")
def car_images(data_dir, tmp_path_factory):
    """Three UIUC single-scale test images (grayscale PGM) plus an unreadable file."""
    src = data_dir / "detection_crops" / "uiuc_car" / "CarData" / "TestImages"
    root = tmp_path_factory.mktemp("cars")
    for i in (0, 1, 2):
        shutil.copy(src / f"test-{i}.pgm", root / f"test-{i}.pgm")
    (root / "zz-broken.png").write_bytes(b"\x89PNG not really")
    return root


def test_folder_jsonl_matches_library_scan(car_images, tmp_path, capsys):
    out = tmp_path / "cars.jsonl"
    code = main(
        ["detect", "vehicle", str(car_images), "-o", str(out), "--threshold", "0.5", "--quiet"]
    )
    assert code == 0
    recs = records(out.read_text())
    assert [r["source"] for r in recs] == ["test-0.pgm", "test-1.pgm", "test-2.pgm"]
    det = load_model("vehicle")
    from torchtrack.cli import detect as d

    kw = {
        "threshold": 0.5,
        "min_scale": d.MIN_HEIGHT / d.object_height(det),
        "scale_step": d.SCALE_STEP,
        "stride": d.STRIDE,
        "nms_iou": d.NMS_IOU,
        "nms_overlap": d.NMS_OVERLAP,
        "vote_iou": d.VOTE_IOU,
    }
    for r in recs:
        frame = read_image(car_images / r["source"])
        boxes, probs = det.scan(frame, **kw)  # object boxes (the vehicle's are its windows)
        assert r["width"] == frame.shape[-1] and r["height"] == frame.shape[-2]
        assert r["time"] is None
        np.testing.assert_allclose(r["boxes"], boxes.numpy().reshape(-1, 4), atol=0.01)
        np.testing.assert_allclose(r["probabilities"], probs.numpy(), atol=1e-5)
        assert all(0.5 <= p <= 1 for p in r["probabilities"])
        assert r["probabilities"] == sorted(r["probabilities"], reverse=True)
    # every test image holds a car and the vehicle model finds at least one per image
    assert all(len(r["boxes"]) >= 1 for r in recs)


def test_unreadable_image_skipped_and_reported(car_images, capsys):
    assert main(["detect", "vehicle", str(car_images)]) == 0
    cap = capsys.readouterr()
    assert len(records(cap.out)) == 3
    assert "skipped frame 3" in cap.err and "zz-broken.png" in cap.err


def test_strict_fails_on_unreadable_image(car_images, tmp_path, capsys):
    out = tmp_path / "x.jsonl"
    code = main(["detect", "vehicle", str(car_images), "--strict", "-o", str(out), "--quiet"])
    assert code == 1
    assert "zz-broken.png" in capsys.readouterr().err
    assert not out.exists()  # atomic: no half-written output


def test_annotate_and_video(car_images, tmp_path, capsys):
    ann = tmp_path / "ann"
    vid = tmp_path / "out.mp4"
    src = tmp_path / "one"
    src.mkdir()
    shutil.copy(car_images / "test-1.pgm", src / "test-1.pgm")
    shutil.copy(car_images / "test-2.pgm", src / "test-2.pgm")
    args = ["detect", "vehicle", str(src), "--annotate", str(ann), "--video", str(vid)]
    with pytest.warns(UserWarning, match="padded or cropped"):  # UIUC images of two sizes
        assert main([*args, "--quiet"]) == 0
    pngs = sorted(p.name for p in ann.iterdir())
    assert pngs == ["test-1.png", "test-2.png"]
    img = cv2.imread(str(ann / "test-1.png"))
    gray = cv2.imread(str(car_images / "test-1.pgm"), cv2.IMREAD_GRAYSCALE)
    assert img.shape[:2] == gray.shape
    # boxes are drawn in green on a gray image: some pixels are no longer gray
    assert int((img[:, :, 1].astype(int) - img[:, :, 2].astype(int)).max()) > 100
    with open_source(vid) as s:
        assert len(list(s)) == 2


def test_grayscale_and_colour_inputs_give_the_same_detections(data_dir, tmp_path, capsys):
    """A gray image and its 3-channel copy give identical output: for a model trained on gray
    crops (vehicle: luma) and for one that reads colour (pedestrian: a gray image is R = G = B,
    so U = V = 0 either way)."""
    img = cv2.imread(
        str(data_dir / "detection_crops/uiuc_car/CarData/TestImages/test-5.pgm"),
        cv2.IMREAD_GRAYSCALE,
    )
    cv2.imwrite(str(tmp_path / "gray.png"), img)
    cv2.imwrite(str(tmp_path / "color.png"), np.repeat(img[:, :, None], 3, axis=2))
    for model in ("vehicle", "pedestrian"):
        outs = []
        for name in ("gray.png", "color.png"):
            kw = ["--min-scale", "0.5"] if model == "pedestrian" else []
            assert main(["detect", model, str(tmp_path / name), "--quiet", *kw]) == 0
            (rec,) = records(capsys.readouterr().out)
            outs.append((rec["boxes"], rec["probabilities"]))
        assert outs[0][0] == outs[1][0]
        np.testing.assert_allclose(outs[0][1], outs[1][1], atol=1e-5)


def test_demo_clip_video_records(capsys):
    clip = demo_clip_path()
    assert clip.is_file() and clip.stat().st_size < 1_000_000
    code = main(
        [
            "detect",
            "pedestrian",
            str(clip),
            "--max-frames",
            "3",
            "--min-scale",
            "0.5",
            "--max-scale",
            "0.5",
            "--batch",
            "2",
            "--quiet",
        ]
    )
    assert code == 0
    recs = records(capsys.readouterr().out)
    assert [r["frame"] for r in recs] == [0, 1, 2]
    assert [r["time"] for r in recs] == pytest.approx([0.0, 0.1, 0.2])
    assert all(r["source"] is None and (r["width"], r["height"]) == (480, 360) for r in recs)


def test_batched_frames_equal_single_frames(capsys):
    """--batch 3 (one batched scan) and --batch 1 give the same records."""
    outs = []
    for b in ("1", "3"):
        args = ["detect", "pedestrian", str(demo_clip_path()), "--max-frames", "3"]
        args += ["--min-scale", "0.5", "--max-scale", "0.5", "--batch", b, "--quiet"]
        assert main(args) == 0
        outs.append(records(capsys.readouterr().out))
    assert [r["boxes"] for r in outs[0]] == [r["boxes"] for r in outs[1]]
    for a, b in zip(outs[0], outs[1], strict=True):
        np.testing.assert_allclose(a["probabilities"], b["probabilities"], atol=1e-5)


def test_a_looser_cascade_finds_more_and_equals_the_library_scan(capsys):
    """--cascade -8 lowers the soft cascade: the records are Detector.scan's with
    cascade_threshold=-8, and the frame's people are found at least as often as at the model's
    own cascade."""
    found = {}
    for extra in ([], ["--cascade", "-8"]):
        args = ["detect", "pedestrian", str(demo_clip_path()), "--max-frames", "2", "--quiet"]
        assert main(args + extra) == 0
        found[len(extra)] = records(capsys.readouterr().out)
    det = load_model("pedestrian")
    from torchtrack.cli import detect as d

    kw = {"threshold": d.THRESHOLD, "scale_step": d.SCALE_STEP, "stride": d.STRIDE}
    kw |= {"min_scale": d.MIN_HEIGHT / d.object_height(det), "nms_iou": d.NMS_IOU}
    kw |= {"nms_overlap": d.NMS_OVERLAP, "vote_iou": d.VOTE_IOU, "pad": d.PAD}
    with open_source(demo_clip_path()) as src:
        frames = [f for _, f in zip(range(2), src, strict=False)]
    for f, own, loose in zip(frames, found[0], found[2], strict=True):
        boxes, probs = det.scan(f, cascade_threshold=-8.0, **kw)
        np.testing.assert_allclose(loose["boxes"], boxes.numpy().reshape(-1, 4), atol=0.01)
        np.testing.assert_allclose(loose["probabilities"], probs.numpy(), atol=1e-5)
        assert len(loose["boxes"]) >= len(own["boxes"]) >= 1
    assert sum(len(r["boxes"]) for r in found[2]) > sum(len(r["boxes"]) for r in found[0])


def test_no_box_regression_reports_the_windows_as_scanned(capsys):
    """By default the bundled pedestrian model's box regressor moves each detection; with
    --no-box-regression the records are the scan's boxes with refine=False, the same
    detections and probabilities, other boxes."""
    out = {}
    for extra in ([], ["--no-box-regression"]):
        args = ["detect", "pedestrian", str(demo_clip_path()), "--max-frames", "1", "--quiet"]
        assert main(args + extra) == 0
        out[len(extra)] = records(capsys.readouterr().out)[0]
    det = load_model("pedestrian")
    from torchtrack.cli import detect as d

    kw = {"threshold": d.THRESHOLD, "scale_step": d.SCALE_STEP, "stride": d.STRIDE}
    kw |= {"min_scale": d.MIN_HEIGHT / d.object_height(det), "nms_iou": d.NMS_IOU}
    kw |= {"nms_overlap": d.NMS_OVERLAP, "vote_iou": d.VOTE_IOU, "pad": d.PAD}
    with open_source(demo_clip_path()) as src:
        frame = next(iter(src))
    for key, refine in ((0, True), (1, False)):
        boxes, probs = det.scan(frame, refine=refine, **kw)
        np.testing.assert_allclose(out[key]["boxes"], boxes.numpy().reshape(-1, 4), atol=0.01)
        np.testing.assert_allclose(out[key]["probabilities"], probs.numpy(), atol=1e-5)
    assert out[0]["probabilities"] == out[1]["probabilities"]
    assert not np.allclose(out[0]["boxes"], out[1]["boxes"], atol=0.5)


def test_video_that_cannot_be_opened(tmp_path, capsys):
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"this is not a video" * 10)
    assert main(["detect", "pedestrian", str(bad), "--quiet"]) == 1
    assert "cannot be opened" in capsys.readouterr().err
    assert main(["detect", "pedestrian", str(tmp_path / "missing.avi"), "--quiet"]) == 1
    assert "does not exist" in capsys.readouterr().err


def test_frame_smaller_than_window(tmp_path, capsys):
    # 30 px: below the smallest scanned person window (--min-height 32 px: 43 x 21 px)
    cv2.imwrite(str(tmp_path / "small.png"), np.full((30, 200), 128, np.uint8))
    assert main(["detect", "pedestrian", str(tmp_path / "small.png"), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "smaller than the detector window 128x64" in err and "min_scale" in err
    # the scale came from --min-height (32 px by default): the hint names that option
    hint = re.search(r"--min-height 32 px: these frames take --min-height ([\d.]+) px", err)
    assert hint, err
    args = ["detect", "pedestrian", str(tmp_path / "small.png"), "--quiet"]
    assert main([*args, "--min-height", hint.group(1)]) == 0  # and that value scans


def test_small_image_in_folder_is_skipped(car_images, tmp_path, capsys):
    d = tmp_path / "mixed"
    d.mkdir()
    shutil.copy(car_images / "test-0.pgm", d / "a.pgm")
    cv2.imwrite(str(d / "b.png"), np.zeros((20, 20), np.uint8))
    assert main(["detect", "vehicle", str(d)]) == 0
    cap = capsys.readouterr()
    assert [r["source"] for r in records(cap.out)] == ["a.pgm"]
    assert "skipped frame 1" in cap.err and "smaller than the detector window" in cap.err


def test_video_of_frames_of_two_sizes_warns(car_images, tmp_path, capsys):
    d = tmp_path / "two"
    d.mkdir()
    shutil.copy(car_images / "test-0.pgm", d / "a.pgm")
    img = cv2.imread(str(car_images / "test-0.pgm"))
    cv2.imwrite(str(d / "b.png"), cv2.resize(img, None, fx=1.5, fy=1.5))
    video = tmp_path / "v.mp4"
    with pytest.warns(UserWarning, match=r"frame 1 is \d+x\d+, the video \d+x\d+"):
        assert main(["detect", "vehicle", str(d), "--video", str(video), "--quiet"]) == 0
    assert video.stat().st_size > 0


@pytest.mark.skipif(not fork_available(), reason="scan workers are forked processes (Linux)")
def test_scan_workers_write_the_same_records(tmp_path, capsys):
    """The bundled clip scanned in two forked workers and in this process: the same JSON
    lines, byte for byte (batches of 2 over 7 frames: more batches in flight than workers)."""
    outs = []
    for w in ("0", "2"):
        out = tmp_path / f"d{w}.jsonl"
        args = ["detect", "pedestrian", str(demo_clip_path()), "--max-frames", "7", "--batch", "2"]
        assert main([*args, "--scan-workers", w, "-o", str(out), "--quiet"]) == 0
        outs.append(out.read_bytes())
    assert outs[0] == outs[1] and outs[0].count(b"\n") == 7


@pytest.mark.skipif(not fork_available(), reason="scan workers are forked processes (Linux)")
def test_small_image_in_folder_is_skipped_by_a_worker_too(car_images, tmp_path, capsys):
    d = tmp_path / "mixed"
    d.mkdir()
    shutil.copy(car_images / "test-0.pgm", d / "a.pgm")
    cv2.imwrite(str(d / "b.png"), np.zeros((20, 20), np.uint8))
    assert main(["detect", "vehicle", str(d), "--scan-workers", "2", "--batch", "1"]) == 0
    cap = capsys.readouterr()
    assert [r["source"] for r in records(cap.out)] == ["a.pgm"]
    assert "skipped frame 1" in cap.err and "smaller than the detector window" in cap.err


def test_unknown_model_lists_bundled(tmp_path, capsys):
    cv2.imwrite(str(tmp_path / "x.png"), np.zeros((200, 200), np.uint8))
    assert main(["detect", "bicycle", str(tmp_path / "x.png")]) == 1
    err = capsys.readouterr().err
    assert "unknown model 'bicycle'" in err and "pedestrian" in err and "vehicle" in err


@pytest.mark.parametrize(
    ("args", "match"),
    [
        (["--threshold", "1.5"], "--threshold"),
        (["--min-scale", "0"], "--min-scale"),
        (["--nms-iou", "0"], "--nms-iou"),
        (["--vote-iou", "1.5"], "--vote-iou"),
        (["--video", "out.avi"], ".mp4"),
        (["--cascade", "nan"], "--cascade"),
        (["--cascade", "-5", "--no-cascade"], "--no-cascade"),
    ],
)
def test_bad_options(tmp_path, capsys, args, match):
    cv2.imwrite(str(tmp_path / "x.png"), np.zeros((200, 200), np.uint8))
    assert main(["detect", "vehicle", str(tmp_path / "x.png"), *args]) == 1
    assert match in capsys.readouterr().err


def test_scan_probabilities_match_score():
    """The probabilities the scan reports are the detector's score of the windows it kept, as
    scanned (``refine=False``); with the box regressor (the default) the same probabilities
    go with the moved boxes."""
    det = load_model("pedestrian")
    with open_source(demo_clip_path()) as s:
        frame = next(iter(s))
    for cascade, least in ((False, 10), (True, 1)):  # the cascade keeps fewer windows
        kw = dict(threshold=None, min_scale=0.5, max_scale=0.5, cascade=cascade)
        boxes, probs = scan(det, frame, refine=False, **kw)
        assert boxes.shape[0] > least
        ref = det.score(frame[None], boxes[None])[0]
        torch.testing.assert_close(probs, ref, atol=1e-4, rtol=1e-4)
        moved, same = scan(det, frame, **kw)
        assert torch.equal(same, probs) and not torch.allclose(moved, boxes, atol=0.5)
