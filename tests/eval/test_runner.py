"""The evaluation harness: protocol, failures, re-initialisation, bad frames, outputs, jobs."""

from __future__ import annotations

import json

import pytest
import torch

from torchtrack.errors import ConfigError
from torchtrack.eval.runner import evaluate, run_sequence
from torchtrack.io.sequences import find_sequences, load_sequence

from .conftest import make_sequence


@pytest.fixture
def seq(tmp_path):
    (s,) = load_sequence(make_sequence(tmp_path / "syn"))
    return s


def test_static_tracker_on_static_target_is_perfect(seq, test_trackers):
    res = run_sequence("test-static", seq)
    assert res.error is None and res.init_frames == [0] and res.n_updates == 5
    assert torch.equal(res.boxes, seq.boxes) and bool(res.visible.all())
    m = res.metrics(seq.boxes)
    assert m.auc == pytest.approx(20 / 21) and m.mean_iou == 1.0 and m.precision_20 == 1.0
    assert res.fps is not None and res.fps > 0


def test_raising_tracker_is_recorded(seq, test_trackers):
    res = run_sequence("test-raising", seq)
    assert res.error == "RuntimeError: boom at the third update" and res.error_frame == 3
    assert torch.isnan(res.boxes[3:]).all() and "boom" in res.traceback


def test_reinit_mode_reinitialises_from_ground_truth(seq, test_trackers):
    res = run_sequence("test-faraway", seq, reinit=True)
    assert res.reinit_frames == [1, 2, 3, 4, 5]
    m = res.metrics(seq.boxes)
    assert m.reinit_per_100 == pytest.approx(100.0) and m.track_length == 0.0
    assert m.track_ratio == 0.0
    one_pass = run_sequence("test-faraway", seq)
    assert one_pass.reinit_frames is None and one_pass.metrics(seq.boxes).reinit_per_100 is None


def test_unreadable_frame_carries_the_box(seq, test_trackers):
    seq.frames[3].write_bytes(b"broken")
    res = run_sequence("test-static", seq)
    assert res.error is None and res.bad_frames == [3]
    assert not bool(res.visible[3]) and torch.equal(res.boxes[3], res.boxes[2])
    assert res.n_updates == 4


def test_absent_first_frame_initialises_on_the_first_present_one(tmp_path, test_trackers):
    (s,) = load_sequence(make_sequence(tmp_path / "late", absent=(0, 1)))
    res = run_sequence("test-static", s)
    assert res.init_frames == [0, 1, 2] and res.n_updates == 3
    assert res.metrics(s.boxes).n_evaluated == 3


def test_evaluate_writes_everything_and_survives_a_failing_tracker(tmp_path, test_trackers):
    make_sequence(tmp_path / "seqs" / "a")
    make_sequence(tmp_path / "seqs" / "b", absent=(4,))
    seqs = find_sequences(tmp_path / "seqs")
    out = tmp_path / "out"
    summary = evaluate(
        seqs, ["test-static", "test-raising"], out, plots=True, progress=False, reinit=True
    )
    on_disk = json.loads((out / "results.json").read_text())
    assert on_disk["overall"] == summary["overall"]
    assert summary["overall"]["test-static"]["n_failed"] == 0
    assert summary["overall"]["test-static"]["auc"] == pytest.approx(20 / 21)
    assert summary["overall"]["test-raising"]["n_failed"] == 2
    assert summary["overall"]["test-raising"]["auc"] is None
    assert summary["per_sequence"]["b"]["test-static"]["n_absent"] == 1
    assert summary["overall_reinit"]["test-static"]["reinit_per_100"] == 0.0
    rec = json.loads((out / "sequences" / "a" / "test-raising.json").read_text())
    assert rec["error"].startswith("RuntimeError") and rec["error_frame"] == 3
    assert (out / "sequences_reinit" / "b" / "test-static.json").is_file()
    md = (out / "results.md").read_text()
    assert "| test-static | 0.952 |" in md and "## Failed runs" in md and "failed" in md
    for f in ("success.png", "precision.png", "plots/a_success.png", "plots/b_precision.png"):
        assert (out / f).stat().st_size > 1000
    assert not list(out.rglob(".*.tmp")) and not list(out.rglob(".results*"))


def test_a_failed_run_is_reported_with_its_frame(tmp_path, test_trackers, capsys):
    # the line named the sequence and the error only: "frame size changed ... during tracking"
    # said neither which frame nor which file
    make_sequence(tmp_path / "seqs" / "a")
    (seq,) = find_sequences(tmp_path / "seqs")
    evaluate([seq], ["test-raising"], tmp_path / "out", progress=False)
    line = next(ln for ln in capsys.readouterr().out.splitlines() if "failed on" in ln)
    assert line == (
        f"test-raising failed on a at frame 3 ({seq.frames[3]}): "
        "RuntimeError: boom at the third update"
    )


def test_bad_tracker_lists_fail_before_running(seq, tmp_path, test_trackers):
    with pytest.raises(ConfigError, match="unknown tracker 'nope'"):
        evaluate([seq], ["test-static", "nope"], tmp_path / "o", progress=False)
    with pytest.raises(ConfigError, match="listed twice"):
        evaluate([seq], ["test-static", "test-static"], tmp_path / "o", progress=False)
    with pytest.raises(ConfigError, match="has no parameter"):
        evaluate([seq], ["test-static:speed=3"], tmp_path / "o", progress=False)
    with pytest.raises(ConfigError, match="jobs must be >= 1"):
        evaluate([seq], ["test-static"], tmp_path / "o", jobs=0, progress=False)
    with pytest.raises(ConfigError, match="no sequence"):
        evaluate([], ["test-static"], tmp_path / "o", progress=False)
    assert not (tmp_path / "o" / "results.json").exists()


def test_source_ending_early_counts_missing_frames(seq, test_trackers):
    """A video shorter than its ground truth (header lied): the missing frames are bad frames."""
    short = seq.head(6)
    short.frames = short.frames[:4]
    res = run_sequence("test-static", short)
    assert res.error is None and res.bad_frames == [4, 5]
    assert torch.equal(res.boxes[5], res.boxes[3]) and not res.visible[4:].any()


def test_parallel_jobs_and_a_crashing_worker(tmp_path):
    """Spawned workers give the same results as a serial run; a worker process dying
    mid-sequence breaks the pool, and the harness reruns the other pairs and records the crash
    against the culprit only. (Spawned workers rebuild the registry: test trackers come from
    an importable module.)"""
    make_sequence(tmp_path / "seqs" / "a", n=4)
    seqs = find_sequences(tmp_path / "seqs")
    summary = evaluate(
        seqs,
        ["camshift", "test-crash"],
        tmp_path / "out",
        jobs=2,
        progress=False,
        modules=["eval.crash_tracker"],
    )
    par = summary["per_sequence"]["a"]["camshift"]
    assert par["error"] is None
    serial = run_sequence("camshift", seqs[0]).metrics(seqs[0].boxes).to_dict()
    for k in ("auc", "mean_iou", "precision_20", "track_ratio"):
        assert par[k] == serial[k]
    assert "crashed" in summary["per_sequence"]["a"]["test-crash"]["error"]
    assert summary["overall"]["test-crash"]["n_failed"] == 1
    with pytest.raises(ConfigError, match="cannot import tracker module"):
        evaluate(seqs, ["camshift"], tmp_path / "o", modules=["no_such_module_xyz"])


def test_mil_on_a_tiny_first_box_is_a_recorded_box_error(tmp_path, monkeypatch):
    # OpenCV's TrackerMIL hangs on such a box: the wrapper refuses it before OpenCV is called,
    # and the runner records it like any tracker error
    import torchtrack.track.opencv as opencv

    class NeverCalled:
        def init(self, img, rect):
            raise AssertionError(f"OpenCV init was called on {rect}")

    monkeypatch.setattr(opencv, "opencv_constructor", lambda kind: NeverCalled)
    (s,) = load_sequence(make_sequence(tmp_path / "tiny", box=(4, 5, 4, 4)))
    res = run_sequence("mil", s)
    assert res.error.startswith("BoxError: OpenCV mil needs an init box of at least 5x5 pixels")
    assert res.error_frame == 0
