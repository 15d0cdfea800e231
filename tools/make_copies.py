"""Copies of single-target sequences that change one thing: the frame rate, the colour, the
light, or the sharpness.

Issue 13's sequences kept aside differ from the dev set in ways the dev set can be made to show
with its own targets, frames and ground truth:

* ``--every K`` keeps every K-th frame, so the target moves K times as far between frames (fast
  motion: a sprinter under a panning camera, an animal's head with blur). Named
  ``<sequence>-every<K>``; ``frames/`` holds symbolic links to the original frames.
* ``--grey`` makes every frame grey (ITU-R 601 luma, as OpenCV's ``COLOR_RGB2GRAY``): a
  monochrome camera, as a quarter of OTB's sequences are. Named ``<sequence>-grey``.
* ``--gain A`` multiplies every frame's brightness by ``1 + A sin(2 pi t / P)`` (``t`` the
  copy's frame index, ``P = --period``, default 100 frames; values clipped to 0..255): light that
  changes while the target is followed (a cloud, a lamp, a camera's exposure). Named
  ``<sequence>-gain<A>``.
* ``--blur S`` blurs every frame with a Gaussian of sd S pixels (a soft lens, a camera out of
  focus, motion blur without its direction): the animal head "moving fast with blur" of the
  sequences kept aside. Named ``<sequence>-blur<S>``.

The options combine (``-every3-grey``). Copies that change pixels write lossless PNG frames;
``--every`` alone links. Each copy has a ``groundtruth.csv`` (``frame,x,y,w,h``; frames where
the target is absent keep NaN boxes), the layout ``torchtrack eval --sequences`` reads.

    python tools/make_copies.py --every 3 --out runs/dev_every3
    python tools/make_copies.py --grey --out runs/dev_grey
    python tools/make_copies.py --gain 0.5 --out runs/dev_gain
    python tools/make_copies.py --blur 1.5 --out runs/dev_blur
    torchtrack eval --sequences runs/dev_grey --seed 0 --jobs 2 --out runs/grey/seed0 \\
        --trackers adaptive-haar mil

Sequences stored as one video file (``video.mp4`` + ``.csv``) have no frame files to link: a
frame-rate copy of one is refused with a message; the others read the video.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("TORCHTRACK_DATA", REPO.parent / "shared" / "data"))
sys.path.insert(0, str(REPO))

from torchtrack.errors import SequenceError, TorchTrackError  # noqa: E402
from torchtrack.io.sequences import Sequence, find_sequences  # noqa: E402
from torchtrack.io.video import FrameSource  # noqa: E402


def copy_name(
    name: str, every: int = 1, grey: bool = False, gain: float = 0.0, blur: float = 0.0
) -> str:
    """The copy's folder name: ``name`` with one suffix per change."""
    return (
        name
        + (f"-every{every}" if every > 1 else "")
        + ("-grey" if grey else "")
        + (f"-gain{gain:g}" if gain else "")
        + (f"-blur{blur:g}" if blur else "")
    )


def gain_at(t: int, gain: float, period: float) -> float:
    """Brightness factor of the copy's frame ``t``: ``1 + gain sin(2 pi t / period)``."""
    return 1.0 + gain * math.sin(2.0 * math.pi * t / period)


def make_copy(
    seq: Sequence,
    every: int,
    out: Path,
    *,
    grey: bool = False,
    gain: float = 0.0,
    period: float = 100.0,
    blur: float = 0.0,
) -> Path:
    """Write the copy of ``seq`` under ``out`` (see the module doc); returns its folder.

    Raises:
        SequenceError: ``every`` < 1, ``gain`` outside [0, 1), ``period`` <= 0, ``blur``
            outside [0, 20] pixels, no change asked for, or a frame-rate-only copy of a
            sequence without frame files (a video).
    """
    if every < 1:
        raise SequenceError(f"--every must be >= 1, got {every}")
    if not 0.0 <= gain < 1.0:
        raise SequenceError(f"--gain must be in [0, 1) (brightness stays positive), got {gain}")
    if not period > 0:
        raise SequenceError(f"--period must be > 0 frames, got {period}")
    if not 0.0 <= blur <= 20.0:
        raise SequenceError(f"--blur must be in [0, 20] pixels (a Gaussian's sd), got {blur}")
    if every == 1 and not grey and not gain and not blur:
        raise SequenceError("nothing to change: give --every K > 1, --grey, --gain A or --blur S")
    links = not grey and not gain and not blur
    if links and not seq.frames:
        raise SequenceError(f"sequence {seq.name} ({seq.root}) has no frame files to link")
    folder = out / copy_name(seq.name, every, grey, gain, blur)
    frames = folder / "frames"
    frames.mkdir(parents=True, exist_ok=True)
    keep = range(0, len(seq), every)
    rows = ["frame,x,y,w,h"]
    for j, i in enumerate(keep):
        box = [float(v) for v in seq.boxes[i]]
        rows.append(f"{j}," + ",".join("nan" if math.isnan(v) else f"{v:.3f}" for v in box))
    if links:
        for j, i in enumerate(keep):
            src = Path(seq.frames[i]).resolve()
            dst = frames / f"{j:06d}{src.suffix}"
            if dst.is_symlink() or dst.exists():
                dst.unlink()
            dst.symlink_to(src)
    else:
        _write_frames(seq, keep, frames, grey, gain, period, blur)
    (folder / "groundtruth.csv").write_text("\n".join(rows) + "\n")
    return folder


def _write_frames(
    seq: Sequence,
    keep: range,
    frames: Path,
    grey: bool,
    gain: float,
    period: float,
    blur: float = 0.0,
) -> None:
    import cv2

    if seq.frames:  # only the kept files are read
        src = FrameSource([seq.frames[i] for i in keep], color="rgb")
        wanted = {j: j for j in range(len(keep))}
    else:  # a video is decoded in order; the frames between are skipped
        src = seq.open("rgb")
        wanted = {i: j for j, i in enumerate(keep)}
    written = 0
    with src:
        for i, frame in src.items():
            j = wanted.get(i)
            if j is None:
                continue
            if frame is None:
                raise SequenceError(f"sequence {seq.name}: frame {keep[j] + 1} could not be read")
            img = frame.permute(1, 2, 0).numpy()  # (H, W, 3) uint8 RGB
            if blur:
                img = cv2.GaussianBlur(img, (0, 0), blur)
            if grey:
                img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
            else:
                img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
            if gain:
                img = np.clip(img.astype(np.float32) * gain_at(j, gain, period), 0, 255)
                img = np.rint(img).astype(np.uint8)
            if not cv2.imwrite(str(frames / f"{j:06d}.png"), img):
                raise SequenceError(f"could not write {frames / f'{j:06d}.png'}")
            written += 1
    if written != len(keep):
        raise SequenceError(
            f"sequence {seq.name}: {written} of {len(keep)} frames read (the ground truth has "
            "more rows than the sequence has frames)"
        )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "sources",
        nargs="*",
        type=Path,
        default=[DATA / "tracking"],
        help="sequence folders or folders of them (default: the shared dev set)",
    )
    ap.add_argument("--every", type=int, default=1, help="keep every K-th frame (default 1)")
    ap.add_argument("--grey", action="store_true", help="grey frames (a monochrome camera)")
    ap.add_argument(
        "--gain",
        type=float,
        default=0.0,
        help="brightness x (1 + A sin(2 pi t / period)), A in [0, 1) (default 0: unchanged)",
    )
    ap.add_argument(
        "--period", type=float, default=100.0, help="frames per cycle of --gain (default 100)"
    )
    ap.add_argument(
        "--blur",
        type=float,
        default=0.0,
        help="Gaussian blur of sd S pixels, S in [0, 20] (default 0: sharp as recorded)",
    )
    ap.add_argument("--out", type=Path, required=True, help="folder of the copies")
    args = ap.parse_args(argv)
    try:
        seqs = [s for src in args.sources for s in find_sequences(src)]
        for s in seqs:
            folder = make_copy(
                s,
                args.every,
                args.out,
                grey=args.grey,
                gain=args.gain,
                period=args.period,
                blur=args.blur,
            )
            print(f"{folder.name}: {len(range(0, len(s), args.every))} frames")
    except TorchTrackError as e:
        print(f"make_copies: error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
