"""Motion models (state transition priors) for batched particle filters.

Each model maps boxes to states and back and samples ``p(X_t | X_{t-1})``:

* ``init(boxes (B, 4), n, generator) -> states (B, N, D)``: particles around the first box.
* ``predict(states (B, N, D), generator) -> (B, N, D)``: one transition per particle.
* ``to_boxes(states (..., D)) -> (..., 4)``: boxes as x, y, w, h (top-left, 0-based pixels,
  the convention of ``torchtrack.boxes``).

**Confinement.** ``confine(states, frame_size)`` keeps particles from running away once the
target is lost: each box centre is clamped to the frame (``[0, W] x [0, H]``), the velocity
along an axis where it was clamped is set to zero, and the box size to at most twice the
frame's. Trackers apply it after every prediction; particles inside the frame are unchanged.

Models (all states carry the box centre, so a change of size keeps the centre):

* ``KleinAR``: Klein et al. sec. II-C eq. (1), first-order AR with velocity,
  state ``(cx, cy, w, h, vx, vy)``.
* ``ChateauAR``: Chateau et al. sec. 2.3 eq. (2)-(4), ``X_{t+1} = A X_t + B v_t``,
  ``v_t ~ N(0, Sigma)``, state ``(cx_t, cy_t, cx_{t-1}, cy_{t-1}, s_t, s_{t-1})``; its A, B,
  Sigma are fitted by least squares from annotated tracks (``torchtrack.filter.dynamics_fit``).
* ``BachooMotion``: Bachoo et al. sec. 3.2 eq. (1)-(4), position, scale, velocity and
  rotation with process noise adapted from a 25-frame velocity history, inflated during
  occlusion; state ``(cx, cy, w, h, vx, vy, r)``.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field

import numpy as np
import torch

from torchtrack.boxes import _check_frame_size, check_boxes
from torchtrack.errors import ConfigError, ShapeError, is_integer, is_number
from torchtrack.filter._random import GeneratorLike, randn

__all__ = ["BachooMotion", "ChateauAR", "KleinAR", "VelocityHistory"]


def _check_boxes(boxes: torch.Tensor) -> None:
    if not isinstance(boxes, torch.Tensor) or boxes.ndim != 2 or boxes.shape[1] != 4:
        shape = tuple(boxes.shape) if isinstance(boxes, torch.Tensor) else type(boxes).__name__
        raise ShapeError(f"boxes must be (B, 4) as x, y, w, h, got {shape}")
    if not boxes.is_floating_point():
        raise ShapeError(f"boxes must be floating point, got {boxes.dtype}")


def _check_states(states: torch.Tensor, d: int, model: str) -> None:
    if not isinstance(states, torch.Tensor) or states.ndim != 3 or states.shape[2] != d:
        shape = tuple(states.shape) if isinstance(states, torch.Tensor) else type(states).__name__
        raise ShapeError(f"{model}: states must be (B, N, {d}), got {shape}")
    if not states.is_floating_point():  # int states were torch's 'normal_kernel_cpu' error
        raise ShapeError(f"{model}: states must be floating point, got {states.dtype}")


def check_window(window, where: str) -> tuple[float, float]:
    """A reference window ``(w, h)`` as two floats, once checked to be two finite numbers > 0
    (ConfigError naming ``where``: window=5 was TypeError "object of type 'int' has no len()",
    ("a", 1) float's ValueError, bools were 1 pixel)."""
    if (
        isinstance(window, (str, bytes))
        or not hasattr(window, "__len__")
        or len(window) != 2
        or not all(is_number(v) and 0 < float(v) < math.inf for v in window)
    ):
        raise ConfigError(
            f"{where}: window must be (w, h) > 0 and finite, two numbers, got {window!r}"
        )
    return float(window[0]), float(window[1])


def _check_noise_scale(ns, b: int, model: str, per_dim: bool = False) -> None:
    """ShapeError unless ``ns`` is a ``(B,)`` tensor (or ``(B, 6)`` where ``per_dim``): a
    float was 'object has no attribute to', a wrong length torch's broadcast error. Shapes
    only, no read of the values (a per-frame call)."""
    if isinstance(ns, torch.Tensor) and (
        tuple(ns.shape) == (b,) or (per_dim and tuple(ns.shape) == (b, 6))
    ):
        return
    want = f"(B,) = ({b},)" + (f" or (B, 6) = ({b}, 6)" if per_dim else "")
    got = tuple(ns.shape) if isinstance(ns, torch.Tensor) else type(ns).__name__
    raise ShapeError(f"{model}: noise_scale must be None or a tensor {want}, got {got}")


def _shape_or_type(x) -> object:
    """A tensor's shape or, for anything else, its type's name (for error messages)."""
    return tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__


def _clamp_centre(out: torch.Tensor, frame_size: tuple[int, int]) -> torch.Tensor:
    """Clamp ``out[..., 0:2]`` (box centres) to the frame in place; ``(..., 2)`` bool: which
    coordinates were moved.

    Raises:
        ShapeError: ``frame_size`` not two finite sizes >= 0 ((True, 320) was a 1 x 320 frame).
    """
    h, w = _check_frame_size(frame_size)
    c = out[..., 0:2]
    lo = torch.zeros(2, dtype=out.dtype, device=out.device)
    hi = torch.tensor([float(w), float(h)], dtype=out.dtype, device=out.device)
    clamped = torch.minimum(torch.maximum(c, lo), hi)
    moved = clamped != c  # NaN centres compare unequal: they are reset too
    out[..., 0:2] = torch.where(torch.isfinite(clamped), clamped, hi / 2)
    return moved


def _clamp_size(out: torch.Tensor, frame_size: tuple[int, int], min_size: float) -> None:
    h, w = frame_size
    out[..., 2] = out[..., 2].clamp(min_size, 2.0 * w)
    out[..., 3] = out[..., 3].clamp(min_size, 2.0 * h)


def _positive(name: str, value: float) -> float:
    """``value`` as a float once it is a finite real number >= 0 (inf was taken: every particle
    went to inf; True was 1 and '1' 1.0)."""
    if (
        isinstance(value, bool)
        or not isinstance(value, numbers.Real)
        or not (0.0 <= float(value) < math.inf)
    ):
        raise ConfigError(f"{name} must be a finite number >= 0, got {value!r}")
    return float(value)


#: the longest velocity history (frames) of :class:`BachooMotion`: 10^12 asked for 16 TB
MAX_HISTORY = 100_000


def _check_count(n) -> int:
    """The particles per box of ``init``: an integer >= 1 (-1 was torch's RuntimeError, True
    one particle, 2.5 a TypeError inside torch)."""
    if not is_integer(n) or n < 1:
        raise ConfigError(f"n must be an integer >= 1 (particles per box), got {n!r}")
    return int(n)


class KleinAR:
    """Klein et al. eq. (1): ``v += N(0, sigma^2)``, ``x += v``; w, h random walks.

    State ``(cx, cy, w, h, vx, vy)``, D = 6 (box centre, size, centre velocity in pixels per
    frame). Defaults are the paper's ``sigma_x = sigma_y = 6.4``, ``sigma_w = sigma_h = 0.64``
    in pixels. ``min_size`` keeps w, h positive (a box of non-positive size has no features).

    ``relative=True`` makes the noise follow the target's size (a departure used by the
    trackers' robust defaults; the paper's pixels are right for its 320 x 240 sequences only):
    the velocity noise is ``sigma_xy * sqrt(w h)`` of each particle (a fraction of its size per
    frame), and the size changes multiplicatively, ``w *= exp(n_s + n_a)``,
    ``h *= exp(n_s - n_a)`` with a common scale noise ``n_s ~ N(0, sigma_wh^2)`` and an aspect
    noise ``n_a ~ N(0, (aspect * sigma_wh)^2)``, so a box grows or shrinks as a whole and keeps
    its shape unless the evidence says otherwise. ``damping`` multiplies the velocity before
    the noise is added (1: eq. 1's random walk; below 1 a lost target's particles stop drifting).
    """

    dim = 6

    def __init__(
        self,
        sigma_xy: float = 6.4,
        sigma_wh: float = 0.64,
        min_size: float = 1.0,
        *,
        relative: bool = False,
        aspect: float = 0.5,
        damping: float = 1.0,
        min_sigma: float = 0.0,
    ) -> None:
        self.sigma_xy = _positive("sigma_xy", sigma_xy)
        self.sigma_wh = _positive("sigma_wh", sigma_wh)
        self.min_size = _positive("min_size", min_size)
        if not isinstance(relative, (bool, np.bool_)):  # bool("no") was True
            raise ConfigError(f"relative must be True or False, got {relative!r}")
        self.relative = bool(relative)
        self.aspect = _positive("aspect", aspect)
        if isinstance(damping, bool) or not 0.0 <= float(damping) <= 1.0:
            raise ConfigError(f"damping must be in [0, 1], got {damping}")
        self.damping = float(damping)
        self.min_sigma = _positive("min_sigma", min_sigma)

    def from_boxes(self, boxes: torch.Tensor) -> torch.Tensor:
        """``(B, 4)`` x, y, w, h -> ``(B, 6)`` states with zero velocity.

        Raises:
            ShapeError: not ``(B, 4)`` floating point.
            BoxError: a box not finite or under one pixel wide or high.
        """
        _check_boxes(boxes)
        check_boxes(boxes)  # finite and a pixel or more: NaN or negative sizes made particles
        x, y, w, h = boxes.unbind(1)
        z = torch.zeros_like(x)
        return torch.stack([x + w / 2, y + h / 2, w, h, z, z], 1)

    def to_boxes(self, states: torch.Tensor) -> torch.Tensor:
        """``(..., 6)`` -> ``(..., 4)`` x, y, w, h."""
        cx, cy, w, h = states[..., 0], states[..., 1], states[..., 2], states[..., 3]
        return torch.stack([cx - w / 2, cy - h / 2, w, h], -1)

    def _velocity_sigma(self, states: torch.Tensor) -> torch.Tensor:
        """``(B, N, 1)`` velocity noise std of each particle (pixels per frame)."""
        if not self.relative:
            return states.new_full((*states.shape[:2], 1), self.sigma_xy)
        s = (states[..., 2:3] * states[..., 3:4]).clamp_min(0).sqrt()
        return (self.sigma_xy * s).clamp_min(self.min_sigma)

    def init(self, boxes: torch.Tensor, n: int, generator: GeneratorLike = None) -> torch.Tensor:
        """Klein et al. sec. II-B: every particle on the first box, velocities ~ N(0, sigma^2).

        Returns:
            ``(B, n, 6)``.
        """
        n = _check_count(n)
        s = self.from_boxes(boxes).unsqueeze(1).repeat(1, n, 1)
        noise = randn((boxes.shape[0], n, 2), generator, boxes.dtype, boxes.device)
        s[..., 4:6] = noise * self._velocity_sigma(s)
        return s

    def predict(
        self,
        states: torch.Tensor,
        generator: GeneratorLike = None,
        noise_scale: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """One step of eq. (1): ``(B, N, 6) -> (B, N, 6)``.

        Args:
            noise_scale: optional ``(B,)`` factor on the velocity noise of each row (a tracker
                widens the search while its evidence is low, or for a fast target); ``None``
                is eq. (1) as configured.
        """
        _check_states(states, 6, "KleinAR")
        b, n, _ = states.shape
        e = randn((b, n, 4), generator, states.dtype, states.device)
        sv = self._velocity_sigma(states)
        if noise_scale is not None:
            _check_noise_scale(noise_scale, b, "KleinAR")
            sv = sv * noise_scale.to(sv).reshape(-1, 1, 1)
        out = states.clone()  # one output buffer, updated in place (no concatenation)
        if self.damping != 1.0:
            out[..., 4:6] *= self.damping
        out[..., 4:6] += e[..., 0:2] * sv  # v_t = v_{t-1} + G(0, sigma^2)
        out[..., 0:2] += out[..., 4:6]  # x_t = x_{t-1} + v_t
        if self.relative:
            common = e[..., 2:3] * self.sigma_wh
            shape = e[..., 3:4] * (self.sigma_wh * self.aspect)
            out[..., 2:3] *= torch.exp(common + shape)
            out[..., 3:4] *= torch.exp(common - shape)
        else:
            out[..., 2:4] += e[..., 2:4] * self.sigma_wh
        out[..., 2:4].clamp_(min=self.min_size)
        return out

    __call__ = predict

    def confine(self, states: torch.Tensor, frame_size: tuple[int, int]) -> torch.Tensor:
        """States ``(B, N, 6)`` with centres clamped to the frame, the clamped axes' velocity
        zeroed and sizes at most twice the frame's (see the module doc)."""
        out = states.clone()
        moved = _clamp_centre(out, frame_size)
        out[..., 4:6] = torch.where(moved, torch.zeros_like(out[..., 4:6]), out[..., 4:6])
        _clamp_size(out, frame_size, self.min_size)
        return out


def _matrix(name: str, value) -> torch.Tensor:
    """``value`` (a tensor or nested lists, e.g. from TOML) as a float64 tensor; ragged or
    non-numeric lists were torch's ValueError / TypeError, naming no parameter."""
    if isinstance(value, torch.Tensor):
        if value.dtype == torch.bool or value.is_complex():
            raise ConfigError(f"ChateauAR: {name} must hold real numbers, got {value.dtype}")
        return value.to(torch.float64)
    try:
        return torch.tensor(value, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError) as e:
        raise ConfigError(
            f"ChateauAR: {name} must be a matrix of numbers (nested lists of equal length), "
            f"got {value!r} ({e})"
        ) from None


class ChateauAR:
    """Chateau et al. eq. (4): ``X_{t+1} = A X_t + B v_t``, ``v_t ~ N(0, Sigma)``.

    State ``X_t = (cx_t, cy_t, cx_{t-1}, cy_{t-1}, s_t, s_{t-1})`` (eq. 2), D = 6. The region is
    ``R(X) = c + s W`` (eq. 3): a box of size ``(s * window_w, s * window_h)`` centred on c,
    where ``window = (window_w, window_h)`` is the reference window (the classifier's training
    size, or the first box of the track: then ``s_0 = 1``).

    Args:
        A: ``(6, 6)`` transition matrix. Default: constant velocity on c, random walk on s.
        B: ``(6, K)`` noise input matrix. Default: noise enters c_t and s_t (K = 3).
        Sigma: ``(K, K)`` noise covariance. Default ``diag(4, 4, 1e-4)`` (pixels^2, scale^2).
        window: ``(w, h)`` of the reference window in pixels.
        min_scale: lower bound on s (keeps boxes positive).
    """

    dim = 6

    def __init__(
        self,
        A: torch.Tensor | None = None,
        B: torch.Tensor | None = None,
        Sigma: torch.Tensor | None = None,
        window: tuple[float, float] = (1.0, 1.0),
        min_scale: float = 1e-3,
    ) -> None:
        self.A = default_chateau_A() if A is None else _matrix("A", A)
        self.B = default_chateau_B() if B is None else _matrix("B", B)
        self.Sigma = (
            torch.diag(torch.tensor([4.0, 4.0, 1e-4], dtype=torch.float64))
            if Sigma is None
            else _matrix("Sigma", Sigma)
        )
        if self.A.shape != (6, 6):
            raise ConfigError(f"ChateauAR: A must be 6 x 6, got {tuple(self.A.shape)}")
        if self.B.ndim != 2 or self.B.shape[0] != 6:
            raise ConfigError(f"ChateauAR: B must be 6 x K, got {tuple(self.B.shape)}")
        k = self.B.shape[1]
        if self.Sigma.shape != (k, k):
            raise ConfigError(
                f"ChateauAR: Sigma must be {k} x {k} to match B, got {tuple(self.Sigma.shape)}"
            )
        try:
            # A tiny jitter admits positive semi-definite Sigma (e.g. a noise-free component).
            jitter = (
                1e-12
                * torch.eye(k, dtype=torch.float64, device=self.Sigma.device)
                * max(1.0, float(self.Sigma.abs().max()))
            )
            self._L = torch.linalg.cholesky(0.5 * (self.Sigma + self.Sigma.T) + jitter)
        except RuntimeError:
            raise ConfigError("ChateauAR: Sigma must be symmetric positive semi-definite") from None
        for name, m in (("A", self.A), ("B", self.B)):
            if not bool(torch.isfinite(m).all()):  # NaN / inf particles, silently
                raise ConfigError(f"ChateauAR: {name} must be finite, got {m.tolist()}")
        self.window = check_window(window, "ChateauAR")
        self.min_scale = _positive("min_scale", min_scale)

    @classmethod
    def from_params(cls, params: dict, window: tuple[float, float] | None = None) -> ChateauAR:
        """Build from a dict with keys ``A``, ``B``, ``Sigma`` (nested lists, e.g. from TOML)."""
        unknown = set(params) - {"A", "B", "Sigma", "window", "min_scale"}
        if unknown:
            raise ConfigError(f"ChateauAR: unknown parameter keys {sorted(unknown)}")
        missing = {"A", "B", "Sigma"} - set(params)
        if missing:
            raise ConfigError(f"ChateauAR: missing parameter keys {sorted(missing)}")
        win = window if window is not None else params.get("window", (1.0, 1.0))
        return cls(
            _matrix("A", params["A"]),
            _matrix("B", params["B"]),
            _matrix("Sigma", params["Sigma"]),
            window=win,
            min_scale=params.get("min_scale", 1e-3),
        )

    def from_boxes(self, boxes: torch.Tensor) -> torch.Tensor:
        """``(B, 4)`` x, y, w, h -> ``(B, 6)``, with ``c_{t-1} = c_t`` and ``s_{t-1} = s_t``;
        ``s = sqrt(w h / (window_w window_h))`` (geometric mean of the two ratios).

        Raises:
            ShapeError: not ``(B, 4)`` floating point.
            BoxError: a box not finite or under one pixel wide or high.
        """
        _check_boxes(boxes)
        check_boxes(boxes)  # finite and a pixel or more: NaN or negative sizes made particles
        x, y, w, h = boxes.unbind(1)
        cx, cy = x + w / 2, y + h / 2
        s = torch.sqrt(w * h / (self.window[0] * self.window[1]))
        return torch.stack([cx, cy, cx, cy, s, s], 1)

    def to_boxes(self, states: torch.Tensor) -> torch.Tensor:
        """Eq. (3): ``(..., 6)`` -> ``(..., 4)`` x, y, w, h of ``c_t + s_t W``."""
        s = states[..., 4]
        w, h = s * self.window[0], s * self.window[1]
        return torch.stack([states[..., 0] - w / 2, states[..., 1] - h / 2, w, h], -1)

    def init(self, boxes: torch.Tensor, n: int, generator: GeneratorLike = None) -> torch.Tensor:
        """``n`` particles on the first box, spread by one step of process noise: ``(B, n, 6)``."""
        n = _check_count(n)
        s = self.from_boxes(boxes).unsqueeze(1).repeat(1, n, 1)
        return s + self._noise(s, generator)

    def _noise(self, states: torch.Tensor, generator: GeneratorLike) -> torch.Tensor:
        b, n, _ = states.shape
        k = self.B.shape[1]
        v = randn((b, n, k), generator, states.dtype, states.device)
        m = (self.B @ self._L).to(states)  # (6, K): B v with v = L z
        return v @ m.T

    def predict(
        self,
        states: torch.Tensor,
        generator: GeneratorLike = None,
        noise_scale: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Eq. (4): ``(B, N, 6) -> (B, N, 6)``.

        Args:
            noise_scale: optional factor on the noise's standard deviation, ``(B,)`` per row
                or ``(B, 6)`` per row and state component (e.g. a multi-target tracker widens
                the search of a target that missed its detections, or scales the centre's
                noise with the target's size); ``None`` is eq. (4) as fitted.
        """
        _check_states(states, 6, "ChateauAR")
        noise = self._noise(states, generator)
        if noise_scale is not None:
            _check_noise_scale(noise_scale, states.shape[0], "ChateauAR", per_dim=True)
            ns = noise_scale.to(noise)
            if ns.ndim == 2:
                noise = noise * ns[:, None, :]
            else:
                noise = noise * ns.reshape(-1, 1, 1)
        out = states @ self.A.to(states).T + noise
        out[..., 4] = out[..., 4].clamp_min(self.min_scale)
        return out

    __call__ = predict

    def confine(self, states: torch.Tensor, frame_size: tuple[int, int]) -> torch.Tensor:
        """States ``(B, N, 6)`` with ``c_t`` clamped to the frame, ``c_{t-1} = c_t`` on the
        clamped axes (zero velocity) and the region at most twice the frame's size."""
        h, w = _check_frame_size(frame_size)
        out = states.clone()
        moved = _clamp_centre(out, frame_size)
        out[..., 2:4] = torch.where(moved, out[..., 0:2], out[..., 2:4])
        s_max = min(2.0 * w / self.window[0], 2.0 * h / self.window[1])
        out[..., 4:6] = out[..., 4:6].clamp(self.min_scale, max(s_max, self.min_scale))
        return out


def default_chateau_A() -> torch.Tensor:
    """Constant velocity on c (``c_{t+1} = 2 c_t - c_{t-1}``), random walk on s."""
    a = torch.zeros(6, 6, dtype=torch.float64)
    a[0, 0], a[0, 2], a[1, 1], a[1, 3] = 2.0, -1.0, 2.0, -1.0
    a[2, 0], a[3, 1] = 1.0, 1.0  # c_t shifts into the c_{t-1} slot
    a[4, 4] = 1.0
    a[5, 4] = 1.0  # s_t shifts into the s_{t-1} slot
    return a


def default_chateau_B() -> torch.Tensor:
    """Noise (v_x, v_y, v_s) enters c_t and s_t only; the lagged slots are exact copies."""
    b = torch.zeros(6, 3, dtype=torch.float64)
    b[0, 0], b[1, 1], b[4, 2] = 1.0, 1.0, 1.0
    return b


@dataclass
class VelocityHistory:
    """Per-target state of ``BachooMotion``: the last ``H`` estimated velocities.

    Attributes:
        velocities: ``(B, H, 2)`` ring buffer of centre velocities (pixels per frame).
        count: ``(B,)`` number of valid entries (saturates at H).
        occluded: ``(B,)`` bool, True while the observation model reports an occlusion.
    """

    velocities: torch.Tensor
    count: torch.Tensor
    occluded: torch.Tensor = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.occluded is None:
            self.occluded = torch.zeros(
                self.velocities.shape[0], dtype=torch.bool, device=self.velocities.device
            )


class BachooMotion:
    """Bachoo et al. sec. 3.2, eq. (1)-(4), with adaptive process noise.

    State ``(cx, cy, w, h, vx, vy, r)``, D = 7: centre, size (the paper's scale of the unit
    square), velocity, rotation (radians) about the centre.

    * eq. (1) ``x_t = x_{t-1} + v_{t-1} + w``, ``w ~ N(0, diag(sigma_x^2, sigma_y^2))`` where
      ``sigma_i = max(min_sigma, gain * mean |v_i|)`` over the last ``history`` estimated
      velocities (greater displacements, more noise), and ``sigma_i = occluded_sigma`` while
      the target is flagged occluded (scatters the particles to re-acquire it);
    * eq. (2) ``s_t = s_{t-1} + N(0, 0.01)``: read here as a relative change of w and h (std
      ``sigma_scale`` = 1 %), since the paper's "pixels" of a unit square would be meaningless
      for boxes tens of pixels wide;
    * eq. (3) ``v_t = x_t - x_{t-1}``;
    * eq. (4) ``r_t = r_{t-1} + N(0, sigma_rot^2)``, ``sigma_rot = 0.02``.

    ``to_boxes`` returns the axis-aligned box of the unrotated patch; observation models that
    warp patches read r from the state.
    """

    dim = 7

    def __init__(
        self,
        min_sigma: float = 1.0,
        gain: float = 1.0,
        occluded_sigma: float = 20.0,
        history: int = 25,
        sigma_scale: float = 0.01,
        sigma_rot: float = 0.02,
        min_size: float = 1.0,
    ) -> None:
        self.min_sigma = _positive("min_sigma", min_sigma)
        self.gain = _positive("gain", gain)
        self.occluded_sigma = _positive("occluded_sigma", occluded_sigma)
        if (
            isinstance(history, bool)
            or not isinstance(history, numbers.Integral)
            or not 1 <= history <= MAX_HISTORY
        ):  # 2.5 ran with 2, 10^12 asked for 16 TB at new_history
            raise ConfigError(
                f"history must be an integer in [1, {MAX_HISTORY}] (frames), got {history!r}"
            )
        self.history = int(history)
        self.sigma_scale = _positive("sigma_scale", sigma_scale)
        self.sigma_rot = _positive("sigma_rot", sigma_rot)
        self.min_size = _positive("min_size", min_size)

    def from_boxes(self, boxes: torch.Tensor) -> torch.Tensor:
        """``(B, 4)`` -> ``(B, 7)`` with zero velocity and rotation.

        Raises:
            ShapeError: not ``(B, 4)`` floating point.
            BoxError: a box not finite or under one pixel wide or high.
        """
        _check_boxes(boxes)
        check_boxes(boxes)  # finite and a pixel or more: NaN or negative sizes made particles
        x, y, w, h = boxes.unbind(1)
        z = torch.zeros_like(x)
        return torch.stack([x + w / 2, y + h / 2, w, h, z, z, z], 1)

    def to_boxes(self, states: torch.Tensor) -> torch.Tensor:
        """``(..., 7)`` -> ``(..., 4)`` x, y, w, h (rotation ignored)."""
        cx, cy, w, h = states[..., 0], states[..., 1], states[..., 2], states[..., 3]
        return torch.stack([cx - w / 2, cy - h / 2, w, h], -1)

    def new_history(self, boxes: torch.Tensor) -> VelocityHistory:
        """Empty velocity history for ``boxes (B, 4)``."""
        _check_boxes(boxes)
        b = boxes.shape[0]
        return VelocityHistory(
            boxes.new_zeros(b, self.history, 2),
            torch.zeros(b, dtype=torch.long, device=boxes.device),
        )

    def update_history(
        self,
        hist: VelocityHistory,
        velocity: torch.Tensor,
        occluded: torch.Tensor | None = None,
    ) -> VelocityHistory:
        """Push the estimated centre velocity ``(B, 2)`` of this frame; set the occlusion flags
        ``(B,)``. Returns a new history (the input is not modified).

        Raises:
            ShapeError: ``velocity`` not a ``(B, 2)`` tensor or ``occluded`` not a ``(B,)``
                tensor, for the history's B (shapes only: this runs every frame).
        """
        b = hist.velocities.shape[0]
        # a list was AttributeError 'list' object has no attribute 'shape'
        if not isinstance(velocity, torch.Tensor) or velocity.shape != (b, 2):
            got = _shape_or_type(velocity)
            raise ShapeError(f"velocity must be a tensor (B, 2) = ({b}, 2), got {got}")
        # a wrong length was taken, and failed later in predict as torch's broadcast error
        if occluded is not None and (
            not isinstance(occluded, torch.Tensor) or occluded.shape != (b,)
        ):
            got = _shape_or_type(occluded)
            raise ShapeError(f"occluded must be None or a tensor (B,) = ({b},), got {got}")
        v = torch.cat([hist.velocities[:, 1:], velocity.unsqueeze(1).to(hist.velocities)], 1)
        count = (hist.count + 1).clamp_max(self.history)
        occ = (
            hist.occluded
            if occluded is None
            else occluded.to(device=hist.velocities.device, dtype=torch.bool)
        )
        return VelocityHistory(v, count, occ)

    def noise_std(self, hist: VelocityHistory) -> torch.Tensor:
        """``(B, 2)`` position noise std from the history (eq. 1's adapted covariance)."""
        h = self.history
        valid = torch.arange(h, device=hist.velocities.device).unsqueeze(0) >= (
            h - hist.count
        ).unsqueeze(1)  # newest entries sit at the end of the buffer
        n = hist.count.clamp_min(1).unsqueeze(1).to(hist.velocities)
        mean_abs = (hist.velocities.abs() * valid.unsqueeze(2)).sum(1) / n
        sigma = (self.gain * mean_abs).clamp_min(self.min_sigma)
        occ = torch.full_like(sigma, self.occluded_sigma)
        return torch.where(hist.occluded.unsqueeze(1), occ, sigma)

    def init(self, boxes: torch.Tensor, n: int, generator: GeneratorLike = None) -> torch.Tensor:
        """``n`` particles on the first box with position noise ``min_sigma``: ``(B, n, 7)``."""
        n = _check_count(n)
        s = self.from_boxes(boxes).unsqueeze(1).repeat(1, n, 1)
        e = randn((boxes.shape[0], n, 2), generator, boxes.dtype, boxes.device)
        s[..., 0:2] += e * self.min_sigma
        return s

    def predict(
        self,
        states: torch.Tensor,
        generator: GeneratorLike = None,
        history: VelocityHistory | None = None,
    ) -> torch.Tensor:
        """Eq. (1)-(4): ``(B, N, 7) -> (B, N, 7)``. Without ``history`` the noise is ``min_sigma``."""
        _check_states(states, 7, "BachooMotion")
        b, n, _ = states.shape
        if history is None:
            sig = states.new_full((b, 2), self.min_sigma)
        else:
            if history.velocities.shape[0] != b:
                raise ShapeError(
                    f"BachooMotion: history is for B={history.velocities.shape[0]} targets, "
                    f"states for B={b}"
                )
            sig = self.noise_std(history).to(states)
        e = randn((b, n, 5), generator, states.dtype, states.device)
        c_prev = states[..., 0:2]
        c = c_prev + states[..., 4:6] + e[..., 0:2] * sig.unsqueeze(1)
        wh = (states[..., 2:4] * (1.0 + self.sigma_scale * e[..., 2:4])).clamp_min(self.min_size)
        v = c - c_prev
        r = states[..., 6:7] + self.sigma_rot * e[..., 4:5]
        return torch.cat([c, wh, v, r], dim=2)

    __call__ = predict

    def confine(self, states: torch.Tensor, frame_size: tuple[int, int]) -> torch.Tensor:
        """States ``(B, N, 7)`` with centres clamped to the frame, the clamped axes' velocity
        zeroed and sizes at most twice the frame's (see the module doc)."""
        out = states.clone()
        moved = _clamp_centre(out, frame_size)
        out[..., 4:6] = torch.where(moved, torch.zeros_like(out[..., 4:6]), out[..., 4:6])
        _clamp_size(out, frame_size, self.min_size)
        return out
