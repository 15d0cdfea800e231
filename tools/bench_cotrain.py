"""Benchmark of the co-training tracker (Jin et al. 2011) on the dev set.

Part A, one ``torchtrack eval`` run: ``cotrain`` (SEIR), ``cotrain:resampler=sir``,
``cotrain:mode=self``, OpenCV ``mil`` and, when this interpreter's OpenCV has the contrib
trackers, ``csrt`` side by side: mean AUC, precision at 20 px, fps and the per-sequence AUC.

Part B, after part A (never at the same time: one heavy process at a time), the co-training
variants driven directly (same seed, the first ``--direct-frames`` frames) for what ``eval``
does not see: mean ESS per frame and SEIR loops (SEIR vs SIR, same likelihood and particle
count), and the pixel classification error of the fused map against the ground-truth box
(co-trained vs self-trained): a pixel of the candidate region is object when its centre lies
in the box; error = fraction of pixels whose sign of fused confidence disagrees, balanced
error = mean of the miss and false-alarm rates.

Writes ``docs/benchmarks/cotrain.md`` (atomically) with the exact command. Run it with the
interpreter of a venv that has opencv-contrib (and torchtrack) to include CSRT:

    /tmp/peers-venv/bin/python tools/bench_cotrain.py --max-frames 0 --jobs 1
"""

from __future__ import annotations

import argparse
import json
import os
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
COTRAIN = ["cotrain", "cotrain:resampler=sir", "cotrain:mode=self"]
PEERS = ["mil", "csrt"]
DIRECT = {
    "cotrain (SEIR)": {},
    "cotrain:resampler=sir": {"resampler": "sir"},
    "cotrain:mode=self": {"mode": "self"},
}


def has_csrt() -> bool:
    import cv2

    return hasattr(cv2, "TrackerCSRT_create") or hasattr(cv2, "TrackerCSRT")


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
        spent = 0.0
        for i, frame in enumerate(seq.open()):
            if i >= max_frames:
                break
            if i == 0:
                t.init(frame, seq.boxes[0])
                continue
            t0 = time.perf_counter()
            t.update(frame)
            spent += time.perf_counter() - t0
            n += 1
            pe = pixel_errors(t.last_maps, seq.boxes[i].double())
            if pe is not None:
                err.append(pe[0])
                berr.append(pe[1])
        fps.append(n / spent if spent > 0 else float("nan"))
        h = [x for x in t.history if x["ess"] == x["ess"]]
        ess += [x["ess"] for x in h]
        iters += [x["iterations"] for x in h]
    return {
        "mean_ess": statistics.mean(ess),
        "median_ess": statistics.median(ess),
        "low_ess": sum(e < 150 for e in ess) / len(ess),
        "mean_iterations": statistics.mean(iters),
        "pixel_error": statistics.mean(err),
        "balanced_pixel_error": statistics.mean(berr),
        "median_fps": statistics.median(fps),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--max-frames", type=int, default=0, help="eval prefix (0 = full length)")
    ap.add_argument("--direct-frames", type=int, default=150, help="part B prefix per sequence")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks" / "cotrain.md")
    args = ap.parse_args()
    torch.set_num_threads(1)
    command = f"{Path(sys.executable)} tools/bench_cotrain.py " + " ".join(sys.argv[1:])
    peers = [p for p in PEERS if p != "csrt" or has_csrt()]
    trackers = COTRAIN + peers
    load0 = os.getloadavg()

    t_a = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "torchtrack", "eval", "--sequences", str(args.data)]
        cmd += ["--trackers", *trackers, "--jobs", str(args.jobs), "--seed", str(args.seed)]
        if args.max_frames:
            cmd += ["--max-frames", str(args.max_frames)]
        cmd += ["--out", tmp, "--no-progress"]
        # One torch thread, as eval's --jobs workers (on a shared 2-core machine a second
        # intra-op thread only adds contention).
        env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
        proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, env=env)
        if proc.returncode != 0:
            print(proc.stdout, proc.stderr)
            return 1
        res = json.loads((Path(tmp) / "results.json").read_text())
    t_a = time.perf_counter() - t_a
    load1 = os.getloadavg()

    seqs = [s.head(args.direct_frames) for s in find_sequences(args.data)]
    t_b = time.perf_counter()
    direct = {k: direct_run(seqs, p, args.direct_frames, args.seed) for k, p in DIRECT.items()}
    t_b = time.perf_counter() - t_b

    ov = res["overall"]
    frames = "full length" if not args.max_frames else f"first {args.max_frames} frames each"
    eval_cmd = "torchtrack eval --sequences " + f"{args.data} --trackers {' '.join(trackers)} "
    eval_cmd += f"--jobs {args.jobs} --seed {args.seed}"
    if args.max_frames:
        eval_cmd += f" --max-frames {args.max_frames}"
    lines = [
        "# Co-training tracker (Jin et al. 2011) on the dev set",
        "",
        f"Command: `{command}`; its part A is `{eval_cmd}` ({len(res['sequences'])} sequences, "
        f"{frames}; {ov[trackers[0]]['n_frames']} frames per tracker; {t_a / 60:.0f} min), "
        f"part B runs afterwards ({args.direct_frames} frames per sequence, {t_b / 60:.0f} min). "
        "One torch thread. "
        f"Shared 2-core machine, load average {load0[0]:.1f} at the start and {load1[0]:.1f} "
        "after part A: fps are only comparable within a table (ratios).",
        "",
        "## Accuracy and speed (one `torchtrack eval` run)",
        "",
    ]
    ref = [p for p in peers]
    head = "| tracker | mean AUC | precision@20px | mean IoU | fps |"
    sep = "|---|---|---|---|---|"
    for p in ref:
        head += f" AUC / {p} | fps / {p} |"
        sep += "---|---|"
    lines += [head, sep]
    for t in trackers:
        o = ov[t]
        row = (
            f"| {t} | {o['auc']:.3f} | {o['precision_20']:.3f} | {o['mean_iou']:.3f} | "
            f"{o['fps']:.1f} |"
        )
        for p in ref:
            row += f" {o['auc'] / ov[p]['auc']:.2f} | {o['fps'] / ov[p]['fps']:.2f} |"
        lines.append(row)
    lines += ["", "Per-sequence AUC:", ""]
    lines.append("| sequence | frames | " + " | ".join(trackers) + " |")
    lines.append("|---|---|" + "---|" * len(trackers))
    for name, row in res["per_sequence"].items():
        n = next(iter(row.values()))["n_frames"]
        cells = [
            f"{row[t]['auc']:.3f}" if row[t].get("auc") is not None else "fail" for t in trackers
        ]
        lines.append(f"| {name} | {n} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "## SEIR vs SIR, co-trained vs self-trained (part B: direct runs, same seed and frames)",
        "",
        "| run | mean ESS / 300 | median ESS | frames with ESS < 150 | mean SEIR loops | "
        "pixel error | balanced pixel error | median fps |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for k, d in direct.items():
        lines.append(
            f"| {k} | {d['mean_ess']:.1f} | {d['median_ess']:.1f} | {100 * d['low_ess']:.1f}% | "
            f"{d['mean_iterations']:.2f} | {d['pixel_error']:.3f} | "
            f"{d['balanced_pixel_error']:.3f} | {d['median_fps']:.1f} |"
        )
    lines += [
        "",
        "ESS is measured after each frame's resampling step (SEIR: after its evolutionary "
        "loops). Pixel error: sign of the fused confidence in the candidate region against "
        "'centre inside the ground-truth box', averaged over frames (the box is a rectangle, "
        "so background pixels inside it count as object: compare the rows, not the absolute "
        "level).",
        "",
    ]
    text = "\n".join(lines)
    write_text_atomic(args.out, text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
