"""Births on video unlike the dev sequences: people found, and targets started on nobody.

The multi-target tracker (``MultiTargetTracker``, defaults unless ``--tracker``) runs, from the
first frame, on:

* **person sequences** with one annotated person (OTB Couple, Jogging1, BoBoT pedestrian): the
  share of annotated frames where a reported box covers that person (IoU >= 0.5; Couple's one
  box around two people: a reported box lying at least 70% inside it), and the identities
  reported. Other people in these videos are not annotated, so this is found, not precision.
* **person-free clips**: each held-out INRIA negative image and each scene negative as a
  60-frame clip, ``static`` (the image with fresh sensor noise, sd 2, on every frame: a still
  camera) and ``pan`` (a crop of 0.8 of the image sliding corner to corner: a moving camera).
  Every identity reported there is a false target.

Usage::

    python tools/check_births.py                                   # the defaults
    python tools/check_births.py --tracker multi:birth_floor=0.9999   # births at a fixed threshold
    python tools/check_births.py --parts pan                       # the moving-camera clips only

Nothing is timed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from torchtrack.boxes import box_iou_matrix  # noqa: E402
from torchtrack.io.crops import read_image  # noqa: E402
from torchtrack.io.sequences import load_sequence  # noqa: E402
from torchtrack.track.base import parse_tracker_spec  # noqa: E402
from torchtrack.track.multi import MultiTargetTracker  # noqa: E402

PERSONS = {
    "Couple": "tracking/otb/Couple",
    "Jogging1": "tracking/otb/Jogging1",
    "BoBoT": "tracking/bobot_pedestrian",
}
NEGATIVES = ("detection_crops/inria_negatives/test/*", "detection_crops/scene_negatives/*.jpg")


def person_found(name: str, root: Path, params: dict, seed: int) -> str:
    seq = load_sequence(root)[0]
    gt = seq.boxes.to(torch.float64)
    mt = MultiTargetTracker(generator=torch.Generator().manual_seed(seed), **params)
    hit = n = 0
    ids: set[int] = set()
    with seq.open() as src:
        for i, frame in src.items():
            if frame is None:
                continue
            out = mt.update(frame)
            ids |= set(out.ids.tolist())
            if not bool(torch.isfinite(gt[i]).all()):
                continue
            n += 1
            if not len(out):
                continue
            if name == "Couple":  # one box around two people: a target inside it
                b, g = out.boxes, gt[i]
                ix = torch.minimum(b[:, 0] + b[:, 2], g[0] + g[2]) - torch.maximum(b[:, 0], g[0])
                iy = torch.minimum(b[:, 1] + b[:, 3], g[1] + g[3]) - torch.maximum(b[:, 1], g[1])
                inside = ix.clamp_min(0) * iy.clamp_min(0) / (b[:, 2] * b[:, 3])
                hit += bool((inside >= 0.7).any())
            else:
                hit += bool((box_iou_matrix(gt[i : i + 1], out.boxes) >= 0.5).any())
    line = mt.birth_summary() or "births at the fixed threshold"
    return f"| {name} | {hit}/{n} ({100 * hit / max(n, 1):.0f}%) | {len(ids)} | {line} |"


def false_targets(mode: str, files: list[Path], params: dict, seed: int) -> str:
    rng = np.random.default_rng(seed)
    clips = ids = boxes = 0
    for fn in files:
        img = read_image(fn, colour=True)
        if img is None:
            raise SystemExit(f"{fn}: not a readable image")
        h, w = img.shape[:2]
        ch, cw = int(h * 0.8), int(w * 0.8)
        mt = MultiTargetTracker(generator=torch.Generator().manual_seed(seed), **params)
        seen: set[int] = set()
        for t in range(60):
            if mode == "static":
                noisy = img.astype(np.float32) + rng.normal(0.0, 2.0, img.shape)
                f = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
            else:
                x, y = round((w - cw) * t / 59), round((h - ch) * t / 59)
                f = np.ascontiguousarray(img[y : y + ch, x : x + cw])
            out = mt.update(torch.from_numpy(f).permute(2, 0, 1).contiguous())
            seen |= set(out.ids.tolist())
            boxes += len(out)
        clips += bool(seen)
        ids += len(seen)
    return f"| {mode} | {clips}/{len(files)} | {ids} | {boxes} / {60 * len(files)} |"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tracker", default="multi", help="multi[:key=value,...]")
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument(
        "--parts",
        nargs="+",
        choices=("persons", "static", "pan"),
        default=["persons", "static", "pan"],
        help="which checks to run (default all)",
    )
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    kind, params = parse_tracker_spec(args.tracker)
    if kind != "multi":
        raise SystemExit(f"--tracker must be multi[:key=value,...], got {args.tracker!r}")
    lines = [
        f"tracker {args.tracker}, seed {args.seed}",
        "",
        "| person sequence | annotated person covered | identities | births |",
        "|---|---|---|---|",
    ]
    for name, rel in PERSONS.items() if "persons" in args.parts else ():
        lines.append(person_found(name, args.data / rel, params, args.seed))
        print(lines[-1], flush=True)
    files = sorted(p for pat in NEGATIVES for p in args.data.glob(pat))
    lines += [
        "",
        "| person-free clips (60 frames) | clips with a false target | identities | boxes / frames |",
        "|---|---|---|---|",
    ]
    for mode in [m for m in ("static", "pan") if m in args.parts]:
        lines.append(false_targets(mode, files, params, args.seed))
        print(lines[-1], flush=True)
    print("\n".join(lines))
    print(
        "\ncommand: python tools/check_births.py "
        + " ".join(argv if argv is not None else sys.argv[1:])
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
