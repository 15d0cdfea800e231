"""tools/make_fast_copies.py: every-K-th-frame copies of tracking sequences (the fast-motion
proxy of docs/benchmarks/sot.md)."""

from __future__ import annotations

import importlib.util
import itertools
from pathlib import Path

import pytest
import torch

from torchtrack.errors import SequenceError
from torchtrack.io.sequences import load_sequence

REPO = Path(__file__).resolve().parents[2]

_spec = importlib.util.spec_from_file_location(
    "make_fast_copies", REPO / "tools" / "make_fast_copies.py"
)
make_fast_copies = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(make_fast_copies)


def test_every_third_frame_of_bobot(data_dir, tmp_path):
    seq = load_sequence(data_dir / "tracking" / "bobot_pedestrian")[0]
    assert make_fast_copies.main(["--every", "3", "--out", str(tmp_path), str(seq.root)]) == 0
    copy = load_sequence(tmp_path / f"{seq.name}-every3")[0]
    n = len(range(0, len(seq.frames), 3))
    assert len(copy.frames) == n == copy.boxes.shape[0]
    # the same frames and boxes, three apart; absent frames stay absent
    for j in (0, 1, n // 2, n - 1):
        assert Path(copy.frames[j]).resolve() == Path(seq.frames[3 * j]).resolve()
    orig = seq.boxes[::3]
    absent = torch.isnan(orig).any(1)
    assert bool(absent.any())  # BoBoT has frames without its target
    assert torch.equal(torch.isnan(copy.boxes).any(1), absent)
    assert torch.allclose(copy.boxes[~absent], orig[~absent], atol=1e-3)
    with seq.open("rgb") as a, copy.open("rgb") as b:
        fa = dict(itertools.islice(a.items(), 4))
        fb = dict(itertools.islice(b.items(), 2))
    assert torch.equal(fb[1], fa[3])


def test_bad_every_and_missing_source(tmp_path, data_dir):
    seq = load_sequence(data_dir / "tracking" / "otb" / "Crossing")[0]
    with pytest.raises(SequenceError, match="--every must be >= 1"):
        make_fast_copies.make_copy(seq, 0, tmp_path)
    assert make_fast_copies.main(["--out", str(tmp_path), str(tmp_path / "missing")]) == 1
