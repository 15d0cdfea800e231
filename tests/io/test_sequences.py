"""Sequence loaders: the real dev-set layouts, and every malformed-input path."""

from __future__ import annotations

import math
import warnings

import cv2
import numpy as np
import pytest
import torch

from torchtrack.errors import ConfigError, SequenceError
from torchtrack.io.sequences import (
    detect_layout,
    find_sequences,
    load_bobot,
    load_frames_csv,
    load_otb,
    load_sequence,
    load_video_csv,
    load_vot,
    parse_box_file,
    read_box_csv,
)


def _frames(folder, n, start=1, fmt="{:04d}.png", skip=()):
    folder.mkdir(parents=True, exist_ok=True)
    for k in range(start, start + n):
        if k in skip:
            continue
        cv2.imwrite(str(folder / fmt.format(k)), np.full((12, 16, 3), k, np.uint8))
    return folder


# ---------------------------------------------------------------------------------------------
# Real data
# ---------------------------------------------------------------------------------------------
def test_dev_set_is_found_with_every_layout(data_dir):
    seqs = {s.name: s for s in find_sequences(data_dir / "tracking")}
    assert set(seqs) == {
        "bobot_pedestrian", "Couple", "Crossing", "David", "DragonBaby", "FaceOcc1",
        "Freeman1", "Jogging1", "MotorRolling", "RedTeam", "Skiing", "Surfer",
    }  # fmt: skip
    expected_len = {"David": 471, "Jogging1": 307, "FaceOcc1": 892, "bobot_pedestrian": 1017}
    for name, n in expected_len.items():
        assert len(seqs[name]) == n and len(seqs[name].frames) == n


def test_otb_david_starts_at_0300_and_is_1_based(data_dir):
    (david,) = load_otb(data_dir / "tracking" / "otb" / "David")
    assert david.first_frame == 300 and david.frames[0].name == "0300.jpg"
    assert david.frames[-1].name == "0770.jpg"
    # groundtruth line 1 is "129,80,64,78" (1-based) -> 0-based x, y
    assert david.boxes[0].tolist() == [128.0, 79.0, 64.0, 78.0]
    assert david.layout == "otb" and bool(david.present.all())


@pytest.mark.parametrize(
    ("name", "first"),
    [
        ("Couple", [50.0, 46.0, 25.0, 62.0]),  # tab delimited
        ("FaceOcc1", [117.0, 68.0, 114.0, 162.0]),  # tab + CRLF
        ("Jogging1", [110.0, 97.0, 25.0, 101.0]),  # no final newline
    ],
)
def test_otb_delimiters(data_dir, name, first):
    (s,) = load_otb(data_dir / "tracking" / "otb" / name)
    assert s.boxes[0].tolist() == first


def test_bobot_corners_and_nan_rows(data_dir):
    s = load_bobot(data_dir / "tracking" / "bobot_pedestrian")
    assert s.frames[0].name == "img0002.jpg" and s.first_frame == 2 and len(s) == 1017
    # line 1: 107.93,46.553,163.62,202.57 (x1, y1, x2, y2)
    assert s.boxes[0].tolist() == pytest.approx([107.93, 46.553, 163.62 - 107.93, 202.57 - 46.553])
    absent = (~s.present).nonzero().flatten().tolist()
    lines = [*range(674, 689), 741, 742, *range(908, 913), 938]  # README, 1-based lines
    assert absent == [k - 1 for k in lines]
    assert torch.isnan(s.boxes[absent]).all()


def test_sequence_open_yields_matching_frames(data_dir):
    (s,) = load_otb(data_dir / "tracking" / "otb" / "Skiing")
    head = s.head(3)
    assert len(head) == 3 and len(head.frames) == 3
    frames = list(head.open())
    assert len(frames) == 3 and frames[0].shape == (3, 360, 640)


# ---------------------------------------------------------------------------------------------
# Synthetic layouts
# ---------------------------------------------------------------------------------------------
def test_otb_mixed_delimiters_nan_rows_and_multi_target(tmp_path):
    seq = tmp_path / "Jog"
    _frames(seq / "img", 4)
    (seq / "groundtruth_rect.1.txt").write_text(
        "1,2,3,4\n2\t3\t4\t5\n3 4  5 6\nNaN,NaN,NaN,NaN\n\n"
    )
    (seq / "groundtruth_rect.2.txt").write_text("5,5,2,2\n5,5,0,0\n5,5,2,2\n5,5,2,2\n")
    a, b = load_sequence(seq)
    assert (a.name, b.name) == ("Jog-1", "Jog-2")
    assert a.boxes[:3].tolist() == [[0, 1, 3, 4], [1, 2, 4, 5], [2, 3, 5, 6]]
    assert torch.isnan(a.boxes[3]).all()
    assert torch.isnan(b.boxes[1]).all()  # zero size = absent (documented rule)
    assert a.present.tolist() == [True, True, True, False]


def test_vot_polygons_to_axis_aligned_boxes(tmp_path):
    seq = tmp_path / "ball"
    _frames(seq / "color", 3, fmt="{:08d}.jpg")
    (seq / "groundtruth.txt").write_text(
        "10,20,30,20,30,50,10,50\n"  # axis-aligned rectangle as polygon
        "15.5,10,25,20,15.5,30,6,20\n"  # rotated diamond
        "0\n"  # VOT: target absent
    )
    assert detect_layout(seq) == "vot"
    (s,) = load_sequence(seq)
    assert s.boxes[0].tolist() == [10, 20, 20, 30]
    assert s.boxes[1].tolist() == [6, 10, 19, 20]
    assert torch.isnan(s.boxes[2]).all()
    assert load_vot(seq).name == "ball"


def test_frames_csv_with_header_sparse_frames_and_visible(tmp_path):
    seq = tmp_path / "mine"
    _frames(seq / "frames", 4, start=0, fmt="frame_{:03d}.png")
    (seq / "groundtruth.csv").write_text(
        "frame,x,y,w,h,confidence,visible\n0,1,2,3,4,0.9,1\n2,5,6,7,8,0.1,0\n3,1,1,2,2,1,1\n"
    )
    (s,) = load_sequence(seq)
    assert s.layout == "csv" and len(s) == 4
    assert s.boxes[0].tolist() == [1, 2, 3, 4]
    assert s.present.tolist() == [True, False, False, True]  # frame 1 missing, frame 2 invisible


def test_csv_without_header_and_corner_header(tmp_path):
    p = tmp_path / "a.csv"
    p.write_text("1,2,3,4\n5,6,7,8\n")
    assert read_box_csv(p).tolist() == [[1, 2, 3, 4], [5, 6, 7, 8]]
    p.write_text("nan,nan,nan,nan\n5,6,7,8\n")  # a NaN first row is not a header
    assert read_box_csv(p)[1].tolist() == [5, 6, 7, 8]
    q = tmp_path / "b.csv"
    q.write_text("x1,y1,x2,y2\n1,2,4,6\n")
    assert read_box_csv(q).tolist() == [[1, 2, 3, 4]]


def test_video_with_csv(tmp_path):
    path = tmp_path / "clip.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (32, 24))
    if not w.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG AVI files")
    for _ in range(4):
        w.write(np.zeros((24, 32, 3), np.uint8))
    w.release()
    (tmp_path / "clip.csv").write_text("x,y,w,h\n1,1,5,5\n2,1,5,5\n3,1,5,5\n4,1,5,5\n")
    (s,) = find_sequences(tmp_path)
    assert s.layout == "video" and s.name == "clip" and len(s) == 4 and s.frames is None
    assert len(list(s.open())) == 4
    (tmp_path / "clip.csv").write_text("1,1,5,5\n")
    with pytest.raises(SequenceError, match=r"clip.csv has 1 box rows but video .* has 4 frames"):
        load_video_csv(path)
    with pytest.raises(SequenceError, match="has no box CSV"):
        load_video_csv(path, tmp_path / "other.csv")


# ---------------------------------------------------------------------------------------------
# Bad input
# ---------------------------------------------------------------------------------------------
@pytest.fixture
def otb3(tmp_path):
    seq = tmp_path / "S"
    _frames(seq / "img", 3)
    return seq


def test_fewer_or_more_rows_than_frames(otb3):
    gt = otb3 / "groundtruth_rect.txt"
    gt.write_text("1,1,4,4\n1,1,4,4\n")
    with pytest.raises(SequenceError, match=r"groundtruth_rect.txt has 2 box rows but .* 3 frames"):
        load_otb(otb3)
    gt.write_text("1,1,4,4\n" * 5)
    with pytest.raises(SequenceError, match=r"has 5 box rows but frame folder .* has 3 frames"):
        load_otb(otb3)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        (s,) = load_otb(otb3, on_mismatch="truncate")
    assert len(s) == 3 and "keeping the first 3" in str(rec[0].message)
    with pytest.raises(ConfigError, match="on_mismatch"):
        load_otb(otb3, on_mismatch="pad")


def test_non_numeric_blank_and_wrong_width_lines(otb3):
    gt = otb3 / "groundtruth_rect.txt"
    gt.write_text("1,1,4,4\n1,one,4,4\n1,1,4,4\n")
    with pytest.raises(SequenceError, match=r"groundtruth_rect.txt line 2 is not numeric"):
        load_otb(otb3)
    gt.write_text("1,1,4,4\n\n1,1,4,4\n")
    with pytest.raises(SequenceError, match="line 2 is blank"):
        load_otb(otb3)
    gt.write_text("1,1,4,4\n2_1,1,4,4\n1,1,4,4\n")  # float() read 2_1 as 21
    with pytest.raises(SequenceError, match="line 2 is not numeric: '2_1,1,4,4'"):
        load_otb(otb3)
    gt.write_text("1,1,4\n1,1,4,4\n1,1,4,4\n")
    with pytest.raises(SequenceError, match="line 1 has 3 values, expected 4"):
        load_otb(otb3)
    # an empty value between commas (or before the first) was skipped: five fields read as the
    # four of a box, every value after the gap one place early
    for row in ("1,,1,4,4", "1, ,1,4,4", ",1,1,4,4", "1,1,4,4,,9"):
        gt.write_text(f"1,1,4,4\n{row}\n1,1,4,4\n")
        with pytest.raises(SequenceError, match=f"line 2 has an empty value .*: '{row}'"):
            load_otb(otb3)
    gt.write_text("1,1,4,4,\n1, 1\t4 4\n1,1,4,4\n")  # a trailing comma, mixed separators
    assert load_otb(otb3)[0].boxes[:2].tolist() == [[0, 0, 4, 4]] * 2
    gt.write_text("\n\n")
    with pytest.raises(SequenceError, match="is empty"):
        load_otb(otb3)
    gt.write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(SequenceError, match="not a text file"):
        load_otb(otb3)


def test_missing_frame_in_numbering(tmp_path):
    seq = tmp_path / "G"
    _frames(seq / "img", 5, skip={3})
    (seq / "groundtruth_rect.txt").write_text("1,1,4,4\n" * 4)
    with pytest.raises(SequenceError, match=r"frame number\(s\) 3 missing before 0004.png"):
        load_otb(seq)


def test_frame_number_given_twice(tmp_path):
    """Two files with one number (a .jpg and a .png, img1 and img01) said 'frame number(s)
    2..0 missing'."""
    seq = tmp_path / "G"
    _frames(seq / "img", 3)
    (seq / "img" / "0001.jpg").write_bytes((seq / "img" / "0001.png").read_bytes())
    (seq / "groundtruth_rect.txt").write_text("1,1,4,4\n" * 4)
    with pytest.raises(
        SequenceError, match=r"0001.jpg and 0001.png both carry frame number 1 \(two frames"
    ):
        load_otb(seq)


def test_empty_folders_and_non_sequences(tmp_path):
    seq = tmp_path / "E"
    (seq / "img").mkdir(parents=True)
    (seq / "groundtruth_rect.txt").write_text("1,1,4,4\n")
    with pytest.raises(SequenceError, match="holds no image file"):
        load_otb(seq)
    (tmp_path / "nothing").mkdir()
    with pytest.raises(SequenceError, match="no tracking sequence found"):
        find_sequences(tmp_path / "nothing")
    with pytest.raises(SequenceError, match="is not a tracking sequence"):
        load_sequence(tmp_path / "nothing")
    with pytest.raises(SequenceError, match="does not exist"):
        find_sequences(tmp_path / "missing")
    with pytest.raises(SequenceError, match=r"has no gt\.txt"):
        load_bobot(tmp_path / "nothing")


def test_bad_csvs(tmp_path):
    frames = _frames(tmp_path / "frames", 3)
    p = tmp_path / "gt.csv"
    p.write_text("a,b,c,d\n1,2,3,4\n")
    with pytest.raises(SequenceError, match="lacks the columns"):
        load_frames_csv(frames, p)
    p.write_text("frame,x,y,w,h\n0,1,1,2,2\n0,1,1,2,2\n")
    with pytest.raises(SequenceError, match="more than once: frame 0 on lines 2 and 3"):
        read_box_csv(p)
    # a frame index that is not a whole number: 1.5 was read as frame 1, inf was an
    # OverflowError traceback
    for frame in ("1.5", "inf", "-inf", "1e400"):
        p.write_text(f"frame,x,y,w,h\n0,1,1,2,2\n{frame},1,1,2,2\n")
        with pytest.raises(SequenceError, match=rf"gt\.csv line 3: frame '{frame}' is not a whole"):
            read_box_csv(p)
    # a frame index beyond any sequence, without a length to check it against: 1e300 was a
    # TypeError from torch.full, 1e9 a table of 32 GB
    for frame in ("1e300", "1000000000"):
        p.write_text(f"frame,x,y,w,h\n0,1,1,2,2\n{frame},1,1,2,2\n")
        with pytest.raises(SequenceError, match=rf"gt\.csv line 3: frame '{frame}' is beyond any"):
            read_box_csv(p)
    p.write_text("frame,x,y,w,h\n0,1,1,2,2\n7,1,1,2,2\n")
    with pytest.raises(SequenceError, match="row for frame 7 but the sequence has 3 frames"):
        load_frames_csv(frames, p)
    p.write_text("x,y,w,h\n1,1,2,2\n1,x,2,2\n")
    with pytest.raises(SequenceError, match="line 3 is not numeric"):
        read_box_csv(p)
    # float() reads 1_0 as 10: a typo became a box at x=10, or frame 10
    for body, no in (
        ("frame,x,y,w,h\n0,1,1,2,2\n1,1_0,1,2,2\n", 3),  # a box value
        ("frame,x,y,w,h\n0,1,1,2,2\n1_0,1,1,2,2\n", 3),  # the frame column
        ("x,y,w,h,visible\n1,1,2,2,0_0\n", 2),  # the visible column
    ):
        p.write_text(body)
        with pytest.raises(SequenceError, match=rf"gt\.csv line {no} is not numeric"):
            read_box_csv(p)
    # x1,y1,x2,y2 columns with the corners reversed: a negative width, read as absent silently
    for row, axis in (("5,1,2,4", "x2 < x1"), ("1,5,2,4", "y2 < y1")):
        p.write_text(f"frame,x1,y1,x2,y2\n0,1,1,3,3\n1,{row}\n")
        with pytest.raises(SequenceError, match=rf"gt\.csv line 3: corners .* reversed \({axis}\)"):
            read_box_csv(p)
    p.write_text("x1,y1,x2,y2,visible\n1,1,3,3,1\n5,1,2,4,0\n")  # hidden rows are not read
    assert read_box_csv(p)[0].tolist() == [1, 1, 2, 2] and read_box_csv(p)[1].isnan().all()
    p.write_text("x,y,w,h,label\n1,1,2,2,car_1\n")  # columns it does not read may hold any text
    assert read_box_csv(p).tolist() == [[1, 1, 2, 2]]
    p.write_text("")
    with pytest.raises(SequenceError, match="is empty"):
        read_box_csv(p)
    # a Latin-1 byte, a field past the csv module's limit: UnicodeDecodeError and csv.Error
    # tracebacks
    p.write_bytes("x,y,w,h\n1,1,2,2\n# caf\u00e9\n".encode("latin-1"))
    with pytest.raises(SequenceError, match=r"gt\.csv is not a text file \(not UTF-8\)"):
        read_box_csv(p)
    p.write_text('x,y,w,h\n"' + "1" * 200_000 + '",1,2,2\n')
    with pytest.raises(SequenceError, match=r"gt\.csv is not a CSV of boxes: field larger"):
        read_box_csv(p)


def test_bobot_reversed_corners_name_the_file_and_line(tmp_path):
    """A corner row with x2 < x1 (or y2 < y1) had a negative width, read as "target absent"
    without a word; BoBoT's own absent marker (NaN rows) and zero-size rows stay absent."""
    p = tmp_path / "gt.txt"
    p.write_text("10,20,50,120\nNaN,NaN,NaN,NaN\n50,20,10,120\n")
    with pytest.raises(
        SequenceError, match=r"gt\.txt line 3: corners .* = 50,20,10,120 are reversed \(x2 < x1\)"
    ):
        parse_box_file(p, "xyxy")
    p.write_text("10,20,50,120\n10,120,50,20\n")
    with pytest.raises(SequenceError, match=r"line 2: .* reversed \(y2 < y1\)"):
        parse_box_file(p, "xyxy")
    p.write_text("10,20,50,120\nNaN,NaN,NaN,NaN\n10,20,10,120\n")
    b = parse_box_file(p, "xyxy")
    assert b[0].tolist() == [10, 20, 40, 100] and torch.isnan(b[1:]).all()


def test_parse_box_file_formats(tmp_path):
    p = tmp_path / "b.txt"
    p.write_text("1 2 3 4\n")
    assert parse_box_file(p, "xywh", one_based=True).tolist() == [[0, 1, 3, 4]]
    assert parse_box_file(p, "xyxy").tolist() == [[1, 2, 2, 2]]
    p.write_text("1,2,3,4,5,6,7,nan\n")
    assert math.isnan(parse_box_file(p, "polygon")[0, 0])
    p.write_text("0\nnan\n1,2,3,4\n")  # VOT's one-value absent markers
    assert parse_box_file(p, "polygon")[:2].isnan().all()
    # any other single value (a cut line, a results file's 1 / 2 marker) was read as absent
    for value in ("5", "1", "2"):
        p.write_text(f"1,2,3,4\n{value}\n")
        with pytest.raises(SequenceError, match=f"b.txt line 2 is the single value {value}: "):
            parse_box_file(p, "polygon")
    with pytest.raises(ConfigError, match="box_format"):
        parse_box_file(p, "cxcywh")
