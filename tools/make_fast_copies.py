"""Fast-motion copies of single-target sequences: every K-th frame, so the target moves K times
as far between frames.

Issue 13's sequences kept aside include fast motion (a sprinter under a panning camera, an
animal head with blur) that the dev set has little of. Playing each dev sequence at a third of
its frame rate turns its ordinary motion into fast motion with the same targets, frames and
ground truth, so a tracker's defaults can be checked on both without new data.

Each copy is a ``frames/`` folder of symbolic links to the original frames (renumbered from 0)
and a ``groundtruth.csv`` (``frame,x,y,w,h``; frames where the target is absent keep NaN boxes),
the layout ``torchtrack eval --sequences`` reads, named ``<sequence>-every<K>``.

    python tools/make_fast_copies.py --every 3 --out runs/dev_every3
    torchtrack eval --sequences runs/dev_every3 --seed 0 --jobs 2 --out runs/e3/seed0 \\
        --trackers adaptive-haar mil

Sequences stored as one video file (``video.mp4`` + ``.csv``) have no frame files to link and
are refused with a message.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("TORCHTRACK_DATA", REPO.parent / "shared" / "data"))
sys.path.insert(0, str(REPO))

from torchtrack.errors import SequenceError, TorchTrackError  # noqa: E402
from torchtrack.io.sequences import Sequence, find_sequences  # noqa: E402


def make_copy(seq: Sequence, every: int, out: Path) -> Path:
    """Write the every-``every``-th-frame copy of ``seq`` under ``out``; returns its folder.

    Raises:
        SequenceError: the sequence has no frame files (a video), or ``every`` < 1.
    """
    if every < 1:
        raise SequenceError(f"--every must be >= 1, got {every}")
    if not seq.frames:
        raise SequenceError(f"sequence {seq.name} ({seq.root}) has no frame files to link")
    folder = out / f"{seq.name}-every{every}"
    frames = folder / "frames"
    frames.mkdir(parents=True, exist_ok=True)
    rows = ["frame,x,y,w,h"]
    for j, i in enumerate(range(0, len(seq.frames), every)):
        src = Path(seq.frames[i]).resolve()
        dst = frames / f"{j:06d}{src.suffix}"
        if dst.is_symlink() or dst.exists():
            dst.unlink()
        dst.symlink_to(src)
        box = [float(v) for v in seq.boxes[i]]
        rows.append(f"{j}," + ",".join("nan" if math.isnan(v) else f"{v:.3f}" for v in box))
    (folder / "groundtruth.csv").write_text("\n".join(rows) + "\n")
    return folder


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "sources",
        nargs="*",
        type=Path,
        default=[DATA / "tracking"],
        help="sequence folders or folders of them (default: the shared dev set)",
    )
    ap.add_argument("--every", type=int, default=3, help="keep every K-th frame (default 3)")
    ap.add_argument("--out", type=Path, required=True, help="folder of the copies")
    args = ap.parse_args(argv)
    try:
        seqs = [s for src in args.sources for s in find_sequences(src)]
        for s in seqs:
            folder = make_copy(s, args.every, args.out)
            print(f"{folder.name}: {len(range(0, len(s.frames), args.every))} frames")
    except TorchTrackError as e:
        print(f"make_fast_copies: error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
