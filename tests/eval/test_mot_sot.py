"""tools/make_mot_sot.py: single-target sequences cut from MOT ground truth (the held-out set of
docs/benchmarks/sot.md)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import torch

from torchtrack.boxes import box_iou
from torchtrack.io.mot import MotRows, read_mot
from torchtrack.io.sequences import find_sequences

REPO = Path(__file__).resolve().parents[2]

_spec = importlib.util.spec_from_file_location("make_mot_sot", REPO / "tools" / "make_mot_sot.py")
make_mot_sot = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(make_mot_sot)


def _rows(rows):
    f, i, x, y, w, h, c = (np.array(v, dtype=float) for v in zip(*rows, strict=True))
    return MotRows.from_arrays(f.astype(int), i.astype(int), np.stack((x, y, w, h), 1), c)


def test_track_spans_rules():
    rows = []
    for f in range(80):
        # target 1 starts on top of target 2 (frames 0-9), then walks away from it
        rows.append((f, 1, 10 + (0 if f < 10 else 3 * f), 10, 10, 20, 1))
        rows.append((f, 2, 10, 10, 10, 20, 1))
        # target 3 starts half outside the frame (x < 0) until frame 5, absent on 40-49
        if not 40 <= f < 50:
            rows.append((f, 3, -5 + f, 60, 10, 20, 1))
        # target 4: an ignore row (conf 0) that is never a target but still counts as a box
        rows.append((f, 4, 200, 10, 10, 20, 0))
    rows.append((0, 5, 300, 10, 10, 20, 1))  # too short
    spans = {s[0]: s for s in make_mot_sot.track_spans(_rows(rows), 400, 100, 0.1, 50)}
    assert sorted(spans) == [1, 2, 3]
    assert spans[1][1:3] == (10, 79)  # first frame apart from target 2
    assert spans[2][1:3] == (10, 79)  # the same for target 2
    assert spans[3][1:3] == (5, 79) and 45 not in spans[3][3] and len(spans[3][3]) == 65


def test_pets_spans_start_alone_and_inside(data_dir):
    gt = read_mot(data_dir / "mot" / "PETS09-S2L1" / "gt" / "gt.txt", 0.625, 795, kind="gt")
    spans = make_mot_sot.track_spans(gt, 480, 360, 0.1, 50)
    assert len(spans) == 19
    for _, first, last, boxes in spans:
        b = np.asarray(boxes[first])
        assert b[0] >= 0 and b[1] >= 0 and b[0] + b[2] <= 480 and b[1] + b[3] <= 360
        others = gt.boxes[(gt.frames == first) & ~np.all(gt.boxes == b, axis=1)]
        assert box_iou(torch.tensor(b[None]), torch.tensor(others)).max() < 0.1
        assert last > first


def test_tud_sequences_load_as_single_target(data_dir, tmp_path):
    assert make_mot_sot.main(["--out", str(tmp_path), "--only", "TUD-Stadtmitte"]) == 0
    seqs = {s.name: s for s in find_sequences(tmp_path)}
    assert len(seqs) == 8 and "TUD-Stadtmitte-id03" in seqs
    s = seqs["TUD-Stadtmitte-id03"]
    assert s.first_frame == 8 and len(s) == 172 and s.present.all()
    gt = read_mot(data_dir / "mot" / "TUD-Stadtmitte" / "gt" / "gt.txt", 1.0, 179, kind="gt")
    row = gt.boxes[(gt.ids == 3) & (gt.frames == 7)][0]
    assert np.allclose(s.boxes[0].numpy(), row, atol=0.01)
    assert s.frames[0].resolve().name == "000008.jpg"
    with pytest.raises(SystemExit):
        make_mot_sot.main(["--out", str(tmp_path), "--only", "nope"])
