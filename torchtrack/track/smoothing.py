"""Fixed-lag smoothing of reported multi-target tracks: short gaps filled, boxes smoothed.

A particle filter reports each target's box from the frames seen so far. Written to a file or a
video, the output can wait a few frames and use what came after:

* **Gaps.** A target hidden for a few frames (behind another person, missed by the scans) is
  not reported there; when it comes back under the same identity within ``fill_gaps`` frames,
  the frames in between get boxes interpolated linearly between the last box before and the
  first after (centre and log-size), as ByteTrack (Zhang et al., ECCV 2022) and StrongSORT's
  GSI (Du et al., IEEE TMM 2023) post-process their tracks. Filled rows are ``detected =
  False`` and carry the interpolated confidence.
* **Jitter.** Each run of consecutive reported frames of one identity (filled gaps included)
  is smoothed on the box's centre and log-size by a local-linear fit with Gaussian weights
  of sd ``sigma`` frames within ``R = int(4 sigma + 0.5)`` frames (SciPy's radius for
  ``gaussian_filter1d``): inside a run it is that Gaussian mean; at a run's ends, where the
  Gaussian with repeated end values would pull a walking target's box back towards where it
  was, the fitted line keeps it on its way.

Both are exact in a stream: frame ``t`` is emitted once frame ``t + lag`` was pushed, ``lag =
R + fill_gaps``: whether a frame within the kernel's reach belongs to a gap that will be filled
is known by then. So the stream gives the same boxes as smoothing the whole track afterwards
(tested against an offline reference), ``lag`` frames late; :meth:`TrackSmoother.flush` emits the rest at the
end. Memory is bounded by the lag: observations older than the kernel's and the gaps' reach
are dropped.

Measured on PETS09-S2L1 and TUD-Stadtmitte (docs/multi_target.md, "Smoothing the reported
tracks").
"""

from __future__ import annotations

import bisect
import math
from collections import deque

import torch

from torchtrack.errors import ConfigError

__all__ = ["TrackSmoother", "gaussian_weights"]


def gaussian_weights(sigma: float) -> torch.Tensor:
    """``(2R + 1,)`` float64 normalised Gaussian weights of ``sigma`` frames, ``R = int(4 sigma +
    0.5)`` (SciPy's ``gaussian_filter1d`` kernel); ``[1.0]`` for ``sigma = 0``."""
    if sigma <= 0:
        return torch.ones(1, dtype=torch.float64)
    r = int(4.0 * sigma + 0.5)
    x = torch.arange(-r, r + 1, dtype=torch.float64)
    w = torch.exp(-0.5 * (x / sigma) ** 2)
    return w / w.sum()


def _local_linear(vals: dict, lo: int, hi: int, w: list[float], r: int) -> list[float]:
    """The value at offset 0 of the weighted least-squares line through ``vals[d]`` (offsets
    ``lo..hi``, weights ``w[d + r]``) for each of the four box components: the Gaussian mean
    where the run extends both ways, and no lag towards the run's middle at its ends (a target
    walking at constant speed keeps its place up to the last frame)."""
    s0 = s1 = s2 = 0.0
    t0, t1 = [0.0] * 4, [0.0] * 4
    for d in range(lo, hi + 1):
        wd, x = w[d + r], vals[d]
        s0 += wd
        s1 += wd * d
        s2 += wd * d * d
        for c in range(4):
            t0[c] += wd * x[c]
            t1[c] += wd * d * x[c]
    den = s0 * s2 - s1 * s1
    if hi == lo or den <= 1e-12 * s0 * s0:  # one frame: the value itself
        return [t / s0 for t in t0]
    return [(s2 * a - s1 * b) / den for a, b in zip(t0, t1, strict=True)]


class TrackSmoother:
    """Fill short gaps and smooth the boxes of a stream of :class:`MultiState` (module notes).

    Args:
        sigma: Gaussian sd in frames on the boxes' centre and log-size (0: no smoothing).
        fill_gaps: fill gaps of at most this many frames (0: none).

    ``push(i, state)`` for every frame index in increasing order (``state`` None for a frame
    that was not tracked, e.g. unreadable) returns the frames now final, as ``(index, state or
    None)`` in order; ``flush()`` returns the rest. A frame pushed as None comes back as None.

    Raises:
        ConfigError: ``sigma`` negative or not finite, ``fill_gaps`` negative.
    """

    def __init__(self, sigma: float = 0.0, fill_gaps: int = 0) -> None:
        if not (math.isfinite(sigma) and sigma >= 0):
            raise ConfigError(f"track smoothing sigma must be a finite number >= 0, got {sigma}")
        if isinstance(fill_gaps, bool) or int(fill_gaps) != fill_gaps or fill_gaps < 0:
            raise ConfigError(f"fill_gaps must be a whole number >= 0, got {fill_gaps!r}")
        self.sigma, self.fill_gaps = float(sigma), int(fill_gaps)
        self.weights = gaussian_weights(self.sigma)
        self.radius = (self.weights.numel() - 1) // 2
        self.lag = self.radius + self.fill_gaps
        self._pending: deque[tuple[int, bool]] = deque()  # (frame, tracked)
        # per identity: frame -> (centre x, centre y, log w, log h, confidence, detected)
        self._obs: dict[int, dict[int, tuple[float, ...]]] = {}
        self._last = -1

    @property
    def active(self) -> bool:
        """False when it would pass every state through unchanged (no gap to fill and a kernel
        of one frame): callers then skip it."""
        return self.lag > 0

    def push(self, i: int, state) -> list:
        if i <= self._last:
            raise ValueError(f"frames must be pushed in increasing order: {i} after {self._last}")
        self._last = i
        if state is not None:
            b = state.boxes.detach().to("cpu", torch.float64)
            cx, cy = b[:, 0] + b[:, 2] / 2, b[:, 1] + b[:, 3] / 2
            lw, lh = b[:, 2].clamp_min(1e-9).log(), b[:, 3].clamp_min(1e-9).log()
            rows = zip(
                state.ids.tolist(),
                cx.tolist(),
                cy.tolist(),
                lw.tolist(),
                lh.tolist(),
                state.confidence.detach().cpu().double().tolist(),
                state.detected.cpu().tolist(),
                strict=True,
            )
            for k, *v in rows:
                self._obs.setdefault(int(k), {})[i] = tuple(v)
        self._pending.append((i, state is not None))
        out = []
        while self._pending and self._pending[0][0] + self.lag <= i:
            out.append(self._emit(*self._pending.popleft()))
        self._trim()
        return out

    def flush(self) -> list:
        out = [self._emit(*p) for p in self._pending]
        self._pending.clear()
        self._obs.clear()
        return out

    # -- internals
    def _trim(self) -> None:
        """Drop observations no emission can reach any more."""
        if not self._pending:
            keep_from = self._last + 1 - self.radius - self.fill_gaps - 1
        else:
            keep_from = self._pending[0][0] - self.radius - self.fill_gaps - 1
        for k in list(self._obs):
            obs = self._obs[k]
            for f in [f for f in obs if f < keep_from]:
                del obs[f]
            if not obs:
                del self._obs[k]

    def _value(self, obs: dict, frames: list[int], u: int):
        """The box of frame ``u`` of one identity: observed, filled (a gap of at most
        ``fill_gaps`` frames between two observations), or None."""
        if u in obs:
            return obs[u]
        if self.fill_gaps == 0:
            return None
        # the last observation before u and the first after it (frames are sorted)
        j = bisect.bisect_left(frames, u)
        if j == 0 or j == len(frames):
            return None
        a, b = frames[j - 1], frames[j]
        if b - a - 1 > self.fill_gaps:
            return None
        t = (u - a) / (b - a)
        va, vb = obs[a], obs[b]
        return (*(x + (y - x) * t for x, y in zip(va[:5], vb[:5], strict=True)), False)

    def _emit(self, t: int, tracked: bool):
        from torchtrack.track.multi import MultiState

        if not tracked:
            return t, None
        ids, rows = [], []
        r, w = self.radius, self.weights.tolist()
        for k in sorted(self._obs):
            obs = self._obs[k]
            frames = sorted(obs)
            v = self._value(obs, frames, t)
            if v is None:
                continue
            if r:
                # the run of consecutive frames around t within the kernel, its ends repeated
                vals = {0: v}
                lo = 0
                while lo > -r and (x := self._value(obs, frames, t + lo - 1)) is not None:
                    lo -= 1
                    vals[lo] = x
                hi = 0
                while hi < r and (x := self._value(obs, frames, t + hi + 1)) is not None:
                    hi += 1
                    vals[hi] = x
                v = (*_local_linear(vals, lo, hi, w, r), v[4], v[5])
            ids.append(k)
            rows.append(v)
        if not rows:
            return t, MultiState(
                torch.zeros(0, dtype=torch.int64),
                torch.zeros((0, 4), dtype=torch.float64),
                torch.zeros(0, dtype=torch.float64),
                torch.zeros(0, dtype=torch.bool),
            )
        a = torch.tensor([x[:5] for x in rows], dtype=torch.float64)
        wdt, hgt = a[:, 2].exp(), a[:, 3].exp()
        boxes = torch.stack((a[:, 0] - wdt / 2, a[:, 1] - hgt / 2, wdt, hgt), 1)
        return t, MultiState(
            torch.tensor(ids, dtype=torch.int64),
            boxes,
            a[:, 4],
            torch.tensor([bool(x[5]) for x in rows], dtype=torch.bool),
        )
