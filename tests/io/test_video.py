"""Frame sources: folders, file lists, video files, cameras; colour modes; bad frames."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest
import torch

from torchtrack.errors import ConfigError, DataError, VideoError
from torchtrack.io.video import (
    FrameSource,
    list_image_files,
    natural_key,
    open_source,
    read_image,
    to_numpy_bgr,
)


def _write(path, img):
    assert cv2.imwrite(str(path), img)


@pytest.fixture
def folder(tmp_path):
    """Three 8x10 frames: pure red, pure blue (as BGR on disk), and a grayscale ramp."""
    red = np.zeros((8, 10, 3), np.uint8)
    red[:, :, 2] = 200  # BGR: red channel last
    blue = np.zeros((8, 10, 3), np.uint8)
    blue[:, :, 0] = 150
    gray = np.tile(np.arange(10, dtype=np.uint8) * 20, (8, 1))
    _write(tmp_path / "f1.png", red)
    _write(tmp_path / "f2.png", blue)
    _write(tmp_path / "f10.png", gray)
    (tmp_path / "notes.txt").write_text("not an image")
    return tmp_path


def test_folder_yields_rgb_uint8_chw_in_natural_order(folder):
    with open_source(folder) as src:
        frames = list(src)
        assert src.kind == "folder" and len(src) == 3 and src.fps is None
        assert [p.name for p in src.files] == ["f1.png", "f2.png", "f10.png"]
    assert all(f.dtype == torch.uint8 and f.shape == (3, 8, 10) for f in frames)
    assert frames[0][0].eq(200).all() and frames[0][1:].eq(0).all()  # red is channel 0
    assert frames[1][2].eq(150).all() and frames[1][:2].eq(0).all()  # blue is channel 2
    # grayscale expanded to three equal channels
    assert torch.equal(frames[2][0], frames[2][1]) and torch.equal(frames[2][0], frames[2][2])
    assert frames[2][0, 0].tolist() == [20 * i for i in range(10)]


def test_color_modes(folder):
    keep = list(FrameSource(folder, color="keep"))
    assert [f.shape[0] for f in keep] == [3, 3, 1]
    gray = list(FrameSource(folder, color="gray"))
    assert [f.shape[0] for f in gray] == [1, 1, 1]
    # BT.601 luma of pure red 200 = 0.299 * 200
    assert abs(int(gray[0][0, 0, 0]) - round(0.299 * 200)) <= 1
    with pytest.raises(ConfigError, match="color must be one of"):
        FrameSource(folder, color="bgr")


def test_unreadable_frame_is_counted_and_skipped(folder):
    (folder / "f2.png").write_bytes(b"this is not a png")
    src = FrameSource(folder)
    items = list(src.items())
    assert [i for i, _ in items] == [0, 1, 2]
    assert items[1][1] is None and items[0][1] is not None
    assert src.n_bad == 1 and src.bad_frames[0].index == 1
    assert "cannot be decoded" in src.bad_frames[0].reason
    src2 = FrameSource(folder)
    assert len(list(src2)) == 2 and src2.n_bad == 1


def test_file_list_source(folder):
    src = FrameSource([folder / "f10.png", folder / "f1.png"])
    assert src.kind == "files"
    frames = list(src)
    assert frames[1][0].eq(200).all()
    with pytest.raises(VideoError, match="list of frame files is empty"):
        FrameSource([])


def test_video_file_roundtrip(tmp_path):
    path = tmp_path / "clip.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (32, 24))
    if not w.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG AVI files")
    for k in range(5):
        img = np.zeros((24, 32, 3), np.uint8)
        img[:, :, 2] = 40 * k  # red grows
        w.write(img)
    w.release()
    with open_source(path) as src:
        frames = list(src)
        assert src.kind == "video" and len(src) == 5 and src.fps == pytest.approx(10.0)
        assert not src.ended_early and src.n_bad == 0
    assert len(frames) == 5 and frames[0].shape == (3, 24, 32)
    reds = [float(f[0].float().mean()) for f in frames]
    assert reds == pytest.approx([40 * k for k in range(5)], abs=6)  # lossy MJPG
    assert max(float(f[2].float().mean()) for f in frames) < 6


def test_a_motchallenge_sequence_folder_points_to_its_img1_folder(tmp_path):
    """A MOTChallenge sequence keeps its frames in img1/ beside gt/ and seqinfo.ini: given the
    sequence's folder, the error says where the frames are instead of only that there are
    none."""
    seq = tmp_path / "TUD-Toy"
    (seq / "img1").mkdir(parents=True)
    (seq / "gt").mkdir()
    (seq / "seqinfo.ini").write_text("[Sequence]\nname=TUD-Toy\nimDir=img1\n")
    cv2.imwrite(str(seq / "img1" / "000001.jpg"), np.zeros((8, 8, 3), np.uint8))
    img1 = re.escape(str(seq / "img1"))
    with pytest.raises(
        VideoError,
        match=rf"holds no image file .*; it looks like a MOTChallenge sequence: give its img1/ "
        rf"folder, {img1}$",
    ):
        FrameSource(seq)
    with FrameSource(seq / "img1") as src:
        assert len(src) == 1


def test_sources_that_cannot_be_opened(tmp_path):
    with pytest.raises(VideoError, match="does not exist"):
        FrameSource(tmp_path / "missing.mp4")
    # a path that exists but is neither a file nor a folder (a device) is not called missing
    with pytest.raises(VideoError, match="neither a video file nor a folder of frames"):
        FrameSource("/dev/null")
    (tmp_path / "empty").mkdir()
    with pytest.raises(VideoError, match=r"holds no image file \(looked for [^)]*\)$"):
        FrameSource(tmp_path / "empty")
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"\x00garbage" * 100)
    with pytest.raises(VideoError, match="cannot be opened"):
        FrameSource(bad)
    with pytest.raises(VideoError, match="camera index 97 cannot be opened"):
        FrameSource(97)
    with pytest.raises(VideoError, match="camera index 98"):
        FrameSource("98")


def test_camera_indices_and_folders_named_by_digits(tmp_path, monkeypatch):
    """A string of digits is a camera only where no file or folder has that name (a frame
    folder '2024' was opened as camera 2024); indices beyond a C int and Unicode digits
    ('²': int() refuses it) were a ValueError or cv2.error traceback."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "2024").mkdir()
    cv2.imwrite(str(tmp_path / "2024" / "0001.png"), np.zeros((8, 8, 3), np.uint8))
    src = FrameSource("2024")
    assert src.kind == "folder" and len(src) == 1
    for index in ("2147483648", "99999999999999999999"):
        with pytest.raises(VideoError, match=f"camera index {index} is out of range"):
            FrameSource(index)
    with pytest.raises(VideoError, match="video source ² does not exist"):
        FrameSource("²")


def test_negative_camera_index_is_refused():
    """A negative camera index reached OpenCV, whose V4L backend died of a segmentation fault
    on -1 and -2 where no camera is found (the whole process, no exception)."""
    for index in (-1, -2, -(2**31)):
        with pytest.raises(VideoError, match=f"camera index {index} is out of range"):
            FrameSource(index)


def test_read_image_errors_and_bgr_roundtrip(tmp_path, folder):
    with pytest.raises(DataError, match="does not exist"):
        read_image(tmp_path / "nope.png")
    (tmp_path / "bad.jpg").write_bytes(b"")
    with pytest.raises(DataError, match="is empty"):
        read_image(tmp_path / "bad.jpg")
    img = cv2.imread(str(folder / "f1.png"))
    assert np.array_equal(to_numpy_bgr(read_image(folder / "f1.png")), img)
    g = read_image(folder / "f10.png", color="keep")
    assert to_numpy_bgr(g).shape == (8, 10, 3)


def test_16bit_and_alpha_images(tmp_path):
    img16 = np.full((4, 5), 257 * 100, np.uint16)
    _write(tmp_path / "a.png", img16)
    assert read_image(tmp_path / "a.png", color="keep").unique().tolist() == [100]
    rgba = np.zeros((4, 5, 4), np.uint8)
    rgba[..., 1] = 77
    rgba[..., 3] = 255
    _write(tmp_path / "b.png", rgba)
    t = read_image(tmp_path / "b.png")
    assert t.shape == (3, 4, 5) and t[1].eq(77).all()


def test_natural_key_and_listing(tmp_path):
    assert sorted(["img10.jpg", "img2.jpg", "img1.jpg"], key=natural_key) == [
        "img1.jpg",
        "img2.jpg",
        "img10.jpg",
    ]
    with pytest.raises(VideoError, match="does not exist"):
        list_image_files(tmp_path / "nothing")


def test_real_grayscale_sequence_frame(data_dir):
    """Freeman1 is stored as grayscale JPEG: C = 3 equal channels by default, C = 1 with keep."""
    first = data_dir / "tracking" / "otb" / "Freeman1" / "img" / "0001.jpg"
    rgb = read_image(first)
    assert rgb.shape == (3, 240, 360)
    assert torch.equal(rgb[0], rgb[1]) and torch.equal(rgb[1], rgb[2])
    assert read_image(first, color="keep").shape == (1, 240, 360)


# ------------------------------------------------------------------ the one image decoder
def _jpeg(path, seed=0, size=(60, 80)):
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.integers(0, 255, (*size, 3), np.uint8), (5, 5), 2)
    assert cv2.imwrite(str(path), img)
    return path


@pytest.mark.parametrize("keep", [0.25, 0.5, 0.9, 0.99])
def test_truncated_jpeg_is_a_bad_frame_and_a_bad_crop(tmp_path, capfd, keep):
    """Issue 12: a JPEG cut short decoded as 80% grey and was tracked; the crop loader refused
    the same file. Now the one decoder refuses it for both, naming the file."""
    from torchtrack.io.crops import load_crops, read_gray

    good = _jpeg(tmp_path / "a.jpg")
    data = good.read_bytes()
    cut = tmp_path / "b.jpg"
    cut.write_bytes(data[: int(len(data) * keep)])
    src = FrameSource(tmp_path)
    frames = list(src.items())
    assert frames[0][1] is not None and frames[1][1] is None
    assert src.n_bad == 1 and "b.jpg is truncated" in src.bad_frames[0].reason
    with pytest.raises(DataError, match=r"b\.jpg is truncated"):
        read_image(cut)
    assert read_gray(cut) is None
    crops = load_crops(tmp_path, (60, 80))
    assert len(crops) == 1 and "truncated" in crops.skipped[0][1]
    assert "JPEG" not in capfd.readouterr().err  # libjpeg's own warning does not leak


def test_one_image_file_is_read_by_the_image_decoder(tmp_path):
    """A single image given as the source went to OpenCV's video reader: a truncated JPEG was
    one grey-filled frame and a float TIFF one black frame, both taken as read. Now they are
    the unreadable frames they are in a folder; a good image is one frame, as there."""
    good = _jpeg(tmp_path / "a.jpg")
    cut = tmp_path / "b.jpg"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    src = FrameSource(cut)
    assert list(src) == [] and src.n_bad == 1
    assert "b.jpg is truncated" in src.bad_frames[0].reason
    _write(tmp_path / "f.tiff", np.full((8, 10), 0.5, np.float32))
    src = FrameSource(tmp_path / "f.tiff")
    assert list(src) == [] and "unsupported image dtype float32" in src.bad_frames[0].reason
    src = FrameSource(good)
    (frame,) = list(src)
    assert src.name == str(good) and len(src) == 1
    assert torch.equal(frame, read_image(good))


def test_truncated_real_frame(data_dir, tmp_path):
    """A BoBoT frame cut to 25% of its bytes (the issue's case)."""
    src = data_dir / "tracking" / "bobot_pedestrian" / "frames" / "img0002.jpg"
    data = src.read_bytes()
    (tmp_path / "img0002.jpg").write_bytes(data[: len(data) // 4])
    (tmp_path / "img0003.jpg").write_bytes(data)
    s = FrameSource(tmp_path)
    assert [f is None for _, f in s.items()] == [True, False] and s.n_bad == 1


def test_decoder_errors_name_the_file(tmp_path, capfd):
    from torchtrack.io.video import decode_image, jpeg_is_truncated

    png = tmp_path / "p.png"
    assert cv2.imwrite(str(png), np.zeros((20, 20, 3), np.uint8) + 90)
    data = png.read_bytes()
    png.write_bytes(data[: len(data) // 2])
    with pytest.raises(DataError, match=r"p\.png cannot be decoded"):
        decode_image(png)
    assert "libpng" not in capfd.readouterr().err  # captured into the message instead
    (tmp_path / "e.jpg").write_bytes(b"")
    with pytest.raises(DataError, match="is empty"):
        decode_image(tmp_path / "e.jpg")
    (tmp_path / "d.jpg").mkdir()
    with pytest.raises(DataError, match="is a folder"):
        decode_image(tmp_path / "d.jpg")
    with pytest.raises(DataError, match="does not exist"):
        decode_image(tmp_path / "missing.png")
    good = _jpeg(tmp_path / "g.jpg").read_bytes()
    assert not jpeg_is_truncated(good) and not jpeg_is_truncated(good + b"trailing")
    assert jpeg_is_truncated(good[:-2]) and not jpeg_is_truncated(b"\x89PNG....")


def test_native_output_is_captured(capfd):
    import os

    from torchtrack.io.video import native_output

    with native_output() as log:
        os.write(2, b"libfoo: warning\n")
    assert log.text == "libfoo: warning\n" and log.first_line() == "libfoo: warning"
    os.write(2, b"after\n")
    assert capfd.readouterr().err == "after\n"


def test_a_broken_symbolic_link_is_an_unreadable_frame_in_its_place(tmp_path):
    """A folder of links whose third target is gone: the broken link is frame 2, unreadable;
    it was dropped from the listing, so the frames after it were numbered one too low."""
    src, linked = tmp_path / "src", tmp_path / "linked"
    src.mkdir()
    linked.mkdir()
    for i in range(4):
        cv2.imwrite(str(src / f"{i}.png"), np.full((8, 8, 3), 40 * i, np.uint8))
        (linked / f"{i}.png").symlink_to(src / f"{i}.png")
    (src / "2.png").unlink()
    with FrameSource(linked) as source:
        assert len(source) == 4
        seen = [(i, None if f is None else int(f[0, 0, 0])) for i, f in source.items()]
    assert seen == [(0, 0), (1, 40), (2, None), (3, 120)]
    (bad,) = source.bad_frames
    assert bad.index == 2 and "2.png is a broken symbolic link" in bad.reason


def test_a_source_that_is_no_path_list_or_camera_index_is_refused():
    """open_source(True) opened camera 1 (a bool is an int to Python); None, a float or bytes
    were a bare TypeError from pathlib."""
    from torchtrack.io.video import open_source

    for bad in (True, False):
        with pytest.raises(VideoError, match=r"a bool is not a camera index, got True|got False"):
            open_source(bad)
    for bad, name in ((None, "NoneType"), (1.5, "float"), (b"frames", "bytes")):
        with pytest.raises(VideoError, match=rf"source must be a path .* got {name}"):
            open_source(bad)
