"""Scan ahead: the multi-target tracker's detector scans of the coming frames, in worker
processes, while the tracker steps the current frame.

A scan depends on its frame and on the tracker's ground plane as it was ``GROUND_LAG`` frames
before (:meth:`~torchtrack.track.multi.MultiTargetTracker.scan_ground`; not on the targets of
the moment), so the frames the tracker will scan can be scanned before it gets to them, up to
``GROUND_LAG`` frames ahead. :class:`ScanAhead` keeps up to ``depth`` frames in flight
over ``workers`` processes and hands them back in order, each with its scan::

    mt = MultiTargetTracker("pedestrian")
    with ScanAhead(mt, workers=2) as ahead:
        for i, frame, scan in ahead.frames(source.items()):
            out = mt.update(frame, scan=scan)

The tracks are the ones of ``mt.update(frame)`` (the workers run the tracker's own
:meth:`~torchtrack.track.multi.MultiTargetTracker.detect` with the line ``scan_ground`` gives,
one torch thread each); only the time changes. On two cores the scan of a 480x360 frame takes ~160 ms and the rest of the step
~40 ms: two workers let the scans of two frames and the tracker's step share the cores
(``docs/multi_target.md``, "Speed").

The workers are forked from this process, so they share its loaded model: nothing is
serialised but the frames and the detections (``"fork"`` start method, Linux). Where fork is
unavailable, or with ``workers=0``, the scans run in this process, one per frame, as
``mt.update(frame)`` would run them.

:class:`Ahead` is the mechanism without the tracker: any function over a stream of arguments,
ahead and in order (``torchtrack detect`` scans its batches of frames with it).
"""

from __future__ import annotations

import collections
import os
import signal
import sys
import time
from collections.abc import Iterable, Iterator
from typing import Any

import torch

from torchtrack.errors import ConfigError, TrackerError

__all__ = ["Ahead", "ScanAhead", "default_scan_batch", "default_scan_workers", "fork_available"]

# The function the forked workers call (inherited through fork, never pickled): one pool at a
# time per process.
_FN: Any = None


def fork_available() -> bool:
    """Whether worker processes can be forked here (Linux: torch and OpenCV are fork-safe
    for CPU work once the child sets its own thread count; macOS and Windows are not used)."""
    import multiprocessing as mp

    return sys.platform.startswith("linux") and "fork" in mp.get_all_start_methods()


def _cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


def default_scan_workers() -> int:
    """Workers for this machine: 2 where there are at least two cores and fork works, else 0
    (measured on 2 cores: 2 workers beat 1 and 3, ``docs/multi_target.md``)."""
    return 2 if fork_available() and _cpus() >= 2 else 0


#: frames a GPU scans together (``ScanAhead(batch=...)``): a frame's scan is thousands of small
#: tensor operations, so a GPU is bound by launching them; 8 frames share each launch
GPU_SCAN_BATCH = 8


def default_scan_batch(device: torch.device | str | None) -> int:
    """Frames scanned together in this process: :data:`GPU_SCAN_BATCH` on a GPU, 1 elsewhere
    (the CPU scans ahead in worker processes instead)."""
    return GPU_SCAN_BATCH if device is not None and torch.device(device).type == "cuda" else 1


def _die_with_parent(parent: int) -> None:
    """SIGKILL this process when its parent dies (Linux ``prctl(PR_SET_PDEATHSIG)``): a forked
    worker holds both ends of its queue's pipe, so it would never see the parent go."""
    import ctypes

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):  # no prctl: the pool's shutdown still ends the workers
        return
    if os.getppid() != parent:  # the parent died before prctl took effect
        os._exit(1)


def _init_worker(parent: int) -> None:
    # Ctrl-C and SIGTERM (sent to the whole process group by a terminal or a service manager)
    # are the parent's to handle: it keeps the results so far and shuts the pool down. A worker
    # must neither raise the CLI's KeyboardInterrupt / Terminated in a scan nor die first (the
    # parent would report a broken worker instead of the interruption). Workers end when the
    # parent closes the pool; if the parent is killed outright, the kernel kills them too.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _die_with_parent(parent)
    torch.set_num_threads(1)


def _call(arg: Any) -> Any:
    """What to submit to a :func:`_fork_pool`: ``pool.submit(_call, arg)`` runs ``fn(arg)``."""
    return _FN(arg)


def _fork_pool(fn: Any, workers: int) -> Any:
    """A ``ProcessPoolExecutor`` of ``workers`` forked processes that run ``fn`` (submit
    :func:`_call` with ``fn``'s argument): the workers share this process's memory as it is now
    (a loaded model, a tracker's settings), so nothing but the arguments and the results
    crosses a pipe. They ignore Ctrl-C and SIGTERM (the caller handles those and shuts the
    pool down), take one torch thread each, and die with this process if it is killed."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    global _FN
    _FN = fn
    return ProcessPoolExecutor(
        workers,
        mp_context=mp.get_context("fork"),
        initializer=_init_worker,
        initargs=(os.getpid(),),
    )


class Ahead:
    """``fn`` over a stream of arguments in ``workers`` forked processes, ahead of the caller
    and handed back in order (:meth:`map`); at most ``depth`` calls in flight, so memory stays
    bounded. With ``workers=0`` (or no fork here) each call runs in this process when its
    result is asked for.

    Raises:
        ConfigError: ``workers < 0`` or ``depth < 1``.
    """

    def __init__(self, fn: Any, workers: int, depth: int | None = None) -> None:
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
            raise ConfigError(f"scan workers must be an integer >= 0, got {workers!r}")
        if depth is not None and (
            isinstance(depth, bool) or not isinstance(depth, int) or depth < 1
        ):
            raise ConfigError(f"scan-ahead depth must be an integer >= 1, got {depth!r}")
        self.fn = fn
        self.workers = workers if fork_available() else 0
        self.depth = depth if depth is not None else max(1, 2 * self.workers)
        self._pool = None
        #: seconds this process spent on the calls: running them (no workers) or waiting
        self.seconds = 0.0

    def __enter__(self) -> Ahead:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        """Stop the workers (pending calls are dropped; the ones running finish). Not cut
        short by a second Ctrl-C or SIGTERM, which would leave the pool half shut and this
        process waiting on its workers for ever."""
        if self._pool is not None:
            from torchtrack.io.atomic import uninterrupted

            with uninterrupted():
                self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def map(self, items: Iterable[tuple[Any, Any]], where: Any = str) -> Iterator[tuple[Any, Any]]:
        """``(key, result)`` for every ``(key, arg)`` of ``items``, in order: ``result`` is
        ``fn(arg)``, or None where ``arg`` is None (no call).

        Raises:
            TrackerError: a worker died (e.g. killed for memory), naming ``where(key)``; an error
                raised by ``fn`` (e.g. :class:`~torchtrack.errors.ShapeError`) comes back as it
                was raised, when its result is reached.
        """
        from concurrent.futures.process import BrokenProcessPool

        queue: collections.deque = collections.deque()
        it = iter(items)
        done = False
        while True:
            while not done and len(queue) < self.depth:
                try:
                    key, arg = next(it)
                except StopIteration:
                    done = True
                    break
                if arg is not None and self.workers:
                    if self._pool is None:
                        self._pool = _fork_pool(self.fn, self.workers)
                    arg = self._pool.submit(_call, arg)
                queue.append((key, arg))
            if not queue:
                return
            key, arg = queue.popleft()
            if arg is None:
                yield key, None
                continue
            t0 = time.perf_counter()
            try:
                result = arg.result() if self.workers else self.fn(arg)
            except BrokenProcessPool:
                self.close()
                raise TrackerError(
                    f"a scan worker stopped unexpectedly at {where(key)} (killed for memory?): run "
                    "again with --scan-workers 0 to scan in this process"
                ) from None
            finally:
                self.seconds += time.perf_counter() - t0
            yield key, result


def _scan_with(tracker: Any) -> Any:
    """``(frame, ground line) -> tracker.detect(frame, line)``: what the workers run."""

    def fn(arg: tuple[torch.Tensor, Any]) -> tuple[torch.Tensor, torch.Tensor]:
        return tracker.detect(*arg)

    return fn


class ScanAhead(Ahead):
    """Detector scans of the coming frames in ``workers`` forked processes (see the module).

    Args:
        tracker: the :class:`~torchtrack.track.multi.MultiTargetTracker` whose scans to run
            (its ``detect`` and ``config.scan_every``); it must be fresh or reset, since the
            frames it scans are counted from the first one given here.
        workers: processes; 0 (or no fork on this platform): the scans run in this process.
        depth: frames in flight at most (default ``2 * workers``, capped at ``GROUND_LAG``;
            a larger one is an error); memory stays bounded.

        batch: with no workers, frames scanned together in one batched call
            (:meth:`~torchtrack.track.multi.MultiTargetTracker.detect_batch`, each with its own
            ground line; the same scans): a frame's scan is thousands of small operations, which
            a GPU runs for a batch at about the cost of one frame (the main job on PETS ran
            23.8 fps with 8 frames a scan against 13.6 with one, on an H200; default 1, at most
            ``GROUND_LAG``). Ignored with workers.
        device: with no workers, where the frames are scanned (None: where they are); the
            frames handed back stay where they were.

    Raises:
        ConfigError: ``workers < 0``, ``depth < 1``, ``depth > GROUND_LAG``, or ``batch``
            outside ``[1, GROUND_LAG]``.
    """

    def __init__(
        self,
        tracker: Any,
        workers: int,
        depth: int | None = None,
        *,
        batch: int = 1,
        device: torch.device | str | None = None,
    ) -> None:
        from torchtrack.track.multi import GROUND_LAG

        super().__init__(_scan_with(tracker), workers, depth)
        if isinstance(batch, bool) or not isinstance(batch, int) or not 1 <= batch <= GROUND_LAG:
            raise ConfigError(
                f"scan batch must be an integer in [1, {GROUND_LAG}] (frames scanned together "
                f"use the ground plane of {GROUND_LAG} frames before), got {batch!r}"
            )
        self.batch = batch
        self.device = None if device is None else torch.device(device)
        if depth is None:  # many workers: no more in flight than the ground plane allows
            self.depth = min(self.depth, GROUND_LAG)
        if self.depth > GROUND_LAG:
            raise ConfigError(
                f"scan-ahead depth must be at most {GROUND_LAG} frames (the scans use the "
                f"tracker's ground plane of {GROUND_LAG} frames before), got {self.depth}"
            )
        self.tracker = tracker

    def frames(
        self, items: Iterable[tuple[int, torch.Tensor | None]]
    ) -> Iterator[tuple[int, torch.Tensor | None, tuple[torch.Tensor, torch.Tensor] | None]]:
        """``(index, frame, scan)`` for every ``(index, frame)`` of ``items``, in order.

        ``scan`` is this frame's ``tracker.detect(frame, tracker.scan_ground(k))`` (``k`` the
        tracker's count of the frame) on the frames the tracker scans
        (every ``scan_every``-th readable frame, from the first), None on the others and for
        unreadable frames (``frame`` None, skipped by the count as the tracker skips them).

        Raises:
            TrackerError: a worker died (e.g. killed for memory); an error raised by a scan
                (e.g. :class:`~torchtrack.errors.ShapeError`) comes back as it was raised
                (with ``batch > 1``, when the first frame of its batch is reached).
        """
        every = int(self.tracker.config.scan_every)
        if not self.workers:
            yield from self._here(items, every)
            return

        def scans():
            k = 0
            for i, frame in items:
                scanned = frame is not None and k % every == 0
                # asked for when the frame is sent: the tracker is then at most `depth` frames
                # behind it, so the line of GROUND_LAG frames before is known
                arg = (frame, self.tracker.scan_ground(k)) if scanned else None
                k += frame is not None
                yield (i, frame), arg

        for (i, frame), scan in self.map(scans(), where=lambda key: f"frame {key[0] + 1}"):
            yield i, frame, scan

    def _here(
        self, items: Iterable[tuple[int, torch.Tensor | None]], every: int
    ) -> Iterator[tuple[int, torch.Tensor | None, tuple[torch.Tensor, torch.Tensor] | None]]:
        """:meth:`frames` without workers: the frames to scan go through ``detect_batch``
        ``batch`` at a time on ``device``. A batch is scanned when the tracker has taken every
        frame before it, and spans fewer than ``GROUND_LAG`` of the tracker's frames, so each
        frame's ground line (``scan_ground``) is known; frames of another size than the
        batch's start a new one."""
        from torchtrack.track.multi import GROUND_LAG

        buf: list[tuple[int, torch.Tensor | None, int | None]] = []  # (index, frame, k)
        k = 0  # the tracker's count of the next readable frame
        k0 = 0  # ... of the buffer's first frame

        def flush():
            todo = [(n, kk) for n, (_, _, kk) in enumerate(buf) if kk is not None]
            found: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
            if todo:
                t0 = time.perf_counter()
                try:
                    frames = torch.stack([buf[n][1] for n, _ in todo])
                    if self.device is not None:
                        frames = frames.to(self.device)
                    lines = [self.tracker.scan_ground(kk) for _, kk in todo]
                    got = self.tracker.detect_batch(frames, lines)
                    found.update((n, r) for (n, _), r in zip(todo, got, strict=True))
                finally:
                    self.seconds += time.perf_counter() - t0
            out = [(i, f, found.get(n)) for n, (i, f, _) in enumerate(buf)]
            buf.clear()
            return out

        for i, frame in items:
            scanned = frame is not None and k % every == 0
            if scanned and buf:
                first = next((f for _, f, kk in buf if kk is not None), None)
                n_scans = sum(kk is not None for _, _, kk in buf)
                if (
                    n_scans >= self.batch
                    or k - k0 >= GROUND_LAG
                    or (first is not None and first.shape != frame.shape)
                ):
                    yield from flush()
            if not buf:
                k0 = k
            buf.append((i, frame, k if scanned else None))
            k += frame is not None
            if self.batch == 1:  # nothing to gather: each frame goes on as it comes
                yield from flush()
        yield from flush()
