"""MOTChallenge files and sequences: the real MOT15 data, round trips, every malformed input."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from torchtrack.errors import MotFormatError, SequenceError, ShapeError, VideoError
from torchtrack.io.mot import (
    MotRows,
    find_mot_sequences,
    is_mot_folder,
    load_mot_sequence,
    read_mot,
    read_seqinfo,
    write_mot,
)


def _write(path, text):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


# ---------------------------------------------------------------------------------------------
# Real data
# ---------------------------------------------------------------------------------------------
def test_tud_stadtmitte_folder(data_dir):
    seq = load_mot_sequence(data_dir / "mot" / "TUD-Stadtmitte")
    assert seq.name == "TUD-Stadtmitte" and seq.n_frames == 179 and len(seq.frames) == 179
    assert (seq.width, seq.height, seq.frame_rate) == (640, 480, 25.0)
    assert len(seq.gt) == 1156 and len(np.unique(seq.gt.ids)) == 10
    # file: 1,1,88,99,61.08,218.56,1,... -> 0-based frame 0, box shifted by one pixel
    assert seq.gt.frames[0] == 0 and seq.gt.ids[0] == 1
    np.testing.assert_allclose(seq.gt.boxes[0], [87, 98, 61.08, 218.56])
    assert seq.gt.extra.shape == (1156, 3)
    det = seq.detections()
    assert len(det) == 1129 and (det.ids == -1).all()
    assert det.conf.min() == pytest.approx(-0.15394) and det.conf.max() == pytest.approx(122.37)
    per_frame = det.split(seq.n_frames)
    assert len(per_frame) == 179 and sum(len(r) for r in per_frame) == 1129
    assert all((det.frames[r] == t).all() for t, r in enumerate(per_frame))
    with seq.open() as src:
        assert next(iter(src)).shape == (3, 480, 640)


def test_pets_video_plus_gt_scales_from_seqinfo(data_dir):
    gt = data_dir / "mot" / "PETS09-S2L1" / "gt" / "gt.txt"
    video = data_dir / "videos" / "pets2009_s2l1_vtest" / "vtest.avi"
    seq = load_mot_sequence(video, gt=gt)
    assert seq.name == "PETS09-S2L1" and seq.n_frames == 795 and seq.scale == 0.625
    assert (seq.width, seq.height) == (480, 360)
    assert len(seq.gt) == 4650 and int((seq.gt.conf == 0).sum()) == 174
    # 1,9,499,158,31.03,75.17 in 768x576 -> (498, 157) 0-based, x0.625
    np.testing.assert_allclose(seq.gt.boxes[0], np.array([498, 157, 31.03, 75.17]) * 0.625)
    explicit = load_mot_sequence(video, gt=gt, scale=1.0)
    np.testing.assert_allclose(explicit.gt.boxes[0], [498, 157, 31.03, 75.17])
    # the folder without frames still loads (its length from seqinfo.ini)
    folder = load_mot_sequence(data_dir / "mot" / "PETS09-S2L1", scale=0.625)
    assert folder.frames is None and folder.n_frames == 795
    np.testing.assert_allclose(folder.gt.boxes, seq.gt.boxes)
    with pytest.raises(VideoError, match="no frames here"):
        folder.open()
    with pytest.raises(MotFormatError, match=r"no det/det.txt"):
        folder.detections()


def test_find_mot_sequences(data_dir):
    found = find_mot_sequences(data_dir / "mot")
    assert [p.name for p in found] == ["PETS09-S2L1", "TUD-Stadtmitte"]
    assert is_mot_folder(data_dir / "mot" / "TUD-Stadtmitte")
    assert not is_mot_folder(data_dir / "mot")


# ---------------------------------------------------------------------------------------------
# Round trip and construction
# ---------------------------------------------------------------------------------------------
def test_write_read_round_trip(tmp_path):
    rows = MotRows.from_arrays(
        frames=torch.tensor([2, 0, 0]),
        ids=torch.tensor([1, 7, 3]),
        boxes=torch.tensor([[1.5, 2.25, 10.0, 20.0], [0.0, 0.0, 5.0, 6.0], [9.0, 8.0, 7.0, 6.0]]),
        conf=torch.tensor([0.5, 0.25, 1.0]),
    )
    out = tmp_path / "res" / "seq.txt"
    write_mot(out, rows)
    lines = out.read_text().splitlines()
    assert lines[0] == "1,3,10.000,9.000,7.000,6.000,1,-1,-1,-1"  # sorted by frame, id; 1-based
    assert lines[2].startswith("3,1,2.500,3.250,10.000,20.000,0.5,")
    back = read_mot(out)
    assert back.frames.tolist() == [0, 0, 2] and back.ids.tolist() == [3, 7, 1]
    np.testing.assert_allclose(back.boxes[2], [1.5, 2.25, 10, 20])
    assert back.lines.tolist() == [1, 2, 3] and back.path == out
    assert not list(tmp_path.glob("res/.*"))  # no temporary file left


def test_empty_rows_and_file(tmp_path):
    write_mot(tmp_path / "e.txt", MotRows.empty())
    assert (tmp_path / "e.txt").read_text() == ""
    rows = read_mot(tmp_path / "e.txt", n_frames=10)
    assert len(rows) == 0 and rows.boxes.shape == (0, 4)
    assert [len(r) for r in rows.split(3)] == [0, 0, 0]
    _write(tmp_path / "blank.txt", "\n\n  \n")
    assert len(read_mot(tmp_path / "blank.txt")) == 0


def test_six_and_seven_column_results(tmp_path):
    r6 = read_mot(_write(tmp_path / "a.txt", "1,1,10,10,5,5\n2,1,11,10,5,5\n"))
    assert r6.conf.tolist() == [1.0, 1.0] and r6.extra.shape == (2, 0)
    r7 = read_mot(_write(tmp_path / "b.txt", "1 1 10 10 5 5 0.3\n"))  # whitespace separated
    assert r7.conf.tolist() == [0.3]


def test_scale_and_split(tmp_path):
    f = _write(tmp_path / "g.txt", "3,1,11,21,10,20,1\n1,2,1,1,4,4,1\n3,2,1,1,4,4,0\n")
    rows = read_mot(f, scale=0.5, kind="gt")
    np.testing.assert_allclose(rows.boxes[0], [5, 10, 5, 10])
    idx = rows.split(4)
    assert [r.tolist() for r in idx] == [[1], [], [0, 2], []]
    assert rows.select(rows.conf > 0).ids.tolist() == [1, 2]


def test_from_arrays_shape_errors():
    with pytest.raises(ShapeError, match="ids must have shape"):
        MotRows.from_arrays([0, 1], [1], np.zeros((2, 4)))
    with pytest.raises(ShapeError, match="boxes must have shape"):
        MotRows.from_arrays([0, 1], [1, 2], np.zeros((3, 4)))
    with pytest.raises(ShapeError, match="boxes must have shape"):  # 2 values: not a box
        MotRows.from_arrays([0], [1], [5, 1])
    with pytest.raises(ShapeError, match="boxes must have shape"):  # (2M, 2): not M boxes
        MotRows.from_arrays([0, 1], [1, 2], np.zeros((4, 2)))
    assert MotRows.from_arrays([0], [1], [5, 1, 2, 3]).boxes.shape == (1, 4)


def test_write_refuses_what_read_refuses(tmp_path):
    """A results file write_mot writes, read_mot and eval read back."""
    for ids, boxes, match in (
        ([-1], [[0, 0, 5, 5]], "identities must be >= 0"),
        ([1], [[0, 0, 0, 5]], "widths and heights must be > 0"),
        ([1], [[0, 0, 5, 2e6]], r"within \+-1e\+06 pixels"),
    ):
        with pytest.raises(ValueError, match=match):
            write_mot(tmp_path / "x.txt", MotRows.from_arrays([0], ids, boxes))
    twice = MotRows.from_arrays([0, 0], [3, 3], np.ones((2, 4)))
    with pytest.raises(ValueError, match="id 3 appears twice in frame 1"):
        write_mot(tmp_path / "x.txt", twice)
    write_mot(
        tmp_path / "d.txt", MotRows.from_arrays([0, 0], [-1, -1], np.ones((2, 4))), kind="det"
    )
    assert len(read_mot(tmp_path / "d.txt", kind="det")) == 2
    assert not (tmp_path / "x.txt").exists()


def test_write_rejects_nan(tmp_path):
    rows = MotRows.from_arrays([0], [1], [[np.nan, 0, 1, 1]])
    with pytest.raises(ValueError, match="finite"):
        write_mot(tmp_path / "x.txt", rows)
    assert not (tmp_path / "x.txt").exists()


# ---------------------------------------------------------------------------------------------
# Malformed files: typed error with file and line
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("text", "kind", "match"),
    [
        ("1,1,1,1,5,5,1\n2,1,1,1,5,5,x\n", "results", r"line 2: not a row of numbers"),
        # float() reads 1_0 as 10: a typo became frame 10
        ("1_0,-1,1,1,5,5,1\n", "det", r"line 1: not a row of numbers"),
        ("1,1,1,1,5\n", "results", r"line 1: 5 columns; a results file has 6 to 10"),
        ("1,1,1,1,5,5\n", "gt", r"line 1: 6 columns; a ground-truth file has 7 to 10"),
        ("1,1,1,1,5,5,1,2,3,4,5\n", "det", r"line 1: 11 columns"),
        ("1,1,1,1,5,5,1\n\n2,1,1,1,5,5\n", "results", r"line 3: 6 columns, line 1 has 7"),
        ("1,1,1,1,5,5,1\n2,1,nan,1,5,5,1\n", "results", r"line 2: a value is not finite"),
        ("1,1,1,1,5,inf,1\n", "det", r"line 1: a value is not finite"),
        ("1.5,1,1,1,5,5,1\n", "results", r"line 1: the frame number is not an integer"),
        ("0,1,1,1,5,5,1\n", "results", r"line 1: frame 0: frames are numbered from 1"),
        ("1,2.5,1,1,5,5,1\n", "results", r"line 1: the id is not an integer"),
        ("1,-1,1,1,5,5,1\n", "results", r"line 1: id -1: identities must be >= 0"),
        ("1,1,1,1,0,5,1\n", "gt", r"line 1: box of size 0 x 5"),
        ("1,1,1,1,5,-2,1\n", "det", r"line 1: box of size 5 x -2"),
        (
            "1,4,1,1,5,5,1\n2,4,1,1,5,5,1\n1,4,9,9,5,5,1\n",
            "results",
            r"line 3: id 4 appears twice in frame 1 \(also on line 1\)",
        ),
        # beyond int64 these used to wrap to -2^63 (and get past the id >= 0 check)
        ("1,1e19,1,1,5,5,1\n", "results", r"line 1: id 1e\+19 is out of range"),
        ("1,1e19,1,1,5,5,1\n", "gt", r"line 1: id 1e\+19 is out of range"),
        ("1e19,1,1,1,5,5,1\n", "results", r"line 1: frame 1e\+19 is beyond any sequence"),
        # finite but absurd: the scoring's areas overflowed (numpy warnings, inf IoU terms)
        ("1,1,1,1,1e308,1e308,1\n", "results", r"line 1: box 1, 1, 1e\+308, 1e\+308 .* beyond"),
        ("1,-1,-2e6,1,5,5,1\n", "det", r"line 1: box -2e\+06, 1, 5, 5 .* beyond \+-1e\+06"),
    ],
)
def test_malformed_rows(tmp_path, text, kind, match):
    f = _write(tmp_path / "f.txt", text)
    with pytest.raises(MotFormatError, match=match) as info:
        read_mot(f, kind=kind)
    assert str(f) in str(info.value)


def test_detections_may_repeat_id_minus_one(tmp_path):
    f = _write(tmp_path / "det.txt", "1,-1,1,1,5,5,0.9\n1,-1,9,9,5,5,0.8\n")
    assert len(read_mot(f, kind="det")) == 2


def test_rows_beyond_the_sequence(tmp_path):
    f = _write(tmp_path / "gt.txt", "1,1,1,1,5,5,1\n11,1,1,1,5,5,1\n")
    assert len(read_mot(f, n_frames=11, kind="gt")) == 2
    with pytest.raises(
        MotFormatError, match=r"line 2: frame 11 is beyond the sequence's 10 frames"
    ):
        read_mot(f, n_frames=10, kind="gt")


def test_missing_and_binary_files(tmp_path):
    with pytest.raises(MotFormatError, match=r"results file .* does not exist"):
        read_mot(tmp_path / "nope.txt")
    (tmp_path / "bin.txt").write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(MotFormatError, match="cannot be read as text"):
        read_mot(tmp_path / "bin.txt")
    with pytest.raises(ValueError, match="scale"):
        read_mot(tmp_path / "bin.txt", scale=0.0)
    with pytest.raises(SequenceError, match=r"scale must be a number in \[0.001, 1000\]"):
        read_mot(tmp_path / "bin.txt", scale=1e-300)  # boxes of 1e-298 px passed as > 0


# ---------------------------------------------------------------------------------------------
# Sequences and seqinfo.ini
# ---------------------------------------------------------------------------------------------
def _mot_folder(root, n_frames=3, ini=True, img=True, gt="1,1,1,1,5,5,1\n"):
    import cv2

    root.mkdir(parents=True)
    if ini:
        _write(
            root / "seqinfo.ini",
            f"[Sequence]\nname=Tiny\nimDir=img1\nframeRate=5\nseqLength={n_frames}\n"
            "imWidth=16\nimHeight=12\nimExt=.png\n",
        )
    if img:
        (root / "img1").mkdir()
        for k in range(1, n_frames + 1):
            cv2.imwrite(str(root / "img1" / f"{k:06d}.png"), np.full((12, 16, 3), k, np.uint8))
    _write(root / "gt" / "gt.txt", gt)
    return root


def test_tiny_folder(tmp_path):
    seq = load_mot_sequence(_mot_folder(tmp_path / "tiny"))
    assert (seq.name, seq.n_frames, seq.frame_rate, seq.det_path) == ("Tiny", 3, 5.0, None)
    no_ini = load_mot_sequence(_mot_folder(tmp_path / "noini", ini=False))
    assert no_ini.name == "noini" and no_ini.n_frames == 3


def test_folder_errors(tmp_path):
    with pytest.raises(SequenceError, match=r"holds 2 frames but .* seqLength=3"):
        d = _mot_folder(tmp_path / "a", n_frames=3)
        (d / "img1" / "000003.png").unlink()
        load_mot_sequence(d)
    with pytest.raises(SequenceError, match=r"neither seqinfo\.ini nor an img1"):
        load_mot_sequence(_mot_folder(tmp_path / "b", ini=False, img=False))
    with pytest.raises(MotFormatError, match=r"gt.txt line 2: frame 4 is beyond .* 3 frames"):
        load_mot_sequence(_mot_folder(tmp_path / "c", gt="1,1,1,1,5,5,1\n4,1,1,1,5,5,1\n"))
    with pytest.raises(SequenceError, match="does not exist"):
        load_mot_sequence(tmp_path / "missing")
    with pytest.raises(SequenceError, match="neither a MOTChallenge folder"):
        load_mot_sequence(_write(tmp_path / "notes.txt", "x"))


def test_seqinfo_errors(tmp_path):
    with pytest.raises(MotFormatError, match=r"no \[Sequence\] section"):
        read_seqinfo(_write(tmp_path / "a.ini", "[Other]\nx=1\n"))
    with pytest.raises(MotFormatError, match="has no seqLength"):
        read_seqinfo(_write(tmp_path / "b.ini", "[Sequence]\nname=x\n"))
    with pytest.raises(MotFormatError, match="seqLength='ten' is not a number"):
        read_seqinfo(_write(tmp_path / "c.ini", "[Sequence]\nseqLength=ten\n"))
    with pytest.raises(MotFormatError, match="must be > 0"):
        read_seqinfo(_write(tmp_path / "d.ini", "[Sequence]\nseqLength=0\n"))
    with pytest.raises(MotFormatError, match="not a valid ini"):
        read_seqinfo(_write(tmp_path / "e.ini", "seqLength=3\n"))
    # the name and imDir are file names beside the sequence, never paths out of its folders
    for key, value in (("name", "../x"), ("name", ""), ("name", "a/b"), ("imDir", "..")):
        with pytest.raises(MotFormatError, match=f"{key}=.* must be one plain file name"):
            read_seqinfo(_write(tmp_path / "f.ini", f"[Sequence]\nseqLength=3\n{key}={value}\n"))
    with pytest.raises(MotFormatError, match="is more than 10000000 frames"):
        read_seqinfo(_write(tmp_path / "g.ini", "[Sequence]\nseqLength=1000000000000\n"))
    (tmp_path / "h.ini").write_bytes(b"\xb3\xff[Sequence]\n")
    with pytest.raises(MotFormatError, match="not a text file"):
        read_seqinfo(tmp_path / "h.ini")
    # '%' is a character of the value, not ConfigParser's interpolation
    assert (
        read_seqinfo(_write(tmp_path / "i.ini", "[Sequence]\nseqLength=3\nname=a%b\n")).name
        == "a%b"
    )


def _video(path, n, size=(32, 24)):
    import cv2

    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, size)
    for k in range(n):
        w.write(np.full((size[1], size[0], 3), 10 * k, np.uint8))
    w.release()
    return path


def test_video_plus_gt(tmp_path):
    video = _video(tmp_path / "clip.mp4", 4)
    gt = _write(tmp_path / "clip_gt.txt", "1,1,1,1,5,5,1\n4,1,2,2,5,5,1\n")
    seq = load_mot_sequence(video, gt=gt)
    assert (seq.name, seq.n_frames, seq.scale, seq.width) == ("clip", 4, 1.0, 32)
    with pytest.raises(SequenceError, match="give its ground-truth file"):
        load_mot_sequence(video)
    # a folder given as the ground-truth file was reported as not existing
    with pytest.raises(SequenceError, match=r"ground-truth file .* is a folder, not a file"):
        load_mot_sequence(video, gt=tmp_path)
    with pytest.raises(SequenceError, match=r"has no ground truth \(.* is a folder, not a file"):
        load_mot_sequence(_mot_folder(tmp_path / "seq"), gt=tmp_path)
    beyond = _write(tmp_path / "long.txt", "1,1,1,1,5,5,1\n5,1,2,2,5,5,1\n")
    with pytest.raises(MotFormatError, match=r"long.txt line 2: frame 5 is beyond .* 4 frames"):
        load_mot_sequence(video, gt=beyond)
    with pytest.raises(SequenceError, match=r"must be a number in \[0.001, 1000\], got -1.0"):
        load_mot_sequence(video, gt=gt, scale=-1.0)
    with pytest.raises(SequenceError, match=r"must be a number in \[0.001, 1000\], got 1e\+308"):
        load_mot_sequence(video, gt=gt, scale=1e308)  # overflowed the boxes to inf


def test_video_gt_from_another_sequence(tmp_path):
    video = _video(tmp_path / "clip.mp4", 4)
    d = _mot_folder(tmp_path / "seq", n_frames=3, img=False)
    with pytest.raises(SequenceError, match=r"has 4 frames but .* seqLength=3"):
        load_mot_sequence(video, gt=d / "gt" / "gt.txt")
    d2 = _mot_folder(tmp_path / "seq2", n_frames=4, img=False)
    seq = load_mot_sequence(video, gt=d2 / "gt" / "gt.txt")  # seqinfo 16x12, video 32x24
    assert seq.name == "Tiny" and seq.scale == 2.0
    _write(d2 / "seqinfo.ini", "[Sequence]\nseqLength=4\nimWidth=16\nimHeight=16\n")
    with pytest.raises(SequenceError, match="another aspect ratio"):
        load_mot_sequence(video, gt=d2 / "gt" / "gt.txt")


def test_frames_folder_named_by_imdir_is_the_one_reported_missing(tmp_path):
    """seqinfo.ini's imDir names another folder than the img1/ that is there: the sequence
    has no frames, and the message names the folder looked for (it said 'no img1/ folder'
    beside an img1/ folder)."""
    d = _mot_folder(tmp_path / "s")
    ini = (d / "seqinfo.ini").read_text().replace("imDir=img1", "imDir=frames")
    (d / "seqinfo.ini").write_text(ini)
    seq = load_mot_sequence(d)
    assert seq.frames is None and seq.im_dir == d / "frames"
    with pytest.raises(VideoError, match=r"no .*[/\\]s[/\\]frames/ folder and no video"):
        seq.open()


def test_seqinfo_numbers_as_written(tmp_path):
    """seqLength=6.0 was 'not a number' (int() of the text) and frameRate=inf was taken; now a
    whole number written with a decimal point is that number, a non-finite frame rate is
    refused by name, and what Python reads but a number in a file is not (1_0, Arabic-Indic
    digits) is refused."""
    info = read_seqinfo(
        _write(tmp_path / "a.ini", "[Sequence]\nseqLength=6.0\nimWidth=64.\nimHeight=4.8e1\n")
    )
    assert (info.seq_length, info.im_width, info.im_height) == (6, 64, 48)
    assert isinstance(info.seq_length, int) and isinstance(info.im_width, int)
    assert (
        read_seqinfo(
            _write(tmp_path / "b.ini", "[Sequence]\nseqLength=3\nframeRate=29.97\n")
        ).frame_rate
        == 29.97
    )
    for key, value, match in (
        ("frameRate", "inf", r"frameRate='inf' must be a finite number > 0"),
        ("frameRate", "-inf", r"frameRate='-inf' must be a finite number > 0"),
        ("frameRate", "nan", r"frameRate='nan' must be a finite number > 0"),
        ("frameRate", "1e999", r"frameRate='1e999' must be a finite number > 0"),
        ("frameRate", "0", r"frameRate='0' must be a finite number > 0"),
        ("imWidth", "6.5", r"imWidth='6.5' must be a whole number"),
        ("imWidth", "inf", r"imWidth='inf' must be a whole number"),
        ("imHeight", "1_0", r"imHeight='1_0' is not a number"),
        ("imHeight", "\u0661\u0662", r"imHeight='\u0661\u0662' is not a number"),
    ):
        with pytest.raises(MotFormatError, match=match):
            read_seqinfo(_write(tmp_path / "c.ini", f"[Sequence]\nseqLength=3\n{key}={value}\n"))
    with pytest.raises(MotFormatError, match=r"seqLength='6.5' must be a whole number"):
        read_seqinfo(_write(tmp_path / "d.ini", "[Sequence]\nseqLength=6.5\n"))


def test_seqinfo_imext_names_the_frames(tmp_path):
    """imExt was read and ignored: a folder of .png frames under imExt=.jpg was taken, and a
    folder holding both a .jpg and a .png of every frame was 'twice seqLength'. Now the frames
    are the imDir files with that extension (what the MOTChallenge devkit reads), a folder
    without any is refused naming imExt, and an imExt that is not an image extension is
    refused; without imExt every image file is a frame, as before."""
    import cv2

    d = _mot_folder(tmp_path / "png")  # imExt=.png, .png frames
    assert [f.suffix for f in load_mot_sequence(d).frames] == [".png"] * 3
    for k in range(1, 4):  # a .jpg copy of every frame beside it
        cv2.imwrite(str(d / "img1" / f"{k:06d}.jpg"), np.full((12, 16, 3), k, np.uint8))
    seq = load_mot_sequence(d)
    assert [f.name for f in seq.frames] == ["000001.png", "000002.png", "000003.png"]
    ini = d / "seqinfo.ini"
    ini.write_text(ini.read_text().replace("imExt=.png", "imExt=.JPG"))
    assert [f.suffix for f in load_mot_sequence(d).frames] == [".jpg"] * 3
    for f in (d / "img1").glob("*.jpg"):
        f.unlink()
    with pytest.raises(
        SequenceError, match=r"img1 holds no \.JPG frame .*imExt=\.JPG.* it holds 3 \.png file"
    ):
        load_mot_sequence(d)
    for bad in ("png", ".txt", ""):
        ini.write_text(ini.read_text().split("imExt=")[0] + f"imExt={bad}\n")
        with pytest.raises(
            MotFormatError, match=f"imExt='{re.escape(bad)}' is not an image file extension"
        ):
            load_mot_sequence(d)
    ini.write_text(ini.read_text().split("imExt=")[0])
    assert read_seqinfo(ini).im_ext is None
    assert len(load_mot_sequence(d).frames) == 3


def test_frame_folder_plus_gt_loads_as_a_video_does(tmp_path):
    """A folder of frames (what `torchtrack track` reads) with a ground-truth file: its frames,
    its size, and the scale from the seqinfo.ini beside the GT, as for a video; a
    MOTChallenge folder is not taken for one."""
    import cv2

    from torchtrack.io.mot import is_frame_folder

    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(4):
        cv2.imwrite(str(frames / f"{k + 1:06d}.png"), np.full((24, 32, 3), 10 * k, np.uint8))
    gt = _write(tmp_path / "clip_gt.txt", "1,1,1,1,5,5,1\n4,1,2,2,5,5,1\n")
    seq = load_mot_sequence(frames, gt=gt)
    assert (seq.name, seq.n_frames, seq.scale, seq.width, seq.height) == ("frames", 4, 1.0, 32, 24)
    assert seq.video is None and [p.name for p in seq.frames] == [
        f"{k:06d}.png" for k in (1, 2, 3, 4)
    ]
    with seq.open() as src:
        assert sum(1 for _ in src.items()) == 4
    d = _mot_folder(tmp_path / "seq", n_frames=4, img=False)  # seqinfo 16x12: frames 2x
    seq = load_mot_sequence(frames, gt=d / "gt" / "gt.txt")
    assert seq.name == "Tiny" and seq.scale == 2.0
    d3 = _mot_folder(tmp_path / "seq3", n_frames=3, img=False)
    with pytest.raises(SequenceError, match=r"frames has 4 frames but .* seqLength=3"):
        load_mot_sequence(frames, gt=d3 / "gt" / "gt.txt")
    beyond = _write(tmp_path / "long.txt", "5,1,2,2,5,5,1\n")
    with pytest.raises(MotFormatError, match="frame 5 is beyond"):
        load_mot_sequence(frames, gt=beyond)
    assert is_frame_folder(frames) and not is_frame_folder(d) and not is_frame_folder(tmp_path)
    with pytest.raises(SequenceError, match="not a MOTChallenge folder"):
        load_mot_sequence(frames)  # without its ground truth: no frame folder reading
