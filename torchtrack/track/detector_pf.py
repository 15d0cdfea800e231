"""Calibrated-detector particle-filter tracker (Chateau, Gay-Belille, Chausse and Lapresté,
"Real-time tracking with classifiers", ECCV workshop 2006), registered as ``detector``.

* State (sec. 2.3, eq. 2): ``X = (c_t, c_{t-1}, s_t, s_{t-1})``; the detector window is
  ``R(X) = c_t + s_t W`` (eq. 3) where ``W`` is the target's reference window, so ``s = 1`` on
  the first frame (the scale convention under which the shipped dynamics were fitted).
* Dynamics: the AR model ``X_{t+1} = A X_t + B v_t`` (eq. 4) with ``A, B, Sigma`` fitted by
  least squares on annotated tracks (``dynamics_chateau.toml``; :class:`~torchtrack.filter.ChateauAR`).
* Likelihood (sec. 2.4, eq. 8 / 11): each particle's weight is the detector's Platt-calibrated
  probability of its window, all particles of a frame scored from one integral image
  (:class:`~torchtrack.observe.detector.DetectorObservation`).
* Filter: CONDENSATION (Fig. 1: resample, predict, weight, estimate), 200 particles by default,
  batched over B targets (one row per target).
* Initialisation (sec. 4.2): with no box, the first frame is scanned over translations and
  scales with the detector; the best detections (after non-maximum suppression) become the
  targets and each target's particles are drawn by importance sampling from the ``init_top_n``
  highest-scoring scan windows that overlap it (probability proportional to the score).

Object box and detector window. Detectors trained on crops with a margin (INRIA pedestrians
stand in the middle of a 64 x 128 window with ~16 px around them) score a window larger than
the object. ``context`` is the window height over the object box height; the window has the
detector's aspect ratio and the object box's centre. The reported box is ``c_t + s_t B0`` with
``B0`` the first box's size. With ``context = 0`` (default) it is chosen on the first frame as
the ratio, among ``context_candidates``, whose window at the given box scores highest.

Visibility. ``confidence`` is the mean calibrated probability of the predicted particles,
the particle estimate of the evidence ``p(Z_t | Z_{0:t-1})``; the target is reported
``visible`` while it is at least ``visible_threshold`` (default 0.1). The best particle's
probability is not used: a class detector finds some window scoring above 0.8 near almost any
target in a cluttered street (measured on Crossing, BoBoT and Jogging1, also during
occlusions). The mean is 0.18-0.3 on Crossing's small pedestrian and 0.5-0.8 on BoBoT's and
Jogging1's larger ones, drops to 0.2-0.4 while Jogging1's runner is behind a pole, and to ~0
when the target leaves the frame (windows outside the frame score 0); occlusion by another
person of the same class is not detected (the detector cannot tell persons apart). A lost
target's weights stay close to uniform (a likelihood floor of 1e-6 keeps them finite), so the
particles keep following the AR dynamics and the track becomes visible again when they land on
the reappearing target.
"""

from __future__ import annotations

import math
import os
import warnings
from pathlib import Path
from typing import Any

import torch

from torchtrack.boxes import box_iou_matrix
from torchtrack.errors import ConfigError, TrackerError
from torchtrack.filter._random import multinomial
from torchtrack.filter.motion import ChateauAR
from torchtrack.filter.sir import sir_step
from torchtrack.observe.detector import DetectorObservation
from torchtrack.track.base import Tracker, TrackState, check_tracker_generator, register_tracker
from torchtrack.track.config import (
    DetectorTrackerConfig,
    apply_overrides,
    resolve_tracker_config,
)

__all__ = ["DetectorTracker", "default_dynamics_path", "load_dynamics", "resolve_detector"]

_PACKAGE = Path(__file__).resolve().parents[1]


def default_dynamics_path(structure: str = "free") -> Path | None:
    """The fitted Chateau dynamics shipped with torchtrack (``torchtrack/data/``, package
    data, refitted by ``tools/fit_dynamics.py``): ``structure="free"`` is eq. (4) with A fitted
    (``dynamics_chateau.toml``), ``"constant_velocity"`` constant velocity with Sigma fitted
    (``dynamics_chateau_cv.toml``, the multi-target tracker's default); ``None`` if the file
    is missing."""
    name = (
        "dynamics_chateau_cv.toml" if structure == "constant_velocity" else "dynamics_chateau.toml"
    )
    cand = _PACKAGE / "data" / name
    return cand if cand.is_file() else None


def load_dynamics(path: str | os.PathLike | None = None, structure: str = "free") -> ChateauAR:
    """The AR dynamics of eq. (4) from ``path`` (default :func:`default_dynamics_path` of
    ``structure``).

    Without any file the constant-velocity defaults of :class:`ChateauAR` are used, with a
    warning.
    """
    from torchtrack.filter.dynamics_fit import load_chateau_toml

    p = Path(path) if path else default_dynamics_path(structure)
    if p is None:
        warnings.warn(
            "dynamics_chateau.toml not found; using constant-velocity default dynamics",
            stacklevel=2,
        )
        return ChateauAR()
    if p.is_dir():
        raise ConfigError(f"dynamics file {os.fspath(p)!r} is a folder; give a TOML file")
    if not p.is_file():
        raise ConfigError(f"dynamics file {os.fspath(p)!r} does not exist")
    return load_chateau_toml(p)


def resolve_detector(model: Any):
    """A :class:`~torchtrack.detect.Detector` from an instance, a bundled model name or a model
    file path.

    Raises:
        ConfigError: an unknown name or a missing file.
        ModelFormatError: a corrupt model file.
    """
    from torchtrack.detect.detector import Detector

    if isinstance(model, Detector):
        return model
    if not isinstance(model, (str, os.PathLike)) or not os.fspath(model):
        raise ConfigError(
            f"model must be a Detector, a bundled model name or a file, got {model!r}"
        )
    try:
        from torchtrack.detect.bundled import load_model
    except ImportError:  # bundled models not available in this version
        load_model = None
    if load_model is not None:
        return load_model(model)
    from torchtrack.detect.model_file import load_detector

    if not Path(model).is_file():
        raise ConfigError(f"detector model {os.fspath(model)!r} is not a file")
    return load_detector(model)


@register_tracker(
    "detector",
    description="Chateau et al. 2006: particle filter weighted by a calibrated class detector",
)
class DetectorTracker(Tracker):
    """Particle filter whose likelihood is a calibrated class detector (see module doc).

    Args:
        model: a :class:`~torchtrack.detect.Detector`, a bundled model name or a model file;
            overrides ``config.model``.
        config: a :class:`DetectorTrackerConfig` or a TOML file of one.
        generator: the source of randomness (reproducible runs).
        **overrides: any :class:`DetectorTrackerConfig` field, e.g. ``n_particles=500``.

    Attributes:
        config: the effective configuration.
        detector: the detector in use.
        context: ``(B,)`` window-over-box height ratio per target (after :meth:`init`).

    Example::

        tracker = DetectorTracker("pedestrian")
        state = tracker.init(frame)             # scan the first frame (or pass a box)
        for frame in frames:
            state = tracker.update(frame)       # state.box (B, 4), state.visible (B,)
    """

    name = "detector"
    max_targets = None
    auto_init = True

    def __init__(
        self,
        model: Any = None,
        config: DetectorTrackerConfig | str | os.PathLike | None = None,
        generator: torch.Generator | None = None,
        **overrides: Any,
    ) -> None:
        super().__init__()
        cfg = resolve_tracker_config(
            DetectorTrackerConfig, config, overrides, where="detector tracker"
        )
        if model is not None and not isinstance(model, (str, os.PathLike)):
            self.detector = resolve_detector(model)
        else:
            if model is not None:
                cfg = apply_overrides(cfg, {"model": os.fspath(model)}, where="detector tracker")
            self.detector = resolve_detector(cfg.model)
        self.config = cfg
        self.generator = check_tracker_generator(generator)
        self.observation = DetectorObservation(
            self.detector, floor=cfg.likelihood_floor, head=cfg.likelihood == "head"
        )
        self.dynamics = load_dynamics(cfg.dynamics or None)
        win_h, win_w = self.detector.window
        self._aspect = float(win_w) / float(win_h)  # detector window width / height
        self.context: torch.Tensor | None = None
        self._states: torch.Tensor | None = None
        self._log_w: torch.Tensor | None = None
        self._obj: torch.Tensor | None = None  # (B, 2) w, h of the object box at s = 1
        self._win: torch.Tensor | None = None  # (B, 2) w, h of the detector window at s = 1
        self._last_p: torch.Tensor | None = None

    # -- geometry ------------------------------------------------------------------------------
    @staticmethod
    def _boxes(states: torch.Tensor, size: torch.Tensor) -> torch.Tensor:
        """Eq. (3): ``states (B, N, 6)``, ``size (B, 2)`` -> boxes ``(B, N, 4)`` of
        ``c_t + s_t size``."""
        s = states[..., 4:5]
        wh = s * size[:, None, :]
        return torch.cat([states[..., 0:2] - wh / 2, wh], -1)

    def window_boxes(self, states: torch.Tensor) -> torch.Tensor:
        """Detector windows ``(B, N, 4)`` of particle ``states (B, N, 6)``."""
        return self._boxes(states, self._win)

    def object_boxes(self, states: torch.Tensor) -> torch.Tensor:
        """Object boxes ``(B, N, 4)`` of particle ``states (B, N, 6)``."""
        return self._boxes(states, self._obj)

    def _window_size(self, boxes: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        h = boxes[:, 3] * context
        return torch.stack([h * self._aspect, h], 1)

    # -- observation ---------------------------------------------------------------------------
    def _probabilities(self, frame: torch.Tensor, windows: torch.Tensor) -> torch.Tensor:
        """``windows (B, N, 4)`` on one ``frame (C, H, W)`` -> ``(B, N)`` probabilities, all
        targets scored from one integral image."""
        b, n = windows.shape[:2]
        p = self.observation.probabilities(frame[None], windows.reshape(1, b * n, 4))
        return p.reshape(b, n).to(torch.float64)

    def _choose_context(self, frame: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
        cands = torch.tensor(
            self.config.context_candidates, dtype=torch.float64, device=boxes.device
        )
        b, k = boxes.shape[0], cands.numel()
        h = boxes[:, 3:4] * cands  # (B, K) window heights
        w = h * self._aspect
        cx = (boxes[:, 0] + boxes[:, 2] / 2)[:, None].expand(b, k)
        cy = (boxes[:, 1] + boxes[:, 3] / 2)[:, None].expand(b, k)
        wins = torch.stack([cx - w / 2, cy - h / 2, w, h], -1)
        p = self._probabilities(frame, wins)
        return cands[p.argmax(1)]

    # -- Tracker API ---------------------------------------------------------------------------
    def _init(self, frame: torch.Tensor, boxes: torch.Tensor | None) -> TrackState:
        cfg = self.config
        n = cfg.n_particles
        if boxes is None:
            return self._init_from_scan(frame)
        boxes = boxes.to(torch.float64)
        b = boxes.shape[0]
        if cfg.context > 0:
            ctx = torch.full((b,), float(cfg.context), dtype=torch.float64, device=boxes.device)
        else:
            ctx = self._choose_context(frame, boxes)
        self.context = ctx
        self._obj = boxes[:, 2:4].clone()
        self._win = self._window_size(boxes, ctx)
        c = boxes[:, 0:2] + boxes[:, 2:4] / 2
        one = torch.ones((b, 1), dtype=torch.float64, device=boxes.device)
        x0 = torch.cat([c, c, one, one], 1)  # (B, 6): c_t = c_{t-1}, s_t = s_{t-1} = 1
        # Spread by one step of the dynamics around the given state (the prior of Fig. 1).
        self._states = self.dynamics.predict(x0[:, None].repeat(1, n, 1), self.generator)
        self._log_w = torch.full((b, n), -math.log(n), dtype=torch.float64, device=boxes.device)
        p = self._probabilities(frame, self._win_boxes_at(boxes, ctx))
        return TrackState(
            box=boxes.clone(),
            confidence=p[:, 0],
            visible=torch.ones(b, dtype=torch.bool, device=boxes.device),
            particles=self._states,
            log_weights=self._log_w,
        )

    def _win_boxes_at(self, boxes: torch.Tensor, ctx: torch.Tensor) -> torch.Tensor:
        size = self._window_size(boxes, ctx)
        c = boxes[:, 0:2] + boxes[:, 2:4] / 2
        return torch.cat([c - size / 2, size], 1)[:, None]

    def _init_from_scan(self, frame: torch.Tensor) -> TrackState:
        """Sec. 4.2: scan the first frame, take the best detections, importance-sample each
        target's particles from the top-N windows overlapping it."""
        from torchtrack.detect.scan import nms, scan

        cfg = self.config
        wins, scores = scan(
            self.detector,
            frame,
            threshold=None,
            nms_iou=None,
            scale_step=cfg.scan_scale_step,
            stride=cfg.scan_stride,
            min_scale=cfg.scan_min_scale,
        )
        wins, scores = wins.to(torch.float64), scores.to(torch.float64)
        strong = scores >= cfg.scan_threshold
        if not bool(strong.any()):
            best = float(scores[0]) if scores.numel() else float("nan")
            raise TrackerError(
                f"no {self.detector.name!r} detection on the first frame (best probability "
                f"{best:.3f} < scan_threshold {cfg.scan_threshold}); give the target's box "
                "(--box x,y,w,h) or lower scan_threshold"
            )
        keep = nms(wins[strong], scores[strong], 0.3)[: cfg.n_targets]
        dets = wins[strong][keep]  # (B, 4) detection windows, best first
        b, n = dets.shape[0], cfg.n_particles
        iou = box_iou_matrix(dets, wins)  # (B, M)
        states, boxes_out, conf = [], [], []
        for i in range(b):  # loop over targets (a handful), not particles
            idx = torch.nonzero(iou[i] >= 0.3).flatten()[: cfg.init_top_n]  # scores sorted
            cand, sc = wins[idx], scores[idx]
            draw = multinomial(sc.to(torch.float64), n, self.generator, replacement=True)
            picked = cand[draw]  # (n, 4)
            c = picked[:, 0:2] + picked[:, 2:4] / 2
            s = picked[:, 3] / dets[i, 3]
            states.append(torch.stack([c[:, 0], c[:, 1], c[:, 0], c[:, 1], s, s], 1))
            wmean = (sc[:, None] * cand).sum(0) / sc.sum()
            boxes_out.append(wmean)
            conf.append(sc[0])
        self._win = dets[:, 2:4].clone()
        self._obj = self._win / cfg.scan_context
        self.context = torch.full(
            (b,), float(cfg.scan_context), dtype=torch.float64, device=dets.device
        )
        st = torch.stack(states)
        # Jitter with one step of process noise so that duplicated windows differ.
        self._states = self.dynamics.predict(st, self.generator)
        self._states[..., 2:4] = st[..., 0:2]
        self._log_w = torch.full((b, n), -math.log(n), dtype=torch.float64, device=dets.device)
        wb = torch.stack(boxes_out)
        c = wb[:, 0:2] + wb[:, 2:4] / 2
        obj = wb[:, 2:4] / cfg.scan_context
        box = torch.cat([c - obj / 2, obj], 1)
        return TrackState(
            box=box,
            confidence=torch.stack(conf),
            visible=torch.ones(b, dtype=torch.bool, device=dets.device),
            particles=self._states,
            log_weights=self._log_w,
        )

    def _update(self, frame: torch.Tensor) -> TrackState:
        cfg = self.config
        holder: dict[str, torch.Tensor] = {}

        def log_likelihood(states: torch.Tensor) -> torch.Tensor:
            p = self._probabilities(frame, self.window_boxes(states))
            holder["p"] = p
            logp = p.clamp_min(cfg.likelihood_floor).log() if cfg.likelihood_floor > 0 else p.log()
            return logp if cfg.likelihood_power == 1.0 else cfg.likelihood_power * logp

        res = sir_step(
            self._states,
            self._log_w,
            self._predict,
            log_likelihood,
            scheme=cfg.resample,
            estimator=cfg.estimator,
            generator=self.generator,
        )
        self._states, self._log_w = res.states, res.log_weights
        p = holder["p"]
        self._last_p = p
        # The mean probability of the predicted particles estimates the evidence
        # p(Z_t | Z_{0:t-1}) (the particles were resampled to equal weights before the step).
        evidence = p.mean(1)
        box = self.object_boxes(res.estimate[:, None])[:, 0]
        return TrackState(
            box=box,
            confidence=evidence,
            visible=evidence >= cfg.visible_threshold,
            particles=self._states,
            log_weights=self._log_w,
        )

    def _predict(self, states: torch.Tensor, generator) -> torch.Tensor:
        """The AR dynamics, confined to the frame (a lost target's particles do not run away:
        :meth:`~torchtrack.filter.ChateauAR.confine`)."""
        return self.dynamics.confine(self.dynamics.predict(states, generator), self.frame_size)

    def particle_boxes(self) -> torch.Tensor:
        """Current particles as object boxes ``(B, N, 4)`` (for drawing)."""
        if self._states is None:
            raise TrackerError("particle_boxes() called before init()")
        return self.object_boxes(self._states)
