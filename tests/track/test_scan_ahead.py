"""Scan ahead: the multi-target tracker's scans in forked workers give the same tracks; errors
come back typed; the tracker refuses a scan for a frame it does not scan."""

import itertools
import os

import pytest
import torch

from torchtrack.errors import ConfigError, ShapeError, TrackerError
from torchtrack.track.multi import MultiTargetTracker
from torchtrack.track.scan_ahead import ScanAhead, fork_available

needs_fork = pytest.mark.skipif(not fork_available(), reason="worker processes are forked (Linux)")


@pytest.fixture(scope="module")
def clip():
    """The first 8 frames of the bundled clip, with an unreadable one (None) as frame 3."""
    from torchtrack.data import demo_clip_path
    from torchtrack.io.video import open_source

    with open_source(demo_clip_path()) as src:
        frames = [f for _, f in itertools.islice(src.items(), 8)]
    frames[3] = None
    return list(enumerate(frames))


def make(**kw):
    return MultiTargetTracker("pedestrian", generator=torch.Generator().manual_seed(0), **kw)


def run(mt, items, workers, **kw):
    out = []
    with ScanAhead(mt, workers, **kw) as ahead:
        for _, frame, scan in ahead.frames(items):
            if frame is not None:
                out.append(mt.update(frame, scan=scan))
    return out, ahead


def same_tracks(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert torch.equal(x.ids, y.ids)
        torch.testing.assert_close(x.boxes, y.boxes, rtol=0, atol=0)
        torch.testing.assert_close(x.confidence, y.confidence, rtol=0, atol=0)


@needs_fork
@pytest.mark.parametrize("scan_every", [1, 2])
def test_workers_give_the_tracks_of_the_tracker_alone(clip, one_thread, scan_every):
    alone = make(scan_every=scan_every)
    ref = [alone.update(f) for _, f in clip if f is not None]
    assert sum(len(r) for r in ref) > 0  # people are tracked on these frames
    mt = make(scan_every=scan_every)
    got, ahead = run(mt, clip, workers=2)
    same_tracks(ref, got)
    assert ahead.workers == 2 and ahead.seconds > 0
    # in-process (workers=0) is the same path as update(frame) scanning itself
    same_tracks(ref, run(make(scan_every=scan_every), clip, workers=0)[0])


def test_frames_come_back_in_order_and_only_scan_frames_are_scanned(clip, monkeypatch):
    mt = make(scan_every=3)
    calls = []
    monkeypatch.setattr(  # the in-process scans go through detect_batch, a frame a call here
        mt,
        "detect_batch",
        lambda fs, gs: [calls.append(1) or (torch.zeros(0, 4), torch.zeros(0)) for _ in fs],
    )
    with ScanAhead(mt, 0) as ahead:
        got = list(ahead.frames(clip))
    assert [i for i, _, _ in got] == list(range(8))
    # readable frames 0, 1, 2, 4, 5, 6, 7 -> counted 0..6; scans on counts 0, 3, 6
    assert [i for i, f, s in got if s is not None] == [0, 4, 7]
    assert len(calls) == 3


@needs_fork
def test_an_error_in_a_worker_comes_back_typed(clip, monkeypatch):
    mt = make()

    def bad(frame, ground=None):
        raise ShapeError("a scan failed on purpose")

    monkeypatch.setattr(mt, "detect", bad)  # inherited by the forked workers
    with ScanAhead(mt, 2) as ahead, pytest.raises(ShapeError, match="on purpose"):
        list(ahead.frames(clip))


@needs_fork
def test_a_worker_that_dies_is_a_tracker_error(clip, monkeypatch):
    mt = make()
    # in the forked worker
    monkeypatch.setattr(mt, "detect", lambda frame, ground=None: os._exit(3))
    with ScanAhead(mt, 1) as ahead, pytest.raises(TrackerError, match="--scan-workers 0"):
        list(ahead.frames(clip))


def test_bad_settings_and_misplaced_scans(clip):
    mt = make(scan_every=2)
    for bad in (-1, 1.5, True):
        with pytest.raises(ConfigError, match="scan workers"):
            ScanAhead(mt, bad)
    with pytest.raises(ConfigError, match="depth"):
        ScanAhead(mt, 1, depth=0)
    with pytest.raises(ConfigError, match="at most 16 frames"):
        ScanAhead(mt, 1, depth=17)  # beyond the ground plane's lag
    assert ScanAhead(mt, 12).depth == 16  # many workers: capped, not refused
    for bad in (0, 17, 2.0, True):
        with pytest.raises(ConfigError, match="scan batch"):
            ScanAhead(mt, 0, batch=bad)
    frame = clip[0][1]
    none = (torch.zeros(0, 4), torch.zeros(0))
    mt.update(frame, scan=none)  # frame 1: scanned
    with pytest.raises(TrackerError, match="does not scan"):
        mt.update(frame, scan=none)  # frame 2 is not
    mt.update(frame)
    with pytest.raises(TrackerError, match="does not scan"):
        mt.update(frame, none, scan=none)  # with outside detections


@needs_fork
def test_scans_that_keep_the_ground_plane_windows_give_the_same_tracks_ahead(one_thread):
    """Once the ground plane is learnt, each scan scores only the windows that fit the line of
    GROUND_LAG frames before: the same line whether the scan runs here or ahead in a worker."""
    from torchtrack.data import demo_clip_path
    from torchtrack.io.video import open_source
    from torchtrack.track.multi import GROUND_LAG

    with open_source(demo_clip_path()) as src:
        frames = list(itertools.islice(src.items(), GROUND_LAG + 14))
    alone = make()
    ref = [alone.update(f) for _, f in frames]
    assert alone.scan_ground(len(frames) - 1) is not None  # the last scans were restricted
    assert alone.ground.fitted and alone.ground.line_.a > 0
    mt = make()
    got, _ = run(mt, frames, workers=2)
    same_tracks(ref, got)
    with pytest.raises(TrackerError, match="at most 16 frames ahead"):
        mt.scan_ground(len(frames) + GROUND_LAG)


@needs_fork
def test_track_sequence_with_scan_workers_gives_the_same_rows(clip, one_thread):
    from torchtrack.track.multi import track_sequence

    class Frames:
        def items(self):
            return iter(clip)

    a = track_sequence(make(), Frames())
    b = track_sequence(make(), Frames(), scan_workers=2)
    assert len(a) > 0
    assert (a.frames == b.frames).all() and (a.ids == b.ids).all() and (a.boxes == b.boxes).all()


def test_frames_scanned_together_come_back_in_order(clip, monkeypatch):
    """``batch=4``: the frames to scan go to ``detect_batch`` four at a time (readable frames
    0, 1, 2, 4, 5, 6, 7 of the clip: calls of 4 and 3), each with its own ground line, and come
    back in order with their own scans; frames of another size start a new batch."""
    mt = make()
    calls = []

    def fake(frames, lines):
        calls.append((frames.shape[0], len(lines)))
        return [(torch.full((1, 4), float(f.float().mean())), torch.ones(1)) for f in frames]

    monkeypatch.setattr(mt, "detect_batch", fake)
    with ScanAhead(mt, 0, batch=4) as ahead:
        got = list(ahead.frames(clip))
    assert [i for i, _, _ in got] == list(range(8)) and calls == [(4, 4), (3, 3)]
    for _, f, s in got:
        assert (s is None) == (f is None)
        if f is not None:
            assert float(s[0][0, 0]) == float(f.float().mean())  # its own frame's scan
    small = [(i, f[:, :200, :300] if i >= 6 and f is not None else f) for i, f in clip]
    calls.clear()
    with ScanAhead(mt, 0, batch=8) as ahead:
        list(ahead.frames(small))
    assert calls == [(5, 5), (2, 2)]  # frames 0, 1, 2, 4, 5 | the smaller 6, 7


def test_batched_scans_give_the_tracks_of_the_tracker_alone(one_thread):
    """Scans of up to 16 frames together (the ground plane's lag), each with the ground line of
    its own frame, give the tracks of the tracker scanning frame by frame, to the bit; also
    when only every other frame is scanned and one frame is unreadable."""
    from torchtrack.data import demo_clip_path
    from torchtrack.io.video import open_source
    from torchtrack.track.multi import GROUND_LAG

    with open_source(demo_clip_path()) as src:
        frames = list(itertools.islice(src.items(), GROUND_LAG + 14))
    frames[20] = (20, None)
    for every in (1, 2):
        alone = make(scan_every=every)
        ref = [alone.update(f) for _, f in frames if f is not None]
        if every == 1:  # the last scans were restricted to the ground plane's windows
            assert alone.scan_ground(len(frames) - 2) is not None
        for batch in (5, GROUND_LAG):
            same_tracks(ref, run(make(scan_every=every), frames, 0, batch=batch)[0])


def test_detect_batch_gives_each_frame_the_scan_of_its_own_ground_line(one_thread):
    """``detect_batch(frames, lines)`` is ``[detect(f, line) for ...]`` with each frame's own
    line, for lines that keep different windows: one for people 1.6x as tall as the clip's, the
    clip's fitted line, and none."""
    from torchtrack.data import demo_clip_path
    from torchtrack.io.video import open_source
    from torchtrack.track.multi import GROUND_LAG

    with open_source(demo_clip_path()) as src:
        frames = [f for _, f in itertools.islice(src.items(), GROUND_LAG + 4)]
    mt = make()
    for f in frames:
        mt.update(f)
    fitted = mt.ground.line_
    assert fitted is not None
    tall = fitted._replace(a=1.6 * fitted.a, b=1.6 * fitted.b)
    batch = torch.stack([frames[-1], frames[-2], frames[-3]])
    lines = [tall, fitted, None]
    got = mt.detect_batch(batch, lines)
    alone = [mt.detect(f, line) for f, line in zip(batch, lines, strict=True)]
    for (a, pa), (b, pb) in zip(alone, got, strict=True):
        assert torch.equal(a, b) and torch.equal(pa, pb)
    # the lines matter: the tall people's line keeps other detections than none on that frame
    assert not torch.equal(alone[0][0], mt.detect(frames[-1], None)[0])
