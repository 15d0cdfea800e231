"""DetectorObservation: calibrated detector probabilities of particle windows."""

from __future__ import annotations

import pytest
import torch

from torchtrack.detect.detector import Detector
from torchtrack.errors import NotFittedError, ShapeError
from torchtrack.features.haar import haar_bank
from torchtrack.io.video import read_image
from torchtrack.learn import BoostedStumps, PlattCalibrator
from torchtrack.observe.detector import DetectorObservation, scorable_boxes


def tiny_detector(seed: int = 0) -> Detector:
    """A small fitted detector (32 x 16 window, 6 features): enough for arithmetic checks."""
    g = torch.Generator().manual_seed(seed)
    bank = haar_bank((32, 16), n_scales=2, stride=4)
    index = torch.randperm(len(bank), generator=g)[:6]
    x = torch.randn(300, 6, generator=g)
    y = (x[:, 0] + 0.5 * x[:, 1] + 0.3 * torch.randn(300, generator=g) > 0).long()
    clf = BoostedStumps(n_estimators=8).fit(x, y)
    cal = PlattCalibrator().fit(clf.decision_function(x), y)
    return Detector(bank, index, clf, cal, name="tiny")


@pytest.fixture(scope="module")
def frame(data_dir):
    return read_image(data_dir / "tracking" / "otb" / "Crossing" / "img" / "0001.jpg")


def random_boxes(n: int, frame_hw, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    h, w = frame_hw
    wh = 8 + 60 * torch.rand(n, 2, generator=g, dtype=torch.float64)
    xy = torch.rand(n, 2, generator=g, dtype=torch.float64) * torch.tensor([w - 8.0, h - 8.0])
    return torch.cat([xy - wh / 3, wh], 1)  # some stick out of the frame on the left / top


def test_probabilities_equal_detector_score_cropped_or_not(frame):
    det = tiny_detector()
    boxes = random_boxes(200, frame.shape[-2:])[None]
    ref = det.score(frame[None].double(), boxes)  # full-frame integral image
    for crop in (True, False):
        p = DetectorObservation(det, crop=crop).probabilities(frame[None], boxes)
        assert p.shape == (1, 200)
        torch.testing.assert_close(p, ref.float(), atol=1e-5, rtol=0)


def test_unscorable_windows_get_zero_and_do_not_disturb_others(frame):
    det = tiny_detector()
    h, w = frame.shape[-2:]
    good = random_boxes(5, (h, w))
    bad = torch.tensor(
        [
            [w + 10.0, 5.0, 20.0, 20.0],  # right of the frame
            [-50.0, 5.0, 20.0, 20.0],  # left of the frame
            [5.0, 5.0, 0.5, 20.0],  # under one pixel wide
            [float("nan"), 5.0, 20.0, 20.0],
        ],
        dtype=torch.float64,
    )
    boxes = torch.cat([good, bad])[None]
    obs = DetectorObservation(det)
    p = obs.probabilities(frame[None], boxes)
    assert scorable_boxes(boxes, (h, w)).tolist() == [[True] * 5 + [False] * 4]
    assert p[0, 5:].tolist() == [0.0, 0.0, 0.0, 0.0]
    torch.testing.assert_close(p[:, :5], obs.probabilities(frame[None], good[None]))
    ll = obs.log_likelihood(frame[None], boxes)
    assert torch.isfinite(ll).all() and float(ll[0, 5]) == pytest.approx(
        torch.log(torch.tensor(1e-6)).item()
    )


def test_batch_of_frames_matches_single_frames(frame):
    det = tiny_detector()
    f2 = torch.flip(frame, dims=[-1])
    b1 = random_boxes(30, frame.shape[-2:], seed=3)
    b2 = random_boxes(30, frame.shape[-2:], seed=4)
    obs = DetectorObservation(det)
    both = obs.probabilities(torch.stack([frame, f2]), torch.stack([b1, b2]))
    torch.testing.assert_close(both[0], obs.probabilities(frame[None], b1[None])[0])
    torch.testing.assert_close(both[1], obs.probabilities(f2[None], b2[None])[0])


def test_errors(frame):
    det = tiny_detector()
    with pytest.raises(NotFittedError, match="no calibration"):
        DetectorObservation(det.with_calibrator(None))
    obs = DetectorObservation(det)
    with pytest.raises(ShapeError, match=r"\(B, N, 4\)"):
        obs.probabilities(frame[None], torch.zeros(3, 4))
    with pytest.raises(ShapeError, match="frame"):
        obs.probabilities(frame[None], torch.zeros(2, 3, 4))


def test_margins_are_the_detector_margins_and_map_to_the_probabilities(frame):
    det = tiny_detector(1)
    h, w = frame.shape[-2:]
    boxes = torch.cat(
        [random_boxes(30, (h, w)), torch.tensor([[w + 5.0, 0.0, 10.0, 10.0]], dtype=torch.float64)]
    )[None]
    obs = DetectorObservation(det)
    m = obs.margins(frame[None], boxes)
    assert m.dtype == torch.float64 and m.shape == (1, 31) and m[0, 30] == -float("inf")
    ref = det.decision_function(frame[None].double(), boxes[:, :30])
    torch.testing.assert_close(m[:, :30], ref.double(), atol=1e-5, rtol=0)
    p = obs.probabilities_from_margins(m)
    assert p[0, 30] == 0.0
    torch.testing.assert_close(p, obs.probabilities(frame[None], boxes))
    torch.testing.assert_close(
        p[:, :30], det.proba_from_margin(m[:, :30]).float(), atol=1e-6, rtol=0
    )
    with pytest.raises(ShapeError, match=r"\(B, N, 4\)"):
        obs.margins(frame[None], boxes[0])


def test_scorable_boxes_refuses_a_frame_size_that_is_not_two_sizes():
    """(True, 64) was a 1 x 64 frame and a NaN size kept no box, silently."""
    b = torch.tensor([[1.0, 1.0, 5.0, 5.0]])
    assert scorable_boxes(b, (48, 64)).tolist() == [True]
    for bad in ((True, 64), (float("nan"), 64), (48,)):
        with pytest.raises(ShapeError, match=r"frame_size must be \(H, W\)"):
            scorable_boxes(b, bad)


@pytest.mark.parametrize("floor", [True, -0.5, float("nan"), "1e-6", 1.0])
def test_likelihood_floor_must_be_a_share(floor):
    """floor=True clamped every probability to 1 (a flat likelihood: the detector ignored), a
    negative or NaN floor was no floor at all, without a word."""
    from torchtrack.errors import ConfigError

    with pytest.raises(ConfigError, match=r"floor must be a number in \[0, 1\)"):
        DetectorObservation(tiny_detector(), floor=floor)
