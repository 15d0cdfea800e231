"""The tracker interface: validation, call order, TrackState, registry and specs."""

from __future__ import annotations

import pytest
import torch

import torchtrack.track.base as base
from torchtrack.errors import BoxError, ConfigError, ShapeError, TrackerError
from torchtrack.track.base import (
    Tracker,
    TrackState,
    available_trackers,
    create_tracker,
    parse_tracker_spec,
    register_tracker,
    tracker_names,
)
from torchtrack.track.opencv import has_contrib


class Shift(Tracker):
    """Moves the box by (dx, 0) each frame: obviously right behaviour to check the plumbing."""

    name = "test-shift"
    max_targets = None

    def __init__(self, dx: float = 1.0) -> None:
        super().__init__()
        self.dx = dx

    def _init(self, frame, boxes):
        self.boxes = boxes.clone()
        return TrackState(
            box=self.boxes.clone(),
            confidence=torch.ones(len(boxes), dtype=torch.float64),
            visible=torch.ones(len(boxes), dtype=torch.bool),
        )

    def _update(self, frame):
        self.boxes[:, 0] += self.dx
        return TrackState(
            box=self.boxes.clone(),
            confidence=torch.ones(len(self.boxes), dtype=torch.float64),
            visible=torch.ones(len(self.boxes), dtype=torch.bool),
        )


@pytest.fixture
def registered():
    register_tracker("test-shift", Shift, description="test")
    yield
    base._REGISTRY.pop("test-shift", None)


FRAME = torch.zeros(3, 20, 30, dtype=torch.uint8)


def test_init_update_batched_and_single():
    t = Shift(dx=2)
    s0 = t.init(FRAME, [1, 2, 5, 6])
    assert s0.box.shape == (1, 4) and s0.box.dtype == torch.float64
    s1 = t.update(FRAME)
    assert s1.box[0].tolist() == [3, 2, 5, 6]
    t2 = Shift()
    s = t2.init(FRAME, torch.tensor([[1.0, 2, 5, 6], [10, 2, 5, 6]]))
    assert s.box.shape == (2, 4)
    assert t2.update(FRAME).box[:, 0].tolist() == [2, 11]


def test_call_order_and_frame_checks():
    t = Shift()
    with pytest.raises(TrackerError, match=r"update\(\) called before init\(\)"):
        t.update(FRAME)
    with pytest.raises(ShapeError, match=r"\(C, H, W\) uint8"):
        t.init(FRAME.float(), [1, 1, 4, 4])
    with pytest.raises(ShapeError, match=r"\(C, H, W\) uint8"):
        t.init(FRAME[None], [1, 1, 4, 4])
    with pytest.raises(ShapeError, match=r"must be a torch\.Tensor"):
        t.init(FRAME.numpy(), [1, 1, 4, 4])
    t.init(FRAME[:1], [1, 1, 4, 4])  # gray frames are accepted
    with pytest.raises(ShapeError, match="frame size changed"):
        t.update(torch.zeros(3, 21, 30, dtype=torch.uint8))


def test_bad_init_boxes():
    t = Shift()
    with pytest.raises(BoxError, match="size below"):
        t.init(FRAME, [1, 1, 0, 4])
    with pytest.raises(BoxError, match="outside the 30x20 frame"):
        t.init(FRAME, [40, 1, 4, 4])
    with pytest.raises(BoxError, match="not finite"):
        t.init(FRAME, [float("nan"), 1, 4, 4])
    with pytest.raises(ShapeError, match=r"\(4,\) or \(B, 4\)"):
        t.init(FRAME, [1, 1, 4])
    with pytest.raises(TrackerError, match="needs an initial box"):
        t.init(FRAME, None)


def test_max_targets():
    class One(Shift):
        name = "one"
        max_targets = 1

    with pytest.raises(TrackerError, match="at most 1 target"):
        One().init(FRAME, [[1, 1, 4, 4], [2, 2, 4, 4]])


def test_trackstate_shapes():
    s = TrackState.single([1, 2, 3, 4], confidence=0.5, visible=False)
    assert (
        s.box.shape == (1, 4) and s.confidence.tolist() == [0.5] and s.visible.tolist() == [False]
    )
    with pytest.raises(ShapeError, match=r"\(B, 4\)"):
        TrackState(torch.zeros(4), torch.zeros(1), torch.zeros(1, dtype=torch.bool))
    with pytest.raises(ShapeError, match=r"must be \(2,\)"):
        TrackState(torch.zeros(2, 4), torch.zeros(1), torch.zeros(2, dtype=torch.bool))


def test_registry(registered):
    assert "test-shift" in tracker_names() and "mil" in tracker_names()
    assert "mil" in available_trackers() and "camshift" in available_trackers()
    t = create_tracker("test-shift", dx=3.0)
    assert isinstance(t, Shift) and t.dx == 3.0
    with pytest.raises(
        ConfigError, match=r"unknown tracker 'nope'; known trackers: .*camshift.*mil"
    ):
        create_tracker("nope")
    with pytest.raises(ConfigError, match=r"has no parameter\(s\) speed; valid: dx"):
        create_tracker("test-shift", speed=2)
    register_tracker("test-shift", Shift)  # same factory again: fine
    with pytest.raises(ConfigError, match="already registered"):
        register_tracker("test-shift", lambda: Shift())


@pytest.mark.skipif(has_contrib(), reason="opencv-contrib is installed: csrt is available")
def test_contrib_tracker_without_contrib_says_what_to_install():
    assert "csrt" in tracker_names() and "csrt" not in available_trackers()
    with pytest.raises(ConfigError, match="needs opencv-contrib-python-headless"):
        create_tracker("csrt")


def test_parse_tracker_spec():
    assert parse_tracker_spec("mil") == ("mil", {})
    assert parse_tracker_spec("adaptive-haar:adapt=none,particles=500,lam=20.5,fast=true") == (
        "adaptive-haar",
        {"adapt": "none", "particles": 500, "lam": 20.5, "fast": True},
    )
    with pytest.raises(ConfigError, match="is not key=value"):
        parse_tracker_spec("mil:fast")
    with pytest.raises(ConfigError, match="has no name"):
        parse_tracker_spec(":a=1")


def test_a_broken_tracker_module_only_warns(monkeypatch):
    monkeypatch.setattr(base, "_loaded", False)
    monkeypatch.setattr(
        base, "BUILTIN_TRACKER_MODULES", [*base.BUILTIN_TRACKER_MODULES, "torchtrack.no_such_mod"]
    )
    with pytest.warns(RuntimeWarning, match=r"tracker module torchtrack\.no_such_mod could not"):
        names = tracker_names()
    assert "mil" in names and "camshift" in names
