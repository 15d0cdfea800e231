"""Scale: does the box grow and shrink with a target whose size changes 3x? (issue 13, point 3)

A real frame (the first of a tracking sequence) is zoomed about its target's centre, the zoom
rising geometrically from 1 to ``--zoom`` over ``--frames`` frames (``in``: the target grows)
or falling from ``--zoom`` to 1 (``out``: it shrinks), with OpenCV's bilinear warp and
reflected borders. The ground truth is the first box zoomed with the frame. Every tracker is
initialised on the first frame and run to the end; the table gives its mean IoU, the IoU over
the last 20 frames, and the final box's size over the target's (``sqrt(w h)`` ratio: 1 = the
box followed the 3x change, 1/3 or 3 = it kept its first size), mean (min-max) over seeds.
Nothing is timed.

The cases are dev targets whose box zoomed 3x stays inside the frame (a box cut by the border
would not measure scale). A tracker that fails (an OpenCV peer that cannot initialise) is
reported as such in its row.

    python tools/bench_zoom.py --trackers adaptive-haar cotrain csrt --seeds 0 1 2
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("TORCHTRACK_DATA", REPO.parent / "shared" / "data"))
# (sequence under DATA/tracking, direction): dev targets whose 3x box stays inside the frame
CASES = (
    ("otb/David", "in"),
    ("otb/Freeman1", "in"),
    ("otb/Surfer", "in"),
    ("otb/David", "out"),
    ("otb/RedTeam", "out"),
    ("otb/DragonBaby", "out"),
)


def zoom_sequence(frame: np.ndarray, box, zoom: float, n: int, direction: str):
    """``n`` frames (``(3, H, W)`` uint8 tensors) of ``frame`` (``H, W, 3``) zoomed about the
    box centre, and their ``(n, 4)`` float64 boxes."""
    import cv2

    h, w = frame.shape[:2]
    x, y, bw, bh = (float(v) for v in box)
    cx, cy = x + bw / 2, y + bh / 2
    if (
        min(cx - zoom * bw / 2, cy - zoom * bh / 2) < 0
        or cx + zoom * bw / 2 > w
        or cy + zoom * bh / 2 > h
    ):
        raise ValueError(f"the box {box} zoomed {zoom}x leaves the {w}x{h} frame")
    frames, boxes = [], []
    for t in range(n):
        u = t / (n - 1)
        s = zoom**u if direction == "in" else zoom ** (1 - u)
        m = np.array([[s, 0, cx - s * cx], [0, s, cy - s * cy]], dtype=np.float64)
        img = cv2.warpAffine(
            frame, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
        )
        frames.append(torch.from_numpy(img).permute(2, 0, 1).contiguous())
        boxes.append([cx - s * bw / 2, cy - s * bh / 2, s * bw, s * bh])
    return frames, torch.tensor(boxes, dtype=torch.float64)


def run_tracker(spec: str, frames, boxes, seed: int) -> dict[str, float]:
    """Mean IoU, last-20 IoU and the final size ratio of one run of ``spec``."""
    from torchtrack.boxes import box_iou
    from torchtrack.track.base import create_tracker, parse_tracker_spec

    name, params = parse_tracker_spec(spec)
    torch.manual_seed(seed)
    tracker = create_tracker(name, **params)
    tracker.init(frames[0], boxes[0])
    out = [boxes[0]]
    for f in frames[1:]:
        out.append(torch.as_tensor(tracker.update(f).box, dtype=torch.float64).reshape(4))
    est = torch.stack(out)
    iou = box_iou(est.float(), boxes.float())
    ratio = math.sqrt(float(est[-1, 2] * est[-1, 3]) / float(boxes[-1, 2] * boxes[-1, 3]))
    return {"iou": float(iou[1:].mean()), "last": float(iou[-20:].mean()), "ratio": ratio}


def case_frames(path: str, zoom: float, n: int, direction: str):
    from torchtrack.io.sequences import load_sequence

    seq = load_sequence(DATA / "tracking" / path)[0]
    with seq.open() as src:
        first = next(iter(src)).permute(1, 2, 0).numpy()
    return seq.name, *zoom_sequence(first, seq.boxes[0].tolist(), zoom, n, direction)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trackers", nargs="+", default=["adaptive-haar", "cotrain"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--zoom", type=float, default=3.0)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    from torchtrack.errors import TorchTrackError

    torch.set_num_threads(args.threads)
    print(
        f"{args.zoom:g}x zoom over {args.frames} frames, seeds {args.seeds}; mean (min-max) over "
        "seeds\n\n| sequence | zoom | tracker | mean IoU | IoU, last 20 frames | final size / "
        "target size |\n|---|---|---|---|---|---|"
    )
    for path, direction in CASES:
        name, frames, boxes = case_frames(path, args.zoom, args.frames, direction)
        for spec in args.trackers:
            try:
                runs = [run_tracker(spec, frames, boxes, s) for s in args.seeds]
            except TorchTrackError as exc:
                print(f"| {name} | {direction} | {spec} | failed: {exc} | | |", flush=True)
                continue

            def cell(key: str, runs=runs) -> str:
                v = [r[key] for r in runs]
                if len(v) == 1 or max(v) - min(v) < 5e-4:
                    return f"{v[0]:.2f}"
                return f"{statistics.mean(v):.2f} ({min(v):.2f}-{max(v):.2f})"

            print(
                f"| {name} | {direction} | {spec} | {cell('iou')} | {cell('last')} | "
                f"{cell('ratio')} |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
