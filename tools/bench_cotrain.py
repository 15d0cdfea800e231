"""Benchmark of the co-training tracker (Jin et al. 2011) on the dev set.

Part A, one ``torchtrack eval`` run: ``cotrain`` (SEIR), ``cotrain:resampler=sir``,
``cotrain:mode=self`` and OpenCV ``mil`` side by side: mean AUC, precision at 20 px, fps.

Part B, the same trackers driven directly (same seed, same frames) for what ``eval`` does not
see: mean ESS per frame and SEIR loops (SEIR vs SIR, same likelihood and particle count), and
the pixel classification error of the fused map against the ground-truth box (co-trained vs
self-trained): a pixel of the candidate region is object when its centre lies in the box;
error = fraction of pixels whose sign of fused confidence disagrees, balanced error = mean of
the miss and false-alarm rates.

Writes ``docs/benchmarks/cotrain.md`` (atomically) with the exact command.

    python tools/bench_cotrain.py --max-frames 100 --jobs 2
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import torch  # noqa: E402

from torchtrack.io.atomic import write_text_atomic  # noqa: E402
from torchtrack.io.sequences import find_sequences  # noqa: E402
from torchtrack.track.cotrain import CoTrainTracker  # noqa: E402

DATA = Path("/work/shared/data/tracking")
TRACKERS = ["cotrain", "cotrain:resampler=sir", "cotrain:mode=self", "mil"]
DIRECT = {
    "cotrain (SEIR)": {},
    "cotrain:resampler=sir": {"resampler": "sir"},
    "cotrain:mode=self": {"mode": "self"},
}


def pixel_errors(maps, gt) -> tuple[float, float] | None:
    if maps is None or not bool(torch.isfinite(gt).all()):
        return None
    x0, y0, x1, y1 = maps.region
    xs = torch.arange(x0, x1, dtype=torch.float64) + 0.5
    ys = torch.arange(y0, y1, dtype=torch.float64) + 0.5
    bx, by, bw, bh = gt.tolist()
    inside = ((ys >= by) & (ys < by + bh))[:, None] & ((xs >= bx) & (xs < bx + bw))[None, :]
    pred = maps.fused > 0
    err = float((pred != inside).double().mean())
    miss = float((~pred & inside).sum() / inside.sum().clamp_min(1))
    fa = float((pred & ~inside).sum() / (~inside).sum().clamp_min(1))
    return err, 0.5 * (miss + fa)


def direct_run(seqs, params: dict, max_frames: int, seed: int) -> dict:
    ess, iters, err, berr, fps = [], [], [], [], []
    for seq in seqs:
        t = CoTrainTracker(generator=torch.Generator().manual_seed(seed), **params)
        n = 0
        t0 = None
        for i, frame in enumerate(seq.open()):
            if i >= max_frames:
                break
            if i == 0:
                t.init(frame, seq.boxes[0])
                t0 = time.perf_counter()
                continue
            t.update(frame)
            n += 1
            pe = pixel_errors(t.last_maps, seq.boxes[i].double())
            if pe is not None:
                err.append(pe[0])
                berr.append(pe[1])
        fps.append(n / (time.perf_counter() - t0))
        h = [x for x in t.history if x["ess"] == x["ess"]]
        ess += [x["ess"] for x in h]
        iters += [x["iterations"] for x in h]
    return {
        "mean_ess": statistics.mean(ess),
        "median_ess": statistics.median(ess),
        "mean_iterations": statistics.mean(iters),
        "pixel_error": statistics.mean(err),
        "balanced_pixel_error": statistics.mean(berr),
        "median_fps": statistics.median(fps),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--max-frames", type=int, default=100)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks" / "cotrain.md")
    args = ap.parse_args()
    command = "python tools/bench_cotrain.py " + " ".join(sys.argv[1:])

    with tempfile.TemporaryDirectory() as tmp:
        cmd = [
            sys.executable,
            "-m",
            "torchtrack",
            "eval",
            "--sequences",
            str(args.data),
            "--trackers",
            *TRACKERS,
            "--max-frames",
            str(args.max_frames),
            "--jobs",
            str(args.jobs),
            "--seed",
            str(args.seed),
            "--out",
            tmp,
            "--no-progress",
        ]
        eval_proc = subprocess.Popen(
            cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )
        seqs = [s.head(args.max_frames) for s in find_sequences(args.data)]
        direct = {k: direct_run(seqs, p, args.max_frames, args.seed) for k, p in DIRECT.items()}
        log, _ = eval_proc.communicate()
        if eval_proc.returncode != 0:
            print(log)
            return 1
        res = json.loads((Path(tmp) / "results.json").read_text())
    ov = res["overall"]

    lines = [
        "# Co-training tracker (Jin et al. 2011) on the dev set",
        "",
        f"Command: `{command}` (eval part: `torchtrack eval --trackers {' '.join(TRACKERS)} "
        f"--max-frames {args.max_frames} --seed {args.seed}`). "
        f"{len(seqs)} sequences (`{args.data}`), first {args.max_frames} frames each. "
        "2 shared CPU cores (other jobs running): fps are noisy, compare within a table.",
        "",
        "## Accuracy and speed (one `torchtrack eval` run)",
        "",
        "| tracker | mean AUC | precision@20px | mean IoU | fps | AUC / MIL | fps / MIL |",
        "|---|---|---|---|---|---|---|",
    ]
    mil = ov["mil"]
    for t in TRACKERS:
        o = ov[t]
        lines.append(
            f"| {t} | {o['auc']:.3f} | {o['precision_20']:.3f} | {o['mean_iou']:.3f} | "
            f"{o['fps']:.1f} | {o['auc'] / mil['auc']:.2f} | {o['fps'] / mil['fps']:.2f} |"
        )
    lines += [
        "",
        "## SEIR vs SIR, co-trained vs self-trained (direct runs, same seed and frames)",
        "",
        "| run | mean ESS / 300 | median ESS | mean SEIR loops | pixel error | balanced "
        "pixel error | median fps |",
        "|---|---|---|---|---|---|---|",
    ]
    for k, d in direct.items():
        lines.append(
            f"| {k} | {d['mean_ess']:.1f} | {d['median_ess']:.1f} | {d['mean_iterations']:.2f} "
            f"| {d['pixel_error']:.3f} | {d['balanced_pixel_error']:.3f} | "
            f"{d['median_fps']:.1f} |"
        )
    lines += [
        "",
        "ESS is measured after each frame's resampling step (SEIR: after its evolutionary "
        "loops). Pixel error: sign of the fused confidence in the candidate region against "
        "'centre inside the ground-truth box', averaged over frames.",
        "",
    ]
    text = "\n".join(lines)
    write_text_atomic(args.out, text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
