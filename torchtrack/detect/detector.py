"""The class detector: window + feature bank + selected features + classifier + calibrator.

``Detector.score(frames, boxes)`` returns the calibrated probability that each box holds an
object of the class (Chateau et al. eq. 11), for boxes of any size and position, straight from
integral images computed once per frame (:meth:`Detector.integrals`). This is the likelihood a
particle filter uses.

The bank is Chateau et al.'s grey Haar bank (:class:`~torchtrack.features.haar.HaarBank`, the
paper setting) or integral channel features (:class:`~torchtrack.features.channels.ChannelBank`:
Haar-like features over LUV, gradient magnitude and oriented gradients); the classifier is
boosted stumps, boosted trees (:class:`~torchtrack.learn.BoostedTrees`, with a soft cascade used
by :meth:`Detector.scan`) or an SVM.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import torch

from torchtrack.errors import ModelFormatError, NotFittedError, ShapeError
from torchtrack.features.channels import ChannelBank
from torchtrack.features.haar import HaarBank

__all__ = ["Detector", "check_object_box"]


def check_object_box(box: Any) -> tuple[float, float, float, float]:
    """Validate an object box given as ``(x, y, w, h)`` fractions of the detector window:
    four finite numbers, ``w, h > 0``, inside ``[0, 1]``.

    Raises:
        ModelFormatError: anything else (the message says what came).
    """
    import math

    if not isinstance(box, (list, tuple)) or len(box) != 4:
        raise ModelFormatError(
            f"object_box must be [x, y, w, h] fractions of the window, got {box!r}"
        )
    vals = []
    for v in box:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ModelFormatError(f"object_box must hold four finite numbers, got {box!r}")
        vals.append(float(v))
    x, y, w, h = vals
    eps = 1e-6
    if not (w > 0 and h > 0 and x >= -eps and y >= -eps and x + w <= 1 + eps and y + h <= 1 + eps):
        raise ModelFormatError(
            f"object_box {box!r} must lie inside the window: x, y >= 0, w, h > 0, "
            "x + w <= 1, y + h <= 1 (fractions of the window)"
        )
    return (x, y, w, h)


CROP_QUANTUM = 32
"""Crops for particle scoring are whole multiples of this many pixels (see :func:`_crop_span`)."""


def _crop_span(lo: float, hi: float, margin: int, align: int, size: int) -> tuple[int, int]:
    """``[start, stop)`` pixels along one axis of a crop holding ``[lo, hi]`` plus ``margin``:
    ``start`` on the ``align`` grid, the length rounded up to a multiple of
    :data:`CROP_QUANTUM` and moved back inside ``[0, size)`` (a crop at the frame's edge ends on
    it). The scores read from any such crop equal the whole frame's; the rounding keeps the
    number of distinct crop shapes small, which matters because oneDNN caches one compiled
    convolution per input shape (up to 1,024 of them): crops of every possible size made the
    channel gradients' cache, and the resident memory of a long multi-target run, grow
    (``tools/bench_memory.py``), and each new shape cost a compilation."""
    import math

    start = max(0, math.floor(lo) - margin) // align * align
    stop = min(size, math.ceil(hi) + margin)
    length = max(stop - start, 1)
    length = -(-length // CROP_QUANTUM) * CROP_QUANTUM
    stop = start + length
    if stop > size:  # end on the frame's edge; start as far left as the quantum asks
        stop = size
        start = max(0, (size - length) // align * align)
    return start, stop


@dataclass
class Detector:
    """A trained detector.

    Attributes:
        bank: the feature bank: the full Haar bank of the training window
            (:class:`~torchtrack.features.haar.HaarBank`) or channel features
            (:class:`~torchtrack.features.channels.ChannelBank`, usually only those the
            classifier uses).
        feature_index: ``(K,)`` int64, the selected features (indices into ``bank``); the
            classifier sees them in this order.
        classifier: a fitted :class:`torchtrack.learn.BoostedStumps`,
            :class:`~torchtrack.learn.BoostedTrees` or :class:`~torchtrack.learn.SVMClassifier`
            (anything with a torch ``decision_function`` on ``(..., K)``, ``n_features_in_`` and
            ``to_state()``).
        calibrator: a fitted :class:`torchtrack.learn.PlattCalibrator` or
            :class:`~torchtrack.learn.IsotonicCalibrator`; ``None`` until calibrated.
        name: a label, e.g. ``"pedestrian"``.
        summary: JSON-safe training summary (data counts, held-out metrics, split).
        object_box: where the object lies inside the detector window, as ``(x, y, w, h)``
            fractions of the window's width and height (``None``: the object fills the window).
            Detectors trained on crops with a margin score a window larger than the object
            (INRIA pedestrians: ``(0.25, 0.125, 0.5, 0.75)``, a 32x96 person in the 64x128
            window, Dalal and Triggs' 16-px margin on every side); detections and tracks are
            reported as object boxes (:meth:`window_to_object`).
        tracking_head: ``(n_trees, calibrator)``: the first ``n_trees`` trees of a boosted-trees
            classifier with a Platt calibration of their own running margin, fitted on the same
            held-out windows as ``calibrator`` (``None``: no head). A particle filter scores
            hundreds of windows per target and frame; the head reads the few features those
            trees use (:meth:`tracking_model`), so its calibrated probability costs a fraction
            of the full classifier's, and it is smoother around the object (a likelihood that
            still rises as a window nears the object), which a particle filter needs.
        box_regressor: a :class:`~torchtrack.detect.box_regression.BoxRegressor` on the
            selected features that moves a detection window to where the training crops put
            the object (:meth:`refine_windows`; scans apply it to the windows they keep), or
            ``None``.

    Save and load it with :func:`torchtrack.detect.save_detector` /
    :func:`~torchtrack.detect.load_detector`.
    """

    bank: HaarBank | ChannelBank
    feature_index: torch.Tensor
    classifier: Any
    calibrator: Any = None
    name: str = "detector"
    summary: dict[str, Any] = field(default_factory=dict)
    object_box: tuple[float, float, float, float] | None = None
    tracking_head: tuple[int, Any] | None = None
    box_regressor: Any = None

    def __post_init__(self) -> None:
        if self.object_box is not None:
            self.object_box = check_object_box(self.object_box)
        self.feature_index = (
            torch.as_tensor(self.feature_index, dtype=torch.int64).reshape(-1).cpu()
        )
        k = self.feature_index.numel()
        if k == 0:
            raise ModelFormatError("a detector needs at least one selected feature")
        if int(self.feature_index.min()) < 0 or int(self.feature_index.max()) >= len(self.bank):
            raise ModelFormatError(
                f"selected feature indices must lie in [0, {len(self.bank)}) for this bank"
            )
        n_in = getattr(self.classifier, "n_features_in_", None)
        if n_in is None:
            raise NotFittedError("the detector's classifier is not fitted (no n_features_in_)")
        if int(n_in) != k:
            raise ModelFormatError(
                f"the classifier reads {n_in} features but {k} features are selected"
            )
        reg = self.box_regressor
        if reg is not None and reg.n_features != k:
            raise ModelFormatError(
                f"the box regressor reads {reg.n_features} features but {k} features are selected"
            )

    @property
    def window(self) -> tuple[int, int]:
        """``(H, W)`` of the training window."""
        return self.bank.window

    def window_to_object(self, boxes: torch.Tensor) -> torch.Tensor:
        """Object boxes ``(..., 4)`` of detector windows ``boxes (..., 4)`` (x, y, w, h pixels);
        the windows themselves when the model has no ``object_box``."""
        if self.object_box is None:
            return boxes
        fx, fy, fw, fh = self.object_box
        x, y, w, h = boxes.unbind(-1)
        return torch.stack((x + fx * w, y + fy * h, fw * w, fh * h), -1)

    def object_to_window(self, boxes: torch.Tensor) -> torch.Tensor:
        """Detector windows ``(..., 4)`` around object boxes ``(..., 4)``: the inverse of
        :meth:`window_to_object` (the window keeps the detector's aspect ratio only when the
        object box has the aspect ratio of ``object_box``; the height decides the scale)."""
        if self.object_box is None:
            return boxes
        fx, fy, fw, fh = self.object_box
        wh, ww = self.window
        x, y, w, h = boxes.unbind(-1)
        win_h = h / fh
        win_w = win_h * (ww / wh)
        cx = x + w / 2 - (fx + fw / 2) * win_w + win_w / 2
        cy = y + h / 2 - (fy + fh / 2) * win_h + win_h / 2
        return torch.stack((cx - win_w / 2, cy - win_h / 2, win_w, win_h), -1)

    def with_calibrator(self, calibrator: Any) -> Detector:
        """A copy with another fitted calibrator (``predict_proba`` on margins); the tracking
        head, calibrated for the old classifier's margins, is dropped."""
        return replace(self, calibrator=calibrator, tracking_head=None)

    def tracking_model(self) -> Detector:
        """The detector the trackers score particle windows with: :attr:`tracking_head`'s
        first trees, reading only the features they use, with the head's calibration; this
        detector itself when it has no head.

        Example::

            det = load_model("pedestrian")          # 1024 trees, ~1,850 features
            fast = det.tracking_model()             # e.g. 64 trees, ~120 features
            p = fast.score(frames, boxes)           # calibrated P(object | window)
        """
        if self.tracking_head is None:
            return self
        n_trees, calibrator = self.tracking_head
        head = self.classifier.truncated(int(n_trees))
        used = torch.unique(head.feature_)
        dev = used.device
        remap = torch.full((self.feature_index.numel(),), -1, dtype=torch.long, device=dev)
        remap[used] = torch.arange(used.numel(), device=dev)
        head.feature_ = remap[head.feature_]
        head.n_features_in_ = int(used.numel())
        return replace(
            self,
            feature_index=self.feature_index[used.cpu()],
            classifier=head,
            calibrator=calibrator,
            name=f"{self.name}[:{n_trees}]",
            tracking_head=None,
            box_regressor=None,  # it reads every selected feature; particles need no refining
        )

    @property
    def colour(self) -> bool:
        """Whether the features read colour (LUV channels): such a model gives lower scores on
        grayscale frames (they are taken as R = G = B, so U = V = 0)."""
        chans = getattr(self.bank, "channels", None)
        return bool(getattr(chans, "colour", False))

    def integrals(self, frames: torch.Tensor) -> Any:
        """The integral images every box on ``frames (B, C, H, W)`` (0..255, C = 1 or RGB) is
        read from: compute them once per frame batch and pass them to :meth:`features`,
        :meth:`decision_function` or :meth:`score` in place of the frames."""
        return self.bank.integrals(frames)

    def integrals_for(
        self, frames: torch.Tensor, boxes: torch.Tensor, ok: torch.Tensor | None = None
    ) -> tuple[Any, torch.Tensor]:
        """Integral images over only the part of ``frames (B, C, H, W)`` that ``boxes
        (B, N, 4)`` need (the boxes' in-frame parts plus the context the features need, e.g.
        the gradient normalisation radius of channel features), and the boxes shifted into that
        crop. Scores read from them equal those of the whole frames; a tracker's particles
        cover a small part of the frame, so this is much cheaper.

        Args:
            ok: ``(B, N)`` bool, the boxes to consider (default all).

        Returns:
            ``(integrals, boxes (B, N, 4) in crop pixels)``.
        """
        import math

        fh, fw = int(frames.shape[-2]), int(frames.shape[-1])
        boxes = boxes.to(frames.device)  # the frame's device wins
        if ok is None:
            ok = torch.ones(boxes.shape[:2], dtype=torch.bool, device=boxes.device)
        ok = ok.to(boxes.device)
        if not bool(ok.any()):
            return self.integrals(frames), boxes
        x, y, w, h = boxes.unbind(-1)
        big = math.inf
        x0 = float(torch.where(ok, x.clamp(0, fw), big).min())
        y0 = float(torch.where(ok, y.clamp(0, fh), big).min())
        x1 = float(torch.where(ok, (x + w).clamp(0, fw), -big).max())
        y1 = float(torch.where(ok, (y + h).clamp(0, fh), -big).max())
        margin, align = self.bank.crop_context(boxes[ok])
        ix0, ix1 = _crop_span(x0, x1, margin, align, fw)
        iy0, iy1 = _crop_span(y0, y1, margin, align, fh)
        sub = frames[:, :, iy0:iy1, ix0:ix1]
        shift = boxes.new_tensor([float(ix0), float(iy0), 0.0, 0.0])
        return self.integrals(sub), boxes - shift

    def features(self, frames: Any, boxes: torch.Tensor, *, check: bool = True) -> torch.Tensor:
        """Selected features ``(B, N, K)`` of ``boxes (B, N, 4)`` (x, y, w, h pixels) on
        ``frames (B, C, H, W)`` (0..255, C = 1 or RGB) or on their :meth:`integrals`.

        Args:
            check: validate the boxes (finite, at least one pixel, overlapping the frame).
        """
        ints = self.integrals(frames) if isinstance(frames, torch.Tensor) else frames
        return self.bank.features_at(ints, boxes, self.feature_index, check=check)

    def refine_windows(self, frames: Any, windows: torch.Tensor) -> torch.Tensor:
        """Detection windows ``(B, N, 4)`` moved and scaled by :attr:`box_regressor` to where
        the object sits in the training crops (read on ``frames (B, C, H, W)`` or their
        :meth:`integrals`); the windows as they are when the detector has no regressor."""
        if self.box_regressor is None or windows.shape[-2] == 0:
            return windows
        return self.box_regressor.apply(windows, self.features(frames, windows, check=False))

    def margin_from_features(self, feats: torch.Tensor) -> torch.Tensor:
        """Raw classifier margins ``m(f)`` of selected features ``(..., K)`` -> ``(...)``."""
        if feats.shape[-1] != self.feature_index.numel():
            raise ShapeError(
                f"expected {self.feature_index.numel()} selected features in the last axis, "
                f"got shape {tuple(feats.shape)}"
            )
        return self.classifier.decision_function(feats)

    def proba_from_margin(self, margin: torch.Tensor) -> torch.Tensor:
        """Calibrated probabilities of margins (eq. 8)."""
        if self.calibrator is None:
            raise NotFittedError(
                f"detector {self.name!r} has no calibration; fit one with `torchtrack calibrate`"
            )
        return self.calibrator.predict_proba(margin)

    def decision_function(self, frames: Any, boxes: torch.Tensor) -> torch.Tensor:
        """Raw margins ``(B, N)`` of ``boxes (B, N, 4)``."""
        return self.margin_from_features(self.features(frames, boxes))

    def score(self, frames: Any, boxes: torch.Tensor) -> torch.Tensor:
        """Calibrated probabilities ``(B, N)`` that each box of ``boxes (B, N, 4)`` (x, y, w, h
        in pixels, any size) holds the class, on ``frames (B, C, H, W)`` or their
        :meth:`integrals` (compute once per frame when scoring several box sets). Every window
        gets the full classifier (no cascade).

        Raises:
            BoxError: a box is not finite, under one pixel, or entirely outside its frame.
            DataError: a pixel is not finite or outside [0, 255].
            NotFittedError: the detector has no calibration.
        """
        return self.proba_from_margin(self.decision_function(frames, boxes))

    def scan(self, frames: torch.Tensor, *, windows: bool = False, **kwargs: Any):
        """Multi-scale sliding-window detection with NMS (paper section 4.2).

        ``frames (C, H, W)`` -> ``(boxes (K, 4), probabilities (K,))``;
        ``frames (B, C, H, W)`` -> a list of B such pairs (batched integral images).

        Frames hold 0..255 levels, uint8 or float (C = 1 or RGB). Float frames scaled to
        [0, 1] must be multiplied by 255 first: read as levels they are a nearly black frame,
        in which nothing is found. They cannot be told from a dark 0..255 frame, so they are
        not refused: a float frame whose values all lie in [0, 1] (not all 0) warns.

        Args:
            windows: report the detector windows instead of the object boxes (by default the
                boxes are :meth:`window_to_object` of the windows, and non-maximum suppression
                compares object boxes, so that people close together are not merged by the
                margins of their windows).
            kwargs: threshold, stride, scale_step, min_scale, max_scale, nms_iou, cascade, ...
                of :func:`torchtrack.detect.scan.scan_batch`.

        Raises:
            ShapeError: not ``(C, H, W)`` or ``(B, C, H, W)``, or smaller than the window.
            DataError: a pixel not finite or outside [0, 255].

        Warns:
            UserWarning: float frames whose values all lie in [0, 1] (not all 0).
        """
        from torchtrack.detect.scan import scan_batch, warn_unit_range

        if not isinstance(frames, torch.Tensor) or frames.ndim not in (3, 4):
            got = tuple(frames.shape) if isinstance(frames, torch.Tensor) else type(frames).__name__
            raise ShapeError(f"scan takes frames (C, H, W) or (B, C, H, W), got {got}")
        single = frames.ndim == 3
        batch = frames[None] if single else frames
        warn_unit_range(batch)
        kwargs.setdefault("nms_on", "window" if windows else "object")
        out = scan_batch(self, batch, **kwargs)
        if not windows:
            out = [(self.window_to_object(b), p) for b, p in out]
        return out[0] if single else out

    def selected_features(self) -> list[dict[str, Any]]:
        """The selected features as ``{"kind", "size", "y", "x"}`` records, in order."""
        return [self.bank.describe(int(i)) for i in self.feature_index]
