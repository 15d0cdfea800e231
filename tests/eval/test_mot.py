"""MOT metrics: hand-computed tiny cases, TrackEval's own MOT15 pipeline on real ground truth,
and a cross-check of MOTA / IDF1 against motmetrics on TUD-Stadtmitte."""

from __future__ import annotations

import math
import sys
import warnings

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from torchtrack.errors import ConfigError, MissingDependencyError, MotFormatError
from torchtrack.eval.mot import (
    TRACKEVAL_INSTALL,
    combine_metrics,
    evaluate_mot,
    gt_as_detections,
    import_trackeval,
    resolve_results,
    score_mot,
    score_sequence,
)
from torchtrack.io.mot import MotRows, load_mot_sequence, write_mot


def rows(*r, conf=None):
    """Rows from (frame, id, x, y, w, h) tuples, 0-based frames."""
    a = np.asarray(r, dtype=float).reshape(-1, 6)
    return MotRows.from_arrays(a[:, 0], a[:, 1], a[:, 2:], conf)


BOX = (10.0, 10.0, 20.0, 40.0)


@pytest.fixture(autouse=True)
def _needs_trackeval(request):
    if request.node.name != "test_missing_trackeval_names_the_install_command":
        request.getfixturevalue("trackeval")


# ---------------------------------------------------------------------------------------------
# Tiny cases computed by hand
# ---------------------------------------------------------------------------------------------
def test_perfect_tracker():
    gt = rows(
        *[(t, 1, 10 + t, 10, 20, 40) for t in range(5)], *[(t, 2, 60, 10, 20, 40) for t in range(3)]
    )
    m = score_mot(gt, gt, 5)
    assert (m.hota, m.deta, m.assa, m.mota, m.motp, m.idf1) == (1.0, 1.0, 1.0, 1.0, 1.0, 1.0)
    assert (m.id_switches, m.fp, m.fn, m.frag, m.mt, m.ml) == (0, 0, 0, 0, 2, 0)
    assert (m.n_gt, m.n_results, m.n_gt_ids, m.n_result_ids) == (8, 8, 2, 2)


def test_one_id_switch():
    # One person over 4 frames; the tracker calls it 1 for two frames, then 2.
    gt = rows(*[(t, 1, *BOX) for t in range(4)])
    res = rows((0, 1, *BOX), (1, 1, *BOX), (2, 2, *BOX), (3, 2, *BOX))
    m = score_mot(gt, res, 4)
    assert (m.tp, m.fp, m.fn, m.id_switches, m.frag) == (4, 0, 0, 1, 0)
    assert m.mota == pytest.approx(1 - 1 / 4)
    # IDF1: one GT id matched to one tracker id for 2 frames: IDTP 2, IDFP 2, IDFN 2
    assert m.idf1 == pytest.approx(2 * 2 / (2 * 2 + 2 + 2))
    # HOTA: every detection matched at IoU 1 (DetA 1); each match's association
    # |TPA| / (|TPA| + |FNA| + |FPA|) = 2 / (2 + 2 + 0) -> AssA 0.5; HOTA = sqrt(1 * 0.5)
    assert m.deta == pytest.approx(1.0) and m.assa == pytest.approx(0.5)
    assert m.hota == pytest.approx(math.sqrt(0.5))


def test_false_positive_and_miss():
    gt = rows((0, 1, *BOX), (1, 1, *BOX))
    res = rows((0, 5, *BOX), (0, 6, 200, 200, 20, 40))  # frame 1 missed; an FP in frame 0
    m = score_mot(gt, res, 2)
    assert (m.tp, m.fp, m.fn, m.id_switches) == (1, 1, 1, 0)
    assert m.mota == pytest.approx((1 - 1 - 0) / 2)
    assert m.recall == pytest.approx(0.5) and m.precision == pytest.approx(0.5)
    # DetA = TP / (TP + FN + FP) at every threshold = 1/3; the one match's association:
    # |TPA| / (|TPA| + |FNA| + |FPA|) = 1 / (1 + 1 + 0) (the GT id's missed frame) -> AssA 0.5
    assert m.deta == pytest.approx(1 / 3) and m.assa == pytest.approx(0.5)
    assert m.hota == pytest.approx(math.sqrt(1 / 3 * 0.5))


def test_fragmentation_without_switch():
    gt = rows(*[(t, 1, *BOX) for t in range(5)])
    far = (2, 9, 300, 300, 20, 40)
    res = rows(*[(t, 3, *BOX) for t in (0, 1, 3, 4)], far)
    m = score_mot(gt, res, 5)
    assert (m.tp, m.fn, m.fp, m.id_switches, m.frag) == (4, 1, 1, 0, 1)
    assert m.mota == pytest.approx((4 - 1) / 5)
    # TrackEval's CLEAR skips a frame without any tracker box when it follows a track (it
    # neither ends nor restarts the track there): the same gap then is no fragmentation.
    m = score_mot(gt, rows(*[(t, 3, *BOX) for t in (0, 1, 3, 4)]), 5)
    assert (m.fn, m.frag) == (1, 0)


def test_motp_is_mean_iou_of_matches_and_threshold():
    gt = rows((0, 1, 0, 0, 10, 10), (1, 1, 0, 0, 10, 10))
    res = rows((0, 1, 0, 0, 10, 8), (1, 1, 0, 0, 10, 4))  # IoU 0.8 (match), IoU 0.4 (no match)
    m = score_mot(gt, res, 2)
    assert (m.tp, m.fp, m.fn) == (1, 1, 1)
    assert m.motp == pytest.approx(0.8)


def test_zero_marked_gt_is_ignored_but_a_box_on_it_is_a_false_positive():
    # Person 2 is marked conf 0: not a miss when untracked, and (MOT15) a box on it is an FP.
    gt = rows((0, 1, *BOX), (0, 2, 100, 10, 20, 40), conf=[1, 0])
    m = score_mot(gt, rows((0, 1, *BOX)), 1)
    assert (m.tp, m.fn, m.fp, m.n_gt, m.n_gt_ignored) == (1, 0, 0, 1, 1)
    m = score_mot(gt, rows((0, 1, *BOX), (0, 2, 100, 10, 20, 40)), 1)
    assert (m.tp, m.fn, m.fp) == (1, 0, 1) and m.mota == pytest.approx(0.0)


def test_empty_tracker_and_empty_gt():
    gt = rows((0, 1, *BOX), (1, 1, *BOX))
    m = score_mot(gt, MotRows.empty(), 3)
    assert (m.hota, m.mota, m.idf1, m.fn, m.fp, m.ml) == (0.0, 0.0, 0.0, 2, 0, 1)
    m = score_mot(MotRows.empty(), gt, 3)
    assert (m.fp, m.fn, m.hota) == (2, 0, 0.0)


def test_combined_sums_counts():
    gt = rows((0, 1, *BOX), (1, 1, *BOX))
    a = score_mot(gt, gt, 2)
    b = score_mot(gt, rows((0, 1, *BOX)), 2)
    c = combine_metrics([a, b])
    assert (c.tp, c.fn, c.n_gt, c.n_frames) == (3, 1, 4, 4)
    assert c.mota == pytest.approx(3 / 4)  # not the mean of 1.0 and 0.5
    with pytest.raises(ValueError, match="at least one"):
        combine_metrics([])


def test_rows_beyond_sequence():
    with pytest.raises(MotFormatError, match="frame 4 is beyond sequence s's 3 frames"):
        score_mot(rows((0, 1, *BOX)), rows((3, 1, *BOX)), 3, name="s")


def test_missing_trackeval_names_the_install_command(monkeypatch):
    monkeypatch.setitem(sys.modules, "trackeval", None)  # import raises ImportError
    with pytest.raises(MissingDependencyError, match="pip install --no-deps trackeval"):
        import_trackeval()
    assert "--no-deps" in TRACKEVAL_INSTALL


def test_import_prints_nothing(capfd):
    import subprocess

    out = subprocess.run(
        [
            sys.executable,
            "-c",
            "from torchtrack.eval.mot import import_trackeval; import_trackeval()",
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    assert out.stdout == ""


# ---------------------------------------------------------------------------------------------
# Real ground truth: identical to TrackEval's own MOT15 pipeline
# ---------------------------------------------------------------------------------------------
def _perturbed(gt: MotRows, seed: int) -> MotRows:
    """GT with 10% of the boxes dropped, 3 px jitter, and two identities swapped half way."""
    rng = np.random.default_rng(seed)
    keep = rng.random(len(gt)) > 0.1
    ids = gt.ids.copy()
    u = np.unique(ids)
    half = gt.frames > np.median(gt.frames)
    a, b = u[0], u[1]
    ids[half & (gt.ids == a)], ids[half & (gt.ids == b)] = b, a
    boxes = gt.boxes + rng.normal(0, 3, gt.boxes.shape) * [1, 1, 0.5, 0.5]
    boxes[:, 2:] = np.maximum(boxes[:, 2:], 2)
    return MotRows.from_arrays(gt.frames[keep], ids[keep], boxes[keep], np.ones(keep.sum()))


def _trackeval_official(tmp_path, seq, res_rows):
    """Score through TrackEval's Evaluator and MotChallenge2DBox (BENCHMARK MOT15) from files."""
    import contextlib
    import io

    trackeval = import_trackeval()
    gt_dir = tmp_path / "gt" / seq.name / "gt"
    gt_dir.mkdir(parents=True)
    write_mot(gt_dir / "gt.txt", seq.gt)  # scaled GT; conf (0/1) kept
    tr_dir = tmp_path / "trackers" / "mine" / "data"
    write_mot(tr_dir / f"{seq.name}.txt", res_rows)
    ds = trackeval.datasets.MotChallenge2DBox(
        {
            "GT_FOLDER": str(tmp_path / "gt"),
            "TRACKERS_FOLDER": str(tmp_path / "trackers"),
            "BENCHMARK": "MOT15",
            "SKIP_SPLIT_FOL": True,
            "SEQ_INFO": {seq.name: seq.n_frames},
            "TRACKERS_TO_EVAL": ["mine"],
            "PRINT_CONFIG": False,
        }
    )
    ev = trackeval.Evaluator(
        {
            "USE_PARALLEL": False,
            "PRINT_RESULTS": False,
            "PRINT_CONFIG": False,
            "TIME_PROGRESS": False,
            "OUTPUT_SUMMARY": False,
            "OUTPUT_DETAILED": False,
            "PLOT_CURVES": False,
            "OUTPUT_EMPTY_CLASSES": False,
            "DISPLAY_LESS_PROGRESS": True,
        }
    )
    quiet = {"PRINT_CONFIG": False}
    metrics = [
        trackeval.metrics.HOTA(quiet),
        trackeval.metrics.CLEAR(quiet),
        trackeval.metrics.Identity(quiet),
    ]
    with contextlib.redirect_stdout(io.StringIO()):
        res, _ = ev.evaluate([ds], metrics)
    return res["MotChallenge2DBox"]["mine"][seq.name]["pedestrian"]


def test_same_as_trackeval_mot15_pipeline_on_pets(tmp_path, data_dir):
    video = data_dir / "videos" / "pets2009_s2l1_vtest" / "vtest.avi"
    seq = load_mot_sequence(video, gt=data_dir / "mot" / "PETS09-S2L1" / "gt" / "gt.txt")
    res = _perturbed(seq.gt, seed=0)  # includes boxes on the 174 conf-0 rows: FPs in MOT15
    ours = score_mot(seq.gt, res, seq.n_frames, name=seq.name)
    official = _trackeval_official(tmp_path, seq, res)
    assert ours.n_gt == 4476 and ours.n_gt_ignored == 174
    assert ours.hota == pytest.approx(float(np.mean(official["HOTA"]["HOTA"])), abs=1e-4)
    assert ours.assa == pytest.approx(float(np.mean(official["HOTA"]["AssA"])), abs=1e-4)
    assert ours.mota == pytest.approx(float(official["CLEAR"]["MOTA"]), abs=1e-4)
    assert ours.idf1 == pytest.approx(float(official["Identity"]["IDF1"]), abs=1e-4)
    for k, f in (("id_switches", "IDSW"), ("fp", "CLR_FP"), ("fn", "CLR_FN"), ("frag", "Frag")):
        assert getattr(ours, k) == int(official["CLEAR"][f]), k
    assert ours.id_switches >= 1 and ours.fp >= 100  # the swap and the conf-0 boxes count


# ---------------------------------------------------------------------------------------------
# Cross-check against motmetrics on a real sequence
# ---------------------------------------------------------------------------------------------
def _link_detections(det: MotRows, n_frames: int, min_score: float = 0.0) -> MotRows:
    """A deterministic tracker: each detection with score > min_score takes the id of the
    previous frame's box it overlaps best (IoU >= 0.3, Hungarian), else a new id."""
    import torch

    from torchtrack.boxes import box_iou_matrix

    det = det.select(det.conf > min_score)
    out_f, out_i, out_b = [], [], []
    prev_boxes, prev_ids, next_id = np.zeros((0, 4)), np.zeros(0, int), 0
    for t, idx in enumerate(det.split(n_frames)):
        boxes = det.boxes[idx]
        ids = np.full(len(idx), -1)
        if len(idx) and len(prev_boxes):
            iou = box_iou_matrix(torch.from_numpy(prev_boxes), torch.from_numpy(boxes)).numpy()
            r, c = linear_sum_assignment(-iou)
            ok = iou[r, c] >= 0.3
            ids[c[ok]] = prev_ids[r[ok]]
        for k in np.nonzero(ids < 0)[0]:
            ids[k], next_id = next_id, next_id + 1
        out_f += [t] * len(idx)
        out_i += ids.tolist()
        out_b += boxes.tolist()
        prev_boxes, prev_ids = boxes, ids
    return MotRows.from_arrays(out_f, out_i, np.asarray(out_b).reshape(-1, 4))


def _motmetrics(mm, gt: MotRows, res: MotRows, n_frames: int) -> dict:

    acc = mm.MOTAccumulator(auto_id=True)
    gs, rs = gt.split(n_frames), res.split(n_frames)
    for gi, ri in zip(gs, rs, strict=True):
        # mm.distances.iou_matrix without its np.asfarray (gone in NumPy 2): motmetrics' boxiou
        g, r = gt.boxes[gi], res.boxes[ri]
        d = np.empty((0, 0))
        if len(g) and len(r):
            d = 1 - mm.distances.boxiou(g[:, None], r[None, :])
            d = np.where(d > 0.5, np.nan, d)
        acc.update(gt.ids[gi].tolist(), res.ids[ri].tolist(), d)
    mh = mm.metrics.create()
    s = mh.compute(
        acc, metrics=["mota", "idf1", "num_switches", "num_false_positives", "num_misses"]
    )
    return {k: float(s[k].iloc[0]) for k in s.columns}


def test_mota_idf1_match_motmetrics_on_tud(data_dir, motmetrics):
    seq = load_mot_sequence(data_dir / "mot" / "TUD-Stadtmitte")
    res = _link_detections(seq.detections(), seq.n_frames, min_score=0.0)
    ours = score_mot(seq.gt, res, seq.n_frames)
    ref = _motmetrics(motmetrics, seq.gt, res, seq.n_frames)
    assert 0.2 < ours.mota < 0.9 and ours.id_switches > 0  # a real, imperfect tracker
    assert ours.mota == pytest.approx(ref["mota"], abs=1e-3)
    assert ours.idf1 == pytest.approx(ref["idf1"], abs=1e-3)
    assert (ours.fp, ours.fn) == (ref["num_false_positives"], ref["num_misses"])
    assert ours.id_switches == ref["num_switches"]


# ---------------------------------------------------------------------------------------------
# Files: score_sequence, resolve_results, evaluate_mot
# ---------------------------------------------------------------------------------------------
def _tiny_seq(tmp_path, name="Tiny", n=3):
    d = tmp_path / name
    (d / "gt").mkdir(parents=True)
    (d / "seqinfo.ini").write_text(f"[Sequence]\nname={name}\nseqLength={n}\n")
    (d / "gt" / "gt.txt").write_text(
        "".join(f"{t},1,11,11,20,40,1,-1,-1,-1\n" for t in range(1, n + 1))
    )
    return load_mot_sequence(d)


def test_score_sequence_empty_results_file(tmp_path):
    seq = _tiny_seq(tmp_path)
    (tmp_path / "empty.txt").write_text("")
    m = score_sequence(seq, tmp_path / "empty.txt")
    assert (m.fn, m.fp, m.mota, m.hota) == (3, 0, 0.0, 0.0)


def test_score_sequence_rejects_rows_beyond(tmp_path):
    seq = _tiny_seq(tmp_path)
    (tmp_path / "r.txt").write_text("1,1,11,11,20,40,1\n4,1,11,11,20,40,1\n")
    with pytest.raises(MotFormatError, match=r"r.txt line 2: frame 4 is beyond the sequence's 3"):
        score_sequence(seq, tmp_path / "r.txt")


def test_score_sequence_warns_when_no_result_box_touches_the_frame(tmp_path):
    d = tmp_path / "Sized"
    (d / "gt").mkdir(parents=True)
    (d / "seqinfo.ini").write_text("[Sequence]\nname=Sized\nseqLength=2\nimWidth=64\nimHeight=48\n")
    (d / "gt" / "gt.txt").write_text("1,1,11,11,20,30,1,-1,-1,-1\n2,1,11,11,20,30,1,-1,-1,-1\n")
    seq = load_mot_sequence(d)
    (tmp_path / "far.txt").write_text("1,1,5011,11,20,30,1\n2,1,11,5011,20,30,1\n")
    with pytest.warns(UserWarning, match=r"no box of .*far.txt' touches the 64x48 frames"):
        m = score_sequence(seq, tmp_path / "far.txt")
    assert m.fp == 2
    (tmp_path / "near.txt").write_text("1,1,5011,11,20,30,1\n2,1,11,11,20,30,1\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # one box in the frame: no warning
        score_sequence(seq, tmp_path / "near.txt")


def test_score_sequence_warns_on_results_made_at_another_size(tmp_path, data_dir):
    # PETS09-S2L1's folder describes 768x576 frames; results made on the 480x360 video and
    # scored against the folder fit inside its frames but match almost nothing: the warning
    # names the factor. At the right scale, and for boxes of another convention, it is silent.
    folder = load_mot_sequence(data_dir / "mot" / "PETS09-S2L1")
    on_video = _perturbed(folder.gt.scaled(0.625), seed=0)
    write_mot(tmp_path / "small.txt", on_video)
    with pytest.warns(UserWarning, match=r"made on a copy of PETS09-S2L1 at another size") as w:
        m = score_sequence(folder, tmp_path / "small.txt")
    assert m.hota < 0.05
    msg = str(w[0].message)
    factor = float(msg.rsplit("(about ", 1)[1].rstrip(")"))
    assert factor == pytest.approx(0.625, abs=0.02)
    right = load_mot_sequence(folder.gt_path.parent.parent, scale=0.625)
    wide = _perturbed(folder.gt, seed=1)
    wide.boxes[:, 2:] *= 1.4  # a wider convention, same size of frames: no scale mismatch
    write_mot(tmp_path / "wide.txt", wide)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert score_sequence(right, tmp_path / "small.txt").hota > 0.5
        score_sequence(folder, tmp_path / "wide.txt")


def test_resolve_results_by_name(tmp_path):
    a, b = _tiny_seq(tmp_path, "A"), _tiny_seq(tmp_path, "B")
    res = tmp_path / "res"
    res.mkdir()
    (res / "A.txt").write_text("")
    (res / "C.txt").write_text("")
    with pytest.raises(ConfigError, match=r"no file for sequence\(s\) B .*found: A.txt, C.txt"):
        resolve_results([a, b], res)
    # a folder named B.txt was listed as found, beside 'no file for B'
    (res / "B.txt").mkdir()
    with pytest.raises(
        ConfigError, match=r"sequence\(s\) B \(B.txt is a folder\) .*found: A.txt, C.txt\)$"
    ):
        resolve_results([a, b], res)
    (res / "B.txt").rmdir()
    (res / "B.txt").write_text("")
    assert [p.name for p in resolve_results([a, b], res)] == ["A.txt", "B.txt"]
    with pytest.raises(ConfigError, match="one file but 2 sequences"):
        resolve_results([a, b], res / "A.txt")
    assert resolve_results([a], res / "C.txt") == [res / "C.txt"]  # one file, one sequence
    with pytest.raises(ConfigError, match="does not exist"):
        resolve_results([a], tmp_path / "nope")


def test_evaluate_mot_writes_json_and_markdown(tmp_path):
    import json

    a, b = _tiny_seq(tmp_path, "A"), _tiny_seq(tmp_path, "B", n=4)
    good, bad = tmp_path / "good", tmp_path / "bad"
    for d in (good, bad):
        d.mkdir()
    write_mot(good / "A.txt", a.gt)
    write_mot(good / "B.txt", b.gt)
    (bad / "A.txt").write_text("")
    write_mot(bad / "B.txt", b.gt)
    out = tmp_path / "out"
    summary = evaluate_mot([a, b], [good, bad], out, command="torchtrack eval --mot ...")
    assert summary["trackers"] == ["good", "bad"]
    assert summary["per_sequence"]["A"]["good"]["mota"] == 1.0
    assert summary["per_sequence"]["A"]["bad"]["fn"] == 3
    assert summary["overall"]["bad"]["mota"] == pytest.approx(4 / 7)
    on_disk = json.loads((out / "results.json").read_text())
    assert on_disk["overall"]["good"]["idf1"] == 1.0
    md = (out / "results.md").read_text()
    assert "| bad | **combined** | " in md and "MOT15" in md
    with pytest.raises(ConfigError, match="given twice"):
        evaluate_mot([a, a], [good])


def test_gt_as_detections_drops_jitters_and_ignores_conf_0_rows():
    n = 2000
    gt = MotRows.from_arrays(
        np.arange(n) // 4, np.arange(n) % 4, np.tile([10.0, 20.0, 30.0, 60.0], (n, 1)),
        np.where(np.arange(n) % 10 == 0, 0.0, 1.0),
    )  # fmt: skip
    d = gt_as_detections(gt, seed=3, drop=0.1, jitter=2.0)
    kept = len(d) / (0.9 * n)  # rows with conf 0 (every 10th) never become detections
    assert 0.85 < kept < 0.95 and (d.ids == -1).all()
    err = d.boxes - np.array([10.0, 20.0, 30.0, 60.0])
    assert abs(err.std() - 2.0) < 0.15 and abs(err.mean()) < 0.15
    again = gt_as_detections(gt, seed=3, drop=0.1, jitter=2.0)
    np.testing.assert_array_equal(again.boxes, d.boxes)  # the same seed, the same draw
    with pytest.raises(ConfigError, match="drop"):
        gt_as_detections(gt, seed=0, drop=1.0)
