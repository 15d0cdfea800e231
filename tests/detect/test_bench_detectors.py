"""tools/bench_detectors.py's blurred test set (``--blur``): every image blurred as OpenCV
blurs it, colour and grey, windows and labels untouched."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location(
        "bench_detectors", REPO / "tools" / "bench_detectors.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    yield mod
    sys.modules.pop("test_sets", None)


def test_blurred_test_set_blurs_every_image_and_keeps_the_windows(bench):
    g = torch.Generator().manual_seed(0)
    colour = torch.randint(0, 256, (3, 40, 30), dtype=torch.uint8, generator=g)
    grey = torch.randint(0, 256, (1, 20, 50), dtype=torch.uint8, generator=g)
    boxes = [torch.tensor([[0, 0, 10, 20]]), torch.tensor([[5, 5, 10, 10], [1, 2, 3, 4]])]
    ts = bench.test_sets.TestSet("t", [colour, grey], boxes, [1, 0], ["a", "b"], "two images")
    out = bench.blurred(ts, 1.5)
    assert out.boxes is ts.boxes and out.labels == [1, 0] and out.groups == ["a", "b"]
    assert "sd 1.5 px" in out.what and ts.what == "two images"
    for before, after in zip(ts.images, out.images, strict=True):
        assert after.shape == before.shape and after.dtype == torch.uint8
        ref = cv2.GaussianBlur(np.ascontiguousarray(before.permute(1, 2, 0).numpy()), (0, 0), 1.5)
        assert np.array_equal(after.permute(1, 2, 0).numpy().reshape(ref.shape), ref)
        assert after.float().std() < before.float().std()  # smoother
    with pytest.raises(SystemExit, match="--blur"):
        bench.blurred(ts, 0.0)
