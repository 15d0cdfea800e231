"""Tracking metrics: OTB success / precision, normalised precision, Klein's average IoU and miss
rate, Bachoo's error / track-length / re-initialisation / track-ratio metrics.

Inputs are per-frame tensors of one sequence: predicted boxes ``pred (T, 4)``, ground truth
``gt (T, 4)`` (both ``x, y, w, h`` pixels; a NaN row in ``gt`` = target absent) and the
tracker's ``visible (T,)`` flags.

Which frames count
------------------
* **Evaluated frames** ``E``: every frame except the initialisation frame(s) (frame 0, plus any
  frame passed in ``init_frames``). ``n = |E|``.
* **Present frames** ``P``: evaluated frames whose ground truth is finite. All accuracy metrics
  (success, precision, IoU, miss rate, centre errors) are over ``P``; absent-target frames never
  enter them, whatever the tracker says there.
* **Absent frames** ``A = E \\ P``: scored only by the visibility answer. ``visible=False`` there
  is a correct rejection, ``visible=True`` a false alarm (``absent_rejection_rate``).
* **Present but the tracker says not visible**: with ``invisible="box"`` (default, the OTB
  protocol: the tracker's box is its answer on every frame) the returned box is scored as is; with
  ``invisible="miss"`` the frame scores IoU 0 and an infinite centre error. Either way it lowers
  ``present_visible_rate`` and Bachoo's track ratio, and its errors go to the "no target" columns.
* A predicted box that is NaN (no estimate) on a present frame scores IoU 0 and an infinite
  centre error.

Definitions
-----------
* Success curve (OTB, Wu et al. 2013): ``S(t) = |{f in P: IoU_f > t}| / |P|`` for the 21
  thresholds ``t = 0, 0.05, ..., 1``; ``auc = mean_t S(t)``.
* Precision curve: ``|{f in P: centre error_f <= t}| / |P|`` for ``t = 0, 1, ..., 50`` pixels;
  ``precision_20`` is its value at 20 px.
* Normalised precision (Müller et al., TrackingNet 2018): the centre offset divided by the ground
  truth width / height, ``||((dx / w_gt), (dy / h_gt))||``, curve over 51 thresholds
  ``0, 0.01, ..., 0.5``; ``norm_precision`` is the mean of that curve (its AUC on [0, 0.5]).
* Klein et al. 2010, sec. IV: ``mean_iou`` = average IoU over ``P`` ("average score"),
  ``miss_rate`` = fraction of ``P`` with ``IoU < 1/3``.
* Losses and re-acquisitions (the tracker-independent count behind a tracker's own re-detection):
  a *loss* is a run of at least ``LOSS_FRAMES`` (10) consecutive present frames with
  ``IoU < 1/3``; ``losses`` counts them, ``reacquisitions`` those after which the tracker's box
  overlaps the target again (``IoU >= 1/3``) on a later present frame.
* Bachoo et al., sec. 4: ``x_error`` / ``y_error`` = mean +- std (population) of
  ``|x_gt - x_est|`` of the box centres over ``P``, also split by the tracker's belief
  (``target`` = visible, ``no_target`` = not visible); a track *breaks* on a present frame whose
  x or y error exceeds 100 px; ``track_length`` = longest run of consecutive evaluated frames
  without a break, in % of ``n`` (absent frames neither break nor end a run);
  ``reinit_per_100`` = re-initialisations per 100 evaluated frames (only meaningful for runs in
  the re-initialising mode of :mod:`torchtrack.eval.runner`, else ``None``); ``track_ratio`` =
  % of evaluated frames where the tracker says it sees the target.
"""

from __future__ import annotations

import math
from collections.abc import Sequence as _Seq
from dataclasses import asdict, dataclass, field

import torch

from torchtrack.boxes import _check_last4, box_iou
from torchtrack.errors import ConfigError, DataError, ShapeError, is_integer

__all__ = [
    "BREAK_PX",
    "LOSS_FRAMES",
    "MISS_IOU",
    "NORM_PRECISION_THRESHOLDS",
    "PRECISION_THRESHOLDS",
    "SUCCESS_THRESHOLDS",
    "SequenceMetrics",
    "aggregate_metrics",
    "centre_errors",
    "evaluate_sequence",
    "frame_ious",
    "longest_run",
    "losses_and_reacquisitions",
    "normalised_centre_errors",
    "precision_curve",
    "success_curve",
]

SUCCESS_THRESHOLDS = torch.linspace(0.0, 1.0, 21, dtype=torch.float64)
PRECISION_THRESHOLDS = torch.arange(0, 51, dtype=torch.float64)
NORM_PRECISION_THRESHOLDS = torch.linspace(0.0, 0.5, 51, dtype=torch.float64)
MISS_IOU = 1.0 / 3.0
BREAK_PX = 100.0
LOSS_FRAMES = 10


def _check(pred: torch.Tensor, gt: torch.Tensor) -> None:
    _check_last4(pred, "pred")  # not a tensor, bool or complex boxes (bools were 0 / 1 pixels)
    _check_last4(gt, "gt")
    if pred.ndim != 2 or pred.shape[-1] != 4 or tuple(pred.shape) != tuple(gt.shape):
        raise ShapeError(
            f"pred and gt must both be (T, 4), got {tuple(pred.shape)} and {tuple(gt.shape)}"
        )
    if gt.is_floating_point():
        # an absent target is a row of NaN; a row with one NaN or an inf (a broken file or
        # conversion) was scored as absent without a word
        nan = torch.isnan(gt)
        bad = torch.isinf(gt).any(1) | (nan.any(1) & ~nan.all(1))
        if bool(bad.any()):
            i = int(bad.nonzero()[0, 0])
            raise DataError(
                f"gt[{i}] = {gt[i].tolist()}: a ground-truth box must be finite, or all NaN "
                "(target absent)"
            )


def frame_ious(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Per-frame IoU ``(T,)`` float64 of ``pred (T, 4)`` vs ``gt (T, 4)``; NaN where the ground
    truth is absent, 0 where the prediction is NaN."""
    _check(pred, gt)
    p, g = pred.to(torch.float64), gt.to(torch.float64)
    iou = box_iou(torch.nan_to_num(p, nan=0.0), torch.nan_to_num(g, nan=0.0))
    iou = torch.where(torch.isfinite(p).all(1), iou, torch.zeros_like(iou))
    return torch.where(torch.isfinite(g).all(1), iou, torch.full_like(iou, math.nan))


def _centre_deltas(pred: torch.Tensor, gt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    p, g = pred.to(torch.float64), gt.to(torch.float64)
    dx = (p[:, 0] + p[:, 2] / 2) - (g[:, 0] + g[:, 2] / 2)
    dy = (p[:, 1] + p[:, 3] / 2) - (g[:, 1] + g[:, 3] / 2)
    return dx, dy


def _mask_errors(err: torch.Tensor, pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    err = torch.where(torch.isfinite(pred).all(1), err, torch.full_like(err, math.inf))
    return torch.where(torch.isfinite(gt).all(1), err, torch.full_like(err, math.nan))


def centre_errors(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Euclidean distance ``(T,)`` between box centres in pixels; NaN where the ground truth is
    absent, inf where the prediction is NaN."""
    _check(pred, gt)
    dx, dy = _centre_deltas(pred, gt)
    return _mask_errors(torch.hypot(dx, dy), pred, gt)


def normalised_centre_errors(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Centre offset divided by the ground-truth width and height, ``(T,)`` (TrackingNet)."""
    _check(pred, gt)
    dx, dy = _centre_deltas(pred, gt)
    g = gt.to(torch.float64)
    return _mask_errors(torch.hypot(dx / g[:, 2], dy / g[:, 3]), pred, gt)


def _check_curve_values(values: torch.Tensor, name: str, fn: str) -> None:
    """ShapeError unless ``values`` is a 1-D real tensor; DataError if it holds NaN (the
    absent-target frames of :func:`frame_ious` / :func:`centre_errors`, which the curves counted
    as failures, lowering every point of the curve)."""
    if not isinstance(values, torch.Tensor) or values.ndim != 1 or values.dtype == torch.bool:
        got = (
            f"{tuple(values.shape)} {values.dtype}"
            if isinstance(values, torch.Tensor)
            else type(values).__name__
        )
        raise ShapeError(f"{fn}: {name} must be a 1-D tensor of numbers (F,), got {got}")
    if values.is_floating_point() and bool(torch.isnan(values).any()):
        raise DataError(
            f"{fn}: {name} hold NaN (frames whose target is absent): keep the present frames "
            f"only, e.g. {name}[~{name}.isnan()]"
        )


def success_curve(ious: torch.Tensor, thresholds: torch.Tensor = SUCCESS_THRESHOLDS):
    """Fraction of ``ious (F,)`` strictly above each threshold -> ``(K,)``; NaN if ``F = 0``.

    Raises:
        ShapeError: ``ious`` not 1-D numbers.
        DataError: a NaN IoU (an absent-target frame of :func:`frame_ious`).
    """
    _check_curve_values(ious, "ious", "success_curve")
    if ious.numel() == 0:
        return torch.full(thresholds.shape, math.nan, dtype=torch.float64)
    return (ious[None, :] > thresholds[:, None]).to(torch.float64).mean(1)


def precision_curve(errors: torch.Tensor, thresholds: torch.Tensor = PRECISION_THRESHOLDS):
    """Fraction of ``errors (F,)`` at or below each threshold -> ``(K,)``; NaN if ``F = 0``.
    An infinite error (no prediction) is a miss at every threshold.

    Raises:
        ShapeError: ``errors`` not 1-D numbers.
        DataError: a NaN error (an absent-target frame of :func:`centre_errors`).
    """
    _check_curve_values(errors, "errors", "precision_curve")
    if errors.numel() == 0:
        return torch.full(thresholds.shape, math.nan, dtype=torch.float64)
    return (errors[None, :] <= thresholds[:, None]).to(torch.float64).mean(1)


def longest_run(mask: torch.Tensor) -> int:
    """Length of the longest run of consecutive True values in a 1-D bool tensor.

    Raises:
        ShapeError: ``mask`` not a 1-D bool tensor (the rows of a 2-D one were each read as
            True, whatever they held).
    """
    _check_flags(mask, "mask", "longest_run")
    best = cur = 0
    for v in mask.tolist():
        cur = cur + 1 if v else 0
        best = max(best, cur)
    return best


def losses_and_reacquisitions(hit: torch.Tensor, min_run: int = LOSS_FRAMES) -> tuple[int, int]:
    """``(losses, reacquisitions)`` of a 1-D bool sequence over present frames (``hit``: the
    tracker overlaps the target): runs of at least ``min_run`` misses, and those of them that
    are followed by a hit.

    Raises:
        ShapeError: ``hit`` not a 1-D bool tensor.
        ConfigError: ``min_run`` not an integer >= 1 (0 counted no loss but every hit after a
            miss as a re-acquisition).
    """
    _check_flags(hit, "hit", "losses_and_reacquisitions")
    if not is_integer(min_run) or min_run < 1:
        raise ConfigError(
            f"losses_and_reacquisitions: min_run must be an integer >= 1, got {min_run!r}"
        )
    losses = found = run = 0
    for v in hit.tolist():  # a loop over frames
        if v:
            if run >= min_run:
                found += 1
            run = 0
        else:
            run += 1
            if run == min_run:
                losses += 1
    return losses, found


def _check_flags(flags: torch.Tensor, name: str, fn: str) -> None:
    if not isinstance(flags, torch.Tensor) or flags.ndim != 1 or flags.dtype != torch.bool:
        got = (
            f"{tuple(flags.shape)} {flags.dtype}"
            if isinstance(flags, torch.Tensor)
            else type(flags).__name__
        )
        raise ShapeError(f"{fn}: {name} must be a 1-D bool tensor, got {got}")


def _mean_std(x: torch.Tensor) -> tuple[float, float]:
    if x.numel() == 0:
        return math.nan, math.nan
    return float(x.mean()), float(x.std(unbiased=False))


@dataclass
class SequenceMetrics:
    """Metrics of one tracker on one sequence (see the module doc for the definitions).

    Rates are fractions in [0, 1] except Bachoo's ``track_length``, ``track_ratio`` (percent)
    and ``reinit_per_100``. NaN marks "undefined" (e.g. no present frame).
    """

    n_frames: int
    n_evaluated: int
    n_present: int
    n_absent: int
    auc: float
    precision_20: float
    norm_precision: float
    mean_iou: float
    miss_rate: float
    x_error: tuple[float, float]
    y_error: tuple[float, float]
    x_error_target: tuple[float, float]
    y_error_target: tuple[float, float]
    x_error_no_target: tuple[float, float]
    y_error_no_target: tuple[float, float]
    track_length: float
    track_ratio: float
    reinit_per_100: float | None
    n_reinit: int | None
    present_visible_rate: float
    absent_rejection_rate: float
    losses: int
    reacquisitions: int
    success: list[float] = field(repr=False)
    precision: list[float] = field(repr=False)
    norm_precision_curve: list[float] = field(repr=False)

    def to_dict(self) -> dict:
        """JSON-ready dict (NaN and inf become ``None``)."""
        return _json_ready(asdict(self))


def _json_ready(obj):
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_ready(v) for v in obj]
    return obj


def evaluate_sequence(
    pred: torch.Tensor,
    gt: torch.Tensor,
    visible: torch.Tensor | None = None,
    *,
    init_frames: _Seq[int] = (0,),
    reinit_frames: _Seq[int] | None = None,
    invisible: str = "box",
) -> SequenceMetrics:
    """Every metric of one sequence.

    Args:
        pred: ``(T, 4)`` predicted boxes x, y, w, h (NaN = no estimate).
        gt: ``(T, 4)`` ground truth; NaN rows = target absent.
        visible: ``(T,)`` bool, the tracker's visibility flags (all True if ``None``).
        init_frames: frame indices excluded as initialisation frames (default: frame 0).
        reinit_frames: frames where the runner re-initialised the tracker from the ground truth
            (re-initialising mode); ``None`` for a one-pass run (``reinit_per_100`` is ``None``).
            Re-initialisation frames are scored (their failing box is what triggered the
            re-initialisation).
        invisible: ``"box"`` or ``"miss"``: how a present-target frame with ``visible=False``
            is scored (module doc).

    Raises:
        ShapeError: mismatched shapes, or boxes that are not real numbers (bool included).
        DataError: a ``visible`` flag other than True / False (or 0 / 1).
        ConfigError: unknown ``invisible`` policy, or a frame of ``init_frames`` /
            ``reinit_frames`` outside the sequence.
    """
    _check(pred, gt)
    t = pred.shape[0]
    if visible is None:
        visible = torch.ones(t, dtype=torch.bool)
    if not isinstance(visible, torch.Tensor):
        raise ShapeError(f"visible must be a ({t},) bool tensor, got {type(visible).__name__}")
    if visible.dtype != torch.bool and not bool(((visible == 0) | (visible == 1)).all()):
        # a confidence given for the flags (0.5, NaN) was read as True by .to(bool)
        bad = visible.reshape(-1)[~((visible == 0) | (visible == 1)).reshape(-1)][0]
        raise DataError(f"visible must be bool flags (or 0 / 1), got the value {bad.item()}")
    visible = visible.to(torch.bool).reshape(-1)
    if visible.shape[0] != t:
        raise ShapeError(f"visible must be ({t},), got {tuple(visible.shape)}")
    if invisible not in ("box", "miss"):
        raise ConfigError(f"invisible must be 'box' or 'miss', got {invisible!r}")

    for name, frames in (("init_frames", init_frames), ("reinit_frames", reinit_frames or ())):
        for i in frames:
            # frames beyond the sequence were skipped (init) or counted (reinit), silently
            if isinstance(i, bool) or not hasattr(i, "__index__") or not 0 <= int(i) < t:
                raise ConfigError(
                    f"{name} must hold frame indices in [0, {t}) (the sequence has {t} frames), "
                    f"got {i!r}"
                )
    evaluated = torch.ones(t, dtype=torch.bool)
    for i in init_frames:
        evaluated[i] = False
    gt_present = torch.isfinite(gt).all(1)
    present = evaluated & gt_present
    absent = evaluated & ~gt_present

    ious = frame_ious(pred, gt)
    err = centre_errors(pred, gt)
    nerr = normalised_centre_errors(pred, gt)
    dx, dy = _centre_deltas(pred, gt)
    adx = _mask_errors(dx.abs(), pred, gt)
    ady = _mask_errors(dy.abs(), pred, gt)
    if invisible == "miss":
        lost = ~visible
        ious = torch.where(lost & gt_present, torch.zeros_like(ious), ious)
        for e in (err, nerr, adx, ady):
            e[lost & gt_present] = math.inf

    iou_p, err_p, nerr_p = ious[present], err[present], nerr[present]
    # a zero-size ground truth has no normalised error (0 / 0): a miss, as it always counted
    nerr_p = torch.nan_to_num(nerr_p, nan=math.inf, posinf=math.inf)
    succ = success_curve(iou_p)
    prec = precision_curve(err_p)
    nprec = precision_curve(nerr_p, NORM_PRECISION_THRESHOLDS)
    n_p = int(present.sum())
    mean_iou = float(iou_p.mean()) if n_p else math.nan
    miss = float((iou_p < MISS_IOU).to(torch.float64).mean()) if n_p else math.nan

    vis_p = visible[present]
    adx_p, ady_p = adx[present], ady[present]
    broken = present & ((adx > BREAK_PX) | (ady > BREAK_PX))
    n_e = int(evaluated.sum())
    run_ok = ~broken[evaluated]
    track_length = 100.0 * longest_run(run_ok) / n_e if n_e else math.nan
    track_ratio = 100.0 * float(visible[evaluated].to(torch.float64).mean()) if n_e else math.nan
    n_reinit = None if reinit_frames is None else len(reinit_frames)
    reinit_rate = None
    if n_reinit is not None:
        reinit_rate = 100.0 * n_reinit / n_e if n_e else math.nan
    n_a = int(absent.sum())
    n_lost, n_found = losses_and_reacquisitions(iou_p >= MISS_IOU)
    return SequenceMetrics(
        n_frames=t,
        n_evaluated=n_e,
        n_present=n_p,
        n_absent=n_a,
        auc=float(succ.mean()),
        precision_20=float(prec[20]),
        norm_precision=float(nprec.mean()),
        mean_iou=mean_iou,
        miss_rate=miss,
        x_error=_mean_std(adx_p),
        y_error=_mean_std(ady_p),
        x_error_target=_mean_std(adx_p[vis_p]),
        y_error_target=_mean_std(ady_p[vis_p]),
        x_error_no_target=_mean_std(adx_p[~vis_p]),
        y_error_no_target=_mean_std(ady_p[~vis_p]),
        track_length=track_length,
        track_ratio=track_ratio,
        reinit_per_100=reinit_rate,
        n_reinit=n_reinit,
        present_visible_rate=float(vis_p.to(torch.float64).mean()) if n_p else math.nan,
        absent_rejection_rate=(
            float((~visible[absent]).to(torch.float64).mean()) if n_a else math.nan
        ),
        losses=n_lost,
        reacquisitions=n_found,
        success=succ.tolist(),
        precision=prec.tolist(),
        norm_precision_curve=nprec.tolist(),
    )


#: Per-sequence scalar metrics that aggregate as means over sequences.
SCALAR_METRICS = (
    "auc",
    "precision_20",
    "norm_precision",
    "mean_iou",
    "miss_rate",
    "track_length",
    "track_ratio",
    "reinit_per_100",
    "present_visible_rate",
    "absent_rejection_rate",
    "losses",
    "reacquisitions",
)


def aggregate_metrics(per_sequence: list[dict]) -> dict:
    """Average per-sequence metric dicts (``SequenceMetrics.to_dict()``) over sequences, the OTB
    way: curves are averaged frame-wise across sequences and ``auc`` / ``precision_20`` /
    ``norm_precision`` are read from the averaged curves; other scalars are sequence means
    (``None`` values skipped). Sequences without a present frame are left out.

    Returns a dict with the same scalar keys plus ``success``, ``precision``,
    ``norm_precision_curve`` and ``n_sequences``.
    """
    seqs = [m for m in per_sequence if m.get("n_present")]
    out: dict = {"n_sequences": len(seqs)}
    if not seqs:
        for k in SCALAR_METRICS:
            out[k] = None
        return out
    for key in ("success", "precision", "norm_precision_curve"):
        curves = torch.tensor([[math.nan if v is None else v for v in m[key]] for m in seqs])
        out[key] = curves.mean(0).tolist()
    for k in SCALAR_METRICS:
        vals = [m[k] for m in seqs if m.get(k) is not None]
        out[k] = sum(vals) / len(vals) if vals else None
    out["auc"] = sum(out["success"]) / len(out["success"])
    out["precision_20"] = out["precision"][20]
    out["norm_precision"] = sum(out["norm_precision_curve"]) / len(out["norm_precision_curve"])
    return _json_ready(out)
