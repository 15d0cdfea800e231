"""``torchtrack eval`` end to end on a few real frames."""

from __future__ import annotations

import json
import os
import re

import pytest

from torchtrack.cli import main


def test_eval_runs_and_writes_results(data_dir, tmp_path, capsys):
    out = tmp_path / "run"
    code = main(
        [
            "eval",
            "--sequences",
            str(data_dir / "tracking" / "bobot_pedestrian"),
            str(data_dir / "tracking" / "otb" / "Crossing"),
            "--trackers",
            "camshift",
            "camshift:bins=8",
            "--out",
            str(out),
            "--max-frames",
            "5",
            "--no-progress",
        ]
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert "| camshift |" in printed and "| camshift:bins=8 |" in printed
    summary = json.loads((out / "results.json").read_text())
    assert [s["name"] for s in summary["sequences"]] == ["bobot_pedestrian", "Crossing"]
    assert summary["command"].startswith("torchtrack eval --sequences")
    assert "--max-frames 5" in summary["command"]
    assert summary["overall"]["camshift"]["n_frames"] == 10
    assert (out / "sequences" / "Crossing" / "camshift_bins_8.json").is_file()
    assert (out / "results.md").is_file()  # plots: tests/eval/test_runner.py


def test_eval_unknown_tracker_is_a_clean_error(data_dir, tmp_path, capsys):
    code = main(
        [
            "eval",
            "--sequences",
            str(data_dir / "tracking" / "bobot_pedestrian"),
            "--trackers",
            "sift",
            "--out",
            str(tmp_path / "o"),
        ]
    )
    err = capsys.readouterr().err
    assert code == 1
    assert "torchtrack eval: error: unknown tracker 'sift'; known trackers:" in err
    assert "mil" in err and "camshift" in err


def test_eval_bad_inputs(tmp_path, capsys):
    assert main(["eval", "--trackers", "mil"]) == 1
    assert "needs --sequences, --out" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    args = ["eval", "--sequences", str(tmp_path / "empty"), "--trackers", "mil", "--out"]
    assert main([*args, str(tmp_path / "o")]) == 1
    assert "no tracking sequence found" in capsys.readouterr().err
    assert main([*args, str(tmp_path / "o"), "--max-frames", "1"]) == 1
    assert "--max-frames must be >= 2" in capsys.readouterr().err
    assert main([*args, str(tmp_path / "o"), "--jobs", "0"]) == 1
    assert "--jobs must be >= 1" in capsys.readouterr().err
    assert main([*args, str(tmp_path / "o"), "--address", "10.0.0.5:6379"]) == 1
    assert "--address names a Ray cluster: use it with --backend ray" in capsys.readouterr().err


def test_list_trackers_and_import(capsys):
    assert main(["eval", "--list-trackers"]) == 0
    out = capsys.readouterr().out
    for name in ("mil", "camshift", "csrt", "kcf"):
        assert name in out
    assert main(["eval", "--import", "eval.crash_tracker", "--list-trackers"]) == 0
    assert "test-crash" in capsys.readouterr().out
    assert main(["eval", "--import", "no_such_module_xyz", "--list-trackers"]) == 1
    assert "cannot import tracker module 'no_such_module_xyz'" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# --mot: scoring MOTChallenge results files
# ---------------------------------------------------------------------------------------------
def test_eval_mot_folder_and_video(data_dir, tmp_path, capsys, trackeval):
    from torchtrack.io.mot import load_mot_sequence, write_mot

    tud = data_dir / "mot" / "TUD-Stadtmitte"
    seq = load_mot_sequence(tud)
    keep = seq.gt.frames % 5 != 0  # every 5th frame missed
    write_mot(tmp_path / "res" / "TUD-Stadtmitte.txt", seq.gt.select(keep))
    out = tmp_path / "out"
    assert (
        main(["eval", "--mot", str(tud), "--results", str(tmp_path / "res"), "-o", str(out)]) == 0
    )
    printed = capsys.readouterr().out
    assert "| res | TUD-Stadtmitte | " in printed
    summary = json.loads((out / "results.json").read_text())
    m = summary["per_sequence"]["TUD-Stadtmitte"]["res"]
    assert m["fp"] == 0 and m["fn"] == int((~keep).sum()) and m["id_switches"] == 0
    assert summary["command"].startswith("torchtrack eval --mot")
    assert (out / "results.md").is_file()
    # the same frames as a folder of frames (what `torchtrack track` read) plus the GT file:
    # the same scores (it said "--gt gives 1 file(s) for 0 video(s)")
    assert (
        main(
            ["eval", "--mot", str(tud / "img1"), "--gt", str(tud / "gt" / "gt.txt"),
             "--results", str(tmp_path / "res"), "-o", str(tmp_path / "out2")]
        )
        == 0
    )  # fmt: skip
    capsys.readouterr()
    again = json.loads((tmp_path / "out2" / "results.json").read_text())
    assert again["per_sequence"]["TUD-Stadtmitte"]["res"] == m

    # the PETS video plus its GT: scale 0.625 from seqinfo.ini; results in video pixels
    video = data_dir / "videos" / "pets2009_s2l1_vtest" / "vtest.avi"
    gt = data_dir / "mot" / "PETS09-S2L1" / "gt" / "gt.txt"
    pets = load_mot_sequence(video, gt=gt)
    write_mot(tmp_path / "pets.txt", pets.gt.select(pets.gt.conf > 0))
    assert (
        main(
            ["eval", "--mot", str(video), "--gt", str(gt), "--results", str(tmp_path / "pets.txt")]
        )
        == 0
    )
    row = capsys.readouterr().out.splitlines()[2]
    assert row.startswith("| pets | PETS09-S2L1 | 100.0 | 100.0 | 100.0 | 100.0 |")
    # without the scale the same file scores badly: the 768x576 GT on 480x360 boxes, which
    # the evaluation says
    with pytest.warns(UserWarning, match="ground-truth boxes of PETS09-S2L1 .* lie wholly outside"):
        assert (
            main(
                [
                    "eval",
                    "--mot",
                    str(video),
                    "--gt",
                    str(gt),
                    "--gt-scale",
                    "1",
                    "--results",
                    str(tmp_path / "pets.txt"),
                ]
            )
            == 0
        )
    assert "| pets | PETS09-S2L1 | 100.0 |" not in capsys.readouterr().out


def _mot_seq(tmp_path, n=3):
    d = tmp_path / "Tiny"
    (d / "gt").mkdir(parents=True)
    (d / "seqinfo.ini").write_text(f"[Sequence]\nname=Tiny\nseqLength={n}\n")
    (d / "gt" / "gt.txt").write_text("1,1,11,11,20,40,1,-1,-1,-1\n2,1,11,11,20,40,1,-1,-1,-1\n")
    return d


def test_eval_mot_empty_results_scores_as_empty_tracker(tmp_path, capsys, trackeval):
    d = _mot_seq(tmp_path)
    (tmp_path / "empty.txt").write_text("")
    assert main(["eval", "--mot", str(d), "--results", str(tmp_path / "empty.txt")]) == 0
    assert (
        "| empty | Tiny | 0.0 | 0.0 | 0.0 | 0.0 | 0.0 | 0.0 | 0 | 0 | 2 |"
        in capsys.readouterr().out
    )


def test_eval_mot_bad_inputs(tmp_path, capsys, trackeval):
    d = _mot_seq(tmp_path)
    out = tmp_path / "out"

    def fails(args, message):
        assert main(["eval", *args]) == 1
        err = capsys.readouterr().err
        assert message in err, err
        assert "Traceback" not in err

    res = tmp_path / "r.txt"
    res.write_text("1,1,11,11,20,40,1\n2,1,11,11,20,x,1\n")
    fails(
        ["--mot", str(d), "--results", str(res), "-o", str(out)],
        f"{res} line 2: not a row of numbers",
    )
    assert not out.exists()  # a failed run leaves no output
    res.write_text("1,1,11,11,20,40,1\n4,1,11,11,20,40,1\n")
    fails(
        ["--mot", str(d), "--results", str(res)],
        f"{res} line 2: frame 4 is beyond the sequence's 3 frames",
    )
    (tmp_path / "resdir").mkdir()
    (tmp_path / "resdir" / "Other.txt").write_text("")
    fails(["--mot", str(d), "--results", str(tmp_path / "resdir")], "no file for sequence(s) Tiny")
    fails(["--mot", str(d)], "MOT scoring needs --mot SEQ ... and either --results")
    fails(
        ["--mot", str(d), "--results", str(res), "--trackers", "mil"], "--trackers do(es) not apply"
    )
    fails(
        ["--mot", str(d), "--results", str(res), "--gt-scale", "-2"],
        "--gt-scale must be 'auto' or a number in [0.001, 1000], got '-2'",
    )
    # 1e308 overflowed the boxes to inf: TrackEval's ValueError escaped as a traceback
    fails(
        ["--mot", str(d), "--results", str(res), "--gt-scale", "1e308"],
        "--gt-scale must be 'auto' or a number in [0.001, 1000], got '1e308'",
    )
    # float() reads 0_625 as 625, within the range: the GT was scored 1000 times too large
    fails(
        ["--mot", str(d), "--results", str(res), "--gt-scale", "0_625"],
        "--gt-scale must be 'auto' or a number in [0.001, 1000], got '0_625'",
    )
    fails(
        ["--mot", str(d), "--results", str(res), "--gt", str(res)],
        "--gt gives 1 file(s) for 0 video(s)",
    )
    fails(
        ["--mot", str(tmp_path / "resdir"), "--results", str(res)], "holds no MOTChallenge sequence"
    )
    # a folder of frames without its ground truth: what to give instead (the sequence above it)
    import cv2
    import numpy as np

    seq = _mot_seq(tmp_path / "other")
    (seq / "img1").mkdir()
    for k in (1, 2, 3):
        cv2.imwrite(str(seq / "img1" / f"{k:06d}.png"), np.zeros((8, 8, 3), np.uint8))
    fails(
        ["--mot", str(seq / "img1"), "--results", str(res)],
        f"it is a folder of frames: give its ground truth with --gt, or the MOTChallenge folder {seq}",
    )
    fails(["--sequences", str(d), "--gt", str(res)], "--gt and --gt-scale go with --mot")
    # GT rows beyond the video's frames
    import cv2
    import numpy as np

    video = tmp_path / "clip.mp4"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 10, (32, 24))
    for _ in range(3):
        w.write(np.zeros((24, 32, 3), np.uint8))
    w.release()
    gt = tmp_path / "clip_gt.txt"
    gt.write_text("1,1,1,1,5,5,1\n9,1,1,1,5,5,1\n")
    fails(
        ["--mot", str(video), "--gt", str(gt), "--results", str(res)],
        f"{gt} line 2: frame 9 is beyond",
    )


def test_mot_runs_the_multi_target_tracker_and_scores_it(data_dir, tmp_path, capsys, trackeval):
    """eval --mot SEQ --trackers multi --public-detections: results per tracker, then TrackEval."""
    import json

    seq = data_dir / "mot" / "TUD-Stadtmitte"
    out = tmp_path / "ev"
    rc = main(
        ["eval", "--mot", str(seq), "--trackers", "multi", "multi:appearance=none",
         "--public-detections", "--max-frames", "15", "-o", str(out), "-q"]
    )  # fmt: skip
    assert rc == 0
    for label in ("multi", "multi_appearance-none"):
        assert (out / label / "TUD-Stadtmitte.txt").is_file()
    res = json.loads((out / "results.json").read_text())
    assert set(res["overall"]) == {"multi", "multi_appearance-none"}
    assert "HOTA" in capsys.readouterr().out
    # only the multi-target tracker runs on MOT sequences; an output folder is needed
    assert main(["eval", "--mot", str(seq), "--trackers", "mil", "-o", str(out)]) == 1
    assert main(["eval", "--mot", str(seq), "--trackers", "multi"]) == 1
    assert main(["eval", "--mot", str(seq), "--results", str(out / "multi"),
                 "--public-detections"]) == 1  # fmt: skip


@pytest.mark.parametrize("stop", [KeyboardInterrupt, "error"])
def test_mot_trackers_run_stopped_keeps_an_earlier_runs_tracks(
    data_dir, tmp_path, capsys, monkeypatch, stop
):
    """eval --mot A B --trackers multi -o DIR, stopped (Ctrl-C or an error) while tracking B:
    A's tracks, written by an earlier run into DIR/multi/A.txt, were deleted with this run's
    outputs. The tracks are now written once every sequence is tracked: the old file stays."""
    import shutil

    import torchtrack.track.multi as multi
    from torchtrack.errors import TrackerError
    from torchtrack.io.mot import read_mot

    tud = data_dir / "mot" / "TUD-Stadtmitte"
    other = tmp_path / "Other"
    (other / "gt").mkdir(parents=True)
    ini = (tud / "seqinfo.ini").read_text().replace("name=TUD-Stadtmitte", "name=Other")
    (other / "seqinfo.ini").write_text(ini)
    (other / "img1").symlink_to(tud / "img1")
    shutil.copy(tud / "gt" / "gt.txt", other / "gt" / "gt.txt")
    earlier = tmp_path / "ev" / "multi" / "TUD-Stadtmitte.txt"  # an earlier run's tracks
    earlier.parent.mkdir(parents=True)
    earlier.write_text("1,1,10,10,20,40,1,-1,-1,-1\n")
    calls = []

    def second_stops(*a, **k):  # the first sequence tracked (one box), the second stopped
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt if stop is KeyboardInterrupt else TrackerError("boom")
        return read_mot(earlier)

    monkeypatch.setattr(multi, "track_sequence", second_stops)
    argv = ["eval", "--mot", str(tud), str(other), "--trackers", "multi", "--max-frames", "3",
            "-o", str(tmp_path / "ev"), "-q"]  # fmt: skip
    assert main(argv) == (130 if stop is KeyboardInterrupt else 1)
    assert "Traceback" not in capsys.readouterr().err
    assert earlier.read_text() == "1,1,10,10,20,40,1,-1,-1,-1\n"
    assert not (earlier.parent / "Other.txt").exists()


@pytest.mark.parametrize(
    "name, says",
    [
        ("", "--import '' is not a module name"),  # importlib's ValueError traceback
        (".rel", "--import '.rel' is not a module name"),  # importlib's TypeError traceback
        ("badsyn", r"cannot import tracker module 'badsyn': invalid syntax \(badsyn.py, line 1\)"),
    ],
)
def test_import_of_a_bad_module_name_or_a_broken_module(name, says, tmp_path, capsys, monkeypatch):
    (tmp_path / "badsyn.py").write_text("def f(:\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert main(["eval", "--import", name, "--list-trackers"]) == 1
    err = capsys.readouterr().err
    assert re.search(says, err) and "Traceback" not in err, err


def test_mot_trackers_with_a_path_in_the_spec_write_one_folder_each(
    data_dir, tmp_path, monkeypatch, capsys, trackeval
):
    """eval --mot SEQ --trackers multi:model=../../../x/v.safetensors -o ev: the tracker's
    folder was named after the spec with its slashes, so the tracks went to nested folders,
    here outside ev (ev/multi_model-../../../x/v.safetensors/ is x/v.safetensors/ beside ev);
    now one folder in ev, the slashes as '_'."""
    import shutil

    import torchtrack.track.multi as multi
    from torchtrack.detect.bundled import MODELS_DIR
    from torchtrack.io.mot import read_mot

    (tmp_path / "x").mkdir()
    shutil.copy(MODELS_DIR / "vehicle.safetensors", tmp_path / "x" / "v.safetensors")
    work = tmp_path / "a" / "b" / "c"
    work.mkdir(parents=True)
    monkeypatch.chdir(work)
    rows = tmp_path / "rows.txt"
    rows.write_text("1,1,10,10,20,40,1,-1,-1,-1\n")
    monkeypatch.setattr(multi, "track_sequence", lambda *a, **k: read_mot(rows))
    spec = "multi:model=../../../x/v.safetensors"
    tud = str(data_dir / "mot" / "TUD-Stadtmitte")
    assert main(["eval", "--mot", tud, "--trackers", spec, "--max-frames", "3", "-o", "ev"]) == 0
    assert (work / "ev" / "multi_model-.._.._.._x_v.safetensors" / "TUD-Stadtmitte.txt").is_file()
    assert sorted(p.name for p in work.iterdir()) == ["ev"]  # nothing beside ev


@pytest.mark.parametrize("existed", [False, True])
def test_eval_stopped_before_any_result_leaves_no_new_folder(
    data_dir, tmp_path, capsys, monkeypatch, existed
):
    """Ctrl-C during `eval --sequences` (before any result was written) left the empty --out
    folder the run had made; it is removed now. A folder that existed before stays."""
    import torchtrack.eval.runner as runner

    out = tmp_path / "run"
    if existed:
        out.mkdir()

    def stopped(seqs, trackers, folder, **kw):
        os.makedirs(folder, exist_ok=True)  # where the runner makes it; then the user stops it
        raise KeyboardInterrupt

    monkeypatch.setattr(runner, "evaluate", stopped)
    seq = str(data_dir / "tracking" / "otb" / "Crossing")
    argv = ["eval", "--sequences", seq, "--trackers", "camshift", "--out", str(out)]
    assert main([*argv, "--no-progress"]) == 130
    assert "interrupted" in capsys.readouterr().err
    assert out.is_dir() == existed
