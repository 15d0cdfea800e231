"""Helpers for the evaluation tests: tiny on-disk sequences and scripted trackers."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

import torchtrack.track.base as base
from torchtrack.track.base import Tracker, TrackState, register_tracker


class Static(Tracker):
    """Returns its init box forever (visible)."""

    name = "test-static"

    def _init(self, frame, boxes):
        self.box = boxes[0].clone()
        self.frames_seen = 0
        return TrackState.single(self.box)

    def _update(self, frame):
        self.frames_seen += 1
        return TrackState.single(self.box)


class Raising(Static):
    """Raises on its third update."""

    name = "test-raising"

    def _update(self, frame):
        if self.frames_seen == 2:
            raise RuntimeError("boom at the third update")
        return super()._update(frame)


class FarAway(Static):
    """Always 200 px to the right of where it was initialised: breaks every frame."""

    name = "test-faraway"

    def __init__(self, generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.generator = generator

    def _update(self, frame):
        self.frames_seen += 1
        b = self.box.clone()
        b[0] += 200
        return TrackState.single(b, visible=False)


@pytest.fixture
def test_trackers():
    for cls in (Static, Raising, FarAway):
        register_tracker(cls.name, cls)
    yield
    for cls in (Static, Raising, FarAway):
        base._REGISTRY.pop(cls.name, None)


def make_sequence(folder, n=6, absent=(), box=(4, 5, 10, 8)):
    """A generic-layout sequence (frames/ + groundtruth.csv) with a static target."""
    (folder / "frames").mkdir(parents=True)
    for k in range(n):
        img = np.full((30, 40, 3), 90, np.uint8)
        x, y, w, h = box
        img[y : y + h, x : x + w] = (20, 200, 20)
        cv2.imwrite(str(folder / "frames" / f"{k:04d}.png"), img)
    rows = ["x,y,w,h"] + [
        "nan,nan,nan,nan" if k in absent else ",".join(str(v) for v in box) for k in range(n)
    ]
    (folder / "groundtruth.csv").write_text("\n".join(rows) + "\n")
    return folder
