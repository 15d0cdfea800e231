"""``torchtrack eval`` end to end on a few real frames."""

from __future__ import annotations

import json

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


def test_eval_output_folder_that_cannot_be_written(data_dir, tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    code = main(
        ["eval", "--sequences", str(data_dir / "tracking" / "otb" / "Crossing"), "--trackers",
         "camshift", "--out", str(tmp_path / "file" / "run"), "--max-frames", "3"]
    )  # fmt: skip
    assert code == 1
    err = capsys.readouterr().err
    assert "--out " in err and "cannot be written: Not a directory" in err


def test_list_trackers_and_import(capsys):
    assert main(["eval", "--list-trackers"]) == 0
    out = capsys.readouterr().out
    for name in ("mil", "camshift", "csrt", "kcf"):
        assert name in out
    assert main(["eval", "--import", "eval.crash_tracker", "--list-trackers"]) == 0
    assert "test-crash" in capsys.readouterr().out
    assert main(["eval", "--import", "no_such_module_xyz", "--list-trackers"]) == 1
    assert "cannot import tracker module 'no_such_module_xyz'" in capsys.readouterr().err
