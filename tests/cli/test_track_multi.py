"""``torchtrack track`` without --box: every target, identities, MOT output, bad input."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest
import torch

from torchtrack.cli import main


@pytest.fixture
def clip(tmp_path):
    """A 12-frame grey clip (no person in it)."""
    path = tmp_path / "grey.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (320, 240))
    for _ in range(12):
        w.write(np.full((240, 320, 3), 90, np.uint8))
    w.release()
    return path


@pytest.fixture
def dets(tmp_path):
    """Two walkers as MOTChallenge detections (1-based frames and pixels), scores in [0, 1]."""
    path = tmp_path / "det.txt"
    lines = []
    for f in range(1, 13):
        for k, (x0, y0) in enumerate(((20, 50), (200, 80))):
            x = x0 + 3 * f if k == 0 else x0 - 2 * f
            lines.append(f"{f},-1,{x + 1},{y0 + 1},20,60,0.97,-1,-1,-1")
    path.write_text("\n".join(lines) + "\n")
    return path


def test_external_detections_to_csv_and_mot(clip, dets, tmp_path, capsys):
    out, mot, vid = tmp_path / "t.csv", tmp_path / "t.txt", tmp_path / "t.mp4"
    rc = main(
        ["track", str(clip), "--detections", str(dets), "--out", str(out), "--mot", str(mot),
         "--video", str(vid), "--no-progress"]
    )  # fmt: skip
    assert rc == 0
    lines = out.read_text().splitlines()
    assert lines[0] == "frame,target,x,y,w,h,confidence,detected"
    rows = [r.split(",") for r in lines[1:]]
    assert {r[1] for r in rows} == {"1", "2"}  # two identities, kept to the end
    # confirmed on the second frame, the first frame's detections back-filled (`backfill`)
    assert {int(r[0]) for r in rows} == set(range(0, 12))
    m = [r.split(",") for r in mot.read_text().splitlines()]
    assert len(m) == len(rows) and all(len(r) == 10 for r in m)
    first = next(r for r in m if r[1] == "1")
    assert int(first[0]) == 1 and abs(float(first[2]) - 24.0) < 4  # 1-based frame and pixels
    assert vid.stat().st_size > 0
    said = capsys.readouterr().out
    assert "2 target(s)" in said and "ground plane" not in said  # outside detections: no line


def test_detections_of_another_video_warn(clip, dets, tmp_path, capsys):
    """Boxes from a wider video (x beyond the 320 px frames): a warning, the run goes on."""
    far = tmp_path / "far.txt"
    rows = [r.split(",") for r in dets.read_text().splitlines()]
    far.write_text("".join(",".join([*r[:2], str(float(r[2]) + 400), *r[3:]]) + "\n" for r in rows))
    with pytest.warns(UserWarning, match=r"24 of the 24 boxes of --detections .* 320x240 frames"):
        assert main(["track", str(clip), "--detections", str(far), "--no-progress"]) == 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the boxes of this clip: no warning
        assert main(["track", str(clip), "--detections", str(dets), "--no-progress"]) == 0


def test_video_without_any_target_writes_empty_tracks(clip, tmp_path, capsys):
    out, mot = tmp_path / "e.csv", tmp_path / "e.txt"
    rc = main(
        ["track", str(clip), "--out", str(out), "--mot", str(mot), "--no-progress",
         "--tracker", "multi:scan_min_scale=1.0"]
    )  # fmt: skip
    assert rc == 0
    assert out.read_text().splitlines() == ["frame,target,x,y,w,h,confidence,detected"]
    assert mot.read_text() == ""
    io = capsys.readouterr()
    assert "0 target(s)" in io.out and "no 'pedestrian' target was found" in io.err


def test_raw_scores_and_calibrated_scores(clip, dets, tmp_path):
    raw = tmp_path / "raw.txt"
    raw.write_text(dets.read_text().replace(",0.97,", ",55.0,"))
    out = tmp_path / "r.txt"
    assert main(["track", str(clip), "--detections", str(raw), "--mot", str(out), "-q"]) == 0
    assert len(out.read_text().splitlines()) == 24  # raw scores: relative to the best (all 12
    # frames of both: the first one back-filled)
    assert main(
        ["track", str(clip), "--detections", str(raw), "--det-min-score", "60",
         "--mot", str(out), "-q"]
    ) == 0  # fmt: skip
    assert out.read_text() == ""
    # a Platt calibration of the raw scores (as `torchtrack calibrate --scores --json` writes)
    import json

    import torch

    from torchtrack.learn import PlattCalibrator, calibrator_to_dict

    s = torch.tensor([10.0, 20.0, 50.0, 60.0, 80.0, 90.0], dtype=torch.float64)
    cal = PlattCalibrator().fit(s, torch.tensor([0, 0, 0, 0, 1, 1]))
    js = tmp_path / "cal.json"
    js.write_text(json.dumps(calibrator_to_dict(cal)))
    assert float(cal.predict_proba(torch.tensor([55.0], dtype=torch.float64))) < 0.5
    args = ["track", str(clip), "--detections", str(raw), "--mot", str(out), "-q"]
    assert main([*args, "--det-calibration", str(js)]) == 0
    assert out.read_text() == ""  # p(55) is below external_birth_threshold: nobody starts
    js.write_text("{}")
    assert main([*args, "--det-calibration", str(js)]) == 1


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--max-targets", "0"], "--max-targets must be >= 1"),
        (["--max-targets", "-2"], "--max-targets must be >= 1"),
        (["--scan-every", "0"], "--scan-every must be >= 1"),
        (["--box", "1,2,3,4", "--mot", "x.txt"], "belong"),
        (["--det-min-score", "3"], "apply to --detections"),
        (["--tracker", "multi:scan_every=0"], "scan_every must be >= 1"),
        (["--tracker", "multi:nonsense=1"], "unknown key"),
        (["--adapt", "global"], "--adapt"),
        (["--scan-workers", "-1"], "--scan-workers must be >= 0"),
        (["--scan-workers", "100000"], "more than 4 per CPU core"),
        (["--scan-workers", "2", "--box", "1,2,3,4"], "belong"),
    ],
)
def test_bad_multi_options(clip, tmp_path, capsys, extra, message):
    out = tmp_path / "o.csv"
    assert main(["track", str(clip), "--out", str(out), "-q", *extra]) == 1
    assert message in capsys.readouterr().err
    assert not out.exists() and not (tmp_path / "o.csv.part").exists()


def test_scan_workers_with_outside_detections_is_refused(clip, dets, tmp_path, capsys):
    out = tmp_path / "o.txt"
    argv = ["track", str(clip), "--detections", str(dets), "--mot", str(out), "-q"]
    assert main([*argv, "--scan-workers", "2"]) == 1
    assert "--detections FILE replaces them" in capsys.readouterr().err and not out.exists()
    assert main([*argv, "--scan-workers", "0"]) == 0


def test_scan_every_with_outside_detections(clip, dets, tmp_path):
    """scan_every k with --detections: the detections of every k-th frame go in, as
    track_sequence gives them (the detections of every frame went in while the tracker counted
    its misses as if it scanned every k-th frame: other tracks, without a word)."""
    from torchtrack.io.mot import read_mot
    from torchtrack.io.video import FrameSource
    from torchtrack.track.multi import MultiTargetTracker, track_sequence

    (tmp_path / "multi.toml").write_text("scan_every = 3\n")
    outs = []
    for k, extra in enumerate(
        (
            ["--scan-every", "3"],
            ["--tracker", "multi:scan_every=3"],
            ["--config", str(tmp_path / "multi.toml")],
            ["--scan-every", "1"],
        )
    ):
        out = tmp_path / f"o{k}.txt"
        argv = [
            "track",
            str(clip),
            "--detections",
            str(dets),
            "--mot",
            str(out),
            "-q",
            "--seed",
            "0",
        ]
        assert main([*argv, *extra]) == 0
        outs.append(out.read_text())
    assert outs[0] == outs[1] == outs[2] != outs[3]
    with FrameSource(clip) as src:
        ref = track_sequence(
            MultiTargetTracker(scan_every=3, generator=torch.Generator().manual_seed(0)),
            src,
            read_mot(dets, kind="det"),
        )
    got = read_mot(tmp_path / "o0.txt")
    assert len(ref) == len(got) > 0
    np.testing.assert_array_equal(got.frames, ref.frames)
    np.testing.assert_allclose(got.boxes, ref.boxes, atol=0.01)


def test_scan_workers_write_the_same_tracks(tmp_path, one_thread):
    """The bundled clip with its scans in two forked workers and in this process: the same
    files, byte for byte."""
    from torchtrack.track.scan_ahead import fork_available

    if not fork_available():
        pytest.skip("scan workers are forked processes (Linux)")
    files = {}
    for w in ("0", "2"):
        mot, csv = tmp_path / f"w{w}.txt", tmp_path / f"w{w}.csv"
        argv = ["track", "demo", "--mot", str(mot), "--out", str(csv), "--max-frames", "12"]
        assert main([*argv, "--scan-workers", w, "-q"]) == 0
        files[w] = (mot.read_bytes(), csv.read_bytes())
    assert files["0"] == files["2"] and files["0"][0].count(b"\n") > 10


def test_malformed_detections_name_file_and_line(clip, tmp_path, capsys):
    bad = tmp_path / "bad.txt"
    bad.write_text("1,-1,10,10,20,60,0.9,-1,-1,-1\n2,-1,10,ten,20,60,0.9,-1,-1,-1\n")
    out = tmp_path / "o.txt"
    assert main(["track", str(clip), "--detections", str(bad), "--mot", str(out), "-q"]) == 1
    err = capsys.readouterr().err
    assert "bad.txt line 2" in err and not out.exists()
    beyond = tmp_path / "late.txt"
    beyond.write_text("40,-1,10,10,20,60,0.9,-1,-1,-1\n")
    assert main(["track", str(clip), "--detections", str(beyond), "--mot", str(out), "-q"]) == 1
    assert "late.txt line 1" in capsys.readouterr().err


def test_wrong_class_model_finds_nothing_on_people(data_dir, tmp_path, capsys):
    """The vehicle model on the pedestrian demo clip: a clean run, few or no targets."""
    out = tmp_path / "v.txt"
    rc = main(
        ["track", "demo", "--detect", "vehicle", "--mot", str(out), "--max-frames", "3", "-q",
         "--tracker", "multi:scan_min_scale=0.8"]
    )  # fmt: skip
    assert rc == 0 and out.exists()


def test_the_readme_main_job_follows_the_clips_people_with_one_identity_each(
    data_dir, tmp_path, capsys
):
    """``torchtrack track demo`` (the README's main job, defaults, seed 0) against the PETS 2009
    ground truth of the clip's 70 frames (frames 601-670 of PETS09-S2L1, boxes x 0.625): each
    person it finds is one identity from start to end, it finds at least 6 of the 8, and its
    boxes lie on them (mean IoU of the matched pairs at least 0.65). Of the other two, person 6
    (42 px tall, at the far side) is never found, and person 7 enters in the clip's last 11
    frames: the tracker confirms it at the end and matches it on one frame, at IoU 0.55 before
    the box regressor and 0.49 after it (so "7 of 8" rested on that one frame)."""
    from scipy.optimize import linear_sum_assignment

    from torchtrack.boxes import box_iou_matrix

    out = tmp_path / "demo.mot.txt"
    assert main(["track", "demo", "--mot", str(out), "--no-progress"]) == 0
    # the summary says what ground plane the clip gave (PETS: about h = 0.23 y + 11)
    said = capsys.readouterr().out
    a = float(said.split("ground plane: h = ")[1].split(" y")[0])
    assert 0.15 < a < 0.3, said
    res = np.loadtxt(out, delimiter=",", ndmin=2)
    gt = np.loadtxt(data_dir / "mot" / "PETS09-S2L1" / "gt" / "gt.txt", delimiter=",")
    gt = gt[(gt[:, 0] > 600) & (gt[:, 0] <= 670) & (gt[:, 6] != 0)]
    gt[:, 2:6] *= 0.625  # the ground truth is for 768x576 frames, the clip is 480x360
    tracks_of: dict[int, set[int]] = {}
    people_of: dict[int, set[int]] = {}
    overlaps = []
    for f in np.unique(gt[:, 0]):
        g, r = gt[gt[:, 0] == f], res[res[:, 0] == f - 600]
        if not len(r):
            continue
        iou = box_iou_matrix(torch.from_numpy(g[:, 2:6]), torch.from_numpy(r[:, 2:6])).numpy()
        for i, j in zip(*linear_sum_assignment(-iou), strict=True):
            if iou[i, j] >= 0.5:
                tracks_of.setdefault(int(g[i, 1]), set()).add(int(r[j, 1]))
                people_of.setdefault(int(r[j, 1]), set()).add(int(g[i, 1]))
                overlaps.append(iou[i, j])
    assert len(np.unique(gt[:, 1])) == 8
    assert len(tracks_of) >= 6  # people found
    assert np.mean(overlaps) >= 0.65, np.mean(overlaps)
    assert all(len(t) == 1 for t in tracks_of.values())  # no identity switch
    assert all(len(p) == 1 for p in people_of.values())  # no identity shared by two people


@pytest.mark.parametrize("extra", [[], ["--tracker", "histogram", "--box", "100,60,40,80"]])
def test_a_run_that_fails_midway_leaves_no_output(tmp_path, capsys, extra):
    """Frames that change size at the third: an error naming it, and none of the outputs
    (a header-only CSV would look like a finished run without targets)."""
    frames = tmp_path / "frames"
    frames.mkdir()
    for i, (h, w) in enumerate([(240, 320)] * 2 + [(120, 160)] * 2):
        cv2.imwrite(str(frames / f"{i:04d}.png"), np.full((h, w, 3), 90, np.uint8))
    out, mot, vid = tmp_path / "o.csv", tmp_path / "o.txt", tmp_path / "o.mp4"
    argv = ["track", str(frames), "--out", str(out), "--video", str(vid), "-q", *extra]
    if not extra:
        argv += ["--mot", str(mot)]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "frame size changed" in err and "0002.png" in err and "Traceback" not in err
    assert {p.name for p in tmp_path.iterdir()} == {"frames"}


def test_gaps_filled_and_boxes_smoothed(clip, tmp_path):
    """A walker whose detections stop for three frames: without ``fill_gaps`` it is not
    reported there; with it (the default) the gap gets interpolated rows (``detected`` 0) under the same
    identity, every output still in frame order, and the video keeps every frame (the held
    frames are written at the end)."""
    dets = tmp_path / "gap.txt"
    lines = []
    for f in range(1, 13):
        for k, (x0, y0) in enumerate(((20, 50), (200, 80))):
            if k == 0 and 6 <= f <= 8:
                continue  # the first walker unseen on frames 6-8 (5-7 counted from 0)
            x = x0 + 3 * f if k == 0 else x0 - 2 * f
            lines.append(f"{f},-1,{x + 1},{y0 + 1},20,60,0.97,-1,-1,-1")
    dets.write_text("\n".join(lines) + "\n")

    def run(extra, name):
        out, vid = tmp_path / f"{name}.csv", tmp_path / f"{name}.avi"
        argv = ["track", str(clip), "--detections", str(dets), "--out", str(out)]
        assert main([*argv, "--video", str(vid), "--no-progress", *extra]) == 0
        rows = np.loadtxt(out, delimiter=",", skiprows=1, ndmin=2)
        cap = cv2.VideoCapture(str(vid))
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        cap.release()
        return rows, n

    plain, n_plain = run(["--tracker", "multi:fill_gaps=0,smooth_sigma=0,backfill=0"], "plain")
    filled, n_filled = run([], "filled")  # the defaults: gaps of <= 10 filled, sigma 4
    assert n_plain == n_filled == 12
    one = plain[:, 1] == plain[0, 1]
    seen = {5, 6, 7} & set(plain[one, 0].astype(int).tolist())  # the CSV counts from 0
    assert len(seen) < 3  # the plain run misses the walker somewhere in the gap
    f1 = filled[filled[:, 1] == plain[0, 1]]
    assert {5, 6, 7} <= set(f1[:, 0].astype(int).tolist())  # filled, same identity
    inside = f1[np.isin(f1[:, 0], sorted({5, 6, 7} - seen))]
    assert len(inside) and (inside[:, 7] == 0).all()  # filled rows are not detections
    assert (np.diff(filled[:, 0]) >= 0).all()  # frame order kept
    # smoothed and filled boxes stay on the walker (x = 20 + 3 (f + 1) px at 0-based frame f)
    assert np.abs(f1[:, 2] - (23 + 3 * f1[:, 0])).max() < 6


@pytest.mark.parametrize(
    "exc",
    [
        RuntimeError(
            "[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate "
            "memory: you tried to allocate 91234567890 bytes. Error code 12 (Cannot allocate "
            "memory)"
        ),
        MemoryError("Unable to allocate 9.09 TiB for an array with shape (10000000000000,)"),
    ],
)
def test_out_of_memory_midway_is_an_error_and_leaves_no_output(
    clip, dets, tmp_path, capsys, monkeypatch, exc
):
    """An allocation failure on the 4th frame (torch's CPU allocator, numpy's MemoryError) was
    a traceback; now a one-line error, exit 1, and the run's outputs are gone."""
    from torchtrack.track.multi import MultiTargetTracker

    update, calls = MultiTargetTracker.update, []

    def failing(self, *a, **k):
        calls.append(1)
        if len(calls) == 4:
            raise exc
        return update(self, *a, **k)

    monkeypatch.setattr(MultiTargetTracker, "update", failing)
    out, mot = tmp_path / "o.csv", tmp_path / "o.txt"
    argv = ["track", str(clip), "--detections", str(dets), "--out", str(out), "--mot", str(mot)]
    assert main([*argv, "-q"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("torchtrack track: error: out of memory (")
    assert ("you tried to allocate 91234567890 bytes" in err) or ("9.09 TiB" in err)
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["det.txt", "grey.avi"]


def test_other_runtime_errors_keep_their_traceback(clip, dets, tmp_path, monkeypatch):
    """Only allocation failures are reported as such: any other RuntimeError is a bug."""
    from torchtrack.track.multi import MultiTargetTracker

    def broken(self, *a, **k):
        raise RuntimeError("shape mismatch in some op")

    monkeypatch.setattr(MultiTargetTracker, "update", broken)
    with pytest.raises(RuntimeError, match="shape mismatch"):
        main(
            ["track", str(clip), "--detections", str(dets), "--mot", str(tmp_path / "o.txt"), "-q"]
        )
    assert not (tmp_path / "o.txt").exists()
