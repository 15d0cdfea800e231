"""The design card's combination, registered as ``fused``: one particle filter whose weight is
the product of an offline class detector's calibrated probability and the online co-trained
pixel likelihood.

    log w(X) = a log max(P_det(X), det_floor) + b log L_cot(X)

* ``P_det``: the detector's Platt-calibrated probability of the particle's detector window
  (Chateau et al.; :class:`~torchtrack.observe.detector.DetectorObservation`), the window being
  ``c + s W`` as in the ``detector`` tracker (same state, AR dynamics, context choice; this
  class extends :class:`~torchtrack.track.detector_pf.DetectorTracker`).
* ``L_cot``: Jin et al.'s eq. (13) on the co-trained colour/texture pixel classifiers
  (:class:`~torchtrack.learn.cotrain.CoTrainer`): the mean positive fused confidence in the
  particle's object box (the window sum of
  :class:`~torchtrack.observe.cotrain.CoTrainLikelihood` over the box area, floored at
  ``cot_floor``) times the Gaussian gate around the previous estimate (sigma ``gate_scale``
  times the box). The classifiers are updated on the blob they find, as in the ``cotrain``
  tracker.
* ``a = det_weight``, ``b = cotrain_weight`` set each term's strength (``b = 0``: the detector
  filter alone; ``a = 0``: the co-training likelihood alone on the same filter).

Why calibration matters. A product of likelihoods is only meaningful if each factor is a
likelihood on a fixed scale: the calibrated ``P_det`` is a probability that is ~0 for
background windows and near 1 on the object in every frame, so its log adds a fixed-scale
evidence term to the co-training term. ``calibration = "raw"`` replaces it with the
uncalibrated margin rescaled to [0, 1] over the frame's particles (min-max): the best particle
of every frame gets 1 and the worst 0 whatever the detector sees, so the factor no longer says
whether the object is there and its weight against the co-training term changes from frame to
frame. ``calibration = "naive"`` is the paper's own uncalibrated baseline (section 2.4): the
margin rescaled by the classifier's fixed range ``[a_min, a_max]`` (for boosted stumps the sums
of each stump's smaller and larger output), a fixed monotone map like Platt's but not fitted
to probabilities: its values crowd in the middle of [0, 1], so the detector factor barely
separates object from background next to the co-training term (see ``tools/bench_fused.py``).

Visibility: visible when (``a > 0``) the mean calibrated probability of the particles is at
least ``visible_threshold`` and (``b > 0``) the co-trained classifiers find a blob.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Any

import torch

from torchtrack.errors import ConfigError
from torchtrack.filter.sir import sir_step
from torchtrack.learn.cotrain import CoTrainer
from torchtrack.observe.cotrain import CoTrainCue
from torchtrack.track.base import TrackState, register_tracker
from torchtrack.track.config import (
    MAX_TRACKER_PARTICLES,
    apply_overrides,
    check_at_most,
    check_context,
    resolve_tracker_config,
)
from torchtrack.track.detector_pf import DetectorTracker

__all__ = ["FusedTracker", "FusedTrackerConfig", "fused_log_weights", "minmax_rescale"]

CALIBRATIONS = ("platt", "raw", "naive")

#: the largest det_weight / cotrain_weight: a log-likelihood term 100 times over is already a
#: likelihood raised to the 100th power (1e308 overflowed the weights to +inf)
MAX_WEIGHT = 100.0


@dataclass
class FusedTrackerConfig:
    """Every parameter of the fused tracker.

    Attributes:
        model: detector: bundled name (``pedestrian``, ``vehicle``) or a model file.
        det_weight: a, strength of the detector term.
        cotrain_weight: b, strength of the co-training term.
        calibration: ``platt`` (the detector's calibrated probability), ``raw`` (the
            uncalibrated margin min-max rescaled over the frame's particles) or ``naive``
            (Chateau et al.'s "naive way", section 2.4: the margin rescaled by the classifier's
            fixed range, ``(m - a_min) / (a_max - a_min)``; boosted-stump detectors only);
            the last two are ablations.
        n_particles: particles.
        det_floor: smallest detector likelihood (keeps logs finite).
        cot_floor: smallest mean positive co-training confidence of a box.
        gate_scale: gate sigma of eq. (13) as a fraction of the box (w, h).
        search_scale: co-training candidate region = this times the box.
        visible_threshold: smallest mean detector probability of the particles for a visible
            target (as the ``detector`` tracker).
        context, context_candidates: detector window over object box height (0: chosen on the
            first frame), as the ``detector`` tracker.
        dynamics: AR dynamics TOML (empty: the shipped fit).
        estimator, resample: particle-filter estimate and resampling scheme.
        cotrain_mode: ``cotrain`` or ``self`` (pixel classifier).
        n_selectors, n_candidates: online boosting sizes of each pixel classifier.
    """

    model: str = "pedestrian"
    det_weight: float = 1.0
    cotrain_weight: float = 1.0
    calibration: str = "platt"
    n_particles: int = 300
    det_floor: float = 1e-6
    cot_floor: float = 1e-4
    gate_scale: float = 1.0
    search_scale: float = 2.0
    visible_threshold: float = 0.25
    context: float = 0.0
    context_candidates: list[float] = field(
        default_factory=lambda: [1.0, 1.1, 1.2, 1.3, 1.4, 1.5, 1.6]
    )
    dynamics: str = ""
    estimator: str = "mean"
    resample: str = "systematic"
    cotrain_mode: str = "cotrain"
    n_selectors: int = 10
    n_candidates: int = 4

    def validate(self) -> None:
        from torchtrack.filter.resample import RESAMPLERS
        from torchtrack.filter.sir import ESTIMATORS

        for k in ("det_weight", "cotrain_weight"):
            if not 0 <= getattr(self, k) <= MAX_WEIGHT:
                raise ConfigError(f"{k} must be in [0, {MAX_WEIGHT:g}], got {getattr(self, k)}")
        if self.det_weight == 0 and self.cotrain_weight == 0:
            raise ConfigError("det_weight and cotrain_weight are both 0: no likelihood left")
        if self.calibration not in CALIBRATIONS:
            raise ConfigError(
                f"calibration must be one of {', '.join(CALIBRATIONS)}, got {self.calibration!r}"
            )
        for k in ("n_particles", "n_selectors", "n_candidates"):
            if getattr(self, k) < 1:
                raise ConfigError(f"{k} must be >= 1, got {getattr(self, k)}")
        check_at_most(self, MAX_TRACKER_PARTICLES, "n_particles")  # 10^9: 48 GB at init
        check_at_most(self, 100, "n_selectors", "n_candidates")
        for k in ("det_floor", "cot_floor", "gate_scale"):
            if not getattr(self, k) > 0:
                raise ConfigError(f"{k} must be > 0, got {getattr(self, k)}")
        if not 1 <= self.search_scale <= 100:
            raise ConfigError(
                f"search_scale (x the box) must be in [1, 100], got {self.search_scale}"
            )
        if not 0 <= self.visible_threshold <= 1:
            raise ConfigError(f"visible_threshold must be in [0, 1], got {self.visible_threshold}")
        check_context(self)
        if self.estimator not in ESTIMATORS:
            raise ConfigError(f"unknown estimator {self.estimator!r}")
        if self.resample not in RESAMPLERS:
            raise ConfigError(f"unknown resampling scheme {self.resample!r}")
        if self.cotrain_mode not in ("cotrain", "self"):
            raise ConfigError(f"cotrain_mode must be cotrain or self, got {self.cotrain_mode!r}")


def minmax_rescale(x: torch.Tensor) -> torch.Tensor:
    """``(B, N)`` -> ``(B, N)`` rescaled to [0, 1] per row over its finite entries (non-finite
    entries become 0; a constant row becomes all ones)."""
    fin = torch.isfinite(x)
    lo = torch.where(fin, x, torch.full_like(x, math.inf)).min(1, keepdim=True).values
    hi = torch.where(fin, x, torch.full_like(x, -math.inf)).max(1, keepdim=True).values
    span = hi - lo
    y = torch.where(span > 0, (x - lo) / span.clamp_min(1e-300), torch.ones_like(x))
    return torch.where(fin, y, torch.zeros_like(x))


def fused_log_weights(
    p_det: torch.Tensor,
    log_cot: torch.Tensor,
    det_weight: float,
    cotrain_weight: float,
    det_floor: float = 1e-6,
) -> torch.Tensor:
    """``a log max(p_det, floor) + b log_cot``: ``(B, N)`` float64. A zero weight drops its term
    entirely (also its -inf entries)."""
    out = torch.zeros(p_det.shape, dtype=torch.float64, device=p_det.device)
    if det_weight > 0:
        out = out + det_weight * p_det.to(torch.float64).clamp_min(det_floor).log()
    if cotrain_weight > 0:
        out = out + cotrain_weight * log_cot.to(torch.float64)
    return out


@register_tracker(
    "fused",
    description="design card: calibrated class detector x online co-trained pixel likelihood "
    "in one particle filter (det_weight, cotrain_weight, calibration=platt|raw|naive)",
)
class FusedTracker(DetectorTracker):
    """Calibrated detector x co-trained pixel likelihood particle filter (see module doc).

    Args:
        model: a Detector, a bundled model name or a model file (overrides ``config.model``).
        config: a :class:`FusedTrackerConfig` or a TOML file of one.
        generator: the source of randomness.
        **overrides: any :class:`FusedTrackerConfig` field.

    Attributes:
        history: per frame after the first: ``p_mean`` (mean detector probability),
            ``blob`` (the co-trained classifiers found the object), ``accepted``.

    Example::

        tracker = FusedTracker("pedestrian", det_weight=1.0, cotrain_weight=0.5)
        state = tracker.init(frame, (x, y, w, h))
        state = tracker.update(next_frame)
    """

    name = "fused"
    max_targets = 1
    auto_init = False

    def __init__(
        self,
        model: Any = None,
        config: FusedTrackerConfig | str | os.PathLike | None = None,
        generator: torch.Generator | None = None,
        **overrides: Any,
    ) -> None:
        cfg = resolve_tracker_config(FusedTrackerConfig, config, overrides, where="fused tracker")
        if model is not None and isinstance(model, (str, os.PathLike)):
            cfg = apply_overrides(cfg, {"model": os.fspath(model)}, where="fused tracker")
            model = None
        super().__init__(
            model=model if model is not None else cfg.model,
            generator=generator,
            n_particles=cfg.n_particles,
            likelihood_floor=cfg.det_floor,
            visible_threshold=cfg.visible_threshold,
            context=cfg.context,
            context_candidates=list(cfg.context_candidates),
            dynamics=cfg.dynamics,
            estimator=cfg.estimator,
            resample=cfg.resample,
        )
        self.fused_config = cfg
        self.trainer = CoTrainer(
            mode=cfg.cotrain_mode, n_selectors=cfg.n_selectors, n_candidates=cfg.n_candidates
        )
        self.cue = CoTrainCue(self.trainer, cfg.search_scale, cfg.cot_floor)
        self.history: list[dict[str, Any]] = []
        self._size: tuple[float, float] | None = None
        self._centre: tuple[float, float] | None = None

    # -- terms ---------------------------------------------------------------------------------
    def margins(self, frame: torch.Tensor, windows: torch.Tensor) -> torch.Tensor:
        """Uncalibrated detector margins ``(B, N)`` of ``windows (B, N, 4)`` on one
        ``frame (C, H, W)`` (``-inf`` for windows that cannot be scored)."""
        b, n = windows.shape[:2]
        m = self.observation.margins(frame[None], windows.reshape(1, b * n, 4))
        return m.reshape(b, n)

    def margin_range(self) -> tuple[float, float]:
        """``(a_min, a_max)``: the smallest and largest margin the detector's classifier can
        give (boosted stumps: the sums of each stump's smaller and larger output; boosted
        trees: of each tree's smallest and largest leaf).

        Raises:
            ConfigError: the classifier has no bounded margin (e.g. an SVM).
        """
        clf = self.observation.detector.classifier  # the tracking head when the model has one
        bounds = getattr(clf, "margin_range", None)
        if callable(bounds):  # boosted trees: the sums of each tree's smallest / largest leaf
            return bounds()
        left, right = getattr(clf, "left_", None), getattr(clf, "right_", None)
        if left is None or right is None:
            raise ConfigError(
                f"calibration='naive' needs a boosted-stump detector (a bounded margin); "
                f"{type(clf).__name__} has none"
            )
        lo = float(torch.minimum(left, right).to(torch.float64).sum())
        hi = float(torch.maximum(left, right).to(torch.float64).sum())
        return lo, hi

    def detector_term(
        self, frame: torch.Tensor, states: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(P_det, p) (B, N)``: the detector factor of the weights (calibrated
        probabilities, or for the ablations the min-max rescaled margins (``raw``) or the
        margins rescaled by the classifier's range (``naive``)) and the calibrated probabilities
        (for the evidence), from one scoring of the windows."""
        wins = self.window_boxes(states)
        m = self.margins(frame, wins)
        p = self.observation.probabilities_from_margins(m).to(torch.float64)
        cal = self.fused_config.calibration
        if cal == "platt":
            return p, p
        if cal == "raw":
            return minmax_rescale(m), p
        lo, hi = self.margin_range()
        return ((m - lo) / max(hi - lo, 1e-12)).clamp(0.0, 1.0), p  # -inf (unscorable) -> 0

    def cotrain_term(self, states: torch.Tensor) -> torch.Tensor:
        """``log L_cot (B, N)``: log mean positive confidence in each particle's object box
        (floored; :class:`~torchtrack.observe.cotrain.CoTrainCue`) minus the gate's squared
        distance / 2; 0 when this frame has no co-training maps (the region left the frame)."""
        cfg = self.fused_config
        if self.cue.maps is None:
            return torch.zeros(states.shape[:2], dtype=torch.float64, device=states.device)
        size = self._size
        gate = (cfg.gate_scale * size[0], cfg.gate_scale * size[1])
        dx = (states[..., 0].to(torch.float64) - self._centre[0]) / gate[0]
        dy = (states[..., 1].to(torch.float64) - self._centre[1]) / gate[1]
        return self.cue.log_likelihood(self.object_boxes(states)) - 0.5 * (dx * dx + dy * dy)

    # -- Tracker API ---------------------------------------------------------------------------
    def _init(self, frame: torch.Tensor, boxes: torch.Tensor | None) -> TrackState:
        st = super()._init(frame, boxes)
        x, y, w, h = (float(v) for v in st.box[0])
        self._size = (w, h)
        self._centre = (x + w / 2, y + h / 2)
        self.history = []
        if self.fused_config.cotrain_weight > 0:
            self.cue.init(frame, (x, y, w, h), self.frame_size, self.generator)
        return st

    def _update(self, frame: torch.Tensor) -> TrackState:
        cfg = self.fused_config
        if cfg.cotrain_weight > 0:
            self.cue.score(frame, self._centre, self._size, self.frame_size)
        hold: dict[str, torch.Tensor] = {}

        def log_likelihood(states: torch.Tensor) -> torch.Tensor:
            p = None
            if cfg.det_weight > 0:
                p, hold["p"] = self.detector_term(frame, states)
            lc = self.cotrain_term(states) if cfg.cotrain_weight > 0 else None
            zeros = torch.zeros(states.shape[:2], dtype=torch.float64, device=states.device)
            return fused_log_weights(
                p if p is not None else zeros,
                lc if lc is not None else zeros,
                cfg.det_weight,
                cfg.cotrain_weight,
                cfg.det_floor,
            ).to(states.dtype)

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
        box = self.object_boxes(res.estimate[:, None])[:, 0]
        x, y, w, h = (float(v) for v in box[0])
        hh, ww = self.frame_size
        self._size = (max(w, 1.0), max(h, 1.0))
        self._centre = (min(max(x + w / 2, 0.0), ww - 1.0), min(max(y + h / 2, 0.0), hh - 1.0))
        evidence = (
            hold["p"].mean(1).to(torch.float64) if "p" in hold else torch.ones(1, device=box.device)
        )
        blob, accepted = self.cue.update(self.generator) if cfg.cotrain_weight > 0 else (0, 0)
        visible = True
        if cfg.det_weight > 0:
            visible = visible and bool(evidence[0] >= cfg.visible_threshold)
        if cfg.cotrain_weight > 0:
            visible = visible and blob
        self.history.append(
            {"p_mean": float(evidence[0]), "blob": bool(blob), "accepted": accepted}
        )
        return TrackState(
            box=box.to(torch.float64),
            confidence=evidence.to(torch.float64),
            visible=torch.tensor([visible], device=box.device),
            particles=self._states,
            log_weights=self._log_w,
        )
