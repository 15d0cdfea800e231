"""The README's picture: every pedestrian of the bundled clip tracked by the multi-target
tracker (the README's main job), one frame drawn with each identity's colour and trail.

    python tools/make_readme_frame.py                       # docs/images/tracked_frame.png
    python tools/make_readme_frame.py --frame 60 --seed 0 --out docs/images/tracked_frame.png

The same tracker, config, smoothing and drawing as ``torchtrack track demo --video tracked.mp4``
(:class:`torchtrack.track.multi.MultiTargetTracker` with its defaults, its reports through
:meth:`~torchtrack.track.multi.MultiTargetTracker.smoother`,
``torchtrack.cli._track_io.draw_multi``); the frame is written atomically.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from torchtrack.cli._track_io import Trails, draw_multi  # noqa: E402
from torchtrack.data import demo_clip_path  # noqa: E402
from torchtrack.io.atomic import write_bytes_atomic  # noqa: E402
from torchtrack.io.video import open_source  # noqa: E402
from torchtrack.track.multi import MultiTargetTracker  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frame", type=int, default=60, help="0-based frame to draw (default 60)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "images" / "tracked_frame.png")
    args = ap.parse_args()
    tracker = MultiTargetTracker(generator=torch.Generator().manual_seed(args.seed))
    smoother = tracker.smoother()  # the reported tracks, as the command writes them
    trails = Trails()
    img = None
    frames: dict[int, torch.Tensor] = {}

    def draw(j: int, out) -> torch.Tensor | None:
        frame = frames.pop(j)  # held only until written
        if out is None:
            return None
        trails.add(j, out)
        if j != args.frame:
            return None
        print(f"frame {j}: {len(out)} targets, identities {out.ids.tolist()}")
        return draw_multi(frame, out, trails)

    with open_source(demo_clip_path()) as src:
        for i, frame in src.items():
            frames[i] = frame
            out = tracker.update(frame) if frame is not None else None
            for j, o in smoother.push(i, out, offset=tracker.camera_offset):
                img = draw(j, o) if img is None else img
            if img is not None:
                break
        if img is None:
            for j, o in smoother.flush():
                img = draw(j, o) if img is None else img
    if img is None:
        raise SystemExit(f"the clip has no frame {args.frame}")
    ok, png = cv2.imencode(".png", img)
    if not ok:
        raise SystemExit("PNG encoding failed")
    write_bytes_atomic(args.out, png.tobytes())
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
