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

* **Swapped identities** (``unswap``). Two identities that came out of a close encounter on
  each other's person are swapped back (:class:`~torchtrack.track.identity.SwapRepair`), on
  the filled and smoothed tracks, ``unswap`` frames later.

* **Late starts** (``backfill``). A target is reported only once its detections reached the
  birth threshold and it was confirmed; the frames before, not written yet, often hold its
  detections. When an identity is reported on a frame but not on the one before (a new
  target, or one back after a gap), its track is extended back in time over those frames
  through the detections that chain to it (:meth:`TrackSmoother._backfill`), and they are
  then filled and smoothed with the rest.

A moving camera is taken out first: :meth:`TrackSmoother.push` takes the camera's translation
since the first frame (the multi-target tracker's ``camera_offset``), and the boxes are
interpolated and smoothed in the scene's coordinates, then put back where the frame shows them
(a pan that turns, or a hand-held camera's jolts, would otherwise be smoothed into every box).

Gaps and jitter are exact in a stream: frame ``t`` is emitted once frame ``t + lag`` was
pushed, ``lag = R + fill_gaps`` (or ``backfill`` when larger): whether a frame within the
kernel's reach belongs to a gap that will be filled is known by then. (Back-filled rows land
on unwritten frames only, so a chain that reaches a run's written end joins it without
re-smoothing the frames already written.) So the stream gives the same boxes as smoothing the whole track afterwards
(tested against an offline reference), ``lag`` frames late; :meth:`TrackSmoother.flush` emits the rest at the
end. Memory is bounded by the lag: observations older than the kernel's and the gaps' reach
are dropped.

Measured on PETS09-S2L1 and TUD-Stadtmitte (docs/multi_target.md, "Smoothing the reported
tracks").
"""

from __future__ import annotations

from collections import deque

import torch

from torchtrack.errors import BoxError, ConfigError, TrackerError, is_integer, is_number

__all__ = ["TrackSmoother", "gaussian_weights"]


def _check_sigma(sigma) -> None:
    """ConfigError unless ``sigma`` is a number in ``[0, MAX_SMOOTH_SIGMA]`` frames (a bool
    was a sd of 1, a string or None a TypeError, 1e9 sized a 64 GB kernel)."""
    from torchtrack.track.config import MAX_SMOOTH_SIGMA

    if not (is_number(sigma) and 0 <= sigma <= MAX_SMOOTH_SIGMA):  # NaN fails too
        raise ConfigError(
            f"track smoothing sigma must be a finite number in [0, {MAX_SMOOTH_SIGMA}] frames, "
            f"got {sigma!r}"
        )


def gaussian_weights(sigma: float) -> torch.Tensor:
    """``(2R + 1,)`` float64 normalised Gaussian weights of ``sigma`` frames, ``R = int(4 sigma +
    0.5)`` (SciPy's ``gaussian_filter1d`` kernel); ``[1.0]`` for ``sigma = 0``.

    Raises:
        ConfigError: ``sigma`` not a number in ``[0, MAX_SMOOTH_SIGMA]`` (250 frames).
    """
    _check_sigma(sigma)
    if sigma <= 0:
        return torch.ones(1, dtype=torch.float64)
    r = int(4.0 * sigma + 0.5)
    x = torch.arange(-r, r + 1, dtype=torch.float64)
    w = torch.exp(-0.5 * (x / sigma) ** 2)
    return w / w.sum()


class TrackSmoother:
    """Fill short gaps and smooth the boxes of a stream of :class:`MultiState` (module notes).

    Args:
        sigma: Gaussian sd in frames on the boxes' centre and log-size (0: no smoothing).
        fill_gaps: fill gaps of at most this many frames (0: none).
        backfill: extend a run of reports back over at most this many unwritten frames
            through the detections given to :meth:`push` (0: none); ``lag`` is at least this.
        backfill_iou: the overlap a detection needs with the box carried back to join.
        unswap: identities swapped at a close encounter are swapped back in the filled and
            smoothed tracks (:class:`~torchtrack.track.identity.SwapRepair` with this window,
            frames), which adds as many frames to ``lag``; 0: none.

    ``push(i, state)`` for every frame index in increasing order (``state`` None for a frame
    that was not tracked, e.g. unreadable) returns the frames now final, as ``(index, state or
    None)`` in order; ``flush()`` returns the rest. A frame pushed as None comes back as None.
    Each emitted frame is one batch of tensor operations over every identity in reach (no loop
    over targets): the observations of the frames around it laid out as a dense ``(identities,
    frames)`` table.

    Raises:
        ConfigError: ``sigma`` not a number in ``[0, 250]`` frames, ``fill_gaps`` or
            ``backfill`` not a whole number in ``[0, 1000]``, ``backfill_iou`` not a number in
            ``(0, 1]`` (bools refused), as :class:`MultiTrackerConfig` bounds them.
    """

    def __init__(
        self,
        sigma: float = 0.0,
        fill_gaps: int = 0,
        backfill: int = 0,
        backfill_iou: float = 0.5,
        unswap: int = 0,
    ) -> None:
        from torchtrack.track.config import MAX_FILL_GAPS

        _check_sigma(sigma)
        for name, v in (("fill_gaps", fill_gaps), ("backfill", backfill)):
            # None was int()'s TypeError, inf its OverflowError, NaN its ValueError
            if not (is_number(v) and 0 <= v <= MAX_FILL_GAPS and int(v) == v):
                raise ConfigError(
                    f"{name} must be a whole number in [0, {MAX_FILL_GAPS}], got {v!r}"
                )
        if not (is_number(backfill_iou) and 0.0 < backfill_iou <= 1.0):  # True was 1.0
            raise ConfigError(f"backfill_iou must be a number in (0, 1], got {backfill_iou!r}")
        self.sigma, self.fill_gaps = float(sigma), int(fill_gaps)
        self.backfill, self.backfill_iou = int(backfill), float(backfill_iou)
        self.weights = gaussian_weights(self.sigma)
        self.radius = (self.weights.numel() - 1) // 2
        from torchtrack.track.identity import SwapRepair

        # identities swapped at close encounters are swapped back last, unswap frames late
        self.repair = SwapRepair(unswap)
        self._lag = max(self.radius + self.fill_gaps, self.backfill)  # the smoothing's own
        self.lag = self._lag + self.repair.window
        # backfill: the detections of the frames not yet emitted, frame -> (M, 6) rows as in
        # _obs (confidence = the detection's probability, detected = 1)
        self._dets: dict[int, torch.Tensor] = {}
        # frame t reads the frames t - reach .. t + lag: the kernel's and a gap's span
        self._reach = self.radius + self.fill_gaps + 1
        self._pending: deque[tuple[int, bool, tuple[float, float]]] = deque()  # frame, tracked,
        # the camera's offset on it
        # the reported frames in reach: (frame, ids (K,), (K, 6) centre x, centre y, log w,
        # log h, confidence, detected)
        self._obs: deque[tuple[int, torch.Tensor, torch.Tensor]] = deque()
        self._last = -1

    @property
    def active(self) -> bool:
        """False when it passes every state through unchanged (no gap to fill and a kernel of
        one frame): :meth:`push` then returns each frame as it comes."""
        return self.lag > 0

    def push(
        self,
        i: int,
        state,
        offset: tuple[float, float] = (0.0, 0.0),
        detections: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> list:
        """Add frame ``i``'s reports; ``offset``: the camera's translation since the first
        frame (:attr:`MultiTargetTracker.camera_offset`), so that the boxes are smoothed and
        interpolated where the scene holds them, not where a panning or shaking camera shows
        them (a pan that turns, or a hand-held camera's jolts, would be smoothed into the
        targets' boxes). ``detections``: the frame's detections ``(boxes (M, 4), probabilities
        (M,))`` in the reported boxes' pixels and convention
        (:attr:`MultiTargetTracker.last_detections`), read by ``backfill``. Returns the frames
        now final."""
        if not is_integer(i):  # True was frame 1
            raise TrackerError(f"TrackSmoother.push: the frame index must be an integer, got {i!r}")
        if i <= self._last:
            raise TrackerError(f"frames must be pushed in increasing order: {i} after {self._last}")
        self._last = i
        if not self.active:  # nothing to repair, fill or smooth: each frame is final as it comes
            return [(i, state)]
        return self._repaired(self._push(i, state, offset, detections))

    def flush(self) -> list:
        out = [(*self._emit(*p), p[2]) for p in self._pending]
        self._pending.clear()
        self._obs.clear()
        self._dets.clear()
        return self._repaired(out) + self.repair.flush()

    # -- internals
    def _repaired(self, frames: list) -> list:
        """Smoothed frames ``(i, state, offset)`` through :attr:`repair`: ``(i, state)``."""
        out = []
        for i, state, offset in frames:
            out += self.repair.push(i, state, offset)
        return out

    def _push(self, i: int, state, offset, detections) -> list:
        """Fill, back-fill and smooth: the frames now final, ``(i, state, offset)``."""
        if self._lag == 0:
            return [(i, state, offset)]
        ox, oy = (float(v) for v in offset)
        if self.backfill and detections is not None:  # a scanned frame, maybe without any
            b, p = detections
            self._dets[i] = _rows(b, p, torch.ones(len(p)), ox, oy)
        self._pending.append((i, state is not None, (ox, oy)))
        if state is not None and len(state):
            ids = state.ids.detach().to("cpu", torch.int64)
            v = _rows(state.boxes, state.confidence, state.detected, ox, oy)
            if not bool(torch.isfinite(v).all()):  # NaN spread over every frame in reach
                k = int((~torch.isfinite(v).all(1)).nonzero()[0, 0])
                raise BoxError(
                    f"TrackSmoother.push: frame {i}, identity {int(ids[k])}: box "
                    f"{state.boxes[k].tolist()} and confidence {float(state.confidence[k])} "
                    f"must be finite (camera offset {(ox, oy)})"
                )
            self._obs.append((i, ids, v))
            if self.backfill:
                prev = next((o[1] for o in reversed(self._obs) if o[0] == i - 1), None)
                before = set(prev.tolist()) if prev is not None else set()
                for k, n in enumerate(ids.tolist()):
                    if n not in before:  # a new identity, or one back after a gap
                        self._backfill(i, n, v[k])
        out = []
        while self._pending and self._pending[0][0] + self._lag <= i:
            p = self._pending.popleft()
            out.append((*self._emit(*p), p[2]))
        self._trim()
        return out

    def _trim(self) -> None:
        """Drop the frames no emission can reach any more."""
        first = self._pending[0][0] if self._pending else self._last + 1
        while self._obs and self._obs[0][0] < first - self._reach:
            self._obs.popleft()
        for f in [f for f in self._dets if f < first]:
            del self._dets[f]

    def _backfill(self, i: int, ident: int, v0: torch.Tensor) -> None:
        """Extend identity ``ident``, reported on frame ``i`` with row ``v0`` but not on frame
        ``i - 1`` (a new identity, or one back after a gap), back in time over the frames not
        yet emitted (at most ``backfill``): on each earlier frame the detection that overlaps
        the box carried back (at the chain's own velocity) at IoU >= ``backfill_iou`` the
        most, and no other identity's box there at 0.5 or more, joins it. The chain stops at
        the identity's own earlier reports, and after ``BACKFILL_SKIP`` scanned frames in a row
        without a detection; the frames it skips are left to ``fill_gaps``."""
        first = self._pending[0][0]
        cur, vel, miss = v0[:4].clone(), torch.zeros(4, dtype=torch.float64), 0
        vel_at = i
        for f in range(i - 1, max(i - self.backfill, first) - 1, -1):
            d = self._dets.get(f)
            if d is None:
                continue
            pred = cur - vel * (vel_at - f)
            entry = next((k for k, o in enumerate(self._obs) if o[0] == f), None)
            cand = d
            if entry is not None:  # detections another identity already explains
                _, ids, rows = self._obs[entry]
                if bool((ids == ident).any()):  # the identity's own earlier run
                    return
                cand = cand[~(_iou(cand, rows) >= 0.5).any(1)]
            if len(cand):
                iou = _iou(pred[None], cand)[0]
                j = int(iou.argmax())
            if not len(cand) or float(iou[j]) < self.backfill_iou:
                miss += 1
                if miss > BACKFILL_SKIP:
                    return
                continue
            row = cand[j]
            vel = torch.zeros(4, dtype=torch.float64)
            vel[:2] = (cur[:2] - row[:2]) / (vel_at - f)
            cur, vel_at, miss = row[:4].clone(), f, 0
            if entry is None:  # a frame where nobody was reported
                k = sum(1 for o in self._obs if o[0] < f)
                self._obs.insert(k, (f, torch.tensor([ident]), row[None]))
            else:
                g, ids, rows = self._obs[entry]
                self._obs[entry] = (
                    g,
                    torch.cat([ids, torch.tensor([ident])]),
                    torch.cat([rows, row[None]]),
                )

    def _emit(self, t: int, tracked: bool, offset: tuple[float, float]):
        from torchtrack.track.multi import MultiState

        if not tracked:
            return t, None
        r, fill, reach = self.radius, self.fill_gaps, self._reach
        near = [o for o in self._obs if t - reach <= o[0] <= t + self._lag]
        if not near:
            return t, _empty_state()
        ids = torch.cat([o[1] for o in near])
        uniq, row = torch.unique(ids, return_inverse=True)
        cols = torch.cat([torch.full((o[1].numel(),), o[0] - t + reach) for o in near])
        width = reach + self._lag + 1  # frames t - reach .. t + lag; t is column `reach`
        u = uniq.numel()
        val = torch.zeros((u, width, 6), dtype=torch.float64)
        seen = torch.zeros((u, width), dtype=torch.bool)
        val[row, cols] = torch.cat([o[2] for o in near])
        seen[row, cols] = True
        col = torch.arange(width)
        # gaps: the observations before and after each column, and the gap's length
        before = torch.where(seen, col, -1).cummax(1).values  # (U, W)
        after = torch.where(seen, col, width).flip(1).cummin(1).values.flip(1)
        filled = ~seen & (before >= 0) & (after < width) & (after - before - 1 <= fill)
        a, b = before.clamp(min=0), after.clamp(max=width - 1)
        frac = ((col - a).double() / (b - a).clamp(min=1).double())[..., None]
        va, vb = (
            val.gather(1, a[..., None].expand(-1, -1, 6)),
            val.gather(1, b[..., None].expand(-1, -1, 6)),
        )
        x = torch.where(filled[..., None], va + (vb - va) * frac, val)
        x[..., 5] = torch.where(filled, 0.0, x[..., 5])  # filled rows are not detections
        have = seen | filled
        keep = have[:, reach]
        if not bool(keep.any()):
            return t, _empty_state()
        x, have = x[keep], have[keep]
        out = x[:, reach, :4]
        if r:
            # the run of consecutive frames around t, within the kernel: [lo, hi]
            hole = ~have
            lo = torch.where(hole[:, : reach + 1], col[: reach + 1], -1).max(1).values + 1
            hi = torch.where(hole[:, reach:], col[reach:], width).min(1).values - 1
            lo, hi = lo.clamp(min=reach - r), hi.clamp(max=reach + r)
            d = (col - reach).to(torch.float64)  # (W,) offsets from t
            w = torch.zeros(width, dtype=torch.float64)
            w[reach - r : reach + r + 1] = self.weights
            m = ((col >= lo[:, None]) & (col <= hi[:, None])).to(torch.float64) * w  # (R, W)
            s0, s1, s2 = m.sum(1), (m * d).sum(1), (m * d * d).sum(1)
            t0 = (m[..., None] * x[..., :4]).sum(1)
            t1 = ((m * d)[..., None] * x[..., :4]).sum(1)
            den = s0 * s2 - s1 * s1
            line = (hi > lo) & (den > 1e-12 * s0 * s0)
            safe = torch.where(line, den, torch.ones_like(den))[:, None]
            out = torch.where(
                line[:, None], (s2[:, None] * t0 - s1[:, None] * t1) / safe, t0 / s0[:, None]
            )
        # back where the frame shows it
        centre = torch.stack((out[:, 0] + offset[0], out[:, 1] + offset[1]), 1)
        boxes = _boxes(torch.cat([centre, out[:, 2:4]], 1))
        return t, MultiState(uniq[keep], boxes, x[:, reach, 4], x[:, reach, 5] > 0.5)


#: backfill: scanned frames in a row without a detection after which a chain back in time stops
BACKFILL_SKIP = 2


def _rows(boxes, confidence, detected, ox: float, oy: float) -> torch.Tensor:
    """``(K, 6)`` float64 rows: centre x, y in the scene (the camera's offset taken out), log
    width, log height, confidence, detected."""
    from torchtrack.boxes import xywh_to_cxcywh

    c = xywh_to_cxcywh(boxes.detach().to("cpu", torch.float64))
    return torch.stack(
        (
            c[:, 0] - ox,
            c[:, 1] - oy,
            c[:, 2].clamp_min(1e-9).log(),
            c[:, 3].clamp_min(1e-9).log(),
            torch.as_tensor(confidence).detach().to("cpu", torch.float64),
            torch.as_tensor(detected).detach().to("cpu", torch.float64),
        ),
        1,
    )


def _boxes(rows: torch.Tensor) -> torch.Tensor:
    """x, y, w, h boxes ``(K, 4)`` of rows (centre x, y, log w, log h, ...): :func:`_rows`'s
    inverse, less the camera's offset."""
    from torchtrack.boxes import cxcywh_to_xywh

    return cxcywh_to_xywh(torch.cat([rows[:, :2], rows[:, 2:4].exp()], 1))


def _iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """IoU ``(A, B)`` of rows (centre x, y, log w, log h, ...) ``a`` and ``b``."""
    from torchtrack.boxes import box_iou_matrix

    return box_iou_matrix(_boxes(a), _boxes(b))


def _empty_state():
    from torchtrack.track.multi import MultiState

    return MultiState(
        torch.zeros(0, dtype=torch.int64),
        torch.zeros((0, 4), dtype=torch.float64),
        torch.zeros(0, dtype=torch.float64),
        torch.zeros(0, dtype=torch.bool),
    )
