"""Cut the demo clip shipped in ``torchtrack/data/`` from the PETS 2009 S2.L1 video.

    python tools/make_demo_clip.py                       # frames 600..669 (7 s at 10 fps)
    python tools/make_demo_clip.py --start 500 --frames 60 --out /tmp/clip.mp4

Reads ``../shared/data/videos/pets2009_s2l1_vtest/vtest.avi`` (480x360, 10 fps, 795 frames),
keeps ``--frames`` consecutive frames from ``--start`` at their own size and rate, and writes
them with OpenCV's ``mp4v`` fourcc (MPEG-4 Part 2: the codec opencv-python-headless can write;
``avc1``/H.264 are not available in its wheels). The file is written atomically and must stay
under 1 MB. Frames 600-669 show five to eight walkers, 35-90 px tall, the nearest one
crossing the lawn towards the camera.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2

from torchtrack.errors import VideoError
from torchtrack.io.atomic import atomic_path

REPO = Path(__file__).resolve().parents[1]
SOURCE = REPO.parent / "shared/data/videos/pets2009_s2l1_vtest/vtest.avi"


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--source", type=Path, default=SOURCE)
    ap.add_argument("--start", type=int, default=600, help="first frame (0-based)")
    ap.add_argument("--frames", type=int, default=70, help="number of frames")
    ap.add_argument("--out", type=Path, default=REPO / "torchtrack/data/pets2009_s2l1_demo.mp4")
    ap.add_argument("--max-bytes", type=int, default=1_000_000)
    args = ap.parse_args()
    cap = cv2.VideoCapture(str(args.source))
    if not cap.isOpened():
        raise VideoError(f"cannot open {args.source}")
    fps = cap.get(cv2.CAP_PROP_FPS) or 10.0
    w = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
    h = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    # Decode from the start: seeking in H.264 AVI is not frame-exact in every OpenCV build.
    for i in range(args.start):
        if not cap.read()[0]:
            raise VideoError(f"{args.source} ends at frame {i}, before --start {args.start}")
    with atomic_path(args.out, suffix=".mp4") as tmp:
        wr = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
        if not wr.isOpened():
            raise VideoError("OpenCV cannot write mp4v video here")
        n = 0
        for _ in range(args.frames):
            ok, frame = cap.read()
            if not ok:
                break
            wr.write(frame)
            n += 1
        wr.release()
        size = tmp.stat().st_size
        if size > args.max_bytes:
            raise SystemExit(f"clip is {size} bytes, over --max-bytes {args.max_bytes}")
    cap.release()
    print(
        f"wrote {args.out}: frames {args.start}..{args.start + n - 1} of {args.source.name}, "
        f"{w}x{h} at {fps:g} fps, {size} bytes"
    )


if __name__ == "__main__":
    main()
