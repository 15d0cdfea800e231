"""Robust template particle tracker (Bachoo, Le Roux and Nicolls, SPIE 2011, sec. 3), registered
as ``template``.

* State (sec. 3.2): ``(cx, cy, w, h, vx, vy, r)``: position, scale (the patch's box size),
  velocity and rotation about the centre; dynamics eq. (1)-(4) by
  :class:`~torchtrack.filter.BachooMotion` (position noise adapted from a 25-frame velocity
  history with a minimum; inflated while occluded).
* Observation (sec. 3.2, eq. 5-6): each particle's patch, warped to a 31 x 31 template with one
  batched ``grid_sample``, is compared to the template by the robust ``gamma`` (d = 0.05,
  T = 1.0, intensities in [0, 1]); see :mod:`torchtrack.observe.template`. Particle weights are
  ``gamma ** sharpness`` (the paper only says the likelihood "is determined by gamma";
  ``sharpness = 1`` is weight = gamma). The estimate is the best particle (the paper: "the
  particle that most likely matches the template"). 400 particles, SIR.
* Occlusion (sec. 3.2): when the best ``gamma < 0.8`` the target is reported not visible; the
  estimate coasts on the mean velocity of the history (position += mean velocity; size and
  rotation kept), the particle cloud is moved with it, weights reset to uniform, and the motion
  noise is set to ``occluded_sigma`` (for ``occluded_fraction`` = half of the particles; the rest keep the
  tracking noise) until the target is found again. The velocity history is
  not fed during the occlusion.
* Template update with drift correction (sec. 3.3, Matthews et al. strategy 3): on a visible
  frame the estimate's warp is refined by inverse-compositional Lucas-Kanade (affine) so that
  the frame matches the FIRST template; when the refined patch reaches ``gamma > 0.95``
  against the first template (``update_against = "first"``, default) or the current one
  (``"current"``), it becomes the new template and the refined pose the estimate.

Grayscale: colour frames are converted to luma (BT.601). Bad input: an initial box larger than
the frame raises :class:`~torchtrack.errors.BoxError`; a box partly outside the frame is clipped
to it before the first template is taken; particles whose patch leaves the frame are scored on
their pixels inside it (0 when less than half is inside), and the estimate may leave the frame
(the track is then not visible).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any

import torch

from torchtrack.boxes import clip_boxes
from torchtrack.errors import BoxError, ConfigError
from torchtrack.filter._random import randn
from torchtrack.filter.motion import BachooMotion, VelocityHistory
from torchtrack.filter.sir import sir_step
from torchtrack.observe.template import (
    TemplateModel,
    align_ic,
    matrix_to_pose,
    pose_matrices,
    to_luma,
)
from torchtrack.track.base import Tracker, TrackState, register_tracker
from torchtrack.track.config import resolve_tracker_config

__all__ = ["TemplateTracker", "TemplateTrackerConfig"]


@dataclass
class TemplateTrackerConfig:
    """Every parameter of the template tracker (paper values where the paper gives one).

    Attributes:
        n_particles: particles (paper: 400).
        template_size: template side S (paper: 31).
        d, t: eq. (5) normalising factor and threshold (paper: 0.05, 1.0).
        detect_threshold: the target is visible while the best gamma is at least this
            (paper: 0.8); below it the track coasts (occlusion).
        update_threshold: the template is replaced when the drift-corrected candidate reaches
            gamma above this (paper: 0.95).
        update_against: ``first`` (gamma of the aligned candidate against the first template)
            or ``current`` (against the current template).
        lk_iterations: inverse-compositional Lucas-Kanade steps per update (0: no update).
        sharpness: particle weight = gamma ** sharpness (not in the paper).
        min_sigma, gain, occluded_sigma, history: position noise of eq. (1) (see
            :class:`~torchtrack.filter.BachooMotion`); history = 25 frames (paper).
        sigma_scale: eq. (2), relative std of the size per frame (paper: 0.01).
        sigma_rot: eq. (4), std of the rotation per frame, radians (paper: 0.02).
        occluded_fraction: while occluded, this fraction of the particles is scattered with
            ``occluded_sigma``; the rest keep the tracking noise around the coasted prediction
            (the paper inflates the noise of all; with its d = 0.05 the match basin is a pixel or
            two wide, and a fully scattered cloud rarely lands in it again).
        min_inside: smallest fraction of a patch inside the frame for it to be scored.
        resample: resampling scheme.
    """

    n_particles: int = 400
    template_size: int = 31
    d: float = 0.05
    t: float = 1.0
    detect_threshold: float = 0.8
    update_threshold: float = 0.95
    update_against: str = "first"
    lk_iterations: int = 10
    sharpness: float = 10.0
    min_sigma: float = 2.0
    gain: float = 1.0
    occluded_sigma: float = 20.0
    history: int = 25
    sigma_scale: float = 0.01
    sigma_rot: float = 0.02
    occluded_fraction: float = 0.5
    min_inside: float = 0.5
    resample: str = "systematic"

    def validate(self) -> None:
        from torchtrack.filter.resample import RESAMPLERS

        for k in ("n_particles", "history"):
            if getattr(self, k) < 1:
                raise ConfigError(f"{k} must be >= 1, got {getattr(self, k)}")
        if self.template_size < 3:
            raise ConfigError(f"template_size must be >= 3, got {self.template_size}")
        if self.lk_iterations < 0:
            raise ConfigError(f"lk_iterations must be >= 0, got {self.lk_iterations}")
        for k in ("detect_threshold", "update_threshold"):
            if not 0.0 <= getattr(self, k) <= 1.0:
                raise ConfigError(f"{k} must be in [0, 1], got {getattr(self, k)}")
        if not 0.0 <= self.occluded_fraction <= 1.0:
            raise ConfigError(f"occluded_fraction must be in [0, 1], got {self.occluded_fraction}")
        if not 0.0 < self.min_inside <= 1.0:
            raise ConfigError(f"min_inside must be in (0, 1], got {self.min_inside}")
        for k in ("d", "t", "sharpness", "min_sigma", "gain", "occluded_sigma"):
            if not getattr(self, k) > 0:
                raise ConfigError(f"{k} must be > 0, got {getattr(self, k)}")
        for k in ("sigma_scale", "sigma_rot"):
            if not getattr(self, k) > 0:
                raise ConfigError(f"{k} must be > 0, got {getattr(self, k)}")
        if self.update_against not in ("first", "current"):
            raise ConfigError(
                f"update_against must be 'first' or 'current', got {self.update_against!r}"
            )
        if self.resample not in RESAMPLERS:
            raise ConfigError(
                f"unknown resampling scheme {self.resample!r}; valid: {', '.join(sorted(RESAMPLERS))}"
            )


_POSE = [0, 1, 2, 3, 6]  # cx, cy, w, h, r inside the 7-D state


@register_tracker(
    "template",
    description="Bachoo et al. 2011: robust 31x31 template particle filter with occlusion "
    "coasting and drift-corrected (inverse-compositional LK) template update",
)
class TemplateTracker(Tracker):
    """Bachoo et al.'s template tracker (see module doc), one target.

    Args:
        config: a :class:`TemplateTrackerConfig` or a TOML file of one.
        generator: the source of randomness.
        **overrides: any :class:`TemplateTrackerConfig` field.

    Attributes:
        model: the :class:`~torchtrack.observe.template.TemplateModel` (first and current
            template).
        history: per frame after the first, a dict with ``gamma`` (best particle),
            ``occluded``, ``updated`` (template replaced) and ``update_gamma``.

    Example::

        tracker = TemplateTracker()
        state = tracker.init(frame, (x, y, w, h))
        for frame in frames:
            state = tracker.update(frame)   # state.visible False while occluded
    """

    name = "template"
    max_targets = 1

    def __init__(
        self,
        config: TemplateTrackerConfig | str | os.PathLike | None = None,
        generator: torch.Generator | None = None,
        **overrides: Any,
    ) -> None:
        super().__init__()
        cfg = resolve_tracker_config(
            TemplateTrackerConfig, config, overrides, where="template tracker"
        )
        self.config = cfg
        self.generator = generator
        self.motion = BachooMotion(
            min_sigma=cfg.min_sigma,
            gain=cfg.gain,
            occluded_sigma=cfg.occluded_sigma,
            history=cfg.history,
            sigma_scale=cfg.sigma_scale,
            sigma_rot=cfg.sigma_rot,
        )
        self.model = TemplateModel(cfg.template_size, cfg.d, cfg.t, cfg.min_inside)
        self.history: list[dict[str, Any]] = []
        self._states: torch.Tensor | None = None
        self._log_w: torch.Tensor | None = None
        self._hist: VelocityHistory | None = None
        self._est: torch.Tensor | None = None  # (7,) current estimate

    # -- helpers -------------------------------------------------------------------------------
    def _log_likelihood(self, luma: torch.Tensor, states: torch.Tensor, out: dict) -> torch.Tensor:
        b, n, _ = states.shape
        g = self.model.gammas(luma, states[..., _POSE].reshape(b * n, 5)).reshape(b, n)
        out["gamma"] = g
        return (self.config.sharpness * torch.log(g.to(torch.float64).clamp_min(1e-6))).to(
            states.dtype
        )

    def _state(self, visible: bool, confidence: float) -> TrackState:
        box = self.motion.to_boxes(self._est[None])
        return TrackState(
            box=box.to(torch.float64),
            confidence=torch.tensor([confidence], dtype=torch.float64),
            visible=torch.tensor([visible]),
            particles=self._states,
            log_weights=self._log_w,
        )

    def _predict(self, states: torch.Tensor, generator, hist: VelocityHistory) -> torch.Tensor:
        """Eq. (1)-(4); while occluded, the first ``occluded_fraction`` of the particles get the
        inflated noise, the others the tracking noise (they stay on the coasted prediction)."""
        pred = self.motion.predict(states, generator, history=hist)
        if not bool(hist.occluded[0]) or self.config.occluded_fraction >= 1.0:
            return pred
        calm = VelocityHistory(hist.velocities, hist.count, torch.zeros_like(hist.occluded))
        near = self.motion.predict(states, generator, history=calm)
        k = round(self.config.occluded_fraction * states.shape[1])
        return torch.cat([pred[:, :k], near[:, k:]], 1)

    def _mean_velocity(self) -> torch.Tensor:
        h = self._hist
        k = int(h.count[0])
        if k == 0:
            return torch.zeros(2, dtype=torch.float64)
        return h.velocities[0, -k:].mean(0)

    # -- Tracker API ---------------------------------------------------------------------------
    def _init(self, frame: torch.Tensor, boxes: torch.Tensor | None) -> TrackState:
        cfg = self.config
        hh, ww = self.frame_size
        box = boxes.to(torch.float64)
        if float(box[0, 2]) > ww or float(box[0, 3]) > hh:
            raise BoxError(
                f"template region {box[0].tolist()} (x, y, w, h) is larger than the "
                f"{ww} x {hh} frame; the template tracker needs a target inside the frame"
            )
        box = clip_boxes(box, (hh, ww))
        luma = to_luma(frame)
        self._est = self.motion.from_boxes(box)[0]
        self.model.init(luma, self._est[_POSE])
        self._states = self.motion.init(box, cfg.n_particles, self.generator)
        self._log_w = torch.full(
            (1, cfg.n_particles), -math.log(cfg.n_particles), dtype=torch.float64
        )
        self._hist = self.motion.new_history(box)
        self.history = []
        return self._state(True, 1.0)

    def _update(self, frame: torch.Tensor) -> TrackState:
        cfg = self.config
        luma = to_luma(frame)
        hold: dict[str, torch.Tensor] = {}
        hist = self._hist
        res = sir_step(
            self._states,
            self._log_w,
            lambda s, g: self._predict(s, g, hist),
            lambda s: self._log_likelihood(luma, s, hold),
            scheme=cfg.resample,
            estimator="best",
            generator=self.generator,
        )
        g_best = float(hold["gamma"].max())
        prev = self._est
        info: dict[str, Any] = {"gamma": g_best, "updated": False, "update_gamma": float("nan")}
        if g_best < cfg.detect_threshold:
            # Occlusion: coast on the velocity history, scatter the particles around it.
            v = self._mean_velocity()
            est = prev.clone()
            est[0:2] = prev[0:2] + v
            est[4:6] = v
            # The cloud restarts on the coasted pose (spread by min_sigma); the next prediction
            # scatters it with the inflated noise. Size and rotation do not diffuse meanwhile.
            n = cfg.n_particles
            states = est[None, None].repeat(1, n, 1).to(res.states.dtype)
            e = randn((1, n, 2), self.generator, states.dtype, states.device)
            states[..., 0:2] += e * cfg.min_sigma
            self._states = states
            self._log_w = torch.full_like(res.log_weights, -math.log(cfg.n_particles))
            self._hist = VelocityHistory(
                hist.velocities, hist.count, torch.ones(1, dtype=torch.bool)
            )
            self._est = est
            info["occluded"] = True
            self.history.append(info)
            return self._state(False, g_best)
        est = res.estimate[0].to(torch.float64).clone()
        if cfg.lk_iterations > 0:
            m0 = pose_matrices(est[_POSE], cfg.template_size)
            m = align_ic(luma, self.model.first, m0, iterations=cfg.lk_iterations)
            ref = self.model.first if cfg.update_against == "first" else self.model.current
            g_upd, patch = self.model.gamma_of_matrix(luma, m, ref)
            info["update_gamma"] = g_upd
            if g_upd > cfg.update_threshold:
                self.model.current = patch.clone()
                pose = matrix_to_pose(m, cfg.template_size)
                if bool(torch.isfinite(pose).all()) and float(pose[2]) >= 1 and float(pose[3]) >= 1:
                    est[_POSE] = pose
                info["updated"] = True
        est[4:6] = est[0:2] - prev[0:2]
        self._est = est
        self._states, self._log_w = res.states, res.log_weights
        self._hist = self.motion.update_history(
            hist, est[None, 4:6], torch.zeros(1, dtype=torch.bool)
        )
        info["occluded"] = False
        self.history.append(info)
        return self._state(True, g_best)
