"""Klein et al. (2010): adaptive centre-surround boosting in a Condensation filter,
registered as ``adaptive-haar``.

* Filter (sec. II): J = 2000 particles, state ``(cx, cy, w, h, vx, vy)``, first-order AR motion
  of eq. (1) (:class:`~torchtrack.filter.KleinAR`, sigma 6.4 / 0.64; initial velocities drawn
  from it, sec. II-B), resampling every frame, weighted-mean estimate (eq. 2).
* Observation (sec. II-D, III): likelihood ``c exp(lambda C)``, lambda = 20, with the
  confidence ``C`` of a Gentle-AdaBoost ensemble of n = 32 threshold classifiers on the 539
  centre-surround features (:mod:`torchtrack.features.centre_surround`,
  :mod:`torchtrack.learn.online_gentle`). The initial classifier is trained on the given box
  and ``neg_max`` random negatives of the first frame.

  **Departure: jittered first positives** (``init_positives`` = 8, ``init_jitter`` = 0.05;
  ``init_positives=0`` is the paper's single positive). Trained on one positive, the boosted
  stumps put their thresholds just beside that one sample's values, so the target moved by a
  pixel in the next frame already fails most of them: on OTB Crossing (a 17 x 50 px walker)
  the first classifier gave the true box of frame 1 a confidence of 0.44 while the best
  background window scored 0.52, below theta, so the classifier never adapted and the track
  was lost by frame 10 (mean IoU 0.03). With eight copies of the given box shifted and scaled
  by up to 5 % of its size the true box scores 0.74-0.84 over frames 1-12, every window
  10 px or more away scores below it, and the track holds (mean IoU 0.76, one seed). The
  copies fill positive slots 1-8 and are replaced like any positive (slot 0, the given box,
  stays).
* ``adapt`` (sec. III-B and IV):

  - ``none``: the first classifier is kept (Table I "n. ad. Hcs");
  - ``global``: one classifier per target, adapted every frame with the estimate as the new
    positive ("adapt. Hcs");
  - ``per-particle``: every particle carries a classifier; each frame the ten best particles
    get their own adapted copy of the classifier they inherited (their state is the new
    positive), which their descendants inherit through the resampling ancestors: training
    data is shared along the ancestry ("adapt. p. part. Hcs"). Classifiers no particle
    carries any more are dropped.

  No classifier adapts while its confidence on the new positive is below ``theta`` = 0.6
  (occlusions, sec. III-B and Fig. 4).

**Visibility.** ``confidence`` is the confidence of the best particle (the curve of the
paper's Fig. 4); the target is reported ``visible`` while it is at least ``visible_threshold``
(default 0.7: the jittered first positives make the classifier more tolerant, and at the
paper's theta = 0.6 eight of BoBoT's fifteen fully occluded frames 673-687 still read
visible; at 0.7, three, the first ones while the occluder enters). On fully occluded frames
it falls below and the track says not visible; the box is then the filter's estimate, which
is not adapted to (that rule stays theta = 0.6).

**Negatives.** Random boxes of the estimate's size, uniformly placed with the box inside the
frame (where it fits), and overlapping the estimate by IoU < ``neg_iou``. Strong negatives
(sec. III-B): of ``neg_candidates`` such boxes the ``ceil(neg_max / 50)`` the classifier of
t-1 scores highest.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any

import torch

from torchtrack.boxes import box_iou
from torchtrack.errors import ConfigError
from torchtrack.features.centre_surround import (
    CentreSurroundPool,
    centre_surround_features,
    channel_integrals,
)
from torchtrack.filter.motion import KleinAR
from torchtrack.filter.particles import normalize_log_weights
from torchtrack.filter.resample import resample
from torchtrack.learn.online_gentle import (
    StumpEnsemble,
    TrainingSet,
    adapt,
    fit_gentle,
    sample_weights,
)
from torchtrack.observe.adaptive_haar import AdaptiveHaarObservation
from torchtrack.track.base import Tracker, TrackState, register_tracker
from torchtrack.track.config import _in_unit, _positive_int, resolve_tracker_config

__all__ = ["ADAPT_MODES", "AdaptiveHaarConfig", "AdaptiveHaarTracker"]

ADAPT_MODES = ("none", "global", "per-particle")


@dataclass
class AdaptiveHaarConfig:
    """Every default of the Klein tracker (paper values where the paper gives one).

    Attributes:
        adapt: ``none``, ``global`` or ``per-particle``.
        n_particles: J (2000).
        sigma_xy, sigma_wh: motion noise of eq. (1) (6.4, 0.64).
        lam: lambda of eq. (3) (20).
        n_weak: weak classifiers per strong classifier, n (32; a multiple of 4).
        k_new: weak classifiers re-selected from the whole pool per adaptation, k (1).
        theta: no adaptation while the confidence on the new positive is below (0.6).
        pos_max, neg_max: training-set capacities (20, 100).
        first_weight: weight of the first positive relative to the others ("higher").
        n_best: per-particle mode: particles adapted per frame ("up to ten").
        neg_candidates: random background boxes scored per frame to find strong negatives.
        neg_iou: largest IoU of a negative with the target box.
        init_positives: extra positives of the first classifier: copies of the given box
            shifted and scaled by up to ``init_jitter`` of its size (0: the paper's single
            positive; see the module doc).
        init_jitter: largest relative shift / scale change of those copies.
        visible_threshold: visible while the best particle's confidence is at least this.
        grids, sizes, surround: the feature pool (:class:`CentreSurroundPool`; 539 features).
        resample: resampling scheme (``torchtrack.filter.RESAMPLERS``).
    """

    adapt: str = "global"
    n_particles: int = 2000
    sigma_xy: float = 6.4
    sigma_wh: float = 0.64
    lam: float = 20.0
    n_weak: int = 32
    k_new: int = 1
    theta: float = 0.6
    pos_max: int = 20
    neg_max: int = 100
    first_weight: float = 5.0
    n_best: int = 10
    neg_candidates: int = 200
    neg_iou: float = 0.3
    visible_threshold: float = 0.7
    init_positives: int = 8
    init_jitter: float = 0.05
    grids: list[int] | None = None
    sizes: list[float] | None = None
    surround: float = 2.0
    resample: str = "systematic"

    def validate(self) -> None:
        if self.adapt not in ADAPT_MODES:
            raise ConfigError(f"adapt must be one of {', '.join(ADAPT_MODES)}, got {self.adapt!r}")
        _positive_int(
            self, "n_particles", "n_weak", "pos_max", "neg_max", "n_best", "neg_candidates"
        )
        if not 0 <= self.init_positives < self.pos_max:
            raise ConfigError(
                f"init_positives must be in [0, pos_max) = [0, {self.pos_max}), "
                f"got {self.init_positives}"
            )
        if not 0 <= self.init_jitter < 0.5:
            raise ConfigError(f"init_jitter must be in [0, 0.5), got {self.init_jitter}")
        if self.n_weak % 4:
            raise ConfigError(
                f"n_weak must be a multiple of 4 (quarter constraint), got {self.n_weak}"
            )
        if not 0 <= self.k_new <= self.n_weak:
            raise ConfigError(f"k_new must be in [0, n_weak], got {self.k_new}")
        _in_unit(self, "theta", "visible_threshold", "neg_iou")
        for k in ("lam", "first_weight"):
            if not getattr(self, k) > 0:
                raise ConfigError(f"{k} must be > 0, got {getattr(self, k)}")
        for k in ("sigma_xy", "sigma_wh"):
            if not getattr(self, k) >= 0:
                raise ConfigError(f"{k} must be >= 0, got {getattr(self, k)}")
        from torchtrack.filter.resample import RESAMPLERS

        if self.resample not in RESAMPLERS:
            raise ConfigError(
                f"unknown resampling scheme {self.resample!r}; valid: {', '.join(sorted(RESAMPLERS))}"
            )
        self.pool()  # checks grids / sizes / surround

    def pool(self) -> CentreSurroundPool:
        kw: dict[str, Any] = {"surround": self.surround}
        if self.grids is not None:
            kw["grids"] = tuple(self.grids)
        if self.sizes is not None:
            kw["sizes"] = tuple(self.sizes)
        return CentreSurroundPool(**kw)


def _random_negatives(
    boxes: torch.Tensor,
    n: int,
    frame_size: tuple[int, int],
    max_iou: float,
    generator: torch.Generator | None,
) -> torch.Tensor:
    """``n`` random boxes per target, the size of ``boxes (B, 4)``, inside the frame where they
    fit, with IoU < ``max_iou`` to the target where possible: ``(B, n, 4)``."""
    b = boxes.shape[0]
    h, w = frame_size
    tries = 4 * n
    bw = boxes[:, 2:3].expand(b, tries)
    bh = boxes[:, 3:4].expand(b, tries)
    u = torch.rand((2, b, tries), generator=generator, dtype=boxes.dtype)
    x = u[0] * (w - bw).clamp_min(0)
    y = u[1] * (h - bh).clamp_min(0)
    cand = torch.stack([x, y, bw, bh], -1)  # (B, tries, 4)
    ok = box_iou(cand, boxes[:, None, :]) < max_iou
    # the first n acceptable candidates (then the least overlapping of the others)
    key = (~ok).to(torch.int8)
    order = torch.argsort(key, dim=1, stable=True)[:, :n]
    return cand.gather(1, order.unsqueeze(2).expand(b, n, 4))


@register_tracker(
    "adaptive-haar",
    description="Klein et al. 2010: adaptive centre-surround Gentle AdaBoost particle filter "
    "(adapt=none|global|per-particle)",
)
class AdaptiveHaarTracker(Tracker):
    """Klein et al.'s tracker (see the module doc), batched over B targets.

    Args:
        adapt: ``none``, ``global`` (default) or ``per-particle``.
        config: an :class:`AdaptiveHaarConfig` or a TOML file of one
            (``configs/trackers/adaptive_haar.toml``).
        generator: the source of randomness (particles and negatives).
        **overrides: any :class:`AdaptiveHaarConfig` field, e.g. ``n_particles=500``.

    Attributes:
        ensemble: the current classifiers (a :class:`StumpEnsemble` of M models).
        training: their training sets (None in the ``none`` mode after init).
        model: ``(B, N)`` int64 classifier of each particle.
        adapted: ``(B,)`` bool, the last update adapted the target's classifier(s).
    """

    name = "adaptive-haar"
    max_targets = None

    def __init__(
        self,
        adapt: str | None = None,
        config: AdaptiveHaarConfig | str | os.PathLike | None = None,
        generator: torch.Generator | None = None,
        **overrides: Any,
    ) -> None:
        super().__init__()
        if adapt is not None:
            overrides = {**overrides, "adapt": adapt}
        cfg = resolve_tracker_config(
            AdaptiveHaarConfig, config, overrides, where="adaptive-haar tracker"
        )
        self.config = cfg
        self.generator = generator
        self.pool = cfg.pool()
        self.quarters = self.pool.quarters()
        self.motion = KleinAR(cfg.sigma_xy, cfg.sigma_wh)
        self.observation = AdaptiveHaarObservation(self.pool, cfg.lam)
        self.ensemble: StumpEnsemble | None = None
        self.training: TrainingSet | None = None
        self.model: torch.Tensor | None = None
        self.adapted: torch.Tensor | None = None
        self._states: torch.Tensor | None = None
        self._log_w: torch.Tensor | None = None
        self._frame = 0

    # ------------------------------------------------------------------------------------------
    def _pool_features(self, ints, boxes: torch.Tensor) -> torch.Tensor:
        """All pool features of ``boxes (B, R, 4)`` on one frame -> ``(B, R, F)``."""
        b, r, _ = boxes.shape
        x = centre_surround_features(ints, boxes.reshape(1, b * r, 4), self.pool)
        return x.view(b, r, -1)

    def _init(self, frame: torch.Tensor, boxes: torch.Tensor | None) -> TrackState:
        cfg = self.config
        boxes = boxes.to(torch.float64)
        b = boxes.shape[0]
        ints = channel_integrals(frame[None])
        negs = _random_negatives(boxes, cfg.neg_max, self.frame_size, cfg.neg_iou, self.generator)
        j = cfg.init_positives
        u = torch.rand((b, j, 4), generator=self.generator, dtype=boxes.dtype) * 2 - 1
        size = boxes[:, None, 2:].expand(b, j, 2)
        scale = 1 + cfg.init_jitter * u[..., 2:]
        jit = torch.cat(
            [
                boxes[:, None, :2] + cfg.init_jitter * u[..., :2] * size + (1 - scale) * size / 2,
                scale * size,
            ],
            2,
        )
        # (B, 1 + J + Q, F): the given box, its jittered copies, the negatives
        x = self._pool_features(ints, torch.cat([boxes[:, None], jit, negs], 1))
        self._frame = 0
        ts = TrainingSet.create(x[:, 0], x[:, 1 + j :], cfg.pos_max, cfg.neg_max, frame=0)
        ts.x[:, 1 : 1 + j] = x[:, 1 : 1 + j]
        ts.valid[:, 1 : 1 + j] = True
        w = sample_weights(ts, cfg.first_weight)
        self.ensemble, _ = fit_gentle(ts.x, ts.labels, w, ts.valid, cfg.n_weak, self.quarters)
        self.training = ts if cfg.adapt != "none" else None
        n = cfg.n_particles
        self.model = torch.arange(b).unsqueeze(1).expand(b, n).contiguous()
        self._states = self.motion.init(boxes, n, self.generator)
        self._log_w = torch.full((b, n), -math.log(n), dtype=torch.float64)
        self.adapted = torch.zeros(b, dtype=torch.bool)
        conf = self.ensemble.pool_confidence(x[:, :1])[:, 0].to(torch.float64)
        return TrackState(
            box=boxes.clone(),
            confidence=conf,
            visible=torch.ones(b, dtype=torch.bool),
            particles=self._states,
            log_weights=self._log_w,
        )

    def _update(self, frame: torch.Tensor) -> TrackState:
        cfg = self.config
        self._frame += 1
        ints = channel_integrals(frame[None])
        # Condensation (sec. II): resample, predict with eq. (1), weight with eq. (3).
        anc, prior_lw, _ = resample(self._log_w, cfg.resample, None, self.generator)
        states = self._states.gather(1, anc.unsqueeze(2).expand(-1, -1, self._states.shape[2]))
        model = self.model.gather(1, anc)
        # eq. (1), confined to the frame so that a lost target's particles do not run away
        states = self.motion.confine(self.motion.predict(states, self.generator), self.frame_size)
        boxes = self.motion.to_boxes(states)
        conf = self.observation.confidence(ints, boxes, self.ensemble, model)  # (B, N)
        ll = self.observation.log_likelihood(conf.to(torch.float64))
        lw, _ = normalize_log_weights(prior_lw + ll, step="adaptive-haar")
        est_state = torch.einsum("bn,bnd->bd", lw.exp(), states)  # eq. (2)
        est_box = self.motion.to_boxes(est_state)
        best = conf.max(1).values.to(torch.float64)  # Fig. 4: confidence of the best particle
        visible = best >= cfg.visible_threshold
        self._states, self._log_w, self.model = states, lw, model
        self.adapted = torch.zeros_like(visible)
        if cfg.adapt == "global":
            self._adapt_global(ints, est_box)
        elif cfg.adapt == "per-particle":
            self._adapt_per_particle(ints, boxes, conf, lw, est_box)
        return TrackState(
            box=est_box,
            confidence=best,
            visible=visible,
            particles=self._states,
            log_weights=self._log_w,
        )

    def _strong_negatives(self, ints, est_box: torch.Tensor, models: torch.Tensor, target):
        """Pool features ``(P, r, F)`` of the ``r = ceil(neg_max / 50)`` strongest of
        ``neg_candidates`` random background boxes for each model in ``models (P,)`` (the
        classifier of t-1 scores them; only the chosen boxes get all pool features).
        ``target (P,)``: the target each model belongs to (its negatives avoid that box)."""
        cfg = self.config
        r = math.ceil(cfg.neg_max / 50)
        cand = _random_negatives(
            est_box, cfg.neg_candidates, self.frame_size, cfg.neg_iou, self.generator
        )[target]  # (P, R, 4)
        p, nc = cand.shape[:2]
        conf = self.observation.confidence(
            ints, cand.reshape(1, p * nc, 4), self.ensemble, models.repeat_interleave(nc)[None]
        ).view(p, nc)
        top = conf.topk(min(r, nc), dim=1).indices
        strong = cand.gather(1, top.unsqueeze(2).expand(-1, -1, 4))
        return self._pool_features(ints, strong)

    def _adapt_global(self, ints, est_box: torch.Tensor) -> None:
        cfg = self.config
        b = est_box.shape[0]
        x_pos = self._pool_features(ints, est_box[:, None])[:, 0]  # (B, F)
        # sec. III-B: no adaptation while the confidence on the new positive is below theta
        c_pos = self.ensemble.pool_confidence(x_pos[:, None])[:, 0]
        rows = torch.nonzero(c_pos >= cfg.theta).flatten()
        if rows.numel() == 0:
            return
        x_neg = self._strong_negatives(ints, est_box, rows, rows)
        ts, ens = adapt(
            self.training.select(rows),
            self.ensemble.select(rows),
            x_pos[rows],
            x_neg,
            self._frame,
            quarters=self.quarters,
            k_new=cfg.k_new,
            first_weight=cfg.first_weight,
        )
        self._replace(rows, ts, ens)
        adapted = torch.zeros(b, dtype=torch.bool)
        adapted[rows] = True
        self.adapted = adapted

    def _replace(self, rows: torch.Tensor, ts: TrainingSet, ens: StumpEnsemble) -> None:
        for name in ("x", "valid", "age"):
            getattr(self.training, name)[rows] = getattr(ts, name)
        for t_old, t_new in zip(self.ensemble._fields(), ens._fields(), strict=True):
            t_old[rows] = t_new

    def _adapt_per_particle(
        self,
        ints,
        boxes: torch.Tensor,
        conf: torch.Tensor,
        lw: torch.Tensor,
        est_box: torch.Tensor,
    ) -> None:
        cfg = self.config
        b, n = conf.shape
        k = min(cfg.n_best, n)
        top = lw.topk(k, dim=1).indices  # (B, k): the ten best particles
        top_conf = conf.gather(1, top)
        keep = top_conf >= cfg.theta  # their own confidence on their new positive
        if not bool(keep.any()):
            return
        bi, ji = torch.nonzero(keep, as_tuple=True)  # adapted (target, rank) pairs
        parents = self.model[bi, top[bi, ji]]
        top_boxes = boxes[bi, top[bi, ji]]  # (P, 4)
        x_pos = self._pool_features(ints, top_boxes[None])[0]  # (P, F)
        x_neg = self._strong_negatives(ints, est_box, parents, bi)
        ts, ens = adapt(
            self.training.select(parents),
            self.ensemble.select(parents),
            x_pos,
            x_neg,
            self._frame,
            quarters=self.quarters,
            k_new=cfg.k_new,
            first_weight=cfg.first_weight,
        )
        m0 = self.ensemble.n_models
        self.ensemble = StumpEnsemble.cat([self.ensemble, ens])
        self.training = TrainingSet.cat([self.training, ts])
        model = self.model.clone()
        model[bi, top[bi, ji]] = m0 + torch.arange(bi.numel())
        # Drop classifiers no particle carries any more (ids renumbered densely).
        alive, inverse = torch.unique(model, return_inverse=True)
        self.ensemble = self.ensemble.select(alive)
        self.training = self.training.select(alive)
        self.model = inverse.view(b, n)
        adapted = torch.zeros(b, dtype=torch.bool)
        adapted[bi] = True
        self.adapted = adapted

    def particle_boxes(self) -> torch.Tensor:
        """Current particles as boxes ``(B, N, 4)`` (for drawing)."""
        return self.motion.to_boxes(self._states)
