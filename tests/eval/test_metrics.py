"""Metrics against hand-computed cases and slow loop references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchtrack.errors import ConfigError, ShapeError
from torchtrack.eval.metrics import (
    SUCCESS_THRESHOLDS,
    aggregate_metrics,
    centre_errors,
    evaluate_sequence,
    frame_ious,
    longest_run,
    precision_curve,
    success_curve,
)

NAN = math.nan


@pytest.fixture
def case():
    """Hand-made 5-frame sequence, 16x16 boxes.

    frame 0: init frame, prediction deliberately wrong (must be ignored)
    frame 1: exact                       IoU 1,        centre error 0,   visible
    frame 2: shifted 3 px right          IoU 208/304,  centre error 3,   NOT visible
    frame 3: target absent (NaN gt)      -,            -,                NOT visible
    frame 4: 200 px off (a break)        IoU 0,        centre error 200, visible
    """
    gt = torch.tensor(
        [[0, 0, 16, 16], [10, 10, 16, 16], [10, 10, 16, 16], [NAN] * 4, [10, 10, 16, 16]],
        dtype=torch.float64,
    )
    pred = torch.tensor(
        [[90, 90, 5, 5], [10, 10, 16, 16], [13, 10, 16, 16], [50, 50, 16, 16], [210, 10, 16, 16]],
        dtype=torch.float64,
    )
    visible = torch.tensor([True, True, False, False, True])
    return pred, gt, visible


def test_hand_computed_case(case):
    m = evaluate_sequence(*case)
    assert (m.n_frames, m.n_evaluated, m.n_present, m.n_absent) == (5, 4, 3, 1)
    # IoUs over present frames: 1, 13/19, 0.
    # success S(t) = #(IoU > t)/3: t = 0..0.65 (14 thresholds) -> 2/3, t = 0.7..0.95 (6) -> 1/3,
    # t = 1 -> 0; AUC = (14 * 2/3 + 6 * 1/3) / 21 = 34/63.
    assert m.success == pytest.approx([2 / 3] * 14 + [1 / 3] * 6 + [0.0])
    assert m.auc == pytest.approx(34 / 63)
    # centre errors 0, 3, 200: precision(t) = 1/3 for t < 3, 2/3 for 3 <= t <= 50
    assert m.precision == pytest.approx([1 / 3] * 3 + [2 / 3] * 48)
    assert m.precision_20 == pytest.approx(2 / 3)
    # normalised offsets 0, 3/16 = 0.1875, 12.5: thresholds 0..0.18 (19) -> 1/3, 0.19..0.5 (32)
    assert m.norm_precision == pytest.approx((19 / 3 + 32 * 2 / 3) / 51)
    # Klein: mean IoU (1 + 13/19 + 0) / 3, miss = IoU < 1/3 -> 1 of 3
    assert m.mean_iou == pytest.approx((1 + 13 / 19) / 3)
    assert m.miss_rate == pytest.approx(1 / 3)
    # Bachoo: |dx| = 0, 3, 200; |dy| = 0, 0, 0 (population std)
    assert m.x_error == pytest.approx((203 / 3, torch.tensor([0.0, 3, 200]).std(False).item()))
    assert m.y_error == pytest.approx((0.0, 0.0))
    assert m.x_error_target == pytest.approx((100.0, 100.0))  # frames 1 and 4
    assert m.x_error_no_target == pytest.approx((3.0, 0.0))  # frame 2
    # breaks: frame 4 only; the absent frame 3 does not break the run 1-2-3 -> 3 of 4 frames
    assert m.track_length == pytest.approx(75.0)
    assert m.track_ratio == pytest.approx(50.0)  # visible on frames 1 and 4 of 1..4
    assert m.reinit_per_100 is None and m.n_reinit is None
    assert m.present_visible_rate == pytest.approx(2 / 3)
    assert m.absent_rejection_rate == pytest.approx(1.0)


def test_invisible_counts_as_miss(case):
    m = evaluate_sequence(*case, invisible="miss")
    # frame 2 (present, not visible) now scores IoU 0 and an infinite error
    assert m.success == pytest.approx([1 / 3] * 20 + [0.0])
    assert m.mean_iou == pytest.approx(1 / 3)
    assert m.miss_rate == pytest.approx(2 / 3)
    assert m.precision_20 == pytest.approx(1 / 3)


def test_first_frame_excluded_and_reinit_rate(case):
    pred, gt, vis = case
    good = pred.clone()
    good[0] = gt[0]
    assert evaluate_sequence(good, gt, vis).to_dict() == evaluate_sequence(pred, gt, vis).to_dict()
    m = evaluate_sequence(pred, gt, vis, reinit_frames=[4])
    assert m.n_reinit == 1 and m.reinit_per_100 == pytest.approx(25.0)
    m2 = evaluate_sequence(pred, gt, vis, init_frames=(0, 1))
    assert m2.n_present == 2 and m2.mean_iou == pytest.approx(13 / 19 / 2)


def test_absent_frame_visible_is_a_false_alarm(case):
    pred, gt, vis = case
    vis = vis.clone()
    vis[3] = True
    m = evaluate_sequence(pred, gt, vis)
    assert m.absent_rejection_rate == 0.0
    assert m.mean_iou == pytest.approx((1 + 13 / 19) / 3)  # accuracy unchanged


def test_nan_prediction_is_a_miss():
    gt = torch.tensor([[0, 0, 10, 10]] * 3, dtype=torch.float64)
    pred = gt.clone()
    pred[2] = NAN
    assert frame_ious(pred, gt).tolist() == [1.0, 1.0, 0.0]
    assert centre_errors(pred, gt)[2] == math.inf
    m = evaluate_sequence(pred, gt)
    assert m.mean_iou == pytest.approx(0.5) and m.precision_20 == pytest.approx(0.5)
    assert m.track_length == pytest.approx(50.0)  # NaN estimate = broken track


def test_no_present_frame_gives_undefined_metrics():
    gt = torch.tensor([[0, 0, 10, 10], [NAN] * 4], dtype=torch.float64)
    m = evaluate_sequence(gt.nan_to_num(0), gt)
    assert m.n_present == 0 and math.isnan(m.auc) and math.isnan(m.mean_iou)
    d = m.to_dict()
    assert d["auc"] is None and d["absent_rejection_rate"] == 0.0


def _iou_loop(a, b):
    ax2, ay2, bx2, by2 = a[0] + a[2], a[1] + a[3], b[0] + b[2], b[1] + b[3]
    iw = max(0.0, min(ax2, bx2) - max(a[0], b[0]))
    ih = max(0.0, min(ay2, by2) - max(a[1], b[1]))
    inter = iw * ih
    return inter / (a[2] * a[3] + b[2] * b[3] - inter)


def test_against_slow_loop_reference():
    g = torch.Generator().manual_seed(3)
    gt = torch.cat(
        [torch.rand(200, 2, generator=g) * 100, 5 + torch.rand(200, 2, generator=g) * 40], 1
    )
    pred = gt + torch.randn(200, 4, generator=g, dtype=torch.float64) * 8
    pred[:, 2:] = pred[:, 2:].clamp(min=1)
    gt = gt.to(torch.float64)
    m = evaluate_sequence(pred, gt)
    ious = [_iou_loop(pred[i].tolist(), gt[i].tolist()) for i in range(1, 200)]
    errs = [
        math.dist(
            (pred[i, 0] + pred[i, 2] / 2, pred[i, 1] + pred[i, 3] / 2),
            (gt[i, 0] + gt[i, 2] / 2, gt[i, 1] + gt[i, 3] / 2),
        )
        for i in range(1, 200)
    ]
    succ = [sum(v > t for v in ious) / 199 for t in SUCCESS_THRESHOLDS.tolist()]
    prec = [sum(e <= t for e in errs) / 199 for t in range(51)]
    assert m.success == pytest.approx(succ)
    assert m.auc == pytest.approx(sum(succ) / 21)
    assert m.precision == pytest.approx(prec)
    assert m.mean_iou == pytest.approx(sum(ious) / 199)
    assert m.miss_rate == pytest.approx(sum(v < 1 / 3 for v in ious) / 199)


def test_curves_and_runs():
    ious = torch.tensor([0.0, 0.05, 0.5, 1.0], dtype=torch.float64)
    s = success_curve(ious)
    assert s[0] == 0.75 and s[1] == 0.5 and s[10] == 0.25 and s[-1] == 0.0  # strict '>'
    assert precision_curve(torch.tensor([0.0, 20.0, 21.0]))[20] == pytest.approx(2 / 3)  # '<='
    assert math.isnan(success_curve(torch.empty(0))[0])
    assert longest_run(torch.tensor([True, True, False, True, True, True, False])) == 3
    assert longest_run(torch.tensor([], dtype=torch.bool)) == 0


def test_aggregate_is_mean_over_sequences(case):
    a = evaluate_sequence(*case).to_dict()
    gt = torch.tensor([[0, 0, 10, 10]] * 3, dtype=torch.float64)
    b = evaluate_sequence(gt.clone(), gt).to_dict()  # perfect: AUC 20/21
    agg = aggregate_metrics([a, b])
    assert agg["n_sequences"] == 2
    assert agg["auc"] == pytest.approx((34 / 63 + 20 / 21) / 2)
    assert agg["mean_iou"] == pytest.approx(((1 + 13 / 19) / 3 + 1) / 2)
    assert agg["precision_20"] == pytest.approx((2 / 3 + 1) / 2)
    assert agg["absent_rejection_rate"] == pytest.approx(1.0)  # b has no absent frame: skipped
    assert aggregate_metrics([])["auc"] is None


def test_errors():
    with pytest.raises(ShapeError, match=r"both be \(T, 4\)"):
        evaluate_sequence(torch.zeros(3, 4), torch.zeros(4, 4))
    with pytest.raises(ShapeError, match=r"visible must be \(3,\)"):
        evaluate_sequence(torch.zeros(3, 4), torch.zeros(3, 4), torch.ones(2))
    with pytest.raises(ConfigError, match="invisible must be"):
        evaluate_sequence(torch.zeros(3, 4), torch.zeros(3, 4), invisible="skip")


def test_init_and_reinit_frames_outside_the_sequence_are_refused():
    """init_frames=[10] on 3 frames was skipped (frame 0 then scored as a tracked frame) and
    reinit_frames=[7, 8] counted two re-initialisations that never happened, silently."""
    z = torch.zeros(3, 4)
    for kw in ({"init_frames": [10]}, {"init_frames": [-1]}, {"reinit_frames": [0, 7]}):
        with pytest.raises(ConfigError, match=r"_frames must hold frame indices in \[0, 3\)"):
            evaluate_sequence(z, z, **kw)
    with pytest.raises(ConfigError, match=r"got 1.5"):
        evaluate_sequence(z, z, init_frames=[1.5])
    m = evaluate_sequence(z, z, init_frames=[np.int64(0), 2], reinit_frames=[1])
    assert m.n_evaluated == 1 and m.n_reinit == 1


def test_losses_and_reacquisitions_count_long_miss_runs():
    from torchtrack.eval.metrics import losses_and_reacquisitions

    hit = torch.tensor([True] * 3 + [False] * 12 + [True] * 2 + [False] * 5 + [True] + [False] * 10)
    # one run of 12 misses then a hit (lost and found), 5 misses (too short), 10 at the end
    assert losses_and_reacquisitions(hit) == (2, 1)
    assert losses_and_reacquisitions(hit, min_run=5) == (3, 2)
    assert losses_and_reacquisitions(torch.ones(20, dtype=torch.bool)) == (0, 0)


def test_curves_refuse_the_nan_of_absent_frames():
    """frame_ious / centre_errors give NaN on absent-target frames; success_curve and
    precision_curve counted those as failures (every point of the curve lowered), silently."""
    from torchtrack.errors import DataError

    with pytest.raises(DataError, match="success_curve: ious hold NaN"):
        success_curve(torch.tensor([1.0, NAN]))
    with pytest.raises(DataError, match="precision_curve: errors hold NaN"):
        precision_curve(torch.tensor([1.0, NAN]))
    assert precision_curve(torch.tensor([0.0, math.inf]))[0] == 0.5  # inf: a miss, as before
    with pytest.raises(ShapeError, match=r"1-D tensor"):
        success_curve(torch.ones(2, 2))


def test_runs_need_1d_bool_flags():
    """longest_run of a 2-D mask read each row as True (zeros(2, 2) gave 2); min_run = 0 counted
    no loss but two re-acquisitions, True was taken as 1."""
    from torchtrack.eval.metrics import losses_and_reacquisitions

    with pytest.raises(ShapeError, match="longest_run: mask must be a 1-D bool tensor"):
        longest_run(torch.zeros(2, 2, dtype=torch.bool))
    with pytest.raises(ShapeError, match="hit must be a 1-D bool tensor"):
        losses_and_reacquisitions(torch.tensor([1.0, 0.0]))
    hit = torch.tensor([True, False, True])
    for bad in (0, True, 1.5):
        with pytest.raises(ConfigError, match="min_run must be an integer >= 1"):
            losses_and_reacquisitions(hit, bad)


def test_visible_must_be_flags_and_boxes_numbers():
    """visible = 0.5 (a confidence) or NaN was read as True; bool boxes were scored as 0 / 1
    pixel boxes."""
    from torchtrack.errors import DataError

    z = torch.zeros(3, 4)
    for bad in (torch.tensor([1.0, 0.5, 0.0]), torch.tensor([1.0, NAN, 0.0])):
        with pytest.raises(DataError, match="visible must be bool flags"):
            evaluate_sequence(z, z, bad)
    m = evaluate_sequence(z, z, torch.tensor([1, 0, 1]))  # 0 / 1 integers are flags
    assert m.track_ratio == 50.0
    with pytest.raises(ShapeError, match="pred must hold real numbers"):
        centre_errors(torch.ones(3, 4, dtype=torch.bool), z)


def test_ground_truth_rows_partly_nan_or_infinite_are_refused():
    """gt rows [NaN, 5, 10, 10] or [inf, 5, 10, 10] were scored as absent-target frames without
    a word; only a row of NaN means the target is absent."""
    from torchtrack.errors import DataError

    pred = torch.tensor([[0.0, 0, 10, 10]] * 3)
    for bad in ([NAN, 5, 10, 10], [math.inf, 5, 10, 10]):
        gt = torch.tensor([[0.0, 0, 10, 10], bad, [0, 0, 10, 10]])
        with pytest.raises(DataError, match=r"gt\[1\] = .* must be finite, or all NaN"):
            evaluate_sequence(pred, gt)
        with pytest.raises(DataError, match=r"gt\[1\]"):
            frame_ious(pred, gt)
    gt = torch.tensor([[0.0, 0, 10, 10], [NAN] * 4, [0, 0, 10, 10]])
    assert evaluate_sequence(pred, gt).n_absent == 1
