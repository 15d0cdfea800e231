"""Scoring speed: windows per second of ``Detector.score`` for 2,000 boxes on a 640x480 frame.

    python tools/bench_score_speed.py [--model pedestrian.safetensors] [--repeats 15]

Three ways to score the same 2,000 random boxes (scales 0.5-3x the window) with the same
detector, in one run, medians of ``--repeats`` timings:

* ``score(frame, boxes)``: integral images of the frame + every box (what one tracker step costs);
* ``score(integrals, boxes)``: integral images computed once and reused (several box sets per
  frame, e.g. particle-filter iterations);
* peer, the resize baseline: cut each box out, ``cv2.resize`` it to the window (area averaging)
  and compute the selected features with the dense training path on the resized crops: what a
  detector without box-scale features has to do.

Without ``--model`` a detector is trained on the fly on a small real subset (selection on 600
crops, 40 features); speed does not depend on the training data. Writes
``docs/benchmarks/score_speed.md`` (atomically) and prints it.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from torchtrack.detect import Detector, load_detector
from torchtrack.features.haar import haar_bank, haar_features_dense
from torchtrack.io.atomic import write_text_atomic
from torchtrack.io.crops import load_crops, mirror
from torchtrack.learn import BoostedStumps, PlattCalibrator, select_features

REPO = Path(__file__).resolve().parents[1]


def quick_detector(data: Path) -> Detector:
    window = (128, 64)
    bank = haar_bank(window)
    pos = load_crops(
        data / "detection_crops" / "inria_person_96x160" / "pos",
        window,
        region=(16, 16, 64, 128),
        crop_size=(160, 96),
    ).subset(list(range(300)))
    rng = np.random.default_rng(0)
    neg = torch.from_numpy(rng.integers(0, 256, (300, 1, 128, 64), dtype=np.uint8))
    x = haar_features_dense(torch.cat((mirror(pos).images[:300], neg)), bank)
    y = torch.cat((torch.ones(300), torch.zeros(300))).long()
    idx = select_features(x, y, 40)
    clf = BoostedStumps(n_estimators=40).fit(x[:, idx], y)
    cal = PlattCalibrator().fit(clf.decision_function(x[:, idx]).double(), y)
    return Detector(bank, idx, clf, cal, name="quick")


def resize_baseline(det: Detector, frame: np.ndarray, boxes: np.ndarray) -> torch.Tensor:
    h, w = det.window
    crops = np.empty((boxes.shape[0], 1, h, w), dtype=np.uint8)
    for i, (x, y, bw, bh) in enumerate(boxes.round().astype(int)):
        crops[i, 0] = cv2.resize(
            frame[y : y + bh, x : x + bw], (w, h), interpolation=cv2.INTER_AREA
        )
    # the selected features of every resized crop, read at scale 1 from its own integral
    # images (the same arithmetic as training)
    ints = det.integrals(torch.from_numpy(crops))
    full = torch.tensor([0.0, 0.0, float(w), float(h)]).expand(crops.shape[0], 1, 4)
    feats = det.features(ints, full, check=False)[:, 0]
    return det.proba_from_margin(det.margin_from_features(feats))


def median_time(fn, repeats: int) -> float:
    fn()  # warm-up
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--model", type=Path)
    ap.add_argument("--boxes", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks" / "score_speed.md")
    args = ap.parse_args()
    det = load_detector(args.model) if args.model else quick_detector(args.data)
    h, w = det.window
    g = torch.Generator().manual_seed(0)
    frame_np = np.random.default_rng(1).integers(0, 256, (480, 640), dtype=np.uint8)
    # a real frame where available: the PETS clip's first frame, resized to 640x480
    video = args.data / "videos" / "pets2009_s2l1_vtest"
    vids = sorted(video.glob("*.avi")) if video.is_dir() else []
    if vids:
        cap = cv2.VideoCapture(str(vids[0]))
        ok, bgr = cap.read()
        cap.release()
        if ok:
            frame_np = cv2.resize(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), (640, 480))
    frame = torch.from_numpy(frame_np)[None, None]
    s = 0.5 + 2.5 * torch.rand(args.boxes, generator=g)
    bw, bh = w * s, h * s
    x = torch.rand(args.boxes, generator=g) * (640 - bw)
    y = torch.rand(args.boxes, generator=g) * (480 - bh)
    boxes = torch.stack((x, y, bw, bh), 1)[None]
    ints = det.integrals(frame)
    n = args.boxes
    rows = []
    for label, fn in (
        ("score(frame, boxes)", lambda: det.score(frame, boxes)),
        ("score(integrals, boxes)", lambda: det.score(ints, boxes)),
        (
            "peer: crop + cv2.resize + features",
            lambda: resize_baseline(det, frame_np, boxes[0].numpy()),
        ),
    ):
        t = median_time(fn, args.repeats)
        rows.append((label, t, n / t))
    base = rows[-1][1]
    p1 = det.score(frame, boxes)[0]
    p2 = resize_baseline(det, frame_np, boxes[0].numpy())
    agree = float((p1 - p2).abs().median())
    cmd = "python tools/bench_score_speed.py " + " ".join(sys.argv[1:])
    lines = [
        "# Detector scoring speed",
        "",
        f"Command: `{cmd.strip()}`",
        "",
        f"{n} random boxes (0.5-3x the {h}x{w} window) on a 640x480 frame, detector "
        f"{det.name!r} with {det.feature_index.numel()} features, torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads, median of {args.repeats} runs.",
        "",
        "| method | median ms | windows / s | speed-up vs resize peer |",
        "|---|---|---|---|",
    ]
    for label, t, wps in rows:
        lines.append(f"| {label} | {1000 * t:.2f} | {wps:,.0f} | {base / t:.1f}x |")
    lines += [
        "",
        f"Median |probability difference| between box-scale scoring and the resize peer: "
        f"{agree:.4f} (the peer rounds boxes to whole pixels and resamples).",
        "",
    ]
    text = "\n".join(lines)
    write_text_atomic(args.out, text)
    print(text)


if __name__ == "__main__":
    main()
