"""TrackSmoother: the stream equals filling the gaps and smoothing each whole track afterwards
(SciPy's gaussian_filter1d), frames come out in order and ``lag`` late, memory stays bounded."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter1d

from torchtrack.errors import BoxError, ConfigError, TrackerError
from torchtrack.track.config import MultiTrackerConfig, apply_overrides
from torchtrack.track.multi import MultiState
from torchtrack.track.smoothing import TrackSmoother, gaussian_weights


def _tracks(seed: int, n_frames: int = 120, n_ids: int = 5):
    """Random tracks with gaps of 1-12 frames: ``{id: {frame: (x, y, w, h, conf, det)}}``."""
    rng = np.random.default_rng(seed)
    out = {}
    for k in range(1, n_ids + 1):
        start, end = sorted(rng.integers(0, n_frames, 2))
        rows, f = {}, int(start)
        x, y, w, h = rng.uniform(0, 400), rng.uniform(0, 300), rng.uniform(10, 40), 0
        h = 3 * w
        while f <= end:
            if rng.random() < 0.1:  # a gap
                f += int(rng.integers(1, 13))
                continue
            x, y = x + rng.normal(0, 3), y + rng.normal(0, 2)
            w, h = w * np.exp(rng.normal(0, 0.05)), h * np.exp(rng.normal(0, 0.05))
            rows[f] = (x, y, w, h, float(rng.uniform(0.5, 1)), bool(rng.random() < 0.7))
            f += 1
        if rows:
            out[k] = rows
    return out


def _states(tracks, n_frames):
    for f in range(n_frames):
        ks = [k for k in sorted(tracks) if f in tracks[k]]
        r = [tracks[k][f] for k in ks]
        yield (
            f,
            MultiState(
                torch.tensor(ks, dtype=torch.int64),
                torch.tensor([v[:4] for v in r], dtype=torch.float64).reshape(-1, 4),
                torch.tensor([v[4] for v in r], dtype=torch.float64),
                torch.tensor([v[5] for v in r], dtype=torch.bool),
            ),
        )


def _local_linear_reference(v: np.ndarray, sigma: float) -> np.ndarray:
    """Each row: the intercept of a weighted line fit (numpy.polyfit, Gaussian weights of sd
    ``sigma`` within ``int(4 sigma + 0.5)`` rows, the run's rows only)."""
    r, n = int(4 * sigma + 0.5), len(v)
    out = np.empty_like(v)
    for t in range(n):
        lo, hi = max(0, t - r), min(n - 1, t + r)
        k = np.arange(lo, hi + 1) - t
        if hi == lo:
            out[t] = v[t]
            continue
        w = np.exp(-0.5 * (k / sigma) ** 2)
        out[t] = np.polyfit(k, v[lo : hi + 1], 1, w=np.sqrt(w))[1]
    return out


def _offline(tracks, sigma: float, fill: int):
    """The reference: per identity, gaps of <= fill frames interpolated linearly (centre and
    log-size), then each run of consecutive frames smoothed by a local-linear Gaussian fit."""
    out = {}
    for k, rows in tracks.items():
        fr = sorted(rows)
        c = {
            f: np.array(
                [
                    rows[f][0] + rows[f][2] / 2,
                    rows[f][1] + rows[f][3] / 2,
                    np.log(rows[f][2]),
                    np.log(rows[f][3]),
                ]
            )
            for f in fr
        }
        for a, b in itertools.pairwise(fr):
            if 1 < b - a <= fill + 1:
                for u in range(a + 1, b):
                    c[u] = c[a] + (c[b] - c[a]) * (u - a) / (b - a)
        allf = sorted(c)
        runs, cur = [], [allf[0]]
        for f in allf[1:]:
            if f == cur[-1] + 1:
                cur.append(f)
            else:
                runs.append(cur)
                cur = [f]
        runs.append(cur)
        for run in runs:
            v = np.stack([c[f] for f in run])
            if sigma > 0:
                v = _local_linear_reference(v, sigma)
            for f, row in zip(run, v, strict=True):
                w, h = np.exp(row[2]), np.exp(row[3])
                out[(f, k)] = np.array([row[0] - w / 2, row[1] - h / 2, w, h])
    return out


@pytest.mark.parametrize("sigma, fill", [(2.0, 0), (0.0, 5), (4.0, 10), (1.5, 3)])
@pytest.mark.parametrize("seed", [0, 1])
def test_stream_equals_offline_smoothing(sigma, fill, seed):
    n = 150
    tracks = _tracks(seed, n)
    sm = TrackSmoother(sigma, fill)
    assert sm.lag == int(4 * sigma + 0.5) * (sigma > 0) + fill
    got, order = {}, []
    for f, st in _states(tracks, n):
        out = sm.push(f, st)
        for t, _ in out:
            assert t + sm.lag <= f  # never earlier than the lag allows
        for t, s in out + ([] if f < n - 1 else sm.flush()):
            order.append(t)
            for k, b, d in zip(s.ids.tolist(), s.boxes, s.detected.tolist(), strict=True):
                got[(t, k)] = (b.numpy(), d)
    assert order == list(range(n))  # every frame once, in order
    ref = _offline(tracks, sigma, fill)
    assert set(got) == set(ref)
    for key, (b, d) in got.items():
        np.testing.assert_allclose(b, ref[key], rtol=1e-9, atol=1e-9)
        if key[1] not in tracks or key[0] not in tracks[key[1]]:
            assert d is False  # a filled frame is never "detected"
    # a filled gap exists in these draws, and it was filled
    if fill:
        assert any(key[0] not in tracks[key[1]] for key in got)


def test_inactive_and_unreadable_frames():
    assert not TrackSmoother(0.0, 0).active
    assert not TrackSmoother(0.1, 0).active  # a kernel of one frame changes nothing
    sm = TrackSmoother(1.0, 2)
    box = torch.tensor([[10.0, 20.0, 8.0, 24.0]], dtype=torch.float64)
    st = MultiState(torch.tensor([1]), box, torch.tensor([0.9]), torch.tensor([True]))
    out = sm.push(0, st) + sm.push(1, None) + sm.push(2, st) + sm.flush()
    assert [t for t, _ in out] == [0, 1, 2]
    assert out[1][1] is None  # an unreadable frame stays without rows
    torch.testing.assert_close(out[0][1].boxes, box)  # a constant track stays where it is
    with pytest.raises(TrackerError, match="increasing order"):
        sm.push(2, st)
    # inactive: each frame comes back at once, the same state
    off = TrackSmoother(0.0, 0)
    assert off.push(0, st) == [(0, st)] and off.push(1, None) == [(1, None)]
    assert off.push(2, st)[0][1] is st and off.flush() == []
    with pytest.raises(TrackerError, match="increasing order"):
        off.push(2, st)


def test_memory_stays_bounded():
    sm = TrackSmoother(4.0, 10, backfill=26)
    box = torch.tensor([[10.0, 20.0, 8.0, 24.0]], dtype=torch.float64)
    dets = (box.clone(), torch.tensor([0.99], dtype=torch.float64))
    for f in range(2000):
        st = MultiState(torch.tensor([f // 50]), box, torch.tensor([0.9]), torch.tensor([True]))
        sm.push(f, st, detections=dets)
        held = sum(o[1].numel() for o in sm._obs)  # one target a frame here
        assert held <= 2 * sm.lag + 2 and len(sm._pending) <= sm.lag + 1
        assert len(sm._dets) <= sm.lag + 1  # detections of the unwritten frames only


def test_inside_a_run_it_is_the_gaussian_mean_and_a_walk_keeps_its_place():
    """Far from a run's ends the fit is SciPy's Gaussian filter; at the ends a target moving
    at constant speed is not pulled back (the Gaussian with repeated ends lags ~0.4 sigma v)."""
    sm = TrackSmoother(2.0, 0)
    rng = np.random.default_rng(0)
    x = 100 + 4.0 * np.arange(60) + rng.normal(0, 2, 60)
    got = {}
    for f in range(60):
        box = torch.tensor([[x[f] - 10, 50.0, 20.0, 60.0]], dtype=torch.float64)
        st = MultiState(torch.tensor([1]), box, torch.tensor([1.0]), torch.tensor([True]))
        for t, s in sm.push(f, st) + (sm.flush() if f == 59 else []):
            got[t] = float(s.boxes[0, 0] + 10)
    ref = gaussian_filter1d(x, 2.0, mode="nearest", truncate=4.0)
    inner = range(sm.radius, 60 - sm.radius)
    np.testing.assert_allclose([got[t] for t in inner], ref[list(inner)], rtol=1e-12)
    truth = 100 + 4.0 * np.arange(60)
    assert abs(got[59] - truth[59]) < 3 < abs(ref[59] - truth[59])  # the end keeps up


def test_weights_are_scipys():
    x = np.zeros(41)
    x[20] = 1.0
    ref = gaussian_filter1d(x, 3.0, mode="constant", truncate=4.0)[8:33]
    np.testing.assert_allclose(gaussian_weights(3.0).numpy(), ref, rtol=1e-12)


@pytest.mark.parametrize(
    "kv, msg",
    [
        ({"fill_gaps": -1}, "fill_gaps"),
        ({"fill_gaps": 2.5}, "integer"),
        ({"smooth_sigma": float("nan")}, "smooth_sigma"),
        ({"smooth_sigma": -1.0}, "smooth_sigma"),
        ({"smooth_sigma": 1e9}, "smooth_sigma"),
    ],
)
def test_config_refuses_bad_values(kv, msg):
    with pytest.raises(ConfigError, match=msg):
        apply_overrides(MultiTrackerConfig(), kv)


@pytest.mark.parametrize("sigma, fill", [(-1.0, 0), (float("inf"), 0), (0.0, -1), (0.0, 1.5)])
def test_smoother_refuses_bad_values(sigma, fill):
    with pytest.raises(ConfigError):
        TrackSmoother(sigma, fill)


def test_a_panning_camera_is_taken_out_before_smoothing():
    """A person still in the scene, filmed by a camera that pans right and back at 6 px a
    frame: with the camera's offset (as the tracker reports it) the smoothed box stays on the
    person through each turn; without it the turns are smoothed into the box."""
    pan = np.concatenate([np.arange(0, 120, 6), np.arange(120, 0, -6)] * 3).astype(float)
    truth = 200.0 + pan  # where the frame shows the person
    got = {True: {}, False: {}}
    for with_offset in (True, False):
        sm = TrackSmoother(4.0, 10)
        for f, x in enumerate(truth):
            box = torch.tensor([[x - 10, 50.0, 20.0, 60.0]], dtype=torch.float64)
            st = MultiState(torch.tensor([1]), box, torch.tensor([1.0]), torch.tensor([True]))
            off = (float(pan[f]), 0.0) if with_offset else (0.0, 0.0)
            done = sm.push(f, st, offset=off)
            for t, s in done + (sm.flush() if f == len(truth) - 1 else []):
                got[with_offset][t] = float(s.boxes[0, 0] + 10)
    err = {k: max(abs(v[t] - truth[t]) for t in v) for k, v in got.items()}
    assert err[True] < 1e-9 and err[False] > 10


def _one(ident: int, box, conf: float = 0.9) -> MultiState:
    return MultiState(
        torch.tensor([ident]),
        torch.tensor([box], dtype=torch.float64),
        torch.tensor([conf], dtype=torch.float64),
        torch.tensor([True]),
    )


def _dets(*boxes, p: float = 0.97):
    b = torch.tensor(boxes, dtype=torch.float64).reshape(-1, 4)
    return b, torch.full((len(b),), p, dtype=torch.float64)


def test_backfill_extends_a_new_identity_back_through_its_detections():
    """A person walking right at 3 px a frame is detected from frame 2 but first reported at
    frame 8 (confirmed late): backfill gives its identity the boxes of frames 2-7 from those
    detections; a second person's detections (reported all along as id 1) and a detection far
    away stay out; without backfill the track starts at frame 8."""

    def walker(f):
        return [100.0 + 3 * f, 50.0, 20.0, 60.0]

    def other(f):
        return [300.0 - 2 * f, 52.0, 20.0, 60.0]

    got = {}
    for bf in (0, 10):
        sm = TrackSmoother(0.0, 0, backfill=bf) if bf else TrackSmoother(0.0, 1)
        out = []
        for f in range(20):
            ids, boxes = [1], [other(f)]
            if f >= 8:
                ids.append(2)
                boxes.append(walker(f))
            st = MultiState(
                torch.tensor(ids),
                torch.tensor(boxes, dtype=torch.float64),
                torch.full((len(ids),), 0.9, dtype=torch.float64),
                torch.ones(len(ids), dtype=torch.bool),
            )
            d = [other(f), [10.0, 200.0, 20.0, 60.0]] + ([walker(f)] if f >= 2 else [])
            out += sm.push(f, st, detections=_dets(*d))
        out += sm.flush()
        got[bf] = {t: dict(zip(s.ids.tolist(), s.boxes.tolist(), strict=True)) for t, s in out}
    assert [t for t in got[0] if 2 in got[0][t]] == list(range(8, 20))
    assert [t for t in got[10] if 2 in got[10][t]] == list(range(2, 20))
    for t in range(2, 8):
        np.testing.assert_allclose(got[10][t][2], walker(t))
        assert sorted(got[10][t]) == [1, 2]  # nobody took the far detection
    assert all(sorted(got[10][t]) == [1] for t in (0, 1))


def test_backfill_stops_at_a_gap_and_does_not_take_another_identitys_detection():
    """The chain back in time skips at most two scanned frames without a detection that fits,
    does not reach frames already written, and leaves a detection an older identity's box
    covers to that identity."""
    box = [100.0, 50.0, 20.0, 60.0]
    sm = TrackSmoother(0.0, 0, backfill=12)
    out = []
    for f in range(16):
        st = (
            _one(2, box)
            if f >= 12
            else MultiState(
                torch.zeros(0, dtype=torch.int64),
                torch.zeros((0, 4), dtype=torch.float64),
                torch.zeros(0, dtype=torch.float64),
                torch.zeros(0, dtype=torch.bool),
            )
        )
        # detections on frames 9-11 and 2-5; none on 6-8 (three scans in a row: the chain stops)
        d = _dets(box) if (9 <= f <= 11 or 2 <= f <= 5) else _dets()
        out += sm.push(f, st, detections=d)
    out += sm.flush()
    have = [t for t, s in out if s is not None and 2 in s.ids.tolist()]
    assert have == list(range(9, 16))
    # an older identity's box over the detection: not taken
    sm = TrackSmoother(0.0, 0, backfill=5)
    out = []
    for f in range(8):
        st = (
            _one(1, box)
            if f < 6
            else MultiState(
                torch.tensor([1, 2]),
                torch.tensor([box, [160.0, 50.0, 20.0, 60.0]], dtype=torch.float64),
                torch.tensor([0.9, 0.9], dtype=torch.float64),
                torch.tensor([True, True]),
            )
        )
        out += sm.push(f, st, detections=_dets(box, [160.0, 50.0, 20.0, 60.0] if f >= 6 else box))
    out += sm.flush()
    assert [t for t, s in out if 2 in s.ids.tolist()] == [6, 7]


def test_backfill_refuses_bad_values():
    with pytest.raises(ConfigError, match="backfill"):
        TrackSmoother(0.0, 0, backfill=-1)
    with pytest.raises(ConfigError, match="backfill_iou"):
        TrackSmoother(0.0, 0, backfill=3, backfill_iou=0.0)
    with pytest.raises(ConfigError, match="backfill"):
        apply_overrides(MultiTrackerConfig(), {"backfill": -2})
    with pytest.raises(ConfigError, match="backfill_iou"):
        apply_overrides(MultiTrackerConfig(), {"backfill_iou": 1.5})
    assert TrackSmoother(0.0, 0, backfill=7).lag == 7  # the output waits for the chain


def test_backfill_covers_a_gap_an_identity_comes_back_from_with_its_detections():
    """Identity 1 reported on frames 0-5 and again from frame 20 (a 14-frame gap, longer than
    fill_gaps): the detections on its way through frames 8-19 join it, and the chain stops at
    frame 7, where the detections stop (frames 6-7 stay a gap: more than fill_gaps frames
    would need filling); with backfill off the gap stays."""

    def box(f):
        return [100.0 + 2 * f, 50.0, 20.0, 60.0]

    for bf, want in (
        (0, list(range(0, 6)) + list(range(20, 30))),
        (26, [*range(0, 6), *range(8, 30)]),
    ):
        sm = TrackSmoother(0.0, 1, backfill=bf)
        out = []
        for f in range(30):
            st = _one(1, box(f)) if (f < 6 or f >= 20) else None
            st = (
                st
                if st is not None
                else MultiState(
                    torch.zeros(0, dtype=torch.int64),
                    torch.zeros((0, 4), dtype=torch.float64),
                    torch.zeros(0, dtype=torch.float64),
                    torch.zeros(0, dtype=torch.bool),
                )
            )
            d = _dets(box(f)) if f >= 8 else _dets()
            out += sm.push(f, st, detections=d)
        out += sm.flush()
        got = [t for t, s in out if 1 in s.ids.tolist()]
        assert got == want, bf


def test_bad_settings_indices_and_boxes_are_refused():
    """sigma=True smoothed over a sd of 1 frame and backfill_iou=True took 1.0; a string or
    None sigma / backfill_iou and a None, inf or NaN fill_gaps / backfill were TypeError,
    OverflowError or ValueError tracebacks; sigma=1e9 tried to allocate a 64 GB kernel. A
    frame pushed out of order was a plain ValueError, a frame index True was frame 1, and a
    NaN box spread NaN over every smoothed box of its identity within the kernel's reach."""
    for kw in ({"sigma": True}, {"sigma": "1"}, {"sigma": None}, {"sigma": 1e9}):
        with pytest.raises(ConfigError, match=r"sigma must be a finite number in \[0, 250"):
            TrackSmoother(**kw)
    with pytest.raises(ConfigError, match="sigma must be"):
        gaussian_weights(float("nan"))
    for kw in ({"fill_gaps": None}, {"fill_gaps": float("inf")}, {"backfill": float("nan")}):
        with pytest.raises(ConfigError, match=r"must be a whole number in \[0, 1000\]"):
            TrackSmoother(**kw)
    for bad in (True, "0.5", None):
        with pytest.raises(ConfigError, match=r"backfill_iou must be a number in \(0, 1\]"):
            TrackSmoother(backfill_iou=bad)
    assert TrackSmoother(sigma=2, fill_gaps=3.0).fill_gaps == 3  # whole floats still taken
    sm = TrackSmoother(1.0, 2)
    with pytest.raises(TrackerError, match="the frame index must be an integer, got True"):
        sm.push(True, None)
    box = torch.tensor([[float("nan"), 20.0, 8.0, 24.0]], dtype=torch.float64)
    st = MultiState(torch.tensor([7]), box, torch.tensor([0.9]), torch.tensor([True]))
    with pytest.raises(BoxError, match=r"frame 0, identity 7: box .* must be finite"):
        sm.push(0, st)
