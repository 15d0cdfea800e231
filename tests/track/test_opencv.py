"""OpenCV peers and the CamShift baseline behind the Tracker interface."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from torchtrack.boxes import box_iou
from torchtrack.errors import BoxError, ConfigError, TrackerError
from torchtrack.io.sequences import load_bobot
from torchtrack.io.video import to_numpy_bgr
from torchtrack.track.base import create_tracker
from torchtrack.track.opencv import CamShiftTracker, OpenCVTracker, has_contrib, opencv_constructor

CONTRIB_KINDS = ["kcf", "csrt", "mosse", "medianflow", "tld", "boosting"]
needs_contrib = pytest.mark.skipif(
    not has_contrib(), reason="opencv-contrib-python-headless (the peers extra) is not installed"
)


@pytest.fixture(scope="module")
def bobot(data_dir):
    s = load_bobot(data_dir / "tracking" / "bobot_pedestrian").head(10)
    return s, list(s.open())


def _run(tracker, frames, box):
    states = [tracker.init(frames[0], box)]
    states += [tracker.update(f) for f in frames[1:]]
    return torch.cat([s.box for s in states]), torch.cat([s.visible for s in states])


def test_mil_is_in_the_main_wheel_and_tracks_bobot(bobot):
    seq, frames = bobot
    assert opencv_constructor("mil") is not None
    t = create_tracker("mil")
    boxes, visible = _run(t, frames, seq.boxes[0])
    iou = box_iou(boxes, seq.boxes)
    assert bool(visible.all()) and t.failures == 0
    assert float(iou[1:].mean()) > 0.7, iou


def test_mil_wrapper_agrees_with_direct_opencv(bobot):
    """Same frames and rect as a direct cv2 call; MIL samples with OpenCV's global RNG from
    several threads, so runs differ by a pixel or two: compare within 4 px."""
    seq, frames = bobot
    ours, _ = _run(OpenCVTracker("mil"), frames, seq.boxes[0])
    x, y, w, h = seq.boxes[0].tolist()
    rect = (round(x), round(y), round(x + w) - round(x), round(y + h) - round(y))
    direct = cv2.TrackerMIL.create()
    direct.init(to_numpy_bgr(frames[0]), rect)
    ref = torch.tensor([direct.update(to_numpy_bgr(f))[1] for f in frames[1:]], dtype=torch.float64)
    assert (ours[1:] - ref).abs().max() <= 4


class _Stub:
    def __init__(self, answers):
        self.answers = list(answers)

    def update(self, img):
        return self.answers.pop(0)


def test_failure_keeps_last_box_and_is_counted():
    frame = torch.zeros(3, 50, 60, dtype=torch.uint8)
    t = OpenCVTracker("mil")
    t.init(frame, [10, 10, 8, 8])
    t._cv = _Stub([(True, (12, 11, 8, 8)), (False, (0, 0, 0, 0)), (True, (5, 5, 0, 0)),
                   (True, (55, 45, 10, 10))])  # fmt: skip
    s1 = t.update(frame)
    assert s1.box[0].tolist() == [12, 11, 8, 8] and bool(s1.visible[0])
    s2 = t.update(frame)  # ok=False: last box, not visible
    assert s2.box[0].tolist() == [12, 11, 8, 8] and not bool(s2.visible[0])
    assert float(s2.confidence[0]) == 0.0
    s3 = t.update(frame)  # empty box: also a failure
    assert s3.box[0].tolist() == [12, 11, 8, 8] and not bool(s3.visible[0])
    assert t.failures == 2
    s4 = t.update(frame)  # sticking out of the frame: clipped
    assert s4.box[0].tolist() == [55, 45, 5, 5]


def _square_frames(n=8, size=(80, 100), gray=False, vanish_at=None):
    gen = torch.Generator().manual_seed(0)
    frames, boxes = [], []
    for k in range(n):
        img = (torch.rand(size, generator=gen) * 60 + 100).to(torch.uint8)
        img = img.expand(3, *size).clone()
        x, y = 10 + 4 * k, 20 + 2 * k
        if vanish_at is None or k < vanish_at:
            if gray:
                img[:, y : y + 16, x : x + 16] = 250
            else:
                img[:, y : y + 16, x : x + 16] = torch.tensor([220, 20, 20], dtype=torch.uint8)[
                    :, None, None
                ]
        frames.append(img[:1] if gray else img)
        boxes.append([x, y, 16, 16])
    return frames, torch.tensor(boxes, dtype=torch.float64)


def test_box_reaching_outside_the_frame_starts_on_its_visible_part(monkeypatch):
    # OpenCV builds differ on such boxes (5.0's MIL throws std::bad_alloc, others crash the
    # process): the wrapper hands OpenCV only the part inside the frame
    frame = torch.randint(
        0, 255, (3, 240, 320), dtype=torch.uint8, generator=torch.Generator().manual_seed(0)
    )
    seen = []

    class Fake:
        def init(self, img, rect):
            seen.append((img.shape, rect))
            return True

    t = create_tracker("mil")
    monkeypatch.setattr(t, "_ctor", Fake)
    for box, rect in [
        ((25.0, -16.0, 75.0, 186.0), (25, 0, 75, 170)),
        ((300.5, 200.0, 40.0, 60.0), (300, 200, 20, 40)),
        ((-10.0, -10.0, 400.0, 300.0), (0, 0, 320, 240)),
    ]:
        state = t.init(frame, torch.tensor(box))
        assert seen[-1] == ((240, 320, 3), rect)
        assert state.box[0].tolist() == list(box)  # the state is the box the user gave
    # and the real MIL starts and follows on the visible part
    mil = create_tracker("mil")
    mil.init(frame, torch.tensor([25.0, -16.0, 75.0, 186.0]))
    assert mil.update(frame).box.shape == (1, 4)


@pytest.mark.parametrize("kind", ["mil", "boosting"])
def test_box_under_5_pixels_is_refused_before_opencv_sees_it(monkeypatch, kind):
    # OpenCV 5.0's TrackerMIL and legacy TrackerBoosting never return from init on a 4x4 box
    # (and ignore SIGTERM); the check runs before OpenCV, so a fake stands in for it
    import torchtrack.track.opencv as opencv

    frame = torch.zeros((3, 240, 320), dtype=torch.uint8)
    seen = []

    class Fake:
        def init(self, img, rect):
            seen.append(rect)
            return True

    monkeypatch.setattr(opencv, "opencv_constructor", lambda k: Fake)
    t = OpenCVTracker(kind)
    for box, got in [((100.0, 100.0, 3.0, 3.0), "3x3"), ((100.0, 100.0, 40.0, 4.0), "40x4"),
                     ((317.0, 100.0, 30.0, 30.0), "3x30")]:  # fmt: skip
        with pytest.raises(BoxError, match=f"OpenCV {kind} needs an init box of at least 5x5 pixels inside the frame, got {got}"):  # fmt: skip
            t.init(frame, torch.tensor(box))
    assert seen == []
    t.init(frame, torch.tensor([100.0, 100.0, 5.0, 5.0]))
    assert seen == [(100, 100, 5, 5)]


def test_opencv_exception_becomes_a_tracker_error(monkeypatch):
    frame = torch.zeros((3, 240, 320), dtype=torch.uint8)

    class Throws:
        def init(self, img, rect):
            raise cv2.error("OpenCV(5.0.0) std::bad_alloc")

    t = create_tracker("mil")
    monkeypatch.setattr(t, "_ctor", Throws)
    with pytest.raises(
        TrackerError, match=r"mil failed to initialise on box \(25, 0, 75, 170\) in a 320x240"
    ):
        t.init(frame, torch.tensor([25.0, -16.0, 75.0, 186.0]))


def test_mil_box_without_room_to_sample_says_so():
    # a box spanning the frame's height: MIL's assertion '!posSamples.empty()' leaked through
    # with OpenCV's banner and source path
    frame = torch.zeros((3, 96, 128), dtype=torch.uint8)
    with pytest.raises(TrackerError, match="no room around the box to sample positives") as e:
        create_tracker("mil").init(frame, torch.tensor([0.0, 0.0, 60.0, 96.0]))
    assert "Assertion" not in str(e.value) and ".cpp" not in str(e.value)


def test_camshift_follows_a_coloured_target():
    frames, gt = _square_frames()
    t = CamShiftTracker()
    boxes, visible = _run(t, frames, gt[0])
    assert t._use_hue and bool(visible.all())
    assert float(box_iou(boxes, gt).min()) > 0.6


def test_camshift_gray_frames_use_brightness():
    frames, gt = _square_frames(gray=True)
    t = create_tracker("camshift")
    boxes, _ = _run(t, frames, gt[0])
    assert not t._use_hue
    assert float(box_iou(boxes, gt).min()) > 0.6


def test_camshift_reports_a_vanished_target():
    frames, gt = _square_frames(vanish_at=5)
    t = CamShiftTracker()
    _, visible = _run(t, frames, gt[0])
    assert visible[:5].all() and not visible[5:].any()
    assert t.failures == 3
    with pytest.raises(ConfigError, match=r"bins must be an integer in \[2, 256\]"):
        CamShiftTracker(bins=1)
    # camshift:min_confidence=true ran at 1.0: the target was (almost) never visible
    with pytest.raises(ConfigError, match=r"min_confidence must be in \[0, 1\] .* got True"):
        CamShiftTracker(min_confidence=True)


def test_unknown_kind():
    with pytest.raises(ConfigError, match="unknown OpenCV tracker kind 'goturn'"):
        opencv_constructor("goturn")


@pytest.mark.skipif(has_contrib(), reason="opencv-contrib is installed")
def test_contrib_kind_without_contrib():
    with pytest.raises(ConfigError, match="not in this cv2 build"):
        OpenCVTracker("csrt")


@needs_contrib
@pytest.mark.parametrize("kind", CONTRIB_KINDS)
def test_contrib_peers_track_bobot(bobot, kind):
    seq, frames = bobot
    t = create_tracker(kind)
    boxes, _ = _run(t, frames[:6], seq.boxes[0])
    assert boxes.shape == (6, 4)
    assert float(box_iou(boxes, seq.boxes[:6])[1:].mean()) > 0.5


@needs_contrib
def test_kcf_wrapper_equals_direct_opencv(bobot):
    """KCF is deterministic: the wrapper gives exactly OpenCV's boxes."""
    seq, frames = bobot
    ours, _ = _run(OpenCVTracker("kcf"), frames, seq.boxes[0])
    x, y, w, h = seq.boxes[0].tolist()
    rect = (round(x), round(y), round(x + w) - round(x), round(y + h) - round(y))
    direct = cv2.TrackerKCF.create()
    direct.init(np.ascontiguousarray(to_numpy_bgr(frames[0])), rect)
    ref = [direct.update(to_numpy_bgr(f)) for f in frames[1:]]
    for k, (ok, b) in enumerate(ref, start=1):
        if ok:
            assert ours[k].tolist() == [float(v) for v in b]
