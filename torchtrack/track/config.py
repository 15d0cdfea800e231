"""Typed tracker configurations: every default in one dataclass, loaded from TOML.

``configs/trackers/<name>.toml`` files hold flat ``key = value`` pairs for one tracker; unknown
keys are rejected by name, values are checked against the field's type. The same checks apply
to keyword overrides (``torchtrack track --tracker detector:n_particles=500`` or
``create_tracker("detector", n_particles=500)``).

Example::

    cfg = load_tracker_config("configs/trackers/detector.toml", DetectorTrackerConfig)
    cfg = apply_overrides(cfg, {"n_particles": 500})
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
import types
import typing
from dataclasses import dataclass, field
from typing import Any, TypeVar

from torchtrack.errors import ConfigError

__all__ = [
    "DetectorTrackerConfig",
    "HistogramTrackerConfig",
    "MultiTrackerConfig",
    "apply_overrides",
    "config_from_dict",
    "load_tracker_config",
    "resolve_tracker_config",
]

C = TypeVar("C")


@dataclass
class DetectorTrackerConfig:
    """Calibrated-detector particle filter (Chateau et al. 2006).

    Attributes:
        model: detector: a bundled model name (``pedestrian``, ``vehicle``) or a model file
            written by ``torchtrack train``.
        n_particles: particles per target (paper: 200).
        dynamics: TOML file of the AR dynamics ``A, B, Sigma`` (eq. 4) as written by
            ``tools/fit_dynamics.py``; empty: the fitted ``dynamics_chateau.toml`` shipped
            with torchtrack.
        visible_threshold: the target is reported visible while the mean calibrated
            probability of the particles (the evidence) is at least this.
        context: height of the detector window over the height of the tracked object box
            (e.g. about 1.33 for INRIA-style pedestrian windows that keep a margin around the
            person). ``0``: chosen on the first frame, among ``context_candidates``, as the
            window at the given box's centre with the highest detector probability.
        context_candidates: window-over-box height ratios tried when ``context = 0``.
        scan_context: for auto-initialisation (no box): the object box reported is the
            detection window divided by this.
        likelihood_floor: smallest likelihood (keeps weights finite when every window is ~0).
        likelihood: ``"full"``: particles are scored by the whole classifier; ``"head"``: by
            the model's tracking head (its first trees with their own calibration,
            :meth:`~torchtrack.detect.Detector.tracking_model`; the whole model when it has
            none), ~4x cheaper but less discriminative: on OTB Crossing (a 17 x 50 px person)
            the 64-tree head of the bundled pedestrian model lost the person (mean IoU 0.17 over
            30 frames) where the whole model followed it (0.65).
        likelihood_power: particle weights are ``max(p, floor) ** likelihood_power``; 1 is the
            paper's eq. (11) (the calibrated probability itself); > 1 sharpens it.
        estimator: ``mean`` (paper Fig. 1 d), ``best`` or ``mode``.
        resample: resampling scheme (``torchtrack.filter.RESAMPLERS``).
        scan_threshold: auto-initialisation: smallest probability of a detection.
        scan_min_scale, scan_scale_step, scan_stride: the first-frame scan (section 4.2), see
            :func:`torchtrack.detect.scan.sliding_windows`.
        init_top_n: auto-initialisation: particles are importance-sampled from the ``N``
            highest-scoring scan windows overlapping the detection.
        n_targets: auto-initialisation: how many detections to track (best first).
    """

    model: str = "pedestrian"
    n_particles: int = 200
    dynamics: str = ""
    visible_threshold: float = 0.1
    context: float = 0.0
    context_candidates: list[float] = field(
        default_factory=lambda: [1.0, 1.1, 1.2, 1.3, 1.4, 1.5, 1.6]
    )
    scan_context: float = 1.0
    likelihood_floor: float = 1e-6
    likelihood: str = "full"
    likelihood_power: float = 1.0
    estimator: str = "mean"
    resample: str = "systematic"
    scan_threshold: float = 0.5
    scan_min_scale: float = 0.5
    scan_scale_step: float = 1.15
    scan_stride: float = 0.08
    init_top_n: int = 50
    n_targets: int = 1

    def validate(self) -> None:
        _positive_int(self, "n_particles", "init_top_n", "n_targets")
        check_at_most(self, MAX_TRACKER_PARTICLES, "n_particles")
        check_product(self, MAX_TRACKER_PARTICLES, "particles", "n_particles", "n_targets")
        _in_unit(self, "visible_threshold", "scan_threshold")
        if not 0.0 <= self.likelihood_floor < 1.0:
            raise ConfigError(f"likelihood_floor must be in [0, 1), got {self.likelihood_floor}")
        if self.likelihood not in ("head", "full"):
            raise ConfigError(f"likelihood must be 'head' or 'full', got {self.likelihood!r}")
        if not 0 < self.likelihood_power <= MAX_LIKELIHOOD_POWER:
            raise ConfigError(
                f"likelihood_power must be in (0, {MAX_LIKELIHOOD_POWER:g}], got "
                f"{self.likelihood_power}"
            )
        check_context(self)
        if not 0 < self.scan_context <= MAX_CONTEXT:
            raise ConfigError(
                f"scan_context (window over box height) must be in (0, {MAX_CONTEXT:g}], got "
                f"{self.scan_context}"
            )
        _check_scan_min_scale(self.scan_min_scale)
        _estimator_and_scheme(self)


@dataclass
class HistogramTrackerConfig:
    """Colour-histogram particle filter (Pérez et al. 2002) on Klein et al.'s filter.

    Attributes:
        n_particles: particles (Klein et al.: J = 2000 for every observation model).
        sigma_xy, sigma_wh: motion noise of Klein et al. eq. (1) (6.4 and 0.64).
        lam: ``lambda`` of the likelihood ``exp(-lambda D^2)`` (Pérez et al.: 20).
        n_h, n_s, n_v, s_min, v_min: HSV binning (Pérez et al.: 10, 10, 10, 0.1, 0.2).
        grid: histogram samples per box side (``grid^2`` samples per particle).
        update_rate: reference update ``q = (1 - a) q + a p(estimate)`` per visible frame
            (0: the first frame's histogram is kept, as in Klein et al.'s baseline).
        visible_threshold: visible while the best particle's Bhattacharyya coefficient is at
            least this.
        estimator: ``mean`` (Klein et al. eq. 2), ``best`` or ``mode``.
        resample: resampling scheme.
    """

    n_particles: int = 2000
    sigma_xy: float = 6.4
    sigma_wh: float = 0.64
    lam: float = 20.0
    n_h: int = 10
    n_s: int = 10
    n_v: int = 10
    s_min: float = 0.1
    v_min: float = 0.2
    grid: int = 16
    update_rate: float = 0.0
    visible_threshold: float = 0.5
    estimator: str = "mean"
    resample: str = "systematic"

    def validate(self) -> None:
        _positive_int(self, "n_particles", "n_h", "n_s", "n_v", "grid")
        check_at_most(self, MAX_TRACKER_PARTICLES, "n_particles")
        check_at_most(self, 256, "n_h", "n_s", "n_v")  # more bins than 8-bit levels: none
        check_product(self, MAX_LIKELIHOOD_SAMPLES, "samples", "n_particles", "grid", 2)
        _in_unit(self, "update_rate", "visible_threshold")
        if not (self.lam > 0 and math.isfinite(self.lam)):
            raise ConfigError(f"lam must be a finite number > 0, got {self.lam}")
        for k in ("sigma_xy", "sigma_wh"):
            if not getattr(self, k) >= 0:
                raise ConfigError(f"{k} must be >= 0, got {getattr(self, k)}")
        _estimator_and_scheme(self)


@dataclass
class MultiTrackerConfig:
    """Multi-target detect-and-track (:class:`torchtrack.track.multi.MultiTargetTracker`).

    Attributes:
        model: the detector (bundled name or model file): it proposes detections and its
            calibrated probability is the particles' likelihood (Chateau et al. eq. 11).
        n_particles: particles per target.
        dynamics: AR dynamics TOML (eq. 4); empty: ``dynamics_chateau_cv.toml``, constant
            velocity with the noise fitted on the tracking sequences (the paper's free fit,
            ``dynamics_chateau.toml``, damps a walker's velocity by half every frame, which
            loses people who cross; measured in ``docs/benchmarks/mot.md``).
        motion_noise: factor on the standard deviation of the dynamics' fitted noise. The
            fit's 4 px per frame is mostly the jitter of hand labels (``tools/fit_dynamics.py
            --noise jitter_corrected`` leaves 1.7 px); 0.25 was chosen by leave-one-sequence-out
            and holds on outside detections too (``docs/multi_target.md``).
        noise_height: object height in pixels at which ``motion_noise`` applies as is: the
            centre's noise then scales with each target's height / ``noise_height`` (a person
            twice as tall, nearer the camera, moves twice as many pixels per frame); 0 keeps
            the noise in pixels whatever the target's size (else at least 1 pixel).
        scan_every: scan the frame with the detector every k-th frame (1: every frame); the
            filter carries the targets in between.
        scan_min_scale, scan_max_scale, scan_scale_step, scan_stride, scan_nms: the scan
            (:func:`torchtrack.detect.scan.sliding_windows`; ``scan_max_scale = 0``: up to the
            largest window that fits the frame; ``scan_scale_step`` at least 1.01). Detections
            given from outside get the scan's NMS on their weak boxes: one below the birth
            threshold that :func:`torchtrack.detect.scan.nms` at ``scan_nms`` suppresses is
            dropped (another detector's looser NMS leaves such boxes beside a person's main box,
            and they would feed a second target on that person; ``docs/multi_target.md``).
        scan_vote: box voting after the scan's NMS (:func:`torchtrack.detect.scan.box_vote`):
            each detection moves to the probability-weighted mean position and scale of the
            windows above ``detection_threshold`` that overlap it by this IoU; 0: off.
        min_frame_height: frames shorter than this many pixels are upsampled 2x (bilinear)
            before the tracker sees them, so that people below the scan's smallest window
            (``scan_min_scale`` x the model window: ~45 px) are found there; boxes in and out
            stay in the frame's own pixels. At half size PETS's people are ~25 px tall: HOTA
            19.5 as it is, 46.1 upsampled; TUD's half-size copy 40.4 / 42.8 (seeds 0-2; chosen
            by leave one sequence out, ``docs/multi_target.md``). 0: off.
        scan_cascade: the scan's soft cascade loosened to at most this (negative) running
            margin: every tree's threshold is the lower of the model's and this (lower: more
            people found, more false ones, slower scans; the bundled pedestrian model's own is
            a constant -1, the vehicle model's -3.18 stays as it is); 0: the model's own. -3 was
            chosen by leave-one-sequence-out over 0, -3 and -5 (``docs/multi_target.md``): the
            births are confirmed and weak detections only extend targets, so the tracker can
            use the windows an early cascade exit would have dropped.
        scan_box_regression: the scan's detections moved and scaled by the model's box
            regressor (:mod:`torchtrack.detect.box_regression`) to where its training crops put
            the object; a model without one: no effect. Learnt from the training crops alone:
            own detections, seeds 0-5 (cached scans), HOTA PETS 50.8 -> 52.2, TUD 44.4 -> 48.4
            (docs/multi_target.md, "Box regression").
        report_box_regression: each reported box moved the same way on its frame (the
            particles stay where the filter put them), when the tracker scans with its own
            model; with outside detections (``--detections``) their boxes set the convention,
            and a model without a regressor has nothing to apply.
        report_shift: each reported box moved up by this fraction of its height when the
            tracker scans with its own model (with ``--detections`` their boxes set the
            convention): the bundled pedestrian model's boxes (where its INRIA training crops
            put a person) sat ~3% of the height lower than the MOTChallenge annotations of
            both PETS09-S2L1 and TUD-Stadtmitte, and both folds of leave one sequence out
            choose 0.03 (cached scans, seeds 0-5: HOTA +1.1 to +1.3 on every PETS seed, +0.5
            to +0.7 on every TUD seed; ``docs/multi_target.md``); 0: the model's own boxes,
            negative moves down.
        scan_pad: windows may hang this fraction of their size over the frame's edges
            (:func:`torchtrack.detect.scan.scan`), so people entering or leaving, cut by the
            edge, are still detected; 0: windows inside the frame.
        detection_threshold: detections below this calibrated probability are dropped; those
            between it and ``birth_threshold`` only extend existing targets (ByteTrack's
            second association, made meaningful by calibration).
        birth_threshold: detections at least this confident start targets and take part in the
            first association (the model's own scans: its calibrated probability on crops
            under-states how rare a person-like window is in a whole frame, hence 0.9999).
            Chosen on the bundled pedestrian model: a model trained elsewhere, even the same
            recipe with another seed, can be surer of twice as many windows (2026-12-02:
            HOTA -2 to -5 at this value, ``docs/multi_target.md``); choose it again for such a
            model (``python tools/loso_multi.py --set model=FILE --grid
            birth_threshold=...``).
        birth_floor: on video where the detector is less sure of everyone (low contrast,
            noise, a camera or scene unlike its training crops), ``birth_threshold`` adapts down
            to the video's own level: ``birth_margin`` logits below the median of the last
            scans' best detections, never below this floor nor above ``birth_threshold``. On
            video whose people score as the detector's training people do, nothing changes;
            ``>= birth_threshold``: fixed.
        birth_margin: see ``birth_floor`` (logits, >= 0).
        external_birth_threshold: the same for detections given from outside (``--detections``:
            another detector's scores, mapped to [0, 1]).
        confirm_hits: a new target is reported once it was matched on this many scans in a row
            (counting the one that started it; at most 1000); a miss before that ends it.
        max_lost: a target unmatched for more than this many frames ends.
        max_coast: an unmatched confirmed target is still reported for up to this many frames
            while the filter's evidence (the mean calibrated probability of its particles) is
            at least ``visible_threshold``: the detector still sees a person where the filter
            is, only the scan's threshold or NMS missed it.
        visible_threshold: see ``max_coast``.
        max_targets: at most this many targets at once (births beyond are refused).
        birth_overlap: a confident detection left unmatched starts a target only if its IoU
            with every live target's box is below this (else it is that target, momentarily
            out of the gate).
        overlap_gate: a target and a detection can pair only if the detection's expected IoU
            under the target's particles is at least this. 0.3 (chosen by
            leave-one-sequence-out, ``docs/multi_target.md``) keeps a detection that barely
            touches a target, most often a neighbour's, from pulling it over; it also means a
            matched target is never re-seeded while ``reseed_overlap`` is 0.3.
        ground_gate: detections whose height is further than this (a log ratio, 0.4 = 49% taller
            or 33% shorter) from the video's own ground-plane line, height against foot row
            (:class:`torchtrack.track.ground.GroundPlane`, fitted online to the boxes of
            confirmed, confidently matched targets), are dropped before association: windows
            of a person's size at the wrong place. Boxes cut by the frame's top or bottom edge
            are kept; until the line rests on enough boxes, and in a scene that is not a ground
            plane (a moving camera), nothing is dropped. Once the line holds, the scans score
            only the windows that fit it (the line of ``GROUND_LAG`` frames before), which is
            what makes the scan faster. Detections given from outside (``--detections``) are
            taken as they come. 0: off.
        max_cost: pairs costing more are not made (see :mod:`torchtrack.track.association`).
        w_overlap, w_appearance: weights of the overlap and appearance cues in the cost.
        appearance: ``"colour"`` (an online HSV histogram per target, Pérez et al. 2002) or
            ``"none"``.
        appearance_lambda: the appearance likelihood of a particle is
            ``exp(-lambda (1 - BC))`` (Pérez et al. eq. 6 with ``D^2 = 1 - BC``); 0: not in the
            particle weights (association only).
        appearance_rate: colour-model update rate on confident, unoccluded matches.
        detection_sigma: a matched detection weights the particles by a Gaussian around it,
            with this standard deviation as a fraction of its height (position) and of its
            scale (log scale); at most 1.
        detection_sigma_rate: 0 keeps ``detection_sigma`` fixed; above 0 the tracker
            estimates it from the video's own matches (innovation-based adaptive estimation:
            the squared distance of each matched detection from its target's predicted
            particles, less the particles' own spread, is the detector's noise), starting at
            ``detection_sigma``, a running average at this rate per scan over the median of
            the frame's matches, held within [0.01, 0.2]. Precise detections then pull the
            targets harder than a coarse scan's.
        exclusion: strength ``k`` of the interaction potential ``exp(-k IoU)`` between a
            particle's window and the other targets' predicted windows (Khan et al. 2005: two
            targets do not take the same place); 0: off.
        reseed_overlap: a matched target whose particles overlap its detection less than this
            (expected IoU) is re-seeded around the detection.
        duplicate_iou: two confirmed targets whose estimated boxes overlap more than this
            (IoU) are one person when one has missed its detection on the last 2 scans while
            the other was matched, or when they take turns at the detections (never both
            matched on one frame): the one matched less recently ends (ByteTrack's duplicate
            removal, which ends the lost one at IoU 0.85 at once); 1: off.
        duplicate_heading: two such targets whose headings point apart (more than 90 degrees)
            are two people crossing, one hidden behind the other, and neither ends as a
            duplicate. A target's heading is the direction from its matched detection 3 frames
            back to its latest one (Cao et al.'s observation-centric velocity, "Observation-
            Centric SORT", CVPR 2023); a move shorter than ``detection_sigma`` of the box
            height gives none.
        lost_noise_growth: the motion noise of an unmatched target grows by this factor per
            frame without a match (up to ``max_noise_scale``): the search widens while it is
            lost.
        max_noise_scale: cap of that growth.
        detection_proposal: the fraction of a matched target's particles drawn afresh around
            its detection (Okuma et al.'s boosted particle filter, ECCV 2004: a mixture of
            the detector and the motion model as the proposal), their velocity the step from
            the target's last estimate to the detection; the detector's likelihood then weighs
            them with the others. A person who moves farther per frame than the motion noise
            reaches (a lower frame rate, a turn) is caught up with in one frame instead of
            being left behind; 0: off (the motion model alone, and a full re-seed below
            ``reseed_overlap``).
        birth_velocity: sd of a new target's velocity, as a fraction of its window height per
            frame: its particles start with velocities drawn from a normal of that sd instead
            of at rest, and its next detections choose among them. A person who moves several
            pixels a frame (a low frame rate) is followed from the first scans instead of
            being left behind while the motion noise (about 1 px a frame) builds the velocity
            up; 0: at rest.
        camera_motion: follow a camera that pans or tilts: the frame's global translation
            since the last frame (phase correlation, used only where it explains the change
            between the frames) moves every target's particles, their current and previous
            centres both (the people's own velocity is kept), before the motion model predicts.
            On a still camera no shift is found and nothing moves; False: off.
        min_visible_fraction: a target whose object box has less than this fraction inside the
            frame has left it and ends (never reported).
        likelihood_floor: smallest detector probability in the weights (keeps them finite).
        likelihood: ``"head"`` (the model's tracking head scores the particles) or ``"full"``
            (the whole classifier), as for :class:`DetectorTrackerConfig`.
        estimator: particle estimate (``mean``, ``mode``, ``best``).
        resample: resampling scheme.
        fill_gaps: the reported tracks (``torchtrack track``'s files and video,
            :func:`~torchtrack.track.multi.track_sequence`) get boxes on the frames of a gap of
            at most this many frames between two reports of one identity, interpolated
            (:class:`~torchtrack.track.smoothing.TrackSmoother`); 0: none. The output then
            comes ``fill_gaps`` frames late (plus the smoothing's radius).
        smooth_sigma: the reported boxes smoothed over time by a local-linear fit with
            Gaussian weights of this sd in frames (centre and log-size; radius ``int(4 sigma +
            0.5)`` frames of delay); 0: none. Defaults 10 and 4 (26 frames of delay) by leave
            one sequence out and the frame-rate copies (docs/multi_target.md, "Smoothing the
            reported tracks"). :meth:`MultiTargetTracker.update` itself always reports the
            frame at hand.
        backfill: the reported track of a new identity, or of one back after a gap, is
            extended back in time over at most this many frames not yet written, through the
            detections of those frames that chain to its first box of the run (each overlapping the box carried back at its velocity at IoU >=
            ``backfill_iou`` and no other identity's box at 0.5 or more; the chain stops after
            two scanned frames without one, and at the identity's own earlier reports): the
            frames before a target was confirmed, and before its detections reached the birth
            threshold. 0: off. The output comes at
            least ``backfill`` frames late: 26, the smoothing's own delay, adds none.
        unswap: two identities that come out of a close encounter (box centres within 0.75
            box heights) each on the other's person are swapped back in the reported tracks:
            each identity's motion over the ``unswap`` frames before the encounter is compared
            with both identities' motion over the ``unswap`` frames after it
            (:class:`~torchtrack.track.identity.SwapRepair`). The output comes ``unswap``
            frames later still; 0: off.
        backfill_iou: the overlap a detection needs with the box carried back to join the
            chain. Defaults 26 and 0.3 by leave one sequence out (docs/multi_target.md,
            "Back-filling a target's first frames").
    """

    model: str = "pedestrian"
    n_particles: int = 100
    dynamics: str = ""
    motion_noise: float = 0.25
    noise_height: float = 0.0
    scan_every: int = 1
    scan_min_scale: float = 0.35
    scan_max_scale: float = 0.0
    scan_scale_step: float = 1.15
    scan_stride: float = 0.08
    scan_nms: float = 0.4
    scan_vote: float = 0.0
    scan_pad: float = 0.0
    scan_box_regression: bool = True
    report_box_regression: bool = True
    report_shift: float = 0.03
    scan_cascade: float = -3.0
    min_frame_height: int = 360
    detection_threshold: float = 0.1
    birth_threshold: float = 0.9999
    birth_floor: float = 0.995
    birth_margin: float = 2.0
    external_birth_threshold: float = 0.5
    confirm_hits: int = 2
    max_lost: int = 30
    max_coast: int = 10
    visible_threshold: float = 0.5
    max_targets: int = 100
    birth_overlap: float = 0.3
    overlap_gate: float = 0.3
    ground_gate: float = 0.4
    max_cost: float = 0.8
    w_overlap: float = 1.0
    w_appearance: float = 0.5
    appearance: str = "colour"
    appearance_lambda: float = 0.0
    appearance_rate: float = 0.05
    detection_sigma: float = 0.05
    detection_sigma_rate: float = 0.0
    exclusion: float = 0.0
    reseed_overlap: float = 0.3
    duplicate_iou: float = 0.6
    duplicate_heading: bool = False
    lost_noise_growth: float = 0.1
    max_noise_scale: float = 3.0
    detection_proposal: float = 0.0
    birth_velocity: float = 0.03
    camera_motion: bool = True
    min_visible_fraction: float = 0.25
    likelihood_floor: float = 1e-6
    likelihood: str = "head"
    estimator: str = "mean"
    resample: str = "systematic"
    fill_gaps: int = 10
    smooth_sigma: float = 4.0
    backfill: int = 26
    backfill_iou: float = 0.3
    unswap: int = 10

    def validate(self) -> None:
        _positive_int(self, "n_particles", "scan_every", "confirm_hits", "max_targets")
        check_at_most(self, MAX_FILL_GAPS, "fill_gaps", "backfill", "unswap", least=0)
        if not (0.0 < self.backfill_iou <= 1.0):
            raise ConfigError(f"backfill_iou must be in (0, 1], got {self.backfill_iou}")
        if not (math.isfinite(self.smooth_sigma) and 0 <= self.smooth_sigma <= MAX_SMOOTH_SIGMA):
            raise ConfigError(
                f"smooth_sigma must be in [0, {MAX_SMOOTH_SIGMA}] frames, got {self.smooth_sigma}"
            )
        if self.confirm_hits > MAX_CONFIRM_HITS:  # 2e9: no target was ever reported, silently
            raise ConfigError(
                f"confirm_hits must be in [1, {MAX_CONFIRM_HITS}] (scans in a row), got "
                f"{self.confirm_hits}"
            )
        for k in ("max_lost", "max_coast"):
            if getattr(self, k) < 0:
                raise ConfigError(f"{k} must be >= 0, got {getattr(self, k)}")
        _in_unit(
            self,
            "detection_threshold",
            "birth_threshold",
            "birth_floor",
            "external_birth_threshold",
            "visible_threshold",
            "overlap_gate",
            "appearance_rate",
            "detection_sigma_rate",
            "reseed_overlap",
            "duplicate_iou",
            "min_visible_fraction",
            "birth_overlap",
            "detection_proposal",
        )
        if self.external_birth_threshold < self.detection_threshold:
            raise ConfigError(
                f"external_birth_threshold ({self.external_birth_threshold}) must be >= "
                f"detection_threshold ({self.detection_threshold})"
            )
        if self.birth_floor < self.detection_threshold:
            raise ConfigError(
                f"birth_floor ({self.birth_floor}) must be >= detection_threshold "
                f"({self.detection_threshold})"
            )
        if self.birth_threshold < self.detection_threshold:
            raise ConfigError(
                f"birth_threshold ({self.birth_threshold}) must be >= detection_threshold "
                f"({self.detection_threshold})"
            )
        _check_scan_min_scale(self.scan_min_scale)
        if not 0 <= self.min_frame_height <= 4320:
            raise ConfigError(
                f"min_frame_height must be in [0, 4320] pixels (0: never upsample), got "
                f"{self.min_frame_height}"
            )
        if not math.isfinite(self.scan_max_scale):
            raise ConfigError(
                f"scan_max_scale must be a finite number (0: no upper bound), got "
                f"{self.scan_max_scale}"
            )
        if self.scan_max_scale != 0 and self.scan_max_scale < self.scan_min_scale:
            raise ConfigError(
                f"scan_max_scale ({self.scan_max_scale}) is below scan_min_scale "
                f"({self.scan_min_scale}); 0 means no upper bound"
            )
        from torchtrack.detect.scan import MIN_SCALE_STEP

        if not MIN_SCALE_STEP <= self.scan_scale_step < math.inf:
            raise ConfigError(
                f"scan_scale_step must be a finite number >= {MIN_SCALE_STEP:g}, got "
                f"{self.scan_scale_step}"
            )
        if not 0 < self.scan_stride <= 1:
            raise ConfigError(f"scan_stride must be in (0, 1], got {self.scan_stride}")
        if not 0 < self.scan_nms <= 1:
            raise ConfigError(f"scan_nms must be in (0, 1], got {self.scan_nms}")
        if not (self.scan_cascade <= 0 and math.isfinite(self.scan_cascade)):
            raise ConfigError(
                f"scan_cascade must be a margin <= 0 (0: the model's own), got {self.scan_cascade}"
            )
        if not 0 <= self.scan_pad <= 0.5:
            raise ConfigError(f"scan_pad must be in [0, 0.5] (0: off), got {self.scan_pad}")
        if not (math.isfinite(self.report_shift) and -0.5 <= self.report_shift <= 0.5):
            raise ConfigError(
                f"report_shift must be in [-0.5, 0.5] (a fraction of the box height), got "
                f"{self.report_shift}"
            )
        if not 0 <= self.scan_vote <= 1:
            raise ConfigError(f"scan_vote must be in [0, 1] (0: off), got {self.scan_vote}")
        for k in (
            "w_overlap",
            "w_appearance",
            "appearance_lambda",
            "lost_noise_growth",
            "exclusion",
            "ground_gate",
            "birth_margin",
            "birth_velocity",
        ):
            v = getattr(self, k)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"{k} must be a finite number >= 0, got {v}")
        if self.w_overlap + self.w_appearance <= 0:
            raise ConfigError("w_overlap and w_appearance cannot both be 0")
        if not math.isfinite(self.w_overlap + self.w_appearance):
            raise ConfigError(
                f"w_overlap and w_appearance must add up to a finite number, got "
                f"{self.w_overlap} and {self.w_appearance}"
            )
        # fractions of a box's height (per frame): beyond 1 they say nothing a tracker can use
        for k in ("detection_sigma", "birth_velocity"):
            if getattr(self, k) > 1:
                raise ConfigError(
                    f"{k} is a fraction of the box height, at most 1, got {getattr(self, k)}"
                )
        if self.n_particles * self.max_targets > MAX_PARTICLES:
            raise ConfigError(
                f"n_particles x max_targets = {self.n_particles} x {self.max_targets} is more "
                f"than {MAX_PARTICLES} particles in all (their states alone would take "
                f"{self.n_particles * self.max_targets * 48 / 2**30:.3g} GiB)"
            )
        if not (self.max_cost > 0 and math.isfinite(self.max_cost)):
            raise ConfigError(f"max_cost must be > 0, got {self.max_cost}")
        if not (self.detection_sigma > 0 and math.isfinite(self.detection_sigma)):
            raise ConfigError(f"detection_sigma must be > 0, got {self.detection_sigma}")
        if not 1 <= self.max_noise_scale < math.inf:
            raise ConfigError(
                f"max_noise_scale must be a finite number >= 1, got {self.max_noise_scale}"
            )
        if not (0 < self.motion_noise <= 100):
            raise ConfigError(
                f"motion_noise (a factor on the fitted noise's sd) must be in (0, 100], got "
                f"{self.motion_noise}"
            )
        # a height in pixels: below 1 px the centre's noise grows by height / noise_height
        # beyond any frame (1e-300 made it infinite: every target lost at once, silently)
        if not (self.noise_height == 0 or 1 <= self.noise_height < math.inf):
            raise ConfigError(
                f"noise_height is an object height in pixels: 0 (noise in pixels) or at "
                f"least 1, got {self.noise_height}"
            )
        if self.appearance not in ("colour", "none"):
            raise ConfigError(f"appearance must be 'colour' or 'none', got {self.appearance!r}")
        if not 0.0 <= self.likelihood_floor < 1.0:
            raise ConfigError(f"likelihood_floor must be in [0, 1), got {self.likelihood_floor}")
        if self.likelihood not in ("head", "full"):
            raise ConfigError(f"likelihood must be 'head' or 'full', got {self.likelihood!r}")
        _estimator_and_scheme(self)


#: the most scans in a row a new target must be matched on before it is reported
MAX_CONFIRM_HITS = 1000

#: the longest gap filled in the reported tracks, and the widest smoothing (frames): the
#: output waits that long (the lag's frames are held in memory, video frames included)
MAX_FILL_GAPS = 1000
MAX_SMOOTH_SIGMA = 250.0

#: the largest detector window over object box height (``context``): the pedestrian windows'
#: margin is about 1.33; a window ten times the object's height no longer looks at it
MAX_CONTEXT = 10.0

#: the largest ``likelihood_power``: the weights ``p ** 100`` of a 1e-6 floor are already 1e-600
MAX_LIKELIHOOD_POWER = 100.0


def check_context(cfg: Any) -> None:
    """``cfg.context`` 0 (chosen) or in (0, MAX_CONTEXT], ``cfg.context_candidates`` a
    non-empty list in (0, MAX_CONTEXT] (the detector and fused trackers)."""
    if cfg.context != 0 and not 0 < cfg.context <= MAX_CONTEXT:
        raise ConfigError(
            f"context (window over box height) must be in (0, {MAX_CONTEXT:g}] (or 0 to choose "
            f"it), got {cfg.context}"
        )
    if not cfg.context_candidates or any(not 0 < c <= MAX_CONTEXT for c in cfg.context_candidates):
        raise ConfigError(
            f"context_candidates must be numbers in (0, {MAX_CONTEXT:g}], got "
            f"{cfg.context_candidates}"
        )


def _positive_int(cfg: Any, *names: str) -> None:
    for n in names:
        if getattr(cfg, n) < 1:
            raise ConfigError(f"{n} must be >= 1, got {getattr(cfg, n)}")


def check_at_most(cfg: Any, limit: int, *names: str, least: int = 1, prefix: str = "") -> None:
    """Every integer field ``names`` of ``cfg`` in ``[least, limit]`` (the sizes of a tracker's
    tensors and loops: see :data:`MAX_TRACKER_PARTICLES`).

    Raises:
        ConfigError: ``{prefix}key must be in [least, limit], got value``.
    """
    for n in names:
        v = getattr(cfg, n)
        if not least <= v <= limit:
            raise ConfigError(f"{prefix}{n} must be in [{least}, {limit}], got {v}")


def check_product(cfg: Any, limit: int, what: str, name: str, other: str, power: int = 1) -> None:
    """``cfg.name x cfg.other ** power`` at most ``limit`` (``what``: the unit, e.g. 'particles').

    Raises:
        ConfigError: ``name x other^power = a x b^power is more than limit what``.
    """
    a, b = getattr(cfg, name), getattr(cfg, other)
    if a * b**power > limit:
        sq = f"^{power}" if power != 1 else ""
        raise ConfigError(
            f"{name} x {other}{sq} = {a} x {b}{sq} is more than {limit} {what} (their tensors "
            "would not fit in memory)"
        )


def _in_unit(cfg: Any, *names: str) -> None:
    for n in names:
        if not 0.0 <= getattr(cfg, n) <= 1.0:
            raise ConfigError(f"{n} must be in [0, 1], got {getattr(cfg, n)}")


def check_float_limits(cfg: Any) -> None:
    """Every float (and list of floats) field of the dataclass ``cfg`` finite and within
    ``+-FLOAT_LIMIT``.

    Raises:
        ConfigError: ``key must be a finite number within +-1e+06, got value``.
    """
    for f in dataclasses.fields(cfg):
        if "float" not in str(f.type):  # float, list[float], float | None, ...
            continue
        v = getattr(cfg, f.name)
        for x in v if isinstance(v, (list, tuple)) else (v,):
            if isinstance(x, (int, float)) and not abs(x) <= FLOAT_LIMIT:
                raise ConfigError(
                    f"{f.name} must be a finite number within +-{FLOAT_LIMIT:g}, got {v}"
                )


def _validate(cfg: Any) -> None:
    cfg.validate()  # the keys' own ranges first: their messages say more
    check_float_limits(cfg)


def _check_scan_min_scale(value: float) -> None:
    """``scan_min_scale`` at least the scan's ``MIN_SCALE`` (1/16: 0.001 asked for a 51 GB
    lattice at the first scan)."""
    from torchtrack.detect.scan import MIN_SCALE

    if not MIN_SCALE <= value < math.inf:
        raise ConfigError(
            f"scan_min_scale must be a finite number >= {MIN_SCALE:g} (frames upsampled at most "
            f"{1 / MIN_SCALE:g}x for the window), got {value}"
        )


def _estimator_and_scheme(cfg: Any) -> None:
    from torchtrack.filter.resample import RESAMPLERS
    from torchtrack.filter.sir import ESTIMATORS

    if cfg.estimator not in ESTIMATORS:
        raise ConfigError(
            f"unknown estimator {cfg.estimator!r}; valid: {', '.join(sorted(ESTIMATORS))}"
        )
    if cfg.resample not in RESAMPLERS:
        raise ConfigError(
            f"unknown resampling scheme {cfg.resample!r}; valid: {', '.join(sorted(RESAMPLERS))}"
        )


#: the most particles the multi-target tracker may hold (n_particles x max_targets): 10^7
#: states of 6 float64 are 0.45 GiB, before the per-particle work of every frame
MAX_PARTICLES = 10_000_000

#: the most particles a single-target tracker may hold (``n_particles``; the detector tracker's
#: ``n_particles x n_targets``): 10^5, 50 times the papers' largest (2000). 10^9 asked for 48 GB
#: at init (a traceback from the CLI); at 10^6 one frame of the detector tracker asked for 7.5 GB
MAX_TRACKER_PARTICLES = 100_000

#: the most samples a particle filter's likelihood reads per frame: the histogram tracker's
#: ``n_particles x grid^2`` colour samples, the template tracker's ``n_particles x
#: template_size^2`` warped pixels (2^25: 2000 particles x a 128 x 128 grid ran in 2.4 GB)
MAX_LIKELIHOOD_SAMPLES = 2**25

#: the largest magnitude of a number a tracker setting takes: far beyond any real setting (pixels,
#: weights, rates, factors), small enough that the products, powers and areas made of it stay
#: finite (1e308 overflowed to inf and NaN inside the trackers, or ran on as nonsense)
FLOAT_LIMIT = 1e6

#: the largest integer a tracker setting takes (counts of frames, particles, targets, scans):
#: 2^31 - 1, far beyond any real setting, and safe in every tensor and C call it reaches
_INT_LIMIT = 2**31 - 1


def _coerce(value: Any, tp: Any, key: str, where: str, int_limit: int = _INT_LIMIT) -> Any:
    """Check ``value`` against the annotation ``tp`` (int, float, str, bool, list[float]);
    integers within ``+-int_limit``.

    Raises:
        ConfigError: ``where: 'key' must be ...``.
    """
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        errors = []
        for arg in typing.get_args(tp):
            if arg is type(None):
                if value is None:
                    return None
                continue
            try:
                return _coerce(value, arg, key, where, int_limit)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(errors[0] if errors else f"{where}: bad value for {key!r}")
    if origin is list:
        (item,) = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: {key!r} must be a list, got {value!r}")
        return [_coerce(v, item, key, where, int_limit) for v in value]
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: {key!r} must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: {key!r} must be an integer, got {value!r}")
        if not -int_limit <= value <= int_limit:  # counts of frames, particles, targets
            raise ConfigError(
                f"{where}: {key!r} must be an integer within +-{int_limit}, got {value!r}"
            )
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: {key!r} must be a number, got {value!r}")
        try:
            return float(value)
        except OverflowError:  # an integer beyond the float range (10**400): a traceback
            raise ConfigError(
                f"{where}: {key} must be a finite number within +-{FLOAT_LIMIT:g}, got an "
                f"integer of {len(str(abs(value)))} digits"
            ) from None
    if tp is str:
        if not isinstance(value, (str, os.PathLike)):
            raise ConfigError(f"{where}: {key!r} must be a string, got {value!r}")
        return os.fspath(value)
    return value  # pragma: no cover - no other annotation is used


#: the typed check of one config value, shared with the detector training config
coerce_value = _coerce


def config_from_dict(cls: type[C], data: dict[str, Any], where: str = "config") -> C:
    """Build ``cls`` from ``data``; unknown keys and wrong types raise :class:`ConfigError`."""
    return apply_overrides(cls(), data, where)


def apply_overrides(cfg: C, overrides: dict[str, Any], where: str = "parameters") -> C:
    """A copy of ``cfg`` with ``overrides`` applied (checked like :func:`config_from_dict`)."""
    cls = type(cfg)
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(overrides) - set(names))
    if unknown:
        raise ConfigError(
            f"{where}: unknown key(s) {', '.join(map(repr, unknown))}; valid keys: "
            f"{', '.join(names)}"
        )
    values = {k: _coerce(v, hints[k], k, where) for k, v in overrides.items()}
    out = dataclasses.replace(cfg, **values)
    try:
        _validate(out)
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None
    return out


def load_tracker_config(path: str | os.PathLike, cls: type[C]) -> C:
    """Load a flat TOML file into ``cls`` (relative ``dynamics`` / ``model`` paths are taken
    relative to the file when such a file exists there).

    Raises:
        ConfigError: unreadable TOML, unknown keys (named), wrong types or values.
    """
    p = os.fspath(path)
    try:
        with open(p, "rb") as f:
            data = tomllib.load(f)
    except OSError as e:
        raise ConfigError(f"cannot read tracker config {p!r}: {e.strerror or e}") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"tracker config {p!r} is not valid TOML: {e}") from None
    except RecursionError:  # '[[[[...' nested 10^5 deep: Python's own traceback
        raise ConfigError(
            f"tracker config {p!r} is not valid TOML: it nests arrays or tables too deeply to read"
        ) from None
    except UnicodeDecodeError as e:
        raise ConfigError(
            f"tracker config {p!r} is not valid TOML: not UTF-8 text ({e.reason} at byte {e.start})"
        ) from None
    base = os.path.dirname(os.path.abspath(p))
    for key in ("dynamics", "model"):
        v = data.get(key)
        if isinstance(v, str) and v and not os.path.isabs(v):
            cand = os.path.join(base, os.path.expanduser(v))
            if os.path.exists(cand):
                data[key] = cand
    return config_from_dict(cls, data, where=p)


def resolve_tracker_config(
    cls: type[C],
    config: C | str | os.PathLike | None,
    overrides: dict[str, Any] | None = None,
    where: str = "parameters",
) -> C:
    """The config a tracker runs with: ``cls()`` defaults, a given ``cls`` instance (its fields
    type-checked like a TOML file's keys), or a TOML file loaded with
    :func:`load_tracker_config`; then keyword ``overrides`` applied and checked.
    """
    if config is None:
        cfg = cls()
    elif isinstance(config, cls):
        # a config built in Python skipped the typed check its TOML keys and keyword overrides
        # get: n_particles=True ran 1 particle, 2.5 particles went on, '3' or None was a
        # TypeError in validate(); its fields now pass that check (a copy, the same values)
        fields = {f.name: getattr(config, f.name) for f in dataclasses.fields(cls)}
        cfg = apply_overrides(cls(), fields, where=where)
    else:
        cfg = load_tracker_config(config, cls)
    if overrides:
        return apply_overrides(cfg, overrides, where=where)
    _validate(cfg)
    return cfg
