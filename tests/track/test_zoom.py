"""Scale (issue 13, point 3): a real frame zoomed 3x about its target (tools/bench_zoom.py);
the adaptive-haar box must grow with the target, the co-training tracker keeps its first size
by design (Jin et al.'s state is the location)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("bench_zoom", REPO / "tools" / "bench_zoom.py")
bench_zoom = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench_zoom)


@pytest.fixture(scope="module")
def david_zoom_in(data_dir):
    bench_zoom.DATA = data_dir
    return bench_zoom.case_frames("otb/David", 3.0, 100, "in")


def test_zoom_sequence_boxes_follow_the_zoom(david_zoom_in):
    _, frames, boxes = david_zoom_in
    assert len(frames) == 100 and frames[0].shape == frames[-1].shape
    assert boxes[-1, 2] / boxes[0, 2] == pytest.approx(3.0)
    centre = boxes[:, :2] + boxes[:, 2:] / 2
    assert (centre - centre[0]).abs().max() < 1e-9  # zoomed about the target's centre


def test_adaptive_haar_box_grows_with_the_target(david_zoom_in, one_thread):
    _, frames, boxes = david_zoom_in
    r = bench_zoom.run_tracker("adaptive-haar", frames, boxes, seed=0)
    assert 0.75 < r["ratio"] < 1.33, r
    assert r["iou"] > 0.7, r


def test_cotrain_keeps_its_first_size(david_zoom_in, one_thread):
    _, frames, boxes = david_zoom_in
    r = bench_zoom.run_tracker("cotrain", frames, boxes, seed=0)
    assert r["ratio"] == pytest.approx(1 / 3, rel=1e-6)
