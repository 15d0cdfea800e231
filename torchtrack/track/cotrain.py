"""Co-training tracker (Jin et al.): online co-trained pixel classifier + SEIR particle filter.

Per frame:

1. the candidate region is ``search_scale`` times the target box around the previous
   estimate (the prediction of the random-walk dynamics ``X_k = X_{k-1} + delta_k``, eq. 4),
   clipped to the frame;
2. the co-trained classifiers score its pixels and fuse their maps
   (:class:`~torchtrack.learn.cotrain.CoTrainer`);
3. a particle filter over the box centre ``(cx, cy)`` weighs particles with eq. (13)
   (:class:`~torchtrack.observe.cotrain.CoTrainLikelihood`): SEIR (Algorithm 3, the default,
   300 particles) or plain SIR (``resampler="sir"``);
4. the most confident blob is searched; none means the target is reported not visible and the
   classifiers are not updated; otherwise they are retrained (Algorithm 2 steps 4-5).

The box size stays that of the first frame (Jin's state is the location). Parameters are the
fields of :class:`CoTrainConfig`; ``configs/trackers/cotrain.toml`` lists them with their
defaults, and ``torchtrack track --tracker cotrain:resampler=sir,particles=500`` overrides them.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import torch

from torchtrack.errors import ConfigError, TrackerError
from torchtrack.filter._random import randn
from torchtrack.filter.particles import uniform_log_weights
from torchtrack.filter.seir import seir_step
from torchtrack.filter.sir import StepResult, sir_step
from torchtrack.learn.cotrain import CoTrainer, region_around
from torchtrack.observe.cotrain import CoTrainLikelihood
from torchtrack.track.base import Tracker, TrackState, check_tracker_generator, register_tracker
from torchtrack.track.config import MAX_TRACKER_PARTICLES, check_at_most, check_float_limits

__all__ = ["CoTrainConfig", "CoTrainTracker", "load_cotrain_config"]

RESAMPLERS = ("seir", "sir")
POSITIVES = ("ellipse", "ellipse_box")


@dataclass
class CoTrainConfig:
    """Every parameter of the co-training tracker, with its default.

    Attributes:
        particles: N (Jin et al. sec. 5.3: 300).
        resampler: ``"seir"`` (Algorithm 3) or ``"sir"``.
        mode: ``"cotrain"`` or ``"self"`` (self-trained pixel classifier, the baseline).
        motion_std: random-walk std of the centre per frame, as a fraction of sqrt(w h).
        mutation_std: SEIR's lambda (eq. 10), as a fraction of sqrt(w h).
        ess_target: SEIR evolves while ESS < ess_target N. max_iter: at most this many loops.
        gate_scale: gate sigma of eq. (13) as a fraction of the box (w, h).
        sharpness: exponent beta on the accumulated confidence, ``p = l^beta g`` (1 = eq. 13
            literally). Default 5: with beta = 1 the likelihood is so flat (a window half on
            the target scores half) that the weighted mean lags a target moving 3 px/frame
            until it is lost (synthetic test), and on David / Jogging1 / BoBoT / Crossing
            (first 50 frames) beta = 5 gave mean IoU 0.56 / 0.76 / 0.84 / 0.64 where beta = 1
            lost David and Jogging1 (0.33 / 0.47).
        search_scale: candidate region = this times the box, around the prediction.
        n_selectors, n_candidates, eps: online real AdaBoost (Algorithm 1) per classifier.
        colour_bins, ltp_threshold, texture_blocks: pixel feature coding (sec. 2;
            ``texture_blocks`` partitions the LTP codes into the weak classifiers' blocks).
        opening_size, border, accept_ratio, max_samples, init_passes: co-training
            (:class:`~torchtrack.learn.cotrain.CoTrainer`).
        replay, pool_size: positives replayed from the labelled pool into every update
            (:class:`~torchtrack.learn.cotrain.CoTrainer`). Default 500: Algorithm 2 retrains
            on the (growing) labelled dataset; ``replay = 0`` trains on the current frame's
            pixels only, which on the dev set collapsed the classifiers to all-background
            after a few frames without accepted positives (AUC 0.309 vs 0.468 with 500, first
            150 frames; 1000 gave 0.411, 250 0.454).
        positives: ``"ellipse"`` (the blob's ellipse, sec. 3.3) or ``"ellipse_box"`` (further
            restricted to the tracker's estimated box).
        estimator: particle-filter estimate, ``"mean"``, ``"best"`` or ``"mode"``.
        velocity: rate of the running mean of the estimate's displacement per frame that is
            added to the prediction (a constant-velocity term; 0: eq. 4's pure random walk).
        lost_growth, max_search_scale: per frame without a blob, the candidate region and the
            motion noise grow by ``lost_growth`` (the search widens while the target is lost),
            the region up to ``max_search_scale`` times the box (0: fixed, the paper).
        scale_step: on frames with a blob the box is rescaled by ``1 +- scale_step`` when that
            raises the contrast of the pixel map, mean positive confidence inside the box minus
            inside the ring up to ``scale_ring`` times the box (0: the first box's size
            throughout, Jin's location-only state).
        scale_ring: outer side of that ring over the box's.
    """

    particles: int = 300
    resampler: str = "seir"
    mode: str = "cotrain"
    motion_std: float = 0.15
    mutation_std: float = 0.05
    ess_target: float = 0.5
    max_iter: int = 5
    gate_scale: float = 1.0
    sharpness: float = 5.0
    search_scale: float = 2.0
    n_selectors: int = 10
    n_candidates: int = 4
    eps: float = 1e-3
    colour_bins: int = 32
    ltp_threshold: float = 5.0
    opening_size: int = 1
    border: int = 3
    accept_ratio: float = 0.5
    max_samples: int = 1000
    init_passes: int = 3
    texture_blocks: str = "full"
    replay: int = 500
    pool_size: int = 4000
    positives: str = "ellipse"
    estimator: str = "mean"
    velocity: float = 0.0
    lost_growth: float = 0.0
    max_search_scale: float = 4.0
    scale_step: float = 0.0
    scale_ring: float = 1.5

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            want = {"int": int, "float": (int, float), "str": str}[f.type]
            if isinstance(v, bool) or not isinstance(v, want):
                raise ConfigError(f"cotrain: {f.name} must be {f.type}, got {v!r}")
        if self.resampler not in RESAMPLERS:
            raise ConfigError(
                f"cotrain: unknown resampler {self.resampler!r}; valid: {', '.join(RESAMPLERS)}"
            )
        if self.particles < 1:
            raise ConfigError(f"cotrain: particles must be >= 1, got {self.particles}")
        # sizes of tensors and loops: 10^9 asked for gigabytes (a traceback from the CLI) or
        # ran for ever (init_passes)
        check_at_most(self, MAX_TRACKER_PARTICLES, "particles", prefix="cotrain: ")
        check_at_most(self, 100, "n_selectors", "n_candidates", "init_passes", prefix="cotrain: ")
        check_at_most(self, 255, "opening_size", prefix="cotrain: ")
        check_at_most(self, 1000, "max_iter", least=0, prefix="cotrain: ")
        for name in ("motion_std", "mutation_std", "gate_scale", "search_scale"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"cotrain: {name} must be > 0, got {getattr(self, name)}")
        if self.positives not in POSITIVES:
            raise ConfigError(
                f"cotrain: unknown positives {self.positives!r}; valid: {', '.join(POSITIVES)}"
            )
        if not 1 <= self.search_scale <= 100:
            raise ConfigError(
                f"cotrain: search_scale (x the box) must be in [1, 100], got {self.search_scale}"
            )
        if not self.max_search_scale <= 100:
            raise ConfigError(
                f"cotrain: max_search_scale (x the box) must be at most 100, got "
                f"{self.max_search_scale}"
            )
        if not 0 <= self.velocity <= 1:
            raise ConfigError(f"cotrain: velocity must be in [0, 1], got {self.velocity}")
        for name in ("lost_growth", "scale_step"):
            if not 0 <= getattr(self, name) < 1:
                raise ConfigError(f"cotrain: {name} must be in [0, 1), got {getattr(self, name)}")
        if self.max_search_scale < self.search_scale:
            raise ConfigError(
                f"cotrain: max_search_scale ({self.max_search_scale}) must be >= search_scale "
                f"({self.search_scale})"
            )
        if not self.scale_ring > 1:
            raise ConfigError(f"cotrain: scale_ring must be > 1, got {self.scale_ring}")
        try:  # 1e308 overflowed: a motion_std of it raised ValueError from inside the filter
            check_float_limits(self)
        except ConfigError as e:
            raise ConfigError(f"cotrain: {e}") from None


def load_cotrain_config(path: str | Path, **overrides: Any) -> CoTrainConfig:
    """Read a TOML file of :class:`CoTrainConfig` fields (a ``[cotrain]`` table or top level),
    then apply ``overrides``.

    Raises:
        ConfigError: unreadable file, bad TOML, unknown keys (named) or bad values.
    """
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except OSError as e:
        raise ConfigError(f"cannot read tracker config {path}: {e}") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"bad TOML in {path}: {e}") from None
    except UnicodeDecodeError as e:  # a binary file: the decoder's own traceback
        raise ConfigError(
            f"bad TOML in {path}: not UTF-8 text ({e.reason} at byte {e.start})"
        ) from None
    except RecursionError:  # '[[[[...' nested 10^5 deep
        raise ConfigError(
            f"bad TOML in {path}: it nests arrays or tables too deeply to read"
        ) from None
    if "cotrain" in data:
        table, rest = data.pop("cotrain"), sorted(data)
        if not isinstance(table, dict):  # 'cotrain = 5': a TypeError from {**5}
            raise ConfigError(
                f"{path}: 'cotrain' must be the [cotrain] table of parameters, got {table!r}"
            )
        if rest:  # they were dropped without a word, the defaults taken instead
            raise ConfigError(
                f"{path}: key(s) {', '.join(map(repr, rest))} outside the [cotrain] table would "
                "not be read: put them inside it"
            )
        data = table
    return _make_config({**data, **overrides}, str(path))


def _make_config(values: dict[str, Any], where: str) -> CoTrainConfig:
    known = {f.name for f in fields(CoTrainConfig)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ConfigError(
            f"{where}: unknown cotrain parameter(s) {', '.join(unknown)}; valid: "
            f"{', '.join(sorted(known))}"
        )
    v = values.get("motion_std")
    if isinstance(v, int) and not isinstance(v, bool):  # true was taken as 1.0, unchecked
        values["motion_std"] = float(v)
    return CoTrainConfig(**values)


class CoTrainTracker(Tracker):
    """Jin et al.'s tracker behind the common :class:`Tracker` interface (one target).

    Args:
        config: a TOML file path (see :func:`load_cotrain_config`) or None for the defaults.
        generator: random source (particles, feature draws, sample subsets).
        **params: :class:`CoTrainConfig` fields overriding the config.

    Attributes:
        history: per frame after the first, a dict with ``ess`` (final ESS), ``iterations``
            (SEIR loops), ``visible``, ``accepted`` (positives added) and ``blob_score``.
        last_maps: the :class:`~torchtrack.learn.cotrain.PixelMaps` of the last frame (or None).

    Raises:
        ConfigError: unknown or invalid parameters.
    """

    name = "cotrain"
    max_targets = 1

    def __init__(
        self,
        config: str | None = None,
        generator: torch.Generator | None = None,
        **params: Any,
    ) -> None:
        super().__init__()
        if config is not None:
            self.config = load_cotrain_config(config, **params)
        else:
            self.config = _make_config(dict(params), "cotrain")
        self.generator = check_tracker_generator(generator)
        c = self.config
        self.trainer = CoTrainer(
            mode=c.mode,
            n_selectors=c.n_selectors,
            n_candidates=c.n_candidates,
            eps=c.eps,
            colour_bins=c.colour_bins,
            ltp_threshold=c.ltp_threshold,
            opening_size=c.opening_size,
            border=c.border,
            accept_ratio=c.accept_ratio,
            max_samples=c.max_samples,
            init_passes=c.init_passes,
            texture_blocks=c.texture_blocks,
            replay=c.replay,
            pool_size=c.pool_size,
        )
        self.history: list[dict[str, Any]] = []
        self.last_maps = None

    def _init(self, frame: torch.Tensor, boxes: torch.Tensor | None) -> TrackState:
        box = boxes[0]
        x, y, w, h = (float(v) for v in box)
        self.size = (w, h)
        self.centre = (x + w / 2, y + h / 2)
        self.scale = math.sqrt(w * h)
        region = region_around(self.centre, self.size, self.config.search_scale, self.frame_size)
        if region is None:  # check_boxes guarantees a box inside the frame; keep it safe
            raise ConfigError(f"init box {tuple(box.tolist())} leaves no region to learn from")
        self.last_maps = self.trainer.init(frame, (x, y, w, h), region, self.generator)
        n = self.config.particles
        states = torch.tensor(self.centre, dtype=torch.float64, device=frame.device)
        states = states.view(1, 1, 2).repeat(1, n, 1)
        self.states = states
        self.log_weights = uniform_log_weights(states)
        self.history = []
        self.velocity = (0.0, 0.0)
        self.lost_frames = 0
        return TrackState.single(box, 1.0, True, particles=states, log_weights=self.log_weights)

    def _widen(self) -> float:
        """Factor on the region and the motion noise while no blob is found (1 when tracked)."""
        c = self.config
        return min(1.0 + c.lost_growth * self.lost_frames, c.max_search_scale / c.search_scale)

    def _motion(self, states: torch.Tensor, generator) -> torch.Tensor:
        # Jin et al. eq. (4): X_k = X_{k-1} + delta_k, delta_k ~ N(0, sigma^2 I); plus the
        # running velocity (0 unless ``velocity > 0``) and the lost-target widening.
        e = randn(tuple(states.shape), generator, states.dtype, states.device)
        v = states.new_tensor(self.velocity)
        return states + v + e * (self.config.motion_std * self.scale * self._widen())

    def _rescale(self, maps) -> None:
        """One step of the scale search on the pixel map (see ``scale_step``)."""
        from torchtrack.features.integral import integral_image
        from torchtrack.observe.cotrain import mean_positive_confidence

        c = self.config
        ii = integral_image(maps.opened.clamp_min(0)[None, None].to(torch.float64))[0, 0]
        f = torch.tensor(
            [1.0 / (1.0 + c.scale_step), 1.0, 1.0 + c.scale_step],
            dtype=torch.float64,
            device=ii.device,
        )
        w, h = self.size
        cx, cy = self.centre
        ws, hs = w * f, h * f
        inner = torch.stack([cx - ws / 2, cy - hs / 2, ws, hs], 1)
        ow, oh = ws * c.scale_ring, hs * c.scale_ring
        outer = torch.stack([cx - ow / 2, cy - oh / 2, ow, oh], 1)
        origin = maps.region[:2]
        m_in = mean_positive_confidence(ii, origin, inner)
        a_in, a_out = ws * hs, ow * oh
        m_out = (mean_positive_confidence(ii, origin, outer) * a_out - m_in * a_in) / (a_out - a_in)
        k = int(torch.argmax(m_in - m_out))
        hh, ww = self.frame_size
        self.size = (min(float(ws[k]), 2.0 * ww), min(float(hs[k]), 2.0 * hh))
        self.scale = math.sqrt(self.size[0] * self.size[1])

    def particle_boxes(self) -> torch.Tensor:
        """Current particles as boxes ``(1, N, 4)`` (for drawing): each particle's centre with
        the target's current size."""
        states = getattr(self, "states", None)
        if states is None:
            raise TrackerError("particle_boxes() called before init()")
        size = states.new_tensor(self.size).expand_as(states)
        return torch.cat([states - size / 2, size], -1)

    def _state(self, visible: bool, confidence: float) -> TrackState:
        cx, cy = self.centre
        w, h = self.size
        return TrackState.single(
            self.states.new_tensor([cx - w / 2, cy - h / 2, w, h]),
            confidence,
            visible,
            particles=self.states,
            log_weights=self.log_weights,
        )

    def _update(self, frame: torch.Tensor) -> TrackState:
        c = self.config
        grow = self._widen()
        pred = (self.centre[0] + self.velocity[0], self.centre[1] + self.velocity[1])
        region = region_around(pred, self.size, c.search_scale * grow, self.frame_size)
        if region is None:  # the prediction left the frame: nothing to see, nothing to learn
            self.last_maps = None
            self.history.append(
                {
                    "ess": float("nan"),
                    "iterations": 0,
                    "visible": False,
                    "accepted": False,
                    "blob_score": 0.0,
                }
            )
            self.lost_frames += 1
            return self._state(False, 0.0)
        maps = self.trainer.score(frame, region)
        self.last_maps = maps
        lik = CoTrainLikelihood(
            maps.opened,
            region[:2],
            self.size,
            pred,
            (c.gate_scale * self.size[0] * grow, c.gate_scale * self.size[1] * grow),
            c.sharpness,
        )
        if c.resampler == "seir":
            step: StepResult = seir_step(
                self.states,
                self.log_weights,
                self._motion,
                lik,
                ess_target=c.ess_target,
                max_iter=c.max_iter,
                mutation_std=c.mutation_std * self.scale,
                estimator=c.estimator,
                generator=self.generator,
            )
        else:
            step = sir_step(
                self.states,
                self.log_weights,
                self._motion,
                lik,
                estimator=c.estimator,
                generator=self.generator,
            )
        self.states, self.log_weights = step.states, step.log_weights
        est = step.estimate[0]
        hh, ww = self.frame_size
        old = self.centre
        # Keep the centre inside the frame, so the next candidate region is never empty.
        self.centre = (float(est[0].clamp(0, ww - 1)), float(est[1].clamp(0, hh - 1)))
        blob = self.trainer.locate(maps)
        visible = blob is not None and not bool(step.recovered[0])
        if visible:
            a = c.velocity
            d = (self.centre[0] - old[0], self.centre[1] - old[1])
            self.velocity = (
                (1 - a) * self.velocity[0] + a * d[0],
                (1 - a) * self.velocity[1] + a * d[1],
            )
            self.lost_frames = 0
            if c.scale_step > 0:
                self._rescale(maps)
        else:
            self.lost_frames += 1
        within = None
        if c.positives == "ellipse_box":
            w, h = self.size
            within = (self.centre[0] - w / 2, self.centre[1] - h / 2, w, h)
        accepted = (
            self.trainer.update(maps, blob, self.generator, within) if blob is not None else False
        )
        ref = self.trainer.reference_ or 1.0
        score = blob.score / ref if blob is not None else 0.0
        self.history.append(
            {
                "ess": float(step.ess[0]),
                "iterations": int(step.iterations[0]),
                "visible": visible,
                "accepted": accepted,
                "blob_score": score,
            }
        )
        return self._state(visible, score)

    def get_config(self) -> dict[str, Any]:
        """The effective parameters as a plain dict."""
        return asdict(self.config)


register_tracker(
    "cotrain",
    CoTrainTracker,
    description="Jin et al. 2011: online co-trained colour/LTP pixel classifiers + SEIR "
    "particle filter (resampler=seir|sir, mode=cotrain|self)",
)
