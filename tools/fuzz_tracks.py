"""Random track streams through the multi-target post-processing, and random detection files
through the whole command: what a test's few hand-made cases do not reach.

* ``--streams N``: N random streams of reported frames (people walking in and out, hidden
  frames, untracked frames, identities the tracker swapped between two people, a camera
  offset, detections with false ones) through :class:`~torchtrack.track.smoothing.TrackSmoother`
  with a random setting of ``smooth_sigma``, ``fill_gaps``, ``backfill``, ``backfill_iou`` and
  ``unswap`` (the identity repair). Each must give every frame back once and in order, no
  identity twice on a frame, finite boxes, and no exception. Trial ``t`` is seeded by ``t``
  alone, so a failure is replayed with ``--first t --streams 1``.
* ``--detections N``: N random MOT detection files (boxes half outside the frame, 1x1 and
  900 px boxes, duplicates, scores above 1, dozens of false boxes a frame, rows beyond the last
  frame) through ``torchtrack track FRAMES --detections FILE`` on the first frames of
  TUD-Stadtmitte, with a random ``multi:`` setting: each must exit 0 without a traceback.

Usage::

    python tools/fuzz_tracks.py --streams 1500            # ~1 minute
    python tools/fuzz_tracks.py --detections 60           # ~3 minutes

Found so far: a KeyError in the identity repair when a swap dropped encounters judged on the
same frame (trials 23, 65, 278, 493 and 500 of the first 600 ``--streams``; fixed, and
``tests/track/test_fuzz_tracks.py`` replays them).
Nothing is timed.
"""

from __future__ import annotations

import argparse
import random
import subprocess
import sys
import tempfile
import traceback
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from torchtrack.track.multi import MultiState  # noqa: E402
from torchtrack.track.smoothing import TrackSmoother  # noqa: E402

SETTINGS = {
    "sigma": (0, 1, 4),
    "fill_gaps": (0, 3, 10),
    "backfill": (0, 5, 26),
    "backfill_iou": (0.3, 0.5),
    "unswap": (0, 3, 10),
}


def random_stream(rng: random.Random, n_frames: int):
    """``(frame, state or None, detections or None)`` for ``n_frames`` frames."""
    people: dict[int, list[float]] = {}
    next_id = 1
    for t in range(n_frames):
        if rng.random() < 0.15 and len(people) < 8:
            people[next_id] = [
                rng.uniform(0, 300), rng.uniform(50, 200), rng.uniform(-4, 4), rng.uniform(20, 80)
            ]  # fmt: skip
            next_id += 1
        for k in list(people):
            if rng.random() < 0.03:
                del people[k]
        rows = []
        for k, p in people.items():
            p[0] += p[2] + rng.gauss(0, 1)
            if rng.random() < 0.1:  # hidden on this frame
                continue
            rows.append((k, p[0], p[1], p[3]))
        if rng.random() < 0.05:  # a frame that was not tracked
            yield t, None, None
            continue
        if rng.random() < 0.05 and len(rows) >= 2:  # the tracker swapped two people
            a, b = rng.sample(range(len(rows)), 2)
            ra, rb = rows[a], rows[b]
            rows[a], rows[b] = (rb[0], *ra[1:]), (ra[0], *rb[1:])
        n = len(rows)
        state = MultiState(
            torch.tensor([r[0] for r in rows], dtype=torch.int64),
            torch.tensor([[r[1], r[2], r[3] * 0.4, r[3]] for r in rows], dtype=torch.float64)
            .reshape(-1, 4),
            torch.full((n,), 0.9, dtype=torch.float64),
            torch.tensor([rng.random() < 0.8 for _ in range(n)], dtype=torch.bool),
        )  # fmt: skip
        db = [[p[0] + rng.gauss(0, 2), p[1], p[3] * 0.4, p[3]] for p in people.values()]
        db += [[rng.uniform(0, 300), rng.uniform(0, 200), 20, 50] for _ in range(rng.randint(0, 3))]
        dets = (
            torch.tensor(db, dtype=torch.float64).reshape(-1, 4),
            torch.tensor([rng.random() for _ in db], dtype=torch.float64),
        )
        yield t, state, dets


def stream_trial(trial: int) -> str | None:
    """One random stream through a randomly set smoother: None, or what went wrong."""
    rng = random.Random(trial)
    kw = {k: rng.choice(v) for k, v in SETTINGS.items()}
    n_frames = rng.randint(5, 200)
    smoother = TrackSmoother(**kw)
    out = []
    try:
        for t, state, dets in random_stream(rng, n_frames):
            out += smoother.push(t, state, offset=(rng.uniform(-2, 2), 0.0), detections=dets)
        out += smoother.flush()
    except Exception:  # any exception is the finding
        return f"trial {trial} {kw}:\n{traceback.format_exc()}"
    if [i for i, _ in out] != list(range(n_frames)):
        return f"trial {trial} {kw}: frames out of order, lost or given twice"
    for i, s in out:
        if s is not None and len(s):
            if s.ids.unique().numel() != s.ids.numel():
                return f"trial {trial} {kw}: an identity twice on frame {i}"
            if not bool(torch.isfinite(s.boxes).all()):
                return f"trial {trial} {kw}: a non-finite box on frame {i}"
    return None


def detections_trial(trial: int, frames: Path, tmp: Path) -> str | None:
    """One random detection file through ``torchtrack track``: None, or what went wrong."""
    rng = random.Random(1000 + trial)
    width, height = 640, 480
    n_frames = rng.randint(2, 40)
    people = [
        [rng.uniform(-50, width), rng.uniform(-50, height), rng.uniform(-8, 8), rng.uniform(5, 400)]
        for _ in range(rng.randint(0, 12))
    ]
    rows = []
    for f in range(1, n_frames + 1 + rng.choice([0, 0, 5])):  # some rows past the last frame
        for p in people:
            p[0] += p[2]
            if rng.random() < 0.8:
                h = p[3] * rng.uniform(0.9, 1.1)
                conf = rng.choice([rng.random(), rng.uniform(0, 100), 1.0])
                rows.append((f, p[0] + rng.gauss(0, 3), p[1], h * 0.4, h, conf))
                if rng.random() < 0.2:  # a duplicate
                    rows.append((f, p[0] + 2, p[1] + 2, h * 0.4, h, rng.random()))
        for _ in range(rng.choice([0, 1, 3, 50])):
            rows.append(
                (f, rng.uniform(-100, width), rng.uniform(-100, height),
                 rng.choice([1, 3, 30, 700]), rng.choice([1, 3, 80, 900]), rng.random())
            )  # fmt: skip
    det = tmp / f"det_{trial}.txt"
    det.write_text(
        "".join(f"{r[0]},-1,{r[1]:.2f},{r[2]:.2f},{r[3]:.2f},{r[4]:.2f},{r[5]:.4f},-1,-1,-1\n" for r in rows)
    )  # fmt: skip
    extra = rng.choice(
        [[], ["multi:unswap=3"], ["multi:backfill=0,fill_gaps=0"], ["multi:max_targets=2"],
         ["multi:smooth_sigma=0"]]
    )  # fmt: skip
    cmd = [
        sys.executable, "-m", "torchtrack", "track", str(frames), "--detections", str(det),
        "--max-frames", str(n_frames), "--mot", str(tmp / f"out_{trial}.txt"), "--no-progress",
        "-q", "--seed", str(trial), *(["--tracker", *extra] if extra else []),
    ]  # fmt: skip
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    if p.returncode != 0 or "Traceback" in p.stderr:
        return f"trial {trial} rc {p.returncode}: {' '.join(cmd)}\n{p.stderr[-3000:]}"
    return None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--streams", type=int, default=0, help="random smoother streams to run")
    ap.add_argument("--detections", type=int, default=0, help="random detection files to run")
    ap.add_argument("--first", type=int, default=0, help="first trial number")
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    args = ap.parse_args(argv)
    if args.streams <= 0 and args.detections <= 0:
        ap.error("give --streams N and/or --detections N")
    failed = 0
    for t in range(args.first, args.first + max(args.streams, 0)):
        why = stream_trial(t)
        if why:
            failed += 1
            print(why)
    if args.detections > 0:
        frames = args.data / "mot" / "TUD-Stadtmitte" / "img1"
        if not frames.is_dir():
            ap.error(f"{frames} does not exist (--data)")
        with tempfile.TemporaryDirectory() as tmp:
            for t in range(args.first, args.first + args.detections):
                why = detections_trial(t, frames, Path(tmp))
                if why:
                    failed += 1
                    print(why)
    print(f"{failed} failed of {max(args.streams, 0) + max(args.detections, 0)} trials")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
