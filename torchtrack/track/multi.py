"""Multi-target detect-and-track: every target of a video in one batched particle filter.

Every live target is one row of a particle set ``(T, N, 6)`` with Chateau et al.'s state
``X = (c_t, c_{t-1}, s_t, s_{t-1})`` (eq. 2: window centre and scale, the scale relative to the
target's reference window) and the fitted AR dynamics of eq. (4); all rows are resampled,
predicted and weighted in one call per frame. Per frame:

1. **Predict** every target (its motion noise widens while it goes unmatched).
2. **Detect** every ``scan_every`` frames (or take detections given from outside): the detector
   scans the frame; its windows, moved by the model's box regressor (``scan_box_regression``),
   become object boxes (:meth:`~torchtrack.detect.Detector.window_to_object`).
   Once the video's ground plane (:class:`~torchtrack.track.ground.GroundPlane`: object height
   against foot row, learnt from the confirmed targets' confident matches) holds, the scan
   scores only the windows whose object box fits it (the line of ``GROUND_LAG`` frames before,
   so that scans run ahead in other processes give the same detections) and detections that do
   not fit the current line are dropped (``ground_gate``).
3. **Associate** (:mod:`torchtrack.track.association`, ``scipy.optimize.linear_sum_assignment``)
   in ByteTrack's order, which calibrated probabilities make meaningful: confirmed targets with
   the confident detections (``>= birth_threshold``) on overlap through the filter plus
   appearance; the confirmed targets left with the weaker ones (``>= detection_threshold``) on
   overlap alone; then the tentative targets with the confident detections left.
4. **Weight** each particle by the detector's calibrated probability of its window (the
   likelihood of Chateau et al. eq. 11, all windows of all targets scored from one integral
   image; by default with the model's tracking head, its first trees with their own Platt
   calibration, :meth:`~torchtrack.detect.Detector.tracking_model`), times the target's colour-model likelihood ``exp(-lambda (1 - BC))`` (Pérez et al.),
   times, for a matched target, a Gaussian around its detection (the detection as a measurement,
   as in Breitenstein et al., "Robust tracking-by-detection using a detector confidence particle
   filter", ICCV 2009). A matched target whose particles do not reach its detection (overlap
   below ``reseed_overlap``) is re-seeded around it; with the default gate (``overlap_gate``
   0.3 = ``reseed_overlap``) a pair that overlaps so little is not made in the first place.
5. **Births and deaths**: a confident detection that matches nothing starts a tentative target
   (its particles' velocities drawn with an sd of ``birth_velocity`` x its window height a
   frame: the next detections choose among them), confirmed (and given its public identity) after ``confirm_hits`` matched scans in a row.
   "Confident" adapts to the video: where even its people score lower than the detector's
   training people do (low contrast, noise, another camera), the threshold follows the
   video's level down to ``birth_floor``, and a birth below ``birth_threshold`` must also be
   moving (its box changed more than the frame does), so a person-like patch of a still
   background does not start one;
   a target unmatched for more than ``max_lost`` frames, or whose box has left the frame, ends;
   so does a confirmed target that sits on another one (IoU above ``duplicate_iou``) and
   either missed its detection on the last scans while the other was matched, or took turns
   with it at one detection (ByteTrack's duplicate removal, safe for two people who overlap).
   At most ``max_targets`` live at once; memory is flat however long the video.

A confirmed target is reported while it is matched, and for up to ``max_coast`` frames after
its last match while the filter's evidence (the mean calibrated probability of its particles)
stays at least ``visible_threshold``. Boxes are object boxes (the person, not the detector
window with its training margin), moved on their frame by the model's box regressor
(``report_box_regression``; on the tracker's own scans) while the particles stay as filtered.

Example::

    mt = MultiTargetTracker("pedestrian", scan_every=2)
    for frame in frames:                       # (C, H, W) uint8
        out = mt.update(frame)                 # MultiState: ids (K,), boxes (K, 4), ...
"""

from __future__ import annotations

import collections
import math
import os
import warnings
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import torch

from torchtrack.boxes import xywh_to_xyxy
from torchtrack.errors import ConfigError, ShapeError, TrackerError
from torchtrack.filter.particles import normalize_with_lse
from torchtrack.filter.resample import resample
from torchtrack.filter.sir import get_estimator
from torchtrack.observe.detector import DetectorObservation
from torchtrack.track.association import association_cost, expected_iou, linear_assignment
from torchtrack.track.base import check_tracker_generator
from torchtrack.track.config import MultiTrackerConfig, apply_overrides, resolve_tracker_config
from torchtrack.track.detector_pf import load_dynamics, resolve_detector
from torchtrack.track.ground import GroundLine, GroundPlane

if TYPE_CHECKING:
    from torchtrack.observe.histogram import FrameBins

__all__ = ["MultiState", "MultiTargetTracker", "score_probabilities", "track_sequence"]

#: the scan of frame t keeps the windows that fit the ground plane as it was after frame
#: t - GROUND_LAG (so scans run ahead in other processes, at most this many frames ahead, use
#: the same line as scans run here)
GROUND_LAG = 16

#: two birth candidates of one frame that overlap more than this (IoU) are the same detection
SAME_BOX_IOU = 0.9

#: adaptive births (``birth_floor``): the video's detection level is the median of the best
#: detection of each of its last LEVEL_SCANS scans, once there are MIN_LEVEL_SCANS of them
LEVEL_SCANS = 64
MIN_LEVEL_SCANS = 8
#: a birth below ``birth_threshold`` (adapted to the video's level) also needs its box to have
#: changed since MOTION_LAG frames before by MOTION_RATIO times the whole frame's median change,
#: plus MOTION_MIN (on the sum of the frame's channels): something moves there, more than the
#: camera's noise does
MOTION_LAG = 4
MOTION_RATIO = 2.0
MOTION_MIN = 3.0
#: the least phase-correlation peak (0..1) taken as the camera's translation between frames,
#: and how much of the frame's median change the translation must explain (aligned median
#: below this share of the unaligned one)
CAMERA_PEAK = 0.1
CAMERA_EXPLAINS = 0.5
#: ``duplicate_heading``: a target's heading runs from its observation (matched detection) this
#: many frames back to its latest one (Cao et al.'s delta t = 3); the last OBSERVATIONS matches
#: are kept
DIRECTION_LAG = 3
OBSERVATIONS = DIRECTION_LAG + 1
#: a target sitting on another one (``duplicate_iou``) that has missed its detection on this
#: many scans in a row while the other was matched more recently is a duplicate of it
DUPLICATE_MISSES = 2


@dataclass
class MultiState:
    """The reported targets of one frame.

    Attributes:
        ids: ``(K,)`` int64 identities (1, 2, ... in order of confirmation; stable while the
            target lives).
        boxes: ``(K, 4)`` float64 object boxes x, y, w, h in pixels.
        confidence: ``(K,)`` float64: the matched detection's calibrated probability, or the
            filter's evidence while the target coasts between detections.
        detected: ``(K,)`` bool: matched to a detection on this frame.
    """

    ids: torch.Tensor
    boxes: torch.Tensor
    confidence: torch.Tensor
    detected: torch.Tensor

    def __len__(self) -> int:
        return int(self.ids.shape[0])


class MultiTargetTracker:
    """Detect and track every target of a video (see the module notes).

    Args:
        model: a :class:`~torchtrack.detect.Detector`, a bundled model name or a model file;
            overrides ``config.model``.
        config: a :class:`MultiTrackerConfig` or a TOML file of one.
        generator: the source of randomness (reproducible runs).
        **overrides: any :class:`MultiTrackerConfig` field, e.g. ``scan_every=3``.

    Raises:
        ConfigError: bad options.
        NotFittedError: the detector has no calibration.
    """

    def __init__(
        self,
        model: Any = None,
        config: MultiTrackerConfig | str | os.PathLike | None = None,
        generator: torch.Generator | None = None,
        **overrides: Any,
    ) -> None:
        cfg = resolve_tracker_config(
            MultiTrackerConfig, config, overrides, where="multi-target tracker"
        )
        if model is not None and not isinstance(model, (str, os.PathLike)):
            self.detector = resolve_detector(model)
        else:
            if model is not None:
                cfg = apply_overrides(
                    cfg, {"model": os.fspath(model)}, where="multi-target tracker"
                )
            self.detector = resolve_detector(cfg.model)
        self.config = cfg
        generator = check_tracker_generator(generator)
        if generator is not None and generator.device.type != "cpu":
            raise ConfigError(
                f"the multi-target tracker's generator must be a CPU generator, got one on "
                f"{generator.device}: its filter keeps its targets on the CPU (the scan and the "
                "particles' likelihood run on the frame's device)"
            )
        self.generator = generator
        self.observation = DetectorObservation(
            self.detector, floor=cfg.likelihood_floor, head=cfg.likelihood == "head"
        )
        self.dynamics = load_dynamics(cfg.dynamics or None, structure="constant_velocity")
        self._estimate = get_estimator(cfg.estimator)
        self._bins = None
        if cfg.appearance == "colour":
            from torchtrack.observe.histogram import HSVBins

            self._bins = HSVBins()
        self._warned_full = False
        self.ground = GroundPlane()
        self.reset()

    # -- state -------------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget every target (a new video)."""
        f64 = torch.float64
        n = self.config.n_particles
        self.frame_index = -1
        # the frames' size as given, and inside the tracker (min_frame_height: upsampled)
        self.input_size: tuple[int, int] | None = None
        self._channels: int | None = None  # the first frame's, kept (1 gray, 3 RGB)
        self.frame_size: tuple[int, int] | None = None
        self.upsample = 1
        self._external = False  # detections come from outside (no scan, their own thresholds)
        self._crop = (None, None)  # (frame index, the particles' integral-image crop of it)
        self.states = torch.zeros((0, n, 6), dtype=f64)
        self.log_weights = torch.zeros((0, n), dtype=f64)
        self.ref = torch.zeros((0, 2), dtype=f64)  # reference window (w, h) at s = 1
        self.aspect = torch.zeros(0, dtype=f64)  # object width / the detector's object width
        self.ids = torch.zeros(0, dtype=torch.int64)  # 0 while tentative
        self.hits = torch.zeros(0, dtype=torch.int64)  # matched scans in a row
        self.since_match = torch.zeros(0, dtype=torch.int64)  # frames since the last match
        self.confirmed = torch.zeros(0, dtype=torch.bool)
        self.evidence = torch.zeros(0, dtype=f64)
        self.last_score = torch.zeros(0, dtype=f64)
        self.detected = torch.zeros(0, dtype=torch.bool)  # matched on this frame
        self.hist = torch.zeros((0, self._bins.n_bins if self._bins else 0), dtype=torch.float32)
        # the last OBSERVATIONS matched detections (centre x, y and height), oldest first, and
        # their frames (-1: none); headings() reads them
        self.obs_frames = torch.full((0, OBSERVATIONS), -1, dtype=torch.int64)
        self.obs = torch.zeros((0, OBSERVATIONS, 3), dtype=f64)
        self._next_id = 1
        # overlapping pairs of confirmed targets (ids) -> (each one matched since they began)
        self._turns: dict[tuple[int, int], tuple[bool, bool]] = {}
        self._scans = 0
        # the best logit of each recent scan, and the birth threshold they give
        self._levels: collections.deque = collections.deque(maxlen=LEVEL_SCANS)
        self._birth_p = self._lowest_birth_p = self.config.birth_threshold
        self._grays: collections.deque = collections.deque(maxlen=MOTION_LAG + 1)
        self._last_gray: torch.Tensor | None = None  # camera_motion: the previous frame
        # camera_motion: the camera's translation since the first frame, in the reported boxes'
        # pixels (a point of the scene is at its first-frame place + this); the smoother of
        # the reported tracks works in the scene's coordinates with it
        self.camera_offset: tuple[float, float] = (0.0, 0.0)
        #: the last frame's detections as the association saw them (after the thresholds and
        #: the ground plane), ``(boxes (M, 4) float64, probabilities (M,))`` in the frame's
        #: pixels and the reported boxes' convention (``report_shift``); None on a frame
        #: without a scan. The smoother's ``backfill`` reads them.
        self.last_detections: tuple[torch.Tensor, torch.Tensor] | None = None
        self.ground.reset()
        self._lines: collections.deque = collections.deque(maxlen=GROUND_LAG + 1)
        # the detector's noise, squared (estimated from the video: detection_sigma_rate)
        self._sigma2 = self.config.detection_sigma**2
        #: counts of what happened: births, confirmations, re-seeds, deaths by reason
        self.stats: Counter[str] = Counter()

    @property
    def n_targets(self) -> int:
        """Live targets, tentative ones included."""
        return int(self.states.shape[0])

    def _keep(self, keep: torch.Tensor) -> None:
        for name in (
            "states",
            "log_weights",
            "ref",
            "aspect",
            "ids",
            "hits",
            "since_match",
            "confirmed",
            "evidence",
            "last_score",
            "detected",
            "hist",
            "obs_frames",
            "obs",
        ):
            setattr(self, name, getattr(self, name)[keep])

    def smoother(self):
        """A :class:`~torchtrack.track.smoothing.TrackSmoother` for this tracker's reports
        (``fill_gaps``, ``smooth_sigma`` of its config): the reported tracks of ``torchtrack
        track`` and :func:`track_sequence` pass through it, ``lag`` frames late."""
        from torchtrack.track.smoothing import TrackSmoother

        cfg = self.config
        return TrackSmoother(
            cfg.smooth_sigma, cfg.fill_gaps, cfg.backfill, cfg.backfill_iou, cfg.unswap
        )

    # -- geometry ------------------------------------------------------------------------------
    def _windows(self, states: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
        """Eq. (3): ``states (T, N, 6)`` -> detector windows ``(T, N, 4)``."""
        wh = states[..., 4:5] * ref[:, None, :]
        return torch.cat([states[..., 0:2] - wh / 2, wh], -1)

    def particle_boxes(self) -> torch.Tensor:
        """Object boxes ``(T, N, 4)`` of every live target's particles (for drawing)."""
        return self.detector.window_to_object(self._windows(self.states, self.ref)) / self.upsample

    # -- detections ----------------------------------------------------------------------------
    def detect(
        self, frame: torch.Tensor, ground: GroundLine | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Scan ``frame (C, H, W)``: object boxes ``(M, 4)`` float64 and calibrated
        probabilities ``(M,)`` of the detections at least ``detection_threshold``.

        ``ground`` (:meth:`scan_ground`, with ``ground_gate`` on): only the windows whose
        object box fits that line (or that the frame's top or bottom edge cuts) are scored;
        the rest of the frame's windows would be dropped before association anyway. A frame
        shorter than ``min_frame_height`` is scanned upsampled 2x, as :meth:`update` tracks
        it (``ground`` is then in the upsampled pixels, as :meth:`scan_ground` gives it); the
        boxes are in the frame's own pixels.

        Raises:
            ShapeError: a frame smaller than the detector window at ``scan_min_scale``.
        """
        if frame.ndim == 3:
            frame = frame[None]
        if frame.ndim != 4 or frame.shape[0] != 1:
            raise ShapeError(f"detect takes one frame (C, H, W), got {tuple(frame.shape)}")
        return self.detect_batch(frame, [ground])[0]

    def detect_batch(
        self, frames: torch.Tensor, grounds: Sequence[GroundLine | None]
    ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """:meth:`detect` of each frame of ``frames (B, C, H, W)`` with its own ground line
        ``grounds[b]``, in one batched scan (:func:`~torchtrack.detect.scan.scan_batch`): the
        same detections as B calls, in fewer and larger tensor operations, which is what a
        GPU needs (:class:`~torchtrack.track.scan_ahead.ScanAhead` batches the frames it scans
        in this process).

        Raises:
            ShapeError: frames smaller than the detector window at ``scan_min_scale``.
            ConfigError: not one line per frame.
        """
        up = self._upsampling(frames.shape[-2])
        found = self._scan(self._upsampled(frames, up), grounds, up)
        return found if up == 1 else [(b / up, p) for b, p in found]

    def _upsampling(self, height: int) -> int:
        """The factor frames ``height`` pixels tall are upsampled by (``min_frame_height``)."""
        return 2 if int(height) < self.config.min_frame_height else 1

    @staticmethod
    def _upsampled(frames: torch.Tensor, up: int) -> torch.Tensor:
        """``frames (..., C, H, W)`` uint8 upsampled ``up`` times (bilinear, pixel centres at
        ``(i + 0.5) * up``, so a box's pixels scale by ``up`` exactly), still uint8."""
        if up == 1:
            return frames
        from kornia.geometry.transform import rescale

        x = frames.float()
        flat = x.reshape(-1, *x.shape[-3:])
        big = rescale(flat, float(up), interpolation="bilinear", align_corners=False)
        big = big.round_().clamp_(0, 255).to(torch.uint8)
        return big.reshape(*x.shape[:-2], *big.shape[-2:])

    def _scan(
        self, frames: torch.Tensor, grounds: Sequence[GroundLine | None], up: int = 1
    ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """:meth:`detect_batch` of frames already upsampled ``up`` times: boxes in their
        pixels."""
        from torchtrack.detect.scan import scan_batch

        cfg = self.config
        fh, fw = frames.shape[-2:]
        wh, ww = self.detector.window
        if fh < wh * cfg.scan_min_scale or fw < ww * cfg.scan_min_scale:
            # no window fits: the tracks would be empty as if the scene had no target
            from torchtrack.detect.scan import MIN_WINDOW_PX

            least = cfg.scan_min_scale
            fits = min(fh / wh, fw / ww)
            advice = (
                f"use scan_min_scale={fits:.3g} or less (--tracker multi:scan_min_scale=...), "
                "or larger frames"
                if fits * wh >= MIN_WINDOW_PX
                else f"frames this small hold no window of at least {MIN_WINDOW_PX} px"
            )
            size = f"{fh // up}x{fw // up} (HxW)"
            if up > 1:
                size += f", upsampled {up}x to {fh}x{fw} (min_frame_height),"
            raise ShapeError(
                f"frame {size} is smaller than the detector window {wh}x{ww} at the "
                f"smallest scan scale {least:g} ({wh * least:g}x{ww * least:g}): no target "
                f"can be detected; {advice}"
            )
        if len(grounds) != frames.shape[0]:
            raise ConfigError(
                f"detect_batch needs one ground line (or None) per frame: {len(grounds)} for "
                f"{frames.shape[0]} frames"
            )
        keeps = [
            None if line is None or cfg.ground_gate <= 0 else self._ground_keep(line, fh)
            for line in grounds
        ]
        found = scan_batch(
            self.detector,
            frames,
            threshold=cfg.detection_threshold,
            scale_step=cfg.scan_scale_step,
            stride=cfg.scan_stride,
            min_scale=cfg.scan_min_scale,
            max_scale=cfg.scan_max_scale or None,
            nms_iou=cfg.scan_nms,
            nms_on="object",  # as Detector.scan: window margins must not merge neighbours
            vote_iou=cfg.scan_vote or None,
            pad=cfg.scan_pad,
            cascade_threshold=cfg.scan_cascade or None,
            keep_windows=keeps,
            refine=cfg.scan_box_regression,
        )
        # the scan runs on the frames' device; the filter's bookkeeping lives on the CPU
        return [
            (self.detector.window_to_object(w.double()).cpu(), p.double().cpu()) for w, p in found
        ]

    def _ground_keep(self, line: GroundLine, height: int):
        """``ground_gate``: ``keep(windows (M, 4)) -> (M,) bool``, the windows whose object box
        fits ``line`` in a frame ``height`` pixels tall. It reads a window's y and height only
        (``by_row``: the scan asks one window per lattice row)."""

        def keep(w: torch.Tensor) -> torch.Tensor:
            return self._on_line(self.detector.window_to_object(w.double()), line, height)

        keep.by_row = True
        return keep

    def _on_line(self, boxes: torch.Tensor, line: GroundLine | None, height: int) -> torch.Tensor:
        """``(M,)`` bool: object boxes ``(M, 4)`` whose height fits ``line`` (``ground_gate``),
        or that the top or bottom edge of a frame ``height`` pixels tall cuts; all True
        without a line."""
        if line is None:
            return torch.ones(boxes.shape[0], dtype=torch.bool, device=boxes.device)
        return _cut(boxes, height) | line.consistent(boxes, self.config.ground_gate)

    def scans_next(self) -> bool:
        """Whether the next :meth:`update` falls on a frame this tracker scans (every
        ``scan_every``-th readable frame, from the first): where detections from outside, or
        cached scans, go in."""
        return (self.frame_index + 1) % self.config.scan_every == 0

    def scan_ground(self, t: int) -> GroundLine | None:
        """The line the scan of frame ``t`` (0-based, counted as :meth:`update` counts) uses:
        the ground plane as it was after frame ``t - GROUND_LAG``; None before that, while it
        is not fitted, or with ``ground_gate`` off.

        Raises:
            TrackerError: that frame is further back than this tracker remembers, or not
                tracked yet (a scan more than ``GROUND_LAG`` frames ahead)."""
        if not self._ground_on() or t < GROUND_LAG:
            return None
        for i, line in self._lines:
            if i == t - GROUND_LAG:
                return line
        raise TrackerError(
            f"the scan of frame {t + 1} needs the ground plane after frame {t - GROUND_LAG + 1}, "
            f"which this tracker does not hold (scans at most {GROUND_LAG} frames ahead)"
        )

    # -- the frame step ------------------------------------------------------------------------
    def update(
        self,
        frame: torch.Tensor,
        detections: tuple[torch.Tensor, torch.Tensor] | None = None,
        *,
        scan: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> MultiState:
        """Track into the next frame.

        Frames shorter than ``min_frame_height`` are upsampled 2x inside (``upsample``;
        ``frame_size`` is then the upsampled size, ``input_size`` the frame's own): boxes in
        and out stay in the frame's own pixels.

        Args:
            frame: ``(C, H, W)`` uint8 RGB or gray.
            detections: optional ``(boxes (M, 4), probabilities (M,))`` object boxes found by
                someone else (e.g. public detections); given, they replace this frame's scan
                (and a frame without them is not scanned either when any were given before).
            scan: this frame's own scan, ``detect(frame)``, computed elsewhere (by
                :class:`~torchtrack.track.scan_ahead.ScanAhead`'s workers): used as the scan
                (the scan's thresholds, not those of outside detections). Only on the frames
                this tracker scans; None there: it scans itself.

        Returns:
            :class:`MultiState` of the targets reported on this frame.

        Raises:
            ShapeError: a frame of the wrong type or size, or malformed detections (not boxes
                ``(M, 4)`` with probabilities ``(M,)`` in [0, 1], or a box that is not finite or
                has no area).
            TrackerError: ``scan`` given with ``detections``, or on a frame not scanned.
        """
        out = self._update(frame, detections, scan)
        if self.upsample == 1:
            return out
        if self.last_detections is not None:
            b, p = self.last_detections
            self.last_detections = (b / self.upsample, p)
        return MultiState(out.ids, out.boxes / self.upsample, out.confidence, out.detected)

    def _update(self, frame, detections, scan) -> MultiState:
        """:meth:`update` in the tracker's pixels (the frame upsampled by ``upsample``)."""
        cfg = self.config
        self._check_frame(frame)
        frame = self._upsampled(frame, self.upsample)
        t = self.frame_index + 1
        if scan is not None and (
            detections is not None or self._external or t % cfg.scan_every != 0
        ):
            raise TrackerError(
                f"scan given for frame {t + 1}, which this tracker does not scan (outside "
                f"detections, or not every scan_every = {cfg.scan_every}-th frame)"
            )
        self.frame_index = t
        gray = None  # the frame's channel sum, for the birth motion test and the camera
        if cfg.birth_floor < cfg.birth_threshold and detections is None and not self._external:
            gray = _channel_sum(frame)
            self._grays.append(gray)
        if detections is not None:
            det_boxes, det_p = self._check_detections(detections)
            det_boxes = det_boxes * self.upsample
            self._external = True
        elif scan is not None:
            det_boxes, det_p = self._check_detections(scan)
            det_boxes = det_boxes * self.upsample
        elif not self._external and t % cfg.scan_every == 0:
            det_boxes, det_p = self._scan(frame[None], [self.scan_ground(t)], self.upsample)[0]
        else:
            det_boxes = det_p = None
        scan = det_boxes is not None
        if scan:
            keep = det_p >= cfg.detection_threshold
            if self._ground_on() and bool(keep.any()):
                # a window of a person's size at the wrong place: a patch of background, a
                # part of one person, a group
                off = keep & ~self._on_line(det_boxes, self.ground.line_, self.frame_size[0])
                self.stats["detections off the ground plane"] += int(off.sum())
                keep &= ~off
            if self._external:
                dup = keep & self._weak_duplicates(det_boxes, det_p)
                self.stats["outside weak duplicates dropped"] += int(dup.sum())
                keep &= ~dup
            det_boxes, det_p = det_boxes[keep], det_p[keep]
            if not self._external:
                self._adapt_birth(det_p)
            shown = det_boxes.detach().to("cpu", torch.float64).clone()
            if cfg.report_shift and not self._external:
                shown[:, 1] -= cfg.report_shift * shown[:, 3]
            self.last_detections = (shown, det_p.detach().to("cpu", torch.float64))
        else:
            self.last_detections = None
        bin_map = None
        need = (scan and det_boxes.shape[0] > 0) or (
            self.n_targets > 0 and cfg.appearance_lambda > 0
        )
        if self._bins is not None and need:
            from torchtrack.observe.histogram import FrameBins

            # binned only where the histograms' samples fall (a few boxes a frame)
            bin_map = FrameBins(frame[None], self._bins)

        if cfg.camera_motion:
            self._follow_camera(_channel_sum(frame) if gray is None else gray)
        matched_det = torch.full((self.n_targets,), -1, dtype=torch.int64)
        if self.n_targets:
            has_dets = scan and det_boxes.shape[0] > 0
            propose = has_dets and cfg.detection_proposal > 0
            before = self._estimate(self.states, self.log_weights) if propose else None
            self._predict()
            if has_dets:  # on the motion model's prediction
                det_hist = (
                    self._histograms(bin_map, det_boxes[None])[0] if bin_map is not None else None
                )
                matched_det, overlap = self._associate(det_boxes, det_p, det_hist)
            if propose:  # part of each matched target's particles drawn at its detection
                self._propose(det_boxes, matched_det, before)
            p = self._probabilities(frame)  # (T, N)
            self.evidence = p.mean(1)
            # Breitenstein et al.'s occlusion term: where another target overlaps this one, the
            # class detector cannot tell whose evidence a window is; its weight shrinks with
            # the overlap (1 alone, 0 fully covered).
            occ, excl = self._interactions()
            log_l = p.clamp_min(cfg.likelihood_floor).log() * (1.0 - occ)[:, None]
            if cfg.exclusion > 0:
                log_l = log_l - cfg.exclusion * excl
            app = None
            if bin_map is not None and cfg.appearance_lambda > 0:
                app = self._particle_appearance(bin_map)  # (T, N) Bhattacharyya coefficients
                log_l = log_l - cfg.appearance_lambda * (1.0 - app)
            if has_dets:
                log_l = log_l + self._detection_term(det_boxes, matched_det)
                log_l = log_l + self._explained_away(det_boxes, matched_det)
                self._reseed(det_boxes, matched_det, overlap)
            self.log_weights, _, _ = normalize_with_lse(log_l, step="multi-target update")
            if scan:
                self._bookkeep(matched_det, det_p, det_boxes, bin_map)
            else:
                self.since_match += 1
                self.detected = torch.zeros_like(self.detected)
        used = set(matched_det[matched_det >= 0].tolist())
        if scan:
            self._scans += 1
            free = [j for j in range(det_boxes.shape[0]) if j not in used]
            self._births(det_boxes, det_p, free, bin_map)
        self._deaths()
        if self._ground_on():
            self._lines.append((t, self.ground.line_))
            self.stats["frames with a ground plane"] += self.ground.line_ is not None
        out = self._report()
        if cfg.report_box_regression and not self._external:
            out = self._refined_report(frame, out)
        if cfg.report_shift and not self._external and len(out.ids):
            boxes = out.boxes.clone()
            boxes[:, 1] -= cfg.report_shift * boxes[:, 3]
            out = replace(out, boxes=boxes)
        return out

    # -- steps ---------------------------------------------------------------------------------
    def _check_frame(self, frame: torch.Tensor) -> None:
        if (
            not isinstance(frame, torch.Tensor)
            or frame.ndim != 3
            or frame.shape[0] not in (1, 3)
            or frame.dtype != torch.uint8
        ):
            got = tuple(frame.shape) if isinstance(frame, torch.Tensor) else type(frame).__name__
            raise ShapeError(f"frame must be (C, H, W) uint8 with C = 1 or 3, got {got}")
        size = (int(frame.shape[-2]), int(frame.shape[-1]))
        if self.input_size is None:
            self.input_size = size
            self._channels = int(frame.shape[0])
            self.upsample = self._upsampling(size[0])
            self.frame_size = (size[0] * self.upsample, size[1] * self.upsample)
        elif size != self.input_size:
            raise ShapeError(
                f"frame size changed from {self.input_size} to {size} (H, W) at frame "
                f"{self.frame_index + 1}"
            )
        elif int(frame.shape[0]) != self._channels:
            # a gray frame after RGB ones was taken, its colour appearance compared with theirs
            raise ShapeError(
                f"frame channels changed from {self._channels} to {int(frame.shape[0])} at frame "
                f"{self.frame_index + 1}: give every frame in the first one's colour mode "
                "(1 gray, 3 RGB)"
            )

    @staticmethod
    def _check_detections(detections) -> tuple[torch.Tensor, torch.Tensor]:
        try:
            boxes, p = detections
        except (TypeError, ValueError):
            raise ShapeError(
                "detections must be a pair (boxes (M, 4), probabilities (M,))"
            ) from None
        try:
            boxes, p = torch.as_tensor(boxes), torch.as_tensor(p)
            # bool boxes were 1 x 1 pixel detections (a target was born on one), a bool
            # probability 1; complex ones lost their imaginary part with only a warning
            real = all(v.dtype != torch.bool and not v.is_complex() for v in (boxes, p))
            if real:
                boxes = boxes.to("cpu", torch.float64)
                p = p.to("cpu", torch.float64)
        except (TypeError, ValueError, RuntimeError, NotImplementedError) as exc:
            raise ShapeError(f"detections must be numeric tensors or arrays ({exc})") from None
        if not real:
            raise ShapeError(
                f"detections must be real numbers, got boxes {boxes.dtype} and probabilities "
                f"{p.dtype}"
            )
        if boxes.numel() == 0:
            boxes = boxes.reshape(0, 4)
        if boxes.ndim != 2 or boxes.shape[1] != 4 or p.ndim != 1:
            raise ShapeError(
                f"detections must be boxes (M, 4) and probabilities (M,), got "
                f"{tuple(boxes.shape)} and {tuple(p.shape)}"
            )
        if p.shape[0] != boxes.shape[0]:
            raise ShapeError(f"{boxes.shape[0]} detection boxes but {p.shape[0]} probabilities")
        bad = ~(torch.isfinite(boxes).all(1) & (boxes[:, 2] > 0) & (boxes[:, 3] > 0))
        if bool(bad.any()):
            k = int(bad.nonzero()[0])
            raise ShapeError(
                f"detection {k}: box {boxes[k].tolist()} must be finite with width and height > 0"
            )
        out = ~((p >= 0) & (p <= 1))  # NaN is out too
        if bool(out.any()):
            k = int(out.nonzero()[0])
            raise ShapeError(
                f"detection {k}: probability {float(p[k])} is not in [0, 1] (map other "
                "detectors' scores first: torchtrack.track.multi.score_probabilities)"
            )
        return boxes, p

    def ground_summary(self) -> str | None:
        """One line on the ground plane of the video so far (None when it is not in use: off,
        or detections given from outside)."""
        if not self._ground_on():
            return None
        used, off = (
            self.stats["frames with a ground plane"],
            self.stats["detections off the ground plane"],
        )
        if not used:
            return "no ground plane learnt (every window scanned)"
        line = self.ground.line_
        now = (
            "no line at the end (its boxes no longer agreed on one)"
            if line is None
            else f"h = {line.a:.3f} y {'+' if line.b >= 0 else '-'} "
            f"{abs(line.b) / self.upsample:.1f} px at foot row y ({line.n} boxes, log-height sd "
            f"{line.sd:.3f})"
        )
        return (
            f"ground plane: {now}; a line on {used} of {self.frame_index + 1} frames, "
            f"{off} detection(s) off it dropped"
        )

    def birth_summary(self) -> str | None:
        """One line on adapted births (``birth_floor``) when the video's level took the birth
        threshold below ``birth_threshold``; None otherwise."""
        cfg = self.config
        if self._lowest_birth_p >= cfg.birth_threshold:
            return None
        return (
            f"births adapted to the video's detection level: threshold down to "
            f"{self._lowest_birth_p:.6g} (from {cfg.birth_threshold:g}), "
            f"{self.stats['adapted births refused: not moving']} still window(s) refused"
        )

    def camera_summary(self) -> str | None:
        """One line on the camera's motion (``camera_motion``) when it moved the targets on
        some frame; None otherwise (a still camera, or off)."""
        n = self.stats["frames with a camera shift"]
        if not n:
            return None
        return f"camera motion followed on {n} of {self.frame_index + 1} frame(s)"

    def _ground_on(self) -> bool:
        """The ground plane is learnt and used on this tracker's own scans (``ground_gate``);
        detections given from outside are taken as they come."""
        return self.config.ground_gate > 0 and not self._external

    def _predict(self) -> None:
        cfg = self.config
        anc, _, _ = resample(self.log_weights, cfg.resample, None, self.generator)
        states = torch.gather(self.states, 1, anc.unsqueeze(-1).expand(-1, -1, 6))
        lost = (self.since_match - (cfg.scan_every - 1)).clamp_min(0).to(torch.float64)
        scale = (1.0 + cfg.lost_noise_growth * lost).clamp(max=cfg.max_noise_scale)
        self.states = self.dynamics.predict(
            states, self.generator, noise_scale=self._noise_scale(states) * scale[:, None]
        )
        n = self.states.shape[1]
        self.log_weights = torch.full_like(self.log_weights, -math.log(n))

    def _noise_scale(self, states: torch.Tensor, ref: torch.Tensor | None = None) -> torch.Tensor:
        """``(T, 6)`` factor on the fitted noise's sd per target and state component:
        ``motion_noise``, times on the centre ``object height / noise_height`` when set."""
        cfg = self.config
        t = states.shape[0]
        out = torch.full((t, 6), cfg.motion_noise, dtype=torch.float64, device=states.device)
        if cfg.noise_height > 0 and t:
            ref = self.ref if ref is None else ref
            fh = self.detector.object_box[3] if self.detector.object_box is not None else 1.0
            h = states[..., 4].mean(1) * ref[:, 1] * fh  # (T,) object height, pixels
            out[:, 0:4] *= (h / cfg.noise_height)[:, None]
        return out

    def _interactions(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Target-target interactions from the predicted boxes (mean field).

        Returns:
            ``occlusion (T,)``: each target's largest IoU with another target's predicted
            window; ``exclusion (T, N)``: each particle window's largest IoU with another
            target's predicted window (the interaction potential of Khan, Balch and Dellaert,
            "MCMC-based particle filtering for tracking a variable number of interacting
            targets", PAMI 2005: two targets do not take the same place).
        """
        t, n = self.states.shape[:2]
        if t < 2:
            z = torch.zeros(t, dtype=torch.float64)
            return z, torch.zeros((t, n), dtype=torch.float64)
        from torchtrack.boxes import box_iou_matrix

        est = self._estimate(self.states, self.log_weights)
        boxes = self._windows(est[:, None], self.ref)[:, 0]  # (T, 4)
        iou = box_iou_matrix(boxes, boxes)
        iou.fill_diagonal_(0)
        pw = self._windows(self.states, self.ref).reshape(t * n, 4)
        piou = box_iou_matrix(pw, boxes).reshape(t, n, t)
        own = torch.arange(t)
        piou[own, :, own] = 0.0
        return iou.max(1).values.clamp(0.0, 1.0), piou.max(2).values

    def _probabilities(self, frame: torch.Tensor) -> torch.Tensor:
        wins = self._windows(self.states, self.ref)
        t, n = wins.shape[:2]
        p = self.observation.probabilities(frame[None], wins.reshape(1, t * n, 4).to(frame.device))
        self._crop = (self.frame_index, self.observation.last_crop)
        return p.reshape(t, n).to("cpu", torch.float64)

    def _histograms(self, bin_map: FrameBins, boxes: torch.Tensor) -> torch.Tensor:
        from torchtrack.observe.histogram import box_histograms

        return box_histograms(bin_map, boxes, self._bins.n_bins, grid=8)

    def _particle_appearance(self, bin_map: FrameBins) -> torch.Tensor:
        from torchtrack.observe.histogram import bhattacharyya

        t, n = self.states.shape[:2]
        boxes = self.particle_boxes().reshape(1, t * n, 4)
        h = self._histograms(bin_map, boxes).reshape(t, n, -1)
        return bhattacharyya(h, self.hist[:, None, :]).to(torch.float64)

    def _weak_duplicates(self, det_boxes: torch.Tensor, det_p: torch.Tensor) -> torch.Tensor:
        """``(M,)`` bool: weak detections (below the birth threshold) that the scan's own NMS
        (:func:`~torchtrack.detect.scan.nms` at ``scan_nms``) would suppress. Another detector
        may suppress less (the MOT15 public detections of TUD-Stadtmitte keep pairs at IoU
        0.4-0.5): its low-score boxes beside a person's main box then feed a second target on
        that person in the weak association, which ends the first as a duplicate, and the
        person changes identity. Only weak boxes are dropped; two confident ones (two people
        side by side) both stay."""
        from torchtrack.detect.scan import nms

        weak = det_p < self._birth_threshold()
        if not bool(weak.any()):
            return weak
        kept = torch.zeros_like(weak)
        kept[nms(det_boxes, det_p, self.config.scan_nms)] = True
        return weak & ~kept

    def _associate(
        self, det_boxes: torch.Tensor, det_p: torch.Tensor, det_hist: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """ByteTrack-order assignment; returns ``(matched detection per target (T,), -1 for
        none; expected overlap (T, M))``."""
        cfg = self.config
        t = self.n_targets
        # Overlap through the filter: the better of the IoU with the estimate and the expected
        # IoU under the particles (the first does not shrink when the particles spread).
        from torchtrack.boxes import box_iou_matrix

        overlap = torch.maximum(
            expected_iou(self.particle_boxes(), self.log_weights, det_boxes),
            box_iou_matrix(self._estimated_boxes(), det_boxes),
        )  # (T, M)
        app = None
        if det_hist is not None:
            from torchtrack.observe.histogram import bhattacharyya

            app = bhattacharyya(self.hist[:, None, :], det_hist[None, :, :]).to(torch.float64)
        matched = torch.full((t,), -1, dtype=torch.int64)
        high = det_p >= self._birth_threshold()
        conf_rows = torch.nonzero(self.confirmed).flatten()
        tent_rows = torch.nonzero(~self.confirmed).flatten()
        free_det = torch.ones(det_boxes.shape[0], dtype=torch.bool)

        def stage(rows: torch.Tensor, cols_mask: torch.Tensor, use_app: bool) -> None:
            cols = torch.nonzero(cols_mask & free_det).flatten()
            rows = rows[matched[rows] < 0]
            if rows.numel() == 0 or cols.numel() == 0:
                return
            o = overlap[rows][:, cols]
            a = app[rows][:, cols] if (use_app and app is not None) else None
            cost = association_cost(
                o,
                a,
                w_overlap=cfg.w_overlap,
                w_appearance=cfg.w_appearance,
                gate=cfg.overlap_gate,
            )
            res = linear_assignment(cost, cfg.max_cost)
            for r, c in res.pairs.tolist():
                matched[rows[r]] = cols[c]
                free_det[cols[c]] = False

        stage(conf_rows, high, use_app=True)
        stage(conf_rows, ~high, use_app=False)
        stage(tent_rows, high, use_app=True)
        return matched, overlap

    def _observe(self, rows: torch.Tensor, boxes: torch.Tensor) -> None:
        """Targets ``rows`` matched (or were born from) detections ``boxes (R, 4)`` on this
        frame: kept as their latest observations."""
        seen = torch.cat([boxes[:, 0:2] + boxes[:, 2:4] / 2, boxes[:, 3:4]], 1)
        self.obs_frames[rows] = torch.cat(
            [self.obs_frames[rows, 1:], torch.full((rows.numel(), 1), self.frame_index)], 1
        )
        self.obs[rows] = torch.cat([self.obs[rows, 1:], seen[:, None]], 1)

    def headings(self) -> torch.Tensor:
        """``(T, 2)`` unit vectors: each target's heading, from its observation
        ``DIRECTION_LAG`` frames before its latest one (the oldest kept from then on, else the
        one before the latest: Cao et al.'s ``k_previous_obs``) to the latest; 0 with a single
        observation, or for a move shorter than ``detection_sigma`` of the latest height."""
        f = self.obs_frames
        before = f[:, :-1]
        recent = (before >= (f[:, -1] - DIRECTION_LAG)[:, None]) & (before >= 0)
        first = torch.where(recent.any(1), recent.long().argmax(1), before.shape[1] - 1)
        rows = torch.arange(f.shape[0])
        latest = self.obs[:, -1]
        d = latest[:, 0:2] - self.obs[rows, first, 0:2]
        norm = d.norm(dim=-1, keepdim=True)
        moved = (f[rows, first] >= 0) & (norm[:, 0] >= self.config.detection_sigma * latest[:, 2])
        return torch.where(moved[:, None], d / norm.clamp_min(1e-9), 0.0)

    def _detection_term(self, det_boxes: torch.Tensor, matched: torch.Tensor) -> torch.Tensor:
        """Log Gaussian of each particle around its target's matched detection (0 elsewhere):
        ``(T, N)``."""
        out = torch.zeros(self.states.shape[:2], dtype=torch.float64)
        rows = torch.nonzero(matched >= 0).flatten()
        if rows.numel() == 0:
            return out
        win = self.detector.object_to_window(det_boxes[matched[rows]])  # (R, 4)
        dc = win[:, 0:2] + win[:, 2:4] / 2
        ds = win[:, 3] / self.ref[rows, 1]
        st = self.states[rows]
        if self.config.detection_sigma_rate > 0:
            self._adapt_sigma(st, dc, ds, win[:, 3])
        sig = self.detection_sigma
        sd = sig * win[:, 3:4]
        d2 = (((st[..., 0:2] - dc[:, None, :]) / sd[:, None, :]) ** 2).sum(-1)
        ls = (st[..., 4].clamp_min(1e-6).log() - ds.log()[:, None]) / sig
        out[rows] = -0.5 * (d2 + ls**2)
        return out

    @property
    def detection_sigma(self) -> float:
        """The detector's noise the matched detections are weighted with: ``detection_sigma``,
        or its running estimate with ``detection_sigma_rate > 0``."""
        return math.sqrt(self._sigma2)

    def _adapt_sigma(
        self, st: torch.Tensor, dc: torch.Tensor, ds: torch.Tensor, h: torch.Tensor
    ) -> None:
        """Innovation-based estimate of the detector's noise from this scan's matches:
        particles ``st (R, N, 6)`` before the detection weighs them, detection window centres
        ``dc (R, 2)``, scales ``ds (R,)`` and heights ``h (R,)``."""
        ls = st[..., 4].clamp_min(1e-6).log()
        c = st[..., 0:2]
        # squared innovation over its 3 components (centre / height, log scale) ...
        z = (((dc - c.mean(1)) / h[:, None]) ** 2).sum(1) + (ds.log() - ls.mean(1)) ** 2
        # ... less the particles' own spread: what is left is the detector's noise
        p = (c.var(1, unbiased=False) / h[:, None] ** 2).sum(1) + ls.var(1, unbiased=False)
        # E[z] = 3 R + p; the median of chi^2 with 3 degrees of freedom is 0.7887 of its mean
        # (a median over the matches: robust to a wrong one)
        r = float(((z / 0.7887 - p) / 3.0).median().clamp_min(0.0))
        a = self.config.detection_sigma_rate
        self._sigma2 = min(max((1 - a) * self._sigma2 + a * r, 0.01**2), 0.2**2)

    def _explained_away(self, det_boxes: torch.Tensor, matched: torch.Tensor) -> torch.Tensor:
        """``(T, N)`` log of ``1 - IoU`` of each particle's object box with the detections
        matched to other targets: a person another target was just matched to explains the
        detector's evidence there, so an unmatched neighbour's particles are not drawn to it."""
        t, n = self.states.shape[:2]
        rows = torch.nonzero(matched >= 0).flatten()
        if t < 2 or rows.numel() == 0:
            return torch.zeros((t, n), dtype=torch.float64)
        from torchtrack.boxes import box_iou_matrix

        boxes = det_boxes[matched[rows]]  # (R, 4) detections of targets `rows`
        iou = box_iou_matrix(self.particle_boxes().reshape(t * n, 4), boxes).reshape(t, n, -1)
        own = rows[None, :] == torch.arange(t)[:, None]  # (T, R): a target's own detection
        iou = iou.masked_fill(own[:, None, :], 0.0)
        return torch.log1p(-iou.max(2).values.clamp(0.0, 0.999))

    def _reseed(
        self, det_boxes: torch.Tensor, matched: torch.Tensor, overlap: torch.Tensor
    ) -> None:
        """Matched targets whose particles barely reach their detection restart around it."""
        rows = torch.nonzero(matched >= 0).flatten()
        if rows.numel() == 0:
            return
        ov = overlap[rows, matched[rows]]
        rows = rows[ov < self.config.reseed_overlap]
        if rows.numel() == 0:
            return
        self.stats["reseeded"] += rows.numel()
        win = self.detector.object_to_window(det_boxes[matched[rows]])
        c = win[:, 0:2] + win[:, 2:4] / 2
        s = win[:, 3] / self.ref[rows, 1]
        old = self._estimate(self.states[rows], self.log_weights[rows])
        vel = old[:, 0:2] - old[:, 2:4]
        x0 = torch.cat([c, c - vel, s[:, None], s[:, None]], 1)
        self.states[rows] = self._spread(x0, self.ref[rows])

    def _propose(
        self, det_boxes: torch.Tensor, matched: torch.Tensor, before: torch.Tensor
    ) -> None:
        """``detection_proposal``: the last ``round(fraction * N)`` particles of each matched
        target drawn around its detection (one step of process noise, as a birth's), their
        lagged centre the target's estimate ``before`` (at frame t - 1), so that their
        velocity is the step to the detection. Which ones are replaced: the last k. With the
        default (systematic) resampling the predicted set is in ancestor order, so the last k
        descend mostly from the end of the previous set, where the previous frame's drawn
        particles were: each frame's draw replaces mostly the descendants of the last one,
        and the motion model's particles that the weights kept are left alone."""
        rows = torch.nonzero(matched >= 0).flatten()
        k = round(self.config.detection_proposal * self.config.n_particles)
        if rows.numel() == 0 or k == 0:
            return
        self.stats["proposed from detections"] += rows.numel()
        win = self.detector.object_to_window(det_boxes[matched[rows]])
        c = win[:, 0:2] + win[:, 2:4] / 2
        s = win[:, 3] / self.ref[rows, 1]
        x0 = torch.cat([c, before[rows, 0:2], s[:, None], before[rows, 4:5]], 1)
        drawn = self._spread(x0, self.ref[rows])[:, :k]
        states = self.states[rows]
        states[:, -k:] = drawn
        self.states[rows] = states

    def _spread(self, x0: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
        """``(R, 6)`` states of targets with reference windows ``ref (R, 2)`` -> ``(R, N, 6)``
        particles spread by one step of process noise around them (lagged slots kept)."""
        n = self.config.n_particles
        rep = x0[:, None, :].repeat(1, n, 1)
        scale = self._noise_scale(rep, ref)[:, None, :]
        out = rep + scale * self.dynamics._noise(rep, self.generator)
        out[..., 4] = out[..., 4].clamp_min(self.dynamics.min_scale)
        out[..., 2:4] = rep[..., 2:4]
        out[..., 5] = rep[..., 5]
        return out

    def _bookkeep(
        self,
        matched: torch.Tensor,
        det_p: torch.Tensor,
        det_boxes: torch.Tensor,
        bin_map: FrameBins | None,
    ) -> None:
        cfg = self.config
        hit = matched >= 0
        self.detected = hit
        self.hits = torch.where(hit, self.hits + 1, torch.zeros_like(self.hits))
        self.since_match = torch.where(
            hit, torch.zeros_like(self.since_match), self.since_match + 1
        )
        self.last_score = torch.where(
            hit, det_p[matched.clamp_min(0)] if det_p.numel() else self.last_score, self.last_score
        )
        rows = torch.nonzero(hit).flatten()
        if rows.numel():
            a = self._aspect_of(det_boxes[matched[rows]])
            self.aspect[rows] = 0.7 * self.aspect[rows] + 0.3 * a
            self._observe(rows, det_boxes[matched[rows]])
        newly = hit & ~self.confirmed & (self.hits >= cfg.confirm_hits)
        for r in torch.nonzero(newly).flatten().tolist():
            self.ids[r] = self._next_id
            self._next_id += 1
        self.confirmed |= newly
        self.stats["confirmed"] += int(newly.sum())
        if self._ground_on() and bool(hit.any()):
            # the ground plane learns from the confident matches of confirmed targets
            sure = hit & self.confirmed & (det_p[matched.clamp_min(0)] >= self._birth_threshold())
            if bool(sure.any()):
                boxes, ids = det_boxes[matched[sure]], self.ids[sure]
                whole = ~_cut(boxes, self.frame_size[0])
                self.ground.add(boxes[whole], ids[whole])
        if bin_map is not None and cfg.appearance_rate > 0:
            rows = torch.nonzero(hit).flatten()
            if rows.numel():
                boxes = det_boxes[matched[rows]]
                ok = det_p[matched[rows]] >= self._birth_threshold()
                if rows.numel() > 1:  # no update while another target overlaps (occlusion)
                    from torchtrack.boxes import box_iou_matrix

                    iou = box_iou_matrix(boxes, boxes)
                    iou.fill_diagonal_(0)
                    ok &= iou.max(1).values < 0.1
                rows, boxes = rows[ok], boxes[ok]
                if rows.numel():
                    h = self._histograms(bin_map, boxes[None])[0]
                    a = cfg.appearance_rate
                    self.hist[rows] = (1 - a) * self.hist[rows] + a * h

    def _births(
        self,
        det_boxes: torch.Tensor,
        det_p: torch.Tensor,
        free: list[int],
        bin_map: FrameBins | None,
    ) -> None:
        cfg = self.config
        cand = [j for j in free if float(det_p[j]) >= self._birth_threshold()]
        low = [j for j in cand if float(det_p[j]) < cfg.birth_threshold and not self._external]
        if low:
            # below the model's own birth threshold a window must also be moving: a
            # person-like patch of a still background does not start a target
            moving = self._moving(det_boxes[low]).tolist()
            still = {j for j, m in zip(low, moving, strict=True) if not m}
            self.stats["adapted births refused: not moving"] += len(still)
            cand = [j for j in cand if j not in still]
        if not cand:
            return
        boxes = det_boxes[cand]
        if self.n_targets:
            # A confident detection on a live (possibly lost or tentative) target is that
            # target, not a new one.
            from torchtrack.boxes import box_iou_matrix

            est = self._estimated_boxes()
            iou = box_iou_matrix(boxes, est)
            keep = iou.max(1).values < cfg.birth_overlap
            boxes = boxes[keep]
            cand = [c for c, k in zip(cand, keep.tolist(), strict=True) if k]
        if len(cand) > 1:
            # Two candidates of one frame with nearly the same box are one person seen twice
            # (a detections file with repeated rows, another detector's unsuppressed windows):
            # the more confident one starts the target. Two people, one half behind the other,
            # overlap far less (IoU ~0.7); our own scans are suppressed far below this already.
            from torchtrack.detect.scan import nms

            kept = set(nms(boxes, det_p[cand], SAME_BOX_IOU).tolist())
            self.stats["births merged: the same detection twice"] += len(cand) - len(kept)
            cand = [c for i, c in enumerate(cand) if i in kept]  # in their order: same draws
            boxes = det_boxes[cand]
        room = cfg.max_targets - self.n_targets
        if len(cand) > room:
            if not self._warned_full:
                warnings.warn(
                    f"max_targets={cfg.max_targets} reached: new targets are not started",
                    RuntimeWarning,
                    stacklevel=3,
                )
                self._warned_full = True
            order = det_p[cand].argsort(descending=True)[: max(room, 0)]
            cand = [cand[i] for i in order.tolist()]
            boxes = det_boxes[cand]
        if not cand:
            return
        k = len(cand)
        self.stats["born"] += k
        win = self.detector.object_to_window(boxes)
        c = win[:, 0:2] + win[:, 2:4] / 2
        one = torch.ones((k, 1), dtype=torch.float64)
        x0 = torch.cat([c, c, one, one], 1)
        n = cfg.n_particles
        born = self._spread(x0, win[:, 2:4])
        if cfg.birth_velocity > 0:  # unknown velocity: a spread the weights choose from
            sd = cfg.birth_velocity * win[:, 3, None, None]
            v = torch.randn((*born.shape[:2], 2), dtype=born.dtype, generator=self.generator)
            born[..., 2:4] = born[..., 0:2] - sd * v
        self.states = torch.cat([self.states, born])
        self.log_weights = torch.cat(
            [self.log_weights, torch.full((k, n), -math.log(n), dtype=torch.float64)]
        )
        self.ref = torch.cat([self.ref, win[:, 2:4]])
        self.aspect = torch.cat([self.aspect, self._aspect_of(boxes)])
        self.ids = torch.cat([self.ids, torch.zeros(k, dtype=torch.int64)])
        self.hits = torch.cat([self.hits, torch.ones(k, dtype=torch.int64)])
        self.since_match = torch.cat([self.since_match, torch.zeros(k, dtype=torch.int64)])
        confirmed = torch.full((k,), cfg.confirm_hits <= 1, dtype=torch.bool)
        self.confirmed = torch.cat([self.confirmed, confirmed])
        ids = torch.zeros(k, dtype=torch.int64)
        if cfg.confirm_hits <= 1:
            ids = torch.arange(self._next_id, self._next_id + k, dtype=torch.int64)
            self._next_id += k
        self.ids[-k:] = ids
        self.evidence = torch.cat([self.evidence, det_p[cand]])
        self.last_score = torch.cat([self.last_score, det_p[cand]])
        self.detected = torch.cat([self.detected, torch.ones(k, dtype=torch.bool)])
        if bin_map is not None:
            h = self._histograms(bin_map, boxes[None])[0]
        else:
            h = torch.zeros((k, self.hist.shape[1]), dtype=torch.float32)
        self.hist = torch.cat([self.hist, h])
        self.obs_frames = torch.cat(
            [self.obs_frames, torch.full((k, OBSERVATIONS), -1, dtype=torch.int64)]
        )
        self.obs = torch.cat([self.obs, torch.zeros((k, OBSERVATIONS, 3), dtype=torch.float64)])
        self._observe(torch.arange(self.n_targets - k, self.n_targets), boxes)

    def _follow_camera(self, gray: torch.Tensor) -> None:
        """``camera_motion``: move every target's particles (current and previous centres) by
        the camera's translation since the last frame (``gray (H, W)``, the frame's channel
        sum), where it explains the change."""
        old, self._last_gray = self._last_gray, gray
        if old is None or old.shape != gray.shape or not self.n_targets:
            return
        sx, sy = _camera_translation(old, gray)
        if sx or sy:
            self.stats["frames with a camera shift"] += 1
            ox, oy = self.camera_offset
            self.camera_offset = (ox + sx / self.upsample, oy + sy / self.upsample)
            self.states[..., 0:4:2] += sx
            self.states[..., 1:4:2] += sy
            self.obs[..., 0] += sx  # the observations are where the scene now shows them
            self.obs[..., 1] += sy

    def _moving(self, boxes: torch.Tensor) -> torch.Tensor:
        """``(M,)`` bool: object boxes ``(M, 4)`` whose pixels changed since ``MOTION_LAG``
        frames before (or the oldest frame kept) by ``MOTION_RATIO`` times the whole frame's
        median change: something moves there, more than the camera's noise or its own motion
        moves the background. A camera that pans is compensated first: the older frame is
        shifted by the frame's global translation (:func:`_camera_translation`), so that a still
        patch of the scene does not count as moving because the whole view slid."""
        if len(self._grays) < 2:
            return torch.zeros(boxes.shape[0], dtype=torch.bool)
        old, new = self._grays[0], self._grays[-1]
        h, w = new.shape
        sx, sy = _camera_translation(old, new)
        if sx or sy:  # new[y, x] shows what old[y - sy, x - sx] showed; none off the overlap
            d = torch.full((h, w), math.nan)
            xa, xb, ya, yb = max(0, sx), min(w, w + sx), max(0, sy), min(h, h + sy)
            d[ya:yb, xa:xb] = (new[ya:yb, xa:xb] - old[ya - sy : yb - sy, xa - sx : xb - sx]).abs()
        else:
            d = (new - old).abs().float()
        median = float(d[::2, ::2].nanmedian())
        level = median * MOTION_RATIO + MOTION_MIN
        out = []
        for x, y, bw, bh in boxes.tolist():
            x0, y0 = max(int(x), 0), max(int(y), 0)
            x1, y1 = min(math.ceil(x + bw), w), min(math.ceil(y + bh), h)
            seen = d[y0:y1, x0:x1]
            mean = seen.mean() if sx == 0 and sy == 0 else seen.nanmean()
            out.append(x1 > x0 and y1 > y0 and float(mean) >= level)
        return torch.tensor(out, dtype=torch.bool)

    def _estimated_boxes(self) -> torch.Tensor:
        est = self._estimate(self.states, self.log_weights)  # (T, 6)
        return self._with_aspect(
            self.detector.window_to_object(self._windows(est[:, None], self.ref)[:, 0]),
            self.aspect,
        )

    @staticmethod
    def _with_aspect(boxes: torch.Tensor, aspect: torch.Tensor) -> torch.Tensor:
        """Object boxes ``(T, 4)`` widened by ``aspect (T,)`` about their centre."""
        w = boxes[:, 2] * aspect
        x = boxes[:, 0] + (boxes[:, 2] - w) / 2
        return torch.stack([x, boxes[:, 1], w, boxes[:, 3]], 1)

    def _aspect_of(self, boxes: torch.Tensor) -> torch.Tensor:
        """Width ratio of object boxes ``(M, 4)`` to the detector's object box of their height
        (1 for the detector's own detections; external detections keep their shape)."""
        std = self.detector.window_to_object(self.detector.object_to_window(boxes))
        return boxes[:, 2] / std[:, 2].clamp_min(1e-9)

    def _deaths(self) -> None:
        if not self.n_targets:
            return
        cfg = self.config
        from torchtrack.boxes import inside_fraction

        # NaN (a degenerate box) compares False: such a target is gone too.
        gone = ~(
            inside_fraction(self._estimated_boxes(), self.frame_size) >= cfg.min_visible_fraction
        )
        lost = self.since_match > cfg.max_lost
        tentative_miss = ~self.confirmed & (self.since_match >= cfg.scan_every)
        dup = self._duplicates() & ~(gone | lost)
        keep = ~(gone | lost | tentative_miss | dup)
        if not bool(keep.all()):
            self.stats["ended: left the frame"] += int((gone & self.confirmed).sum())
            self.stats["ended: lost"] += int((lost & ~gone & self.confirmed).sum())
            self.stats["ended: duplicate"] += int(dup.sum())
            self.stats["ended: tentative"] += int((~keep & ~self.confirmed).sum())
            self._keep(keep)

    def _birth_threshold(self) -> float:
        """``birth_threshold`` for the model's own scans, adapted down to the video's level
        (``birth_floor``); ``external_birth_threshold`` once detections come from outside
        (another detector's scores, on another scale)."""
        return self.config.external_birth_threshold if self._external else self._birth_p

    def _adapt_birth(self, det_p: torch.Tensor) -> None:
        """Note this scan's best detection ``det_p (M,)`` (the detections kept) and set the
        birth threshold from the video's level: ``birth_margin`` logits below the median of
        the last scans' best, within ``[birth_floor, birth_threshold]``."""
        cfg = self.config
        if cfg.birth_floor >= cfg.birth_threshold:
            return
        best = float(det_p.max()) if det_p.numel() else cfg.detection_threshold
        self._levels.append(_logit(best))
        if len(self._levels) < MIN_LEVEL_SCANS:
            return
        level = float(torch.tensor(list(self._levels)).median())
        x = level - cfg.birth_margin
        if x >= _logit(cfg.birth_threshold):
            self._birth_p = cfg.birth_threshold
        elif x <= _logit(cfg.birth_floor):
            self._birth_p = cfg.birth_floor
        else:
            self._birth_p = 1.0 / (1.0 + math.exp(-x))
        self._lowest_birth_p = min(self._lowest_birth_p, self._birth_p)

    def _duplicates(self) -> torch.Tensor:
        """``(T,)`` bool: confirmed targets that sit on another confirmed target (estimated
        boxes' IoU above ``duplicate_iou``) and are one person with it (ByteTrack's duplicate
        removal between tracked and lost tracks, made safe for people who overlap):

        * it has missed its detection on at least the last ``DUPLICATE_MISSES`` scans while
          the other was matched more recently: one detection where two targets sit (one
          missed scan is not enough: a person behind another one whose detection the scan
          dropped once is still there); or
        * the two have taken turns at the detections since they began to overlap: each was
          matched on some frame of that run, never both on one (two people overlapping are
          matched together whenever the scan sees both); the one matched less recently ends.

        A target that drifted onto a neighbour whose detection it lost in the assignment is
        such a target; two people side by side, both detected, are never one. With
        ``duplicate_heading``, neither are two targets whose headings (:meth:`headings`) point
        apart (more than 90 degrees): people crossing, one hidden behind the other."""
        t = self.n_targets
        out = torch.zeros(t, dtype=torch.bool)
        if t < 2 or self.config.duplicate_iou >= 1.0:
            self._turns = {}
            return out
        from torchtrack.boxes import box_iou_matrix

        boxes = self._estimated_boxes()
        iou = box_iou_matrix(boxes, boxes)
        iou.fill_diagonal_(0.0)
        both = self.confirmed[:, None] & self.confirmed[None, :]
        pair = both & (iou > self.config.duplicate_iou)
        sm = self.since_match
        worse = sm[:, None] > sm[None, :]  # i matched less recently than j
        missed = sm >= DUPLICATE_MISSES * self.config.scan_every
        if self.config.duplicate_heading:
            # headings that point apart: two people crossing, one hidden behind the other
            # (a duplicate follows the one person the other target follows)
            h = self.headings()
            pair = pair & ~((h @ h.T) < 0)
        out = (pair & worse & missed[:, None]).any(1)
        turns: dict[tuple[int, int], tuple[bool, bool]] = {}
        ids, det = self.ids.tolist(), self.detected.tolist()
        for i, j in torch.nonzero(torch.triu(pair, 1)).tolist():
            seen_i, seen_j = self._turns.get((ids[i], ids[j]), (False, False))
            if det[i] and det[j]:  # both detected: two people
                seen_i = seen_j = False
            else:
                seen_i, seen_j = seen_i or det[i], seen_j or det[j]
            turns[(ids[i], ids[j])] = (seen_i, seen_j)
            if seen_i and seen_j:
                out[i] |= bool(worse[i, j])
                out[j] |= bool(worse[j, i])
        self._turns = turns  # pairs that stopped overlapping start afresh
        return out

    def _refined_report(self, frame: torch.Tensor, out: MultiState) -> MultiState:
        """``out`` with each box moved by the detector's box regressor on ``frame`` (the
        reported boxes only: the particles stay where the filter put them)."""
        det = self.detector
        if det.box_regressor is None or not len(out.ids):
            return out
        win = det.object_to_window(out.boxes).to(torch.float32)[None]  # (1, K, 4)
        at, crop = self._crop
        inside = False
        if at == self.frame_index and crop is not None:
            ints, (dx, dy), hull = crop
            fh, fw = frame.shape[-2:]
            size = torch.tensor([fw, fh, fw, fh], dtype=win.dtype)
            xyxy = torch.minimum(xywh_to_xyxy(win[0]).clamp_min(0), size)  # in-frame parts
            hull = torch.tensor(hull, dtype=win.dtype)
            inside = bool((xyxy[:, :2] >= hull[:2]).all() and (xyxy[:, 2:] <= hull[2:]).all())
        if inside:  # the particles' integral images of this frame cover every box: reuse
            rel = (win - torch.tensor([dx, dy, 0.0, 0.0])).to(frame.device)
        else:
            ints, rel = det.integrals_for(frame[None], win)
        moved = det.refine_windows(ints, rel) + (win.to(rel.device) - rel)
        boxes = det.window_to_object(moved[0].to(device="cpu", dtype=torch.float64))
        return MultiState(out.ids, boxes, out.confidence, out.detected)

    def _report(self) -> MultiState:
        cfg = self.config
        if not self.n_targets:
            z = torch.zeros(0, dtype=torch.float64)
            return MultiState(
                torch.zeros(0, dtype=torch.int64),
                z.reshape(0, 4),
                z,
                torch.zeros(0, dtype=torch.bool),
            )
        fresh = self.since_match < cfg.scan_every
        coast = (self.since_match <= cfg.max_coast) & (self.evidence >= cfg.visible_threshold)
        show = self.confirmed & (fresh | coast)
        boxes = self._estimated_boxes()
        detected = self.detected
        conf = torch.where(self.since_match == 0, self.last_score, self.evidence)
        order = torch.argsort(self.ids[show])
        return MultiState(
            ids=self.ids[show][order],
            boxes=boxes[show][order],
            confidence=conf[show][order],
            detected=detected[show][order],
        )

    def __repr__(self) -> str:
        return (
            f"MultiTargetTracker({self.detector.name!r}, targets={self.n_targets}, "
            f"scan_every={self.config.scan_every})"
        )


def _logit(p: float) -> float:
    """``log(p / (1 - p))`` of a probability, held within about +-27.6 (p in [1e-12,
    1 - 1e-12])."""
    p = min(max(p, 1e-12), 1.0 - 1e-12)
    return math.log(p / (1.0 - p))


def _camera_translation(old: torch.Tensor, new: torch.Tensor) -> tuple[int, int]:
    """The camera's translation ``(sx, sy)`` between two gray frames (:func:`_camera_shift`),
    kept only where it explains the change: the median absolute change after the shift (over
    every other pixel of the frames' overlap) below ``CAMERA_EXPLAINS`` times the median
    change without it; else ``(0, 0)``: the correlation followed something moving over a
    plain, still background."""
    sx, sy = _camera_shift(old, new)
    if not (sx or sy):
        return 0, 0
    h, w = new.shape
    raw = float((new[::2, ::2] - old[::2, ::2]).abs().median())
    # the even rows and columns of the overlap: new[y, x] against old[y - sy, x - sx]
    ya, xa = max(0, sy), max(0, sx)
    ya, xa = ya + ya % 2, xa + xa % 2
    yb, xb = min(h, h + sy), min(w, w + sx)
    shifted = (new[ya:yb:2, xa:xb:2] - old[ya - sy : yb - sy : 2, xa - sx : xb - sx : 2]).abs()
    return (sx, sy) if float(shifted.median()) < CAMERA_EXPLAINS * raw else (0, 0)


def _channel_sum(frame: torch.Tensor) -> torch.Tensor:
    """``(H, W)`` int16 sum of a ``(C, H, W)`` uint8 frame's channels, on the CPU: the values of
    ``frame.to(torch.int16).sum(0)`` (exact; at most 765), in C - 1 in-place additions instead
    of a reduction into int64, and kept in 16 bits."""
    out = frame[0].to(torch.int16, copy=True)
    for c in range(1, frame.shape[0]):
        out += frame[c]
    return out.cpu()


def _camera_shift(old: torch.Tensor, new: torch.Tensor) -> tuple[int, int]:
    """The camera's translation between two frames ``(H, W)`` in whole pixels, ``(sx, sy)``
    with ``new[y, x]`` showing what ``old[y - sy, x - sx]`` showed (phase correlation through a
    Hann window, OpenCV's ``phaseCorrelate``); ``(0, 0)`` for a still camera, a weak
    correlation peak (no single translation explains the change) or a shift beyond a quarter
    of the frame."""
    import cv2

    h, w = new.shape
    if h < 8 or w < 8:
        return 0, 0
    a = old.numpy().astype("float32")
    b = new.numpy().astype("float32")
    (sx, sy), peak = cv2.phaseCorrelate(a, b, cv2.createHanningWindow((w, h), cv2.CV_32F))
    sx, sy = round(sx), round(sy)
    if peak < CAMERA_PEAK or abs(sx) > w // 4 or abs(sy) > h // 4:
        return 0, 0
    return sx, sy


def _cut(boxes: torch.Tensor, height: int) -> torch.Tensor:
    """``(M,)`` bool: object boxes ``(M, 4)`` that the top or bottom edge of a frame ``height``
    pixels tall cuts (their height says nothing of where their foot is)."""
    return (boxes[:, 1] <= 0) | (boxes[:, 1] + boxes[:, 3] >= height - 1)


def track_sequence(
    tracker: MultiTargetTracker,
    frames,
    detections=None,
    max_frames: int | None = None,
    scan_workers: int = 0,
    as_scans: bool = False,
    device: torch.device | str | None = None,
    scan_batch: int | None = None,
):
    """Run ``tracker`` over ``frames`` and collect the reported targets.

    Args:
        tracker: a fresh (or :meth:`~MultiTargetTracker.reset`) tracker.
        frames: a :class:`~torchtrack.io.video.FrameSource` (or anything with ``items()``
            yielding ``(index, frame or None)``); unreadable frames are skipped.
        detections: optional per-frame detections: a :class:`~torchtrack.io.mot.MotRows` of
            object boxes with scores in [0, 1] (e.g. public detections, or a cache of the
            tracker's own scans), used instead of scans on the frames the tracker would scan
            (every ``scan_every``-th readable frame, from the first; unreadable frames are
            skipped by the count).
        max_frames: stop after this many frames.
        scan_workers: without ``detections``, scan the coming frames in this many forked
            processes (:class:`~torchtrack.track.scan_ahead.ScanAhead`: the same tracks); 0
            scans in this process.
        as_scans: ``detections`` are a cache of this tracker's own scans (:meth:`detect`):
            they go in as ``update(frame, scan=...)``, with the scan's thresholds and the
            ground plane, instead of as detections from outside.
        device: where the frames go before the tracker sees them (its scan and particle
            likelihood run there); None: where they are.
        scan_batch: without workers, frames scanned together
            (:class:`~torchtrack.track.scan_ahead.ScanAhead`; the same tracks); None: 8 on a
            GPU, 1 elsewhere (:func:`~torchtrack.track.scan_ahead.default_scan_batch`).

    Returns:
        :class:`~torchtrack.io.mot.MotRows` (0-based frames) of every reported target, gaps
        filled and boxes smoothed as the tracker's ``fill_gaps`` and ``smooth_sigma`` say
        (:meth:`MultiTargetTracker.smoother`), as ``torchtrack track`` writes them.
    """
    import numpy as np

    from torchtrack.io.mot import MotRows

    per_frame = None
    if detections is not None:
        n = int(detections.frames.max()) + 1 if len(detections) else 0
        per_frame = detections.split(n)
        boxes_all = torch.from_numpy(detections.boxes)
        conf_all = torch.from_numpy(detections.conf.astype(np.float64)).clamp(0.0, 1.0)
    import itertools

    from torchtrack.track.scan_ahead import ScanAhead, default_scan_batch

    if scan_batch is None:
        scan_batch = default_scan_batch(device)
    f_, i_, b_, c_ = [], [], [], []
    empty = (torch.zeros((0, 4), dtype=torch.float64), torch.zeros(0, dtype=torch.float64))
    smoother = tracker.smoother()

    def collect(i: int, out) -> None:
        if out is not None and len(out):
            f_.append(torch.full((len(out),), i, dtype=torch.int64))
            i_.append(out.ids)
            b_.append(out.boxes)
            c_.append(out.confidence)

    items = itertools.takewhile(lambda p: max_frames is None or p[0] < max_frames, frames.items())
    with ScanAhead(
        tracker, scan_workers if per_frame is None else 0, batch=scan_batch, device=device
    ) as ahead:
        stream = ahead.frames(items) if per_frame is None else ((i, f, None) for i, f in items)
        for i, frame, scan in stream:
            if frame is None:
                continue
            d = None
            # the frames the tracker would scan: every scan_every-th readable one, its own count
            if per_frame is not None and tracker.scans_next():
                idx = torch.from_numpy(per_frame[i]) if i < len(per_frame) else None
                d = empty if idx is None or idx.numel() == 0 else (boxes_all[idx], conf_all[idx])
            if as_scans:
                d, scan = None, d
            out = tracker.update(frame if device is None else frame.to(device), d, scan=scan)
            pushed = smoother.push(
                i, out, offset=tracker.camera_offset, detections=tracker.last_detections
            )
            for j, o in pushed:
                collect(j, o)
    for j, o in smoother.flush():
        collect(j, o)
    if not f_:
        return MotRows.empty()
    return MotRows.from_arrays(torch.cat(f_), torch.cat(i_), torch.cat(b_), torch.cat(c_))


def score_probabilities(scores: torch.Tensor) -> torch.Tensor:
    """Detection scores of an outside detector as probabilities ``(M,)`` float64: scores all in
    ``[0, 1]`` are taken as they are; raw scores (e.g. the MOT15 public detections' -0.2..122)
    are divided by the highest one (a crude map: calibrate them with ``torchtrack calibrate
    --scores`` when labelled scores exist). Where no score is positive, dividing would make them
    all 0: they are mapped linearly from their lowest (0) to their highest (1), and scores that
    are all equal (no ranking in them, e.g. every one -1) all become 1."""
    s = torch.as_tensor(scores, dtype=torch.float64).reshape(-1)
    if s.numel() == 0 or bool(((s >= 0) & (s <= 1)).all()):
        return s
    hi = s.max()
    if hi > 0:
        return (s / hi).clamp(0.0, 1.0)
    lo = s.min()
    if hi == lo:
        return torch.ones_like(s)
    return (s - lo) / (hi - lo)
