"""Identity repair at close encounters: two identities that swapped people are swapped back.

When two people cross, one hidden behind the other or both behind a third thing, a tracker can
come out of the crossing with their identities exchanged. On PETS09-S2L1 the multi-target
tracker's two longest tracks do so on half the seeds: two people walk towards each other behind
a sign, both targets stall on the sign while they are hidden, and each then takes the person who
comes out on its own side, so that each identity turns back where it came from. Such a swap
shows in the tracks themselves: each identity's motion before the encounter continues in the
other identity after it.

:class:`SwapRepair` looks for it in the stream of reported frames, with a delay of ``window``
frames. Two identities are *close* on a frame when their box centres are less than
:data:`REACH` box heights apart; close frames at most :data:`GAP` apart make one *encounter*,
from ``t0`` to ``t1``. Once ``window`` frames after ``t1`` are in, each identity's centre is fitted
by a line (least squares) over the ``window`` frames before ``t0`` and over the ``window``
frames after ``t1``, and two pairings are compared, each by its change of velocity plus how far
the line before misses the line after, per frame of the gap, both in box heights:

* *kept*: each identity's line before joined to its own line after;
* *swapped*: each identity's line before joined to the other's line after.

If swapped costs less than :data:`RATIO` times kept, and kept costs at least
:data:`MIN_CHANGE` (someone's motion did change), the identities are exchanged on every frame
after ``t1`` (the frames of the encounter itself keep theirs: which of them came before the
exchange is not known, and the delay stays ``window`` frames), and the tracker's identities map
to them so from then on (OC-SORT's
observation-centric view, Cao et al., CVPR 2023: the observations before an occlusion say
where a target is going better than the filter that coasted through it). An identity reported
on fewer than half of either window's frames is not judged; encounters longer than
:data:`MAX_ENCOUNTER` frames (people walking together) are not judged either.

Boxes are compared in the scene's coordinates (the camera's offset taken out, as the smoother
does). The frames pass through unchanged apart from their identities.
"""

from __future__ import annotations

from collections import deque
from dataclasses import replace

import torch

from torchtrack.errors import ConfigError

__all__ = ["SwapRepair"]

#: two identities are close on a frame when their box centres are less than this many (mean)
#: box heights apart
REACH = 0.75
#: close frames at most this many frames apart make one encounter
GAP = 3
#: the swapped pairing must cost less than this fraction of the kept one
RATIO = 0.5
#: ... and the kept pairing at least this much (box heights): someone's motion changed
MIN_CHANGE = 0.03
#: encounters longer than this many frames (people walking together) are not judged
MAX_ENCOUNTER = 50


class SwapRepair:
    """Swap identities back after close encounters (module notes), ``window`` frames late.

    Args:
        window: frames of motion compared before and after an encounter, and the delay (0:
            frames pass through as they come).

    ``push(i, state, offset)`` for every frame index in increasing order (``state`` a
    :class:`~torchtrack.track.multi.MultiState` or None, ``offset`` the camera's translation
    since the first frame) returns the frames now final, as ``(i, state)`` in order, the
    states' identities repaired; ``flush()`` returns the rest. ``swaps`` lists the repairs made: ``(first frame, identity,
    identity)``.

    Raises:
        ConfigError: ``window`` negative or not whole.
    """

    def __init__(self, window: int = 10) -> None:
        if isinstance(window, bool) or int(window) != window or window < 0:
            raise ConfigError(f"identity repair window must be a whole number >= 0, got {window!r}")
        self.window = int(window)
        self.swaps: list[tuple[int, int, int]] = []
        self._held: deque[list] = deque()  # [i, state] of the last window frames
        self._map: dict[int, int] = {}  # the tracker's identity -> the one reported
        # identity -> deque of (frame, centre x, centre y, height) in the scene
        self._track: dict[int, deque] = {}
        self._open: dict[tuple[int, int], list[int]] = {}  # (a, b), a < b -> [t0, t1]
        self._last = -1

    @property
    def active(self) -> bool:
        return self.window > 0

    def push(self, i: int, state, offset=(0.0, 0.0)) -> list:
        if not self.active:
            return [(i, state)]
        self._last = i
        if state is not None and len(state):
            state = self._mapped(state)
            self._observe(i, state, offset)
        self._held.append([i, state])
        self._judge(i, final=False)
        out = []
        while self._held and self._held[0][0] <= i - self.window:
            out.append(tuple(self._held.popleft()))
        self._trim(i)
        return out

    def flush(self) -> list:
        if self.active:
            self._judge(self._last, final=True)
        out = [tuple(h) for h in self._held]
        self._held.clear()
        self._open.clear()
        self._track.clear()
        return out

    # -- internals
    def _mapped(self, state):
        """``state`` with the tracker's identities mapped to the reported ones."""
        if not self._map:
            return state
        ids = state.ids.detach().to("cpu", torch.int64)
        new = torch.tensor([self._map.get(n, n) for n in ids.tolist()], dtype=torch.int64)
        return replace(state, ids=new.to(state.ids.device))

    def _observe(self, i: int, state, offset) -> None:
        ox, oy = (float(v) for v in offset)
        b = state.boxes.detach().to("cpu", torch.float64)
        c = torch.stack((b[:, 0] + b[:, 2] / 2 - ox, b[:, 1] + b[:, 3] / 2 - oy), 1)  # (K, 2)
        h = b[:, 3]
        ids = state.ids.detach().to("cpu", torch.int64)
        for n, (x, y), hh in zip(ids.tolist(), c.tolist(), h.tolist(), strict=True):
            self._track.setdefault(n, deque()).append((i, x, y, hh))
        # the pairs close on this frame, in one distance matrix (then a loop over those few)
        close = torch.cdist(c, c) < REACH * (h[:, None] + h[None, :]) / 2
        for k, m in torch.triu(close, diagonal=1).nonzero().tolist():
            a, o = int(ids[k]), int(ids[m])
            key = (min(a, o), max(a, o))
            span = self._open.get(key)
            if span is not None and i - span[1] <= GAP:
                span[1] = i
            else:
                if span is not None:  # an earlier encounter not judged yet
                    self._decide(key, *span)
                self._open[key] = [i, i]

    def _judge(self, i: int, final: bool) -> None:
        """Decide the encounters whose ``window`` frames after have come (all of them at the
        end of the stream)."""
        for key in list(self._open):
            span = self._open.get(key)
            if span is None:  # dropped by a swap decided in this loop: its meaning changed
                continue
            t0, t1 = span
            if final or i >= t1 + self.window:
                del self._open[key]
                self._decide(key, t0, t1)

    def _line(self, n: int, lo: int, hi: int):
        """Least-squares line of identity ``n``'s centre over frames ``lo..hi``: ``(velocity
        (2,), centre at the mean frame (2,), mean frame, mean height)``, or None when it was
        reported on fewer than half of them."""
        rows = [r for r in self._track.get(n, ()) if lo <= r[0] <= hi]
        if len(rows) < max(2, (hi - lo + 1) // 2):
            return None
        t = torch.tensor(rows, dtype=torch.float64)
        f = t[:, 0] - t[:, 0].mean()
        den = float((f * f).sum())
        v = (f[:, None] * t[:, 1:3]).sum(0) / den
        return v, t[:, 1:3].mean(0), float(t[:, 0].mean()), float(t[:, 3].mean())

    def _decide(self, key: tuple[int, int], t0: int, t1: int) -> None:
        a, b = key
        w = self.window
        if t1 - t0 + 1 > MAX_ENCOUNTER:
            return
        pa, pb = self._line(a, t0 - w, t0 - 1), self._line(b, t0 - w, t0 - 1)
        qa, qb = self._line(a, t1 + 1, t1 + w), self._line(b, t1 + 1, t1 + w)
        if pa is None or pb is None or qa is None or qb is None:
            return
        h = (pa[3] + pb[3]) / 2

        def cost(p, q) -> float:  # velocity change + the line before's miss, per frame
            dv = float((p[0] - q[0]).norm()) / h
            miss = p[1] + p[0] * (q[2] - p[2]) - q[1]
            return dv + float(miss.norm()) / h / max(q[2] - p[2], 1.0)

        kept = cost(pa, qa) + cost(pb, qb)
        swapped = cost(pa, qb) + cost(pb, qa)
        if swapped < RATIO * kept and kept >= MIN_CHANGE:
            self._swap(a, b, t1 + 1)

    def _swap(self, a: int, b: int, first: int) -> None:
        """Exchange identities ``a`` and ``b`` on every frame from ``first`` on."""
        self.swaps.append((first, a, b))
        for h in self._held:
            if h[0] >= first and h[1] is not None and len(h[1]):
                ids = h[1].ids
                na, nb = ids == a, ids == b
                if bool(na.any()) or bool(nb.any()):
                    new = ids.clone()
                    new[na], new[nb] = b, a
                    h[1] = replace(h[1], ids=new)
        ta, tb = self._track.get(a, deque()), self._track.get(b, deque())
        keep_a = deque(r for r in ta if r[0] < first)
        keep_b = deque(r for r in tb if r[0] < first)
        keep_a.extend(r for r in tb if r[0] >= first)
        keep_b.extend(r for r in ta if r[0] >= first)
        self._track[a], self._track[b] = keep_a, keep_b
        # the map stays a permutation: the tracker's identities reported as a (or b) now as b
        # (or a), those not in it yet being reported as themselves
        keys = {k for k, v in self._map.items() if v in (a, b)}
        keys.update(n for n in (a, b) if n not in self._map)
        for k in keys:
            self._map[k] = b if self._map.get(k, k) == a else a
        for key in [k for k in self._open if a in k or b in k]:  # their meaning changed
            del self._open[key]

    def _trim(self, i: int) -> None:
        """Forget what no encounter can read any more: a track's frames before the earliest
        encounter that may still open, less the window before it."""
        # an encounter already longer than MAX_ENCOUNTER will not be judged: its start does
        # not hold the history (two people side by side all along: memory stays flat)
        first = min((t0 for t0, t1 in self._open.values() if t1 - t0 < MAX_ENCOUNTER), default=i)
        keep_from = min(first, i) - self.window - 1
        for n in list(self._track):
            q = self._track[n]
            while q and q[0][0] < keep_from:
                q.popleft()
            if not q:
                del self._track[n]
