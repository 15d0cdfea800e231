"""Colour-histogram particle filter (Pérez et al. 2002), registered as ``histogram``.

The baseline of Klein et al. (2010) Table I, on the same particle filter as their trackers
(sec. II): state ``(cx, cy, w, h, vx, vy)`` with the first-order AR motion of eq. (1)
(``sigma_xy = 6.4``, ``sigma_wh = 0.64``, :class:`~torchtrack.filter.KleinAR`), J = 2000
particles, SIR with resampling every frame and the weighted-mean estimate (eq. 2). The
observation model is Pérez et al.'s: the HSV histogram of each particle box against the first
frame's reference histogram, likelihood ``exp(-lambda D^2)`` with the Bhattacharyya distance
``D`` and ``lambda = 20`` (:mod:`torchtrack.observe.histogram`).

``confidence`` is the best particle's Bhattacharyya coefficient ``1 - D^2`` in [0, 1]; the
target is ``visible`` while it is at least ``visible_threshold`` (0.5). Optionally
(``update_rate > 0``) the reference adapts to the estimate's histogram on visible frames
(Pérez et al. sec. 3.2 discuss such updates; Klein et al.'s baseline keeps it fixed).
"""

from __future__ import annotations

import math
import os
from typing import Any

import torch

from torchtrack.filter.motion import KleinAR
from torchtrack.filter.sir import sir_step
from torchtrack.observe.histogram import HSVBins, bhattacharyya, box_histograms, hsv_bin_map
from torchtrack.track.base import Tracker, TrackState, check_tracker_generator, register_tracker
from torchtrack.track.config import (
    HistogramTrackerConfig,
    resolve_tracker_config,
)

__all__ = ["HistogramTracker"]


@register_tracker(
    "histogram",
    description="Pérez et al. 2002: HSV colour-histogram particle filter (Klein Table I baseline)",
)
class HistogramTracker(Tracker):
    """Colour-histogram particle filter (see module doc), batched over B targets.

    Args:
        config: a :class:`HistogramTrackerConfig` or a TOML file of one.
        generator: the source of randomness.
        **overrides: any :class:`HistogramTrackerConfig` field, e.g. ``n_particles=500``.

    Attributes:
        reference: ``(B, n_bins)`` reference histograms (after :meth:`init`).
    """

    name = "histogram"
    max_targets = None

    def __init__(
        self,
        config: HistogramTrackerConfig | str | os.PathLike | None = None,
        generator: torch.Generator | None = None,
        **overrides: Any,
    ) -> None:
        super().__init__()
        cfg = resolve_tracker_config(
            HistogramTrackerConfig, config, overrides, where="histogram tracker"
        )
        self.config = cfg
        self.generator = check_tracker_generator(generator)
        self.bins = HSVBins(cfg.n_h, cfg.n_s, cfg.n_v, cfg.s_min, cfg.v_min)
        self.motion = KleinAR(cfg.sigma_xy, cfg.sigma_wh)
        self.reference: torch.Tensor | None = None
        self._states: torch.Tensor | None = None
        self._log_w: torch.Tensor | None = None

    def _histograms(self, bin_map: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
        """``boxes (B, N, 4)`` on one frame's ``bin_map (1, H, W)`` -> ``(B, N, n_bins)``."""
        b, n = boxes.shape[:2]
        h = box_histograms(bin_map, boxes.reshape(1, b * n, 4), self.bins.n_bins, self.config.grid)
        return h.reshape(b, n, -1)

    def _init(self, frame: torch.Tensor, boxes: torch.Tensor | None) -> TrackState:
        boxes = boxes.to(torch.float64)
        bin_map = hsv_bin_map(frame[None], self.bins)
        self.reference = self._histograms(bin_map, boxes[:, None])[:, 0]  # (B, K)
        n = self.config.n_particles
        self._states = self.motion.init(boxes, n, self.generator)
        self._log_w = torch.full(
            (boxes.shape[0], n), -math.log(n), dtype=torch.float64, device=boxes.device
        )
        return TrackState(
            box=boxes.clone(),
            confidence=torch.ones(boxes.shape[0], dtype=torch.float64, device=boxes.device),
            visible=torch.ones(boxes.shape[0], dtype=torch.bool, device=boxes.device),
            particles=self._states,
            log_weights=self._log_w,
        )

    def _update(self, frame: torch.Tensor) -> TrackState:
        cfg = self.config
        bin_map = hsv_bin_map(frame[None], self.bins)
        holder: dict[str, torch.Tensor] = {}

        def log_likelihood(states: torch.Tensor) -> torch.Tensor:
            hist = self._histograms(bin_map, self.motion.to_boxes(states))
            rho = bhattacharyya(hist, self.reference[:, None, :]).to(torch.float64)
            holder["rho"] = rho
            # Pérez et al. eq. (6): p(y | x) ∝ exp(-lambda D^2), D^2 = 1 - rho
            return -cfg.lam * (1.0 - rho)

        res = sir_step(
            self._states,
            self._log_w,
            lambda s, g: self.motion.confine(self.motion.predict(s, g), self.frame_size),
            log_likelihood,
            scheme=cfg.resample,
            estimator=cfg.estimator,
            generator=self.generator,
        )
        self._states, self._log_w = res.states, res.log_weights
        best = holder["rho"].max(1).values.clamp(0.0, 1.0)
        visible = best >= cfg.visible_threshold
        box = self.motion.to_boxes(res.estimate)
        if cfg.update_rate > 0 and bool(visible.any()):
            est = self._histograms(bin_map, box[:, None])[:, 0]
            a = cfg.update_rate * visible.to(est.dtype)[:, None]
            self.reference = (1 - a) * self.reference + a * est
        return TrackState(
            box=box,
            confidence=best,
            visible=visible,
            particles=self._states,
            log_weights=self._log_w,
        )

    def particle_boxes(self) -> torch.Tensor:
        """Current particles as boxes ``(B, N, 4)`` (for drawing)."""
        return self.motion.to_boxes(self._states)
