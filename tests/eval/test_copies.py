"""tools/make_copies.py: copies of tracking sequences at a lower frame rate, in grey, or under
changing light (the proxies of docs/benchmarks/sot.md for what the dev set lacks)."""

from __future__ import annotations

import importlib.util
import itertools
import math
from pathlib import Path

import cv2
import pytest
import torch

from torchtrack.errors import SequenceError
from torchtrack.io.sequences import load_sequence

REPO = Path(__file__).resolve().parents[2]

_spec = importlib.util.spec_from_file_location("make_copies", REPO / "tools" / "make_copies.py")
make_copies = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(make_copies)


def _frames(seq, n):
    with seq.open("rgb") as src:
        return dict(itertools.islice(src.items(), n))


def test_every_third_frame_of_bobot(data_dir, tmp_path):
    seq = load_sequence(data_dir / "tracking" / "bobot_pedestrian")[0]
    assert make_copies.main(["--every", "3", "--out", str(tmp_path), str(seq.root)]) == 0
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
    fa, fb = _frames(seq, 4), _frames(copy, 2)
    assert torch.equal(fb[1], fa[3])


def test_grey_copy_is_the_luma_of_every_frame(data_dir, tmp_path):
    seq = load_sequence(data_dir / "tracking" / "otb" / "Crossing")[0].head(5)
    folder = make_copies.make_copy(seq, 1, tmp_path, grey=True)
    assert folder.name == "Crossing-grey"
    copy = load_sequence(folder)[0]
    assert len(copy) == 5 and torch.equal(copy.boxes.float(), seq.boxes.float().round(decimals=3))
    fa, fb = _frames(seq, 5), _frames(copy, 5)
    for i in range(5):
        luma = cv2.cvtColor(fa[i].permute(1, 2, 0).numpy(), cv2.COLOR_RGB2GRAY)
        assert torch.equal(fb[i][0], torch.from_numpy(luma))  # lossless: exactly the luma
        assert torch.equal(fb[i][0], fb[i][1]) and torch.equal(fb[i][1], fb[i][2])
    assert bool((fa[0][0] != fa[0][2]).any())  # the source was colour


def test_gain_copy_follows_the_sine(data_dir, tmp_path):
    seq = load_sequence(data_dir / "tracking" / "otb" / "Crossing")[0].head(30)
    folder = make_copies.make_copy(seq, 1, tmp_path, gain=0.5, period=20)
    assert folder.name == "Crossing-gain0.5"
    fa, fb = _frames(seq, 30), _frames(load_sequence(folder)[0], 30)
    for j in (0, 5, 15):  # factors 1, 1.5 (peak), 0.5 (trough)
        g = 1 + 0.5 * math.sin(2 * math.pi * j / 20)
        want = (fa[j].double() * g).clamp(0, 255).round()
        assert (fb[j].double() - want).abs().max() <= 1  # float32 rounding of the product
    assert fb[15].double().mean() < 0.6 * fa[15].double().mean()
    assert fb[5].double().mean() > 1.3 * fa[5].double().mean()


def test_blur_copy_is_the_gaussian_blur_of_every_frame(data_dir, tmp_path):
    import cv2

    seq = load_sequence(data_dir / "tracking" / "otb" / "Crossing")[0].head(4)
    folder = make_copies.make_copy(seq, 1, tmp_path, blur=1.5)
    assert folder.name == "Crossing-blur1.5"
    fa, fb = _frames(seq, 4), _frames(load_sequence(folder)[0], 4)
    for i in range(4):
        want = cv2.GaussianBlur(fa[i].permute(1, 2, 0).numpy(), (0, 0), 1.5)
        assert torch.equal(fb[i], torch.from_numpy(want).permute(2, 0, 1))  # lossless PNG
    assert not torch.equal(fa[0], fb[0])


def test_changes_combine_in_the_name():
    assert make_copies.copy_name("BoBoT", 3, True, 0.25) == "BoBoT-every3-grey-gain0.25"
    assert make_copies.copy_name("BoBoT", 1, False, 0.0, 2.0) == "BoBoT-blur2"
    assert make_copies.copy_name("BoBoT", 1, False, 0.0) == "BoBoT"


def test_bad_arguments_and_missing_source(tmp_path, data_dir):
    seq = load_sequence(data_dir / "tracking" / "otb" / "Crossing")[0]
    with pytest.raises(SequenceError, match="--every must be >= 1"):
        make_copies.make_copy(seq, 0, tmp_path)
    with pytest.raises(SequenceError, match=r"--gain must be in \[0, 1\)"):
        make_copies.make_copy(seq, 1, tmp_path, gain=1.0)
    with pytest.raises(SequenceError, match="--period must be > 0"):
        make_copies.make_copy(seq, 1, tmp_path, gain=0.5, period=0)
    with pytest.raises(SequenceError, match=r"--blur must be in \[0, 20\]"):
        make_copies.make_copy(seq, 1, tmp_path, blur=-1.0)
    with pytest.raises(SequenceError, match="nothing to change"):
        make_copies.make_copy(seq, 1, tmp_path)
    assert make_copies.main(["--out", str(tmp_path), str(tmp_path / "missing")]) == 1
    assert make_copies.main(["--out", str(tmp_path), str(seq.root)]) == 1  # nothing to change
    assert not (tmp_path / "Crossing").exists()
