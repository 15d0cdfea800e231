"""Single-target sequences cut from MOT ground truth: a held-out set for the trackers.

Every ground-truth track of a MOTChallenge sequence becomes one single-target sequence in the
``frames/ + groundtruth.csv`` layout that ``torchtrack eval --sequences`` reads. None of the
single-object trackers' defaults were chosen on these videos (they were chosen on the OTB and
BoBoT dev set), so this is video nobody tuned them on: small pedestrians (PETS09-S2L1 people
are 20-60 px tall in the 480x360 video) walking behind a sign and each other, and TUD's crowd.

The rules, fixed before any tracker was run on the output:

* rows with ``conf == 0`` are not targets (MOT15's ignore rows) and are skipped;
* a track starts at its first frame whose box lies inside the frame and overlaps no other
  ground-truth box (IoU < ``--max-iou``, 0.1): the box of frame 1 is what ``torchtrack eval``
  gives the tracker, so it must show the target alone;
* it ends at the track's last ground-truth row; frames without a row in between are absent;
* it is kept when it has at least ``--min-frames`` (50) frames with a box.

PETS09-S2L1's frames are the shared 480x360 video (ground truth x0.625), decoded once into
``OUT/.frames/`` as PNG; TUD-Stadtmitte's are its ``img1`` JPEGs. Each sequence's ``frames/``
holds symbolic links to them, named with the original frame numbers.

    python tools/make_mot_sot.py --out runs/mot_sot
    for s in 0 1 2 3 4; do torchtrack eval --sequences runs/mot_sot --seed $s --jobs 2 \\
        --out runs/mot_sot_eval/seed$s --trackers adaptive-haar cotrain csrt; done
    python tools/bench_sot.py --data runs/mot_sot --results runs/mot_sot_eval/seed*
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("TORCHTRACK_DATA", REPO.parent / "shared" / "data"))
sys.path.insert(0, str(REPO))

from torchtrack.boxes import box_iou  # noqa: E402
from torchtrack.errors import TorchTrackError  # noqa: E402
from torchtrack.io.mot import load_mot_sequence  # noqa: E402
from torchtrack.io.video import to_numpy_bgr  # noqa: E402


def track_spans(gt, width: int, height: int, max_iou: float, min_frames: int):
    """``[(id, first, last, {frame: box})]`` by the rules of the module doc (0-based frames,
    as :class:`~torchtrack.io.mot.MotRows` holds them)."""
    frames, ids, boxes, conf = gt.frames, gt.ids, gt.boxes, gt.conf
    tboxes = torch.from_numpy(boxes)
    by_frame = {int(f): np.flatnonzero(frames == f) for f in np.unique(frames)}
    spans = []
    for tid in np.unique(ids[conf > 0]):
        rows = np.flatnonzero((ids == tid) & (conf > 0))
        rows = rows[np.argsort(frames[rows])]
        start = None
        for r in rows:
            x, y, w, h = boxes[r]
            if x < 0 or y < 0 or x + w > width or y + h > height:
                continue
            others = [k for k in by_frame[int(frames[r])] if k != r]
            if others and box_iou(tboxes[r], tboxes[others]).max() >= max_iou:
                continue
            start = int(frames[r])
            break
        if start is None:
            continue
        keep = rows[frames[rows] >= start]
        if keep.size < min_frames:
            continue
        spans.append(
            (int(tid), start, int(frames[keep[-1]]), {int(frames[r]): boxes[r] for r in keep})
        )
    return spans


def frame_files(seq, out: Path) -> list[Path]:
    """The sequence's frame files, 0-based frame ``f`` at index ``f`` (a video is decoded once
    into ``out/.frames/<name>/``, named by the 1-based MOT frame number)."""
    if seq.frames is not None:
        return [Path(p).resolve() for p in seq.frames]
    d = out / ".frames" / seq.name
    files = [d / f"{i + 1:06d}.png" for i in range(seq.n_frames)]
    if not all(f.is_file() for f in files):
        d.mkdir(parents=True, exist_ok=True)
        with seq.open() as src:  # the frames the trackers would read from the video
            n = 0
            for f, frame in zip(files, src, strict=False):
                cv2.imwrite(str(f), to_numpy_bgr(frame))
                n += 1
        if n < len(files):
            sys.exit(f"{seq.video} ended before frame {n + 1} of {len(files)}")
    return [f.resolve() for f in files]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=REPO / "runs" / "mot_sot")
    ap.add_argument("--max-iou", type=float, default=0.1)
    ap.add_argument("--min-frames", type=int, default=50)
    ap.add_argument(
        "--only", nargs="*", choices=("PETS09-S2L1", "TUD-Stadtmitte"), help="default: both"
    )
    args = ap.parse_args(argv)
    mot = DATA / "mot"
    loaders = {
        "PETS09-S2L1": lambda: load_mot_sequence(
            DATA / "videos" / "pets2009_s2l1_vtest" / "vtest.avi",
            gt=mot / "PETS09-S2L1" / "gt" / "gt.txt",
        ),
        "TUD-Stadtmitte": lambda: load_mot_sequence(mot / "TUD-Stadtmitte"),
    }
    try:
        sources = [load() for name, load in loaders.items() if not args.only or name in args.only]
    except TorchTrackError as exc:
        sys.exit(f"make_mot_sot: {exc} (the MOT data is looked up in {DATA}; set TORCHTRACK_DATA)")
    args.out.mkdir(parents=True, exist_ok=True)
    lines = []
    for seq in sources:
        files = frame_files(seq, args.out)
        height, width = cv2.imread(str(files[0])).shape[:2]
        for tid, first, last, rows in track_spans(
            seq.gt, width, height, args.max_iou, args.min_frames
        ):
            d = args.out / f"{seq.name}-id{tid:02d}"
            fd = d / "frames"
            fd.mkdir(parents=True, exist_ok=True)
            for old in fd.iterdir():
                old.unlink()
            for f in range(first, last + 1):
                (fd / f"{f + 1:06d}{files[f].suffix}").symlink_to(files[f])
            with open(d / "groundtruth.csv", "w", encoding="utf-8") as fh:
                fh.write("frame,x,y,w,h\n")
                for f, b in sorted(rows.items()):
                    fh.write(f"{f - first},{b[0]:.2f},{b[1]:.2f},{b[2]:.2f},{b[3]:.2f}\n")
            h0 = rows[first][3]
            lines.append(
                f"{d.name}: MOT frames {first + 1}-{last + 1} ({last - first + 1}, {len(rows)} with a box), "
                f"first box {rows[first][2]:.0f}x{h0:.0f} px"
            )
    print("\n".join(lines))
    print(f"{len(lines)} sequences in {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
