"""``torchtrack track`` over many sources (``--out-dir``) on real clips: outputs equal to the
single-source command's, failures reported while the rest finish, resuming, bad input."""

from __future__ import annotations

import json
import re
import shutil

import pytest

from torchtrack.cli import main
from torchtrack.data import demo_clip_path

BOX = "200,100,30,60"
OPTS = ["--tracker", "histogram:n_particles=200", "--box", BOX, "--max-frames", "4",
        "--no-progress"]  # fmt: skip


@pytest.fixture
def clips(data_dir, tmp_path):
    d = tmp_path / "clips"
    d.mkdir()
    shutil.copy(data_dir / "videos" / "pets2009_s2l1_vtest" / "vtest.avi", d / "vtest.avi")
    shutil.copy(demo_clip_path(), d / "demo.mp4")
    (d / "corrupt.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + b"\x17" * 500)
    (tmp_path / "readme.txt").write_text("not a video\n")
    return d


def test_corpus_equals_single_runs_reports_failures_and_resumes(clips, tmp_path, capsys):
    out = tmp_path / "out"
    args = ["track", str(clips), str(tmp_path / "readme.txt"), "--out-dir", str(out)]
    assert main([*args, "--write", "csv,video", *OPTS]) == 1
    captured = capsys.readouterr()
    assert "4 source(s): 2 done, 0 already done (skipped), 2 failed" in captured.out
    assert "corrupt.mp4: VideoError: video file" in captured.err
    assert "readme.txt: VideoError: video file" in captured.err
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [
        "demo.csv", "demo.mp4", "manifest.jsonl", "vtest.csv", "vtest.mp4"
    ]  # fmt: skip
    for name, src in (("demo", clips / "demo.mp4"), ("vtest", clips / "vtest.avi")):
        single = tmp_path / f"{name}-single.csv"
        assert main(["track", str(src), "--out", str(single), *OPTS]) == 0
        assert (out / f"{name}.csv").read_bytes() == single.read_bytes()
    capsys.readouterr()
    (clips / "corrupt.mp4").unlink()
    assert main(["track", str(clips), "--out-dir", str(out), "--write", "csv,video", *OPTS]) == 0
    captured = capsys.readouterr()
    assert "2 source(s): 0 done, 2 already done (skipped), 0 failed" in captured.out
    assert "skipping 2 source(s) already done" in captured.err
    header = json.loads((out / "manifest.jsonl").read_text().splitlines()[0])
    assert header["settings"]["tracker"] == "histogram:n_particles=200"
    assert header["command"].startswith("torchtrack track ")
    changed = [a if a != "4" else "5" for a in OPTS]
    assert main(["track", str(clips), "--out-dir", str(out), *changed]) == 1
    assert "other settings (max_frames: 4 there, 5 now)" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["a.mp4", "b.mp4"], "2 sources make a corpus run: give --out-dir DIR"),
        (["{clips}"], "the videos in folder '.*clips' make a corpus run"),
        (["{clips}/*.avi"], r"the paths matched by '.*\*.avi' make a corpus run"),
        (["@list.txt"], "the sources listed in 'list.txt' make a corpus run"),
        (["{clips}/demo.mp4", "--jobs", "2"], "only corpus runs use --jobs: give --out-dir"),
        (["{clips}/demo.mp4", "--backend", "ray"], "only corpus runs use --backend ray"),
        (["{clips}", "--out-dir", "o", "--out", "x.csv"], "choose them with --write .*not --out"),
        (["{clips}", "--out-dir", "o", "--write", "csv,gif"], "--write takes .* csv, mot, video"),
        (["{clips}", "--out-dir", "o", "--particles"], "add it with --write video"),
        (["{clips}", "--out-dir", "{clips}/demo.mp4/o"], "--out-dir .*demo.mp4' is not a folder"),
        (["{clips}", "--out-dir", "o", "--detections", "d.txt"], "cannot use one file for every"),
        (["0", "--out-dir", "o"], "'0' is a camera index"),
        (["{clips}", "--out-dir", "o", "--jobs", "0"], "--jobs must be >= 1"),
    ],
)
def test_bad_input(clips, tmp_path, monkeypatch, capsys, argv, message):
    monkeypatch.chdir(tmp_path)
    argv = [a.format(clips=clips) for a in argv]
    assert main(["track", *argv, "--box", BOX]) == 1
    err = capsys.readouterr().err
    assert err.startswith("torchtrack track: error: ") and "Traceback" not in err
    assert re.search(message, err), err
    assert not (tmp_path / "o").exists()


def test_multi_target_corpus_writes_the_mot_file_of_a_single_run(tmp_path):
    """Without --box every source gets the multi-target tracker; --write mot is its --mot."""
    opts = ["--max-frames", "3", "--no-progress"]
    assert main(["track", "demo", "--out-dir", str(tmp_path / "c"), "--write", "mot", *opts]) == 0
    assert main(["track", "demo", "--mot", str(tmp_path / "one.txt"), *opts]) == 0
    got = (tmp_path / "c" / "pets2009_s2l1_demo.mot.txt").read_bytes()
    assert got == (tmp_path / "one.txt").read_bytes() and got.count(b"\n") > 3
