"""Detectors on the fixed held-out test sets, every method on the identical windows, with
bootstrap intervals over test images (``train/test_sets.py`` defines the sets).

    python tools/bench_detectors.py --classes pedestrian --train --chateau --hog
    python tools/bench_detectors.py --classes vehicle --train --hog

Rows (per class):

* **ours, shipped**: the bundled model (``torchtrack/models/<class>.safetensors``);
* **ours, trained here** (``--train``): ``torchtrack train --config configs/<class>.toml`` run
  as a child process (``--threads``), with its wall-clock time and peak resident memory;
* **Chateau et al. (paper setting)** (``--chateau``): the same config with
  ``features.kind = "haar"`` (grey Haar bank, 40 AdaBoost-selected features, discrete AdaBoost,
  Platt) and one mining round of 2,000 windows (the previous shipped recipe; three rounds of
  full Haar selection would take an hour);
* **HOG + LinearSVC** (``--hog``, the peer; scikit-image and scikit-learn, the ``bench``
  extra): Dalal & Triggs' descriptor (9 orientations, 8x8 cells, 2x2 blocks, L2-Hys) of the
  window resized to the model window (grayscale 64x128 / 40x100; colour for pedestrians, the
  channel with the largest gradient), LinearSVC (C = 0.01), trained on the same positives and
  the same random windows of the same negative images, then ``--hog-rounds`` rounds of
  hard-negative mining on those images (windows scanned on scaled images at 8-pixel steps,
  decision >= -1, at most 5,000 per round).

* **ours, model file** (``--models A.safetensors ...``): any other model of the class (a
  candidate recipe trained elsewhere), scored on the same windows.

``--blur S`` blurs every test image (the positives' photographs and the negative images) by a
Gaussian of sd S pixels before any method scores it: the same windows on soft video (a lens out
of focus, compression, footage upscaled from a smaller size). The peer is trained as usual; only
the test images change.

    python tools/bench_detectors.py --classes pedestrian --models runs/ped_blur.safetensors --blur 1 --out runs/blur1.md

Each row: detection rate at 1% FPR with its 90% bootstrap interval (1,000 resamples of
positive source photographs and negative images), AUC, and for calibrated models the expected
calibration error (15 bins) of the calibrated probabilities on the test windows. Writes
``docs/benchmarks/detectors.md`` (atomically) and prints it; ``--cache DIR`` keeps trained
models and scores under DIR (default ``runs/bench_detectors``).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("test_sets", REPO / "train" / "test_sets.py")
test_sets = importlib.util.module_from_spec(_spec)
sys.modules["test_sets"] = test_sets  # dataclasses look their module up while being defined
_spec.loader.exec_module(test_sets)


def log(s: str) -> None:
    print(s, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- our detectors
def train_child(cfg: Path, out: Path, overrides: list[str], threads: int) -> dict:
    """``torchtrack train`` in a child process: wall time and the child's peak RSS."""
    code = (
        "import sys, torch; torch.set_num_threads(int(sys.argv[1])); "
        "from torchtrack.detect.config import load_train_config; "
        "from torchtrack.detect.training import train_detector; "
        "from torchtrack.detect import save_detector; "
        "import json; ov = json.loads(sys.argv[4]); "
        "cfg = load_train_config(sys.argv[2], ov); "
        "det = train_detector(cfg, log=lambda s: print(s, file=sys.stderr, flush=True)); "
        "save_detector(sys.argv[3], det)"
    )
    ov = {}
    for o in overrides:
        k, v = o.split("=", 1)
        ov[k] = json.loads(v)
    out.parent.mkdir(parents=True, exist_ok=True)
    stats = out.with_suffix(".time")
    t0 = time.perf_counter()
    subprocess.run(
        [
            *("/usr/bin/time", "-f", "%M", "-o", str(stats), sys.executable, "-c", code),
            *(str(threads), str(cfg), str(out), json.dumps(ov)),
        ],
        check=True,
    )
    wall = time.perf_counter() - t0
    peak = int(stats.read_text().split()[-1]) / 1024**2  # GNU time: maximum RSS in KiB
    return {"train_s": wall, "peak_gib": peak}


def detector_scores(det, ts):
    """Margins and calibrated probabilities on every test window."""
    m = test_sets.score_test_set(lambda img, bx: det.decision_function(img, bx), ts)
    p = test_sets.score_test_set(lambda img, bx: det.score(img, bx), ts) if det.calibrator else None
    return m, p


def blurred(ts, sigma: float):
    """The test set with every image blurred by a Gaussian of sd ``sigma`` pixels (OpenCV)."""
    import dataclasses

    if not 0 < sigma <= 20:
        raise SystemExit(f"--blur must be in (0, 20] pixels, got {sigma}")
    images = []
    for im in ts.images:
        a = cv2.GaussianBlur(np.ascontiguousarray(im.permute(1, 2, 0).numpy()), (0, 0), sigma)
        t = torch.from_numpy(a.reshape(im.shape[1], im.shape[2], -1))
        images.append(t.permute(2, 0, 1).contiguous())
    what = f"{ts.what}; every image blurred by a Gaussian of sd {sigma:g} px (`--blur`)"
    return dataclasses.replace(ts, images=images, what=what)


# --------------------------------------------------------------------------------- the peer
class HogPeer:
    """Dalal & Triggs: HOG of the window resized to the model window, LinearSVC."""

    def __init__(self, window: tuple[int, int], colour: bool, C: float = 0.01) -> None:
        self.window = window
        self.colour = colour
        self.C = C
        self.svm = None

    def _hog(self, img: np.ndarray, feature_vector: bool = True) -> np.ndarray:
        from skimage.feature import hog

        return hog(
            img,
            orientations=9,
            pixels_per_cell=(8, 8),
            cells_per_block=(2, 2),
            block_norm="L2-Hys",
            feature_vector=feature_vector,
            channel_axis=-1 if img.ndim == 3 else None,
        )

    def _np(self, img: torch.Tensor) -> np.ndarray:
        a = img.permute(1, 2, 0).numpy()
        if not self.colour:
            a = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY) if a.shape[2] == 3 else a[:, :, 0]
        elif a.shape[2] == 1:
            a = np.repeat(a, 3, 2)
        return a

    def descriptors(self, img: torch.Tensor, boxes: torch.Tensor) -> np.ndarray:
        a = self._np(img)
        h, w = self.window
        out = []
        for x, y, bw, bh in boxes.tolist():
            x0, y0 = max(0, round(x)), max(0, round(y))
            x1, y1 = min(a.shape[1], round(x + bw)), min(a.shape[0], round(y + bh))
            crop = cv2.resize(a[y0:y1, x0:x1], (w, h), interpolation=cv2.INTER_AREA)
            out.append(self._hog(crop))
        return np.asarray(out, dtype=np.float32)

    def fit(self, x: np.ndarray, y: np.ndarray) -> HogPeer:
        from sklearn.svm import LinearSVC

        self.svm = LinearSVC(C=self.C, dual="auto", max_iter=5000).fit(x, y)
        return self

    def decision(self, x: np.ndarray) -> np.ndarray:
        return self.svm.decision_function(x)

    def mine(self, images: list[torch.Tensor], n: int, margin: float = -1.0) -> list:
        """Windows of every scale (ratio 1.2, 8-px steps) scoring at least ``margin``."""
        h, w = self.window
        wt = self.svm.coef_.reshape(-1).astype(np.float32)
        b0 = float(self.svm.intercept_[0])
        bh, bw = h // 8 - 1, w // 8 - 1  # blocks per window
        cand = []
        for i, img in enumerate(images):
            a = self._np(img)
            s = 1.0
            while a.shape[0] / s >= h and a.shape[1] / s >= w:
                im = cv2.resize(
                    a, (round(a.shape[1] / s), round(a.shape[0] / s)), interpolation=cv2.INTER_AREA
                )
                blocks = self._hog(im, feature_vector=False).astype(np.float32)
                ny, nx = blocks.shape[0] - bh + 1, blocks.shape[1] - bw + 1
                if ny > 0 and nx > 0:
                    view = np.lib.stride_tricks.sliding_window_view(blocks, (bh, bw), axis=(0, 1))
                    # (ny, nx, 2, 2, 9, bh, bw) -> descriptor order (bh, bw, 2, 2, 9)
                    d = np.moveaxis(view, (-2, -1), (2, 3)).reshape(ny, nx, -1)
                    sc = d @ wt + b0
                    for yy, xx in zip(*np.nonzero(sc >= margin), strict=True):
                        cand.append((float(sc[yy, xx]), i, [xx * 8 * s, yy * 8 * s, w * s, h * s]))
                s *= 1.2
        cand.sort(key=lambda c: -c[0])
        return cand[:n]


def train_hog(name: str, cfg_path: Path, rounds: int, log) -> tuple[HogPeer, dict]:
    """The peer on the config's training data (same positives, random windows, images)."""
    from torchtrack.detect.config import load_train_config
    from torchtrack.detect.train_channels import load_channel_data
    from torchtrack.io.crops import sample_boxes

    cfg = load_train_config(cfg_path)
    t0 = time.perf_counter()
    data = load_channel_data(cfg)
    window = tuple(cfg.window)
    peer = HogPeer(
        window, colour=cfg.features.kind == "channels" and cfg.features.channel_set().colour
    )
    crops = data.positives[0]  # scale 1 (+ mirrors)
    reg = torch.tensor([list(crops.region)], dtype=torch.float64)
    xp = np.concatenate([peer.descriptors(im, reg) for im in crops.images])
    xs = [xp]
    if data.negative_crops is not None:
        nc = data.negative_crops
        reg = torch.tensor([list(nc.region)], dtype=torch.float64)
        xs.append(np.concatenate([peer.descriptors(im, reg) for im in nc.images]))
    picks = sample_boxes(
        [tuple(im.shape[-2:]) for im in data.images],
        window,
        cfg.data.random_negatives,
        min_scale=max(1.0, cfg.data.negative_min_scale),
        generator=torch.Generator().manual_seed(cfg.seed),
    )
    per: dict[int, list] = {}
    for i, x, y, w, h in picks:
        per.setdefault(i, []).append([x, y, w, h])
    for i, bx in per.items():
        xs.append(peer.descriptors(data.images[i], torch.tensor(bx, dtype=torch.float64)))
    x = np.concatenate(xs)
    y = np.concatenate([np.ones(len(xp)), np.zeros(len(x) - len(xp))])
    peer.fit(x, y)
    info = {"rounds": []}
    for r in range(rounds):
        hard = peer.mine(data.images, 5000)
        per = {}
        for _, i, b in hard:
            per.setdefault(i, []).append(b)
        extra = [
            peer.descriptors(data.images[i], torch.tensor(b, dtype=torch.float64))
            for i, b in per.items()
        ]
        if extra:
            x = np.concatenate([x, *extra])
            y = np.concatenate([y, np.zeros(sum(len(e) for e in extra))])
            peer.fit(x, y)
        info["rounds"].append(len(hard))
        log(f"[{name}] HOG mining round {r + 1}: +{len(hard)} hard negatives")
    info["train_s"] = time.perf_counter() - t0
    info["n_train"] = len(y)
    return peer, info


def hog_scores(peer: HogPeer, ts):
    def score(img, bx):
        return torch.from_numpy(peer.decision(peer.descriptors(img[0], bx[0])))

    return test_sets.score_test_set(score, ts)


# -------------------------------------------------------------------------------- the table
def row(label, scores, probs, reps, extra=""):
    from torchtrack.detect.evaluate import roc_auc
    from torchtrack.learn import calibration_metrics

    pos, neg, pg, ng = scores
    dr = test_sets.dr_at_fpr(pos, neg, 0.01)
    lo, hi = test_sets.bootstrap_dr(pos, neg, pg, ng, reps=reps)
    y = torch.cat((torch.ones(pos.numel()), torch.zeros(neg.numel())))
    auc = roc_auc(torch.cat((pos, neg)), y)
    ece = ""
    if probs is not None:
        p = torch.cat((probs[0], probs[1])).clamp(0, 1)
        ece = f"{calibration_metrics(p, y.long())['ece']:.4f}"
    return (
        f"| {label} | **{100 * dr:.1f}%** | {100 * lo:.1f} - {100 * hi:.1f}% | {auc:.4f} | "
        f"{ece} | {extra} |"
    )


def reliability_section(name, det, probs) -> list[str]:
    """Where the shipped model's ECE on the test windows comes from: the bins, and the share
    of positives in the calibration hold-out against the test set's (a calibrated probability
    is calibrated to the class balance it was fitted on)."""
    from torchtrack.learn import reliability_bins

    pp, pn = probs[0], probs[1]
    y = torch.cat((torch.ones(pp.numel()), torch.zeros(pn.numel()))).long()
    rows = reliability_bins(torch.cat((pp, pn)).clamp(0, 1), y)
    cnt = det.summary.get("counts", {})
    npc, nnc = cnt.get("positives_calibration"), cnt.get("negatives_calibration")
    share = (
        f"{npc} / {nnc} ({npc / (npc + nnc):.1%} positives)"
        if npc and nnc
        else "not recorded in the model"
    )
    out = [
        f"Reliability of `{name}` on these windows (15 bins; the ECE is the sum of the last "
        f"column). Positives: {pp.numel()} of {pp.numel() + pn.numel()} windows "
        f"({pp.numel() / (pp.numel() + pn.numel()):.1%}); the calibration hold-out the Platt "
        f"fit saw: {share}.",
        "",
        "| predicted | windows | mean predicted | observed positive frequency | ECE share |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        out.append(
            f"| {r['lo']:.2f}-{r['hi']:.2f} | {r['count']} | {r['mean_p']:.3f} | "
            f"{r['frequency']:.3f} | {r['ece_share']:.4f} |"
        )
    return [*out, ""]


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--classes", nargs="+", default=["pedestrian"], choices=["pedestrian", "vehicle"]
    )
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks" / "detectors.md")
    ap.add_argument("--cache", type=Path, default=REPO / "runs" / "bench_detectors")
    ap.add_argument("--train", action="store_true", help="train ours from configs/<class>.toml")
    ap.add_argument("--chateau", action="store_true", help="train the paper-setting Haar row")
    ap.add_argument("--hog", action="store_true", help="train and score the HOG + LinearSVC peer")
    ap.add_argument("--hog-rounds", type=int, default=1)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--reps", type=int, default=1000, help="bootstrap resamples")
    ap.add_argument("--models", nargs="+", type=Path, default=[], help="more model files to score")
    ap.add_argument(
        "--blur", type=float, default=0.0, metavar="S", help="blur the test images by sd S px"
    )
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    from torchtrack.detect import load_detector
    from torchtrack.detect.bundled import resolve_model

    cmd = "python tools/bench_detectors.py " + " ".join(sys.argv[1:])
    lines = [
        "# Detectors on the held-out test sets (identical windows for every method)",
        "",
        f"Command: `{cmd.strip()}` ({args.threads} thread(s); load average at the start "
        f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)",
        "",
        "Detection rate at 1% false-positive rate over test *windows* (the rate at the "
        "threshold that lets 1% of the negative windows through), with a 90% bootstrap interval "
        f"({args.reps} resamples of positive source photographs and negative images); ECE: "
        "expected calibration error (15 bins) of the calibrated probabilities on the same "
        "windows. Training time is wall-clock on the shared machine; peak memory is the "
        "training process's maximum resident set.",
        "",
    ]
    for name in args.classes:
        ts = test_sets.test_set(name, args.data)
        if args.blur > 0:
            ts = blurred(ts, args.blur)
        n_pos, n_neg = ts.counts()
        log(f"[{name}] test set: {n_pos} positive, {n_neg} negative windows")
        lines += [
            f"## {name}",
            "",
            f"Test set: {ts.what}.",
            "",
            "| method | detection rate @1% FPR | 90% interval | AUC | ECE | training |",
            "|---|---|---|---|---|---|",
        ]
        cfg = REPO / "configs" / f"{name}.toml"
        det = load_detector(resolve_model(name))
        m, p = detector_scores(det, ts)
        reliability = reliability_section(name, det, p) if p is not None else []
        s = det.summary
        lines.append(
            row(
                f"ours, shipped (`{name}`: {len(det.bank)} channel features, "
                f"{det.classifier.feature_.shape[0]} trees)"
                if hasattr(det.classifier, "leaf_")
                else f"ours, shipped (`{name}`)",
                m,
                p,
                args.reps,
                f"{s.get('train_seconds', float('nan')):.0f} s (recorded in the model)",
            )
        )
        if args.train:
            out = args.cache / f"{name}.safetensors"
            info = train_child(cfg, out, [], args.threads)
            det_t = load_detector(out)
            m, p = detector_scores(det_t, ts)
            lines.append(
                row(
                    "ours, trained in this run (`configs/" + name + ".toml`)",
                    m,
                    p,
                    args.reps,
                    f"{info['train_s']:.0f} s wall, peak {info['peak_gib']:.2f} GiB",
                )
            )
        for path in args.models:
            m, p = detector_scores(load_detector(path), ts)
            lines.append(row(f"ours, model file `{path}`", m, p, args.reps))
        if args.chateau:
            out = args.cache / f"{name}_chateau.safetensors"
            ov = [
                'features.kind="haar"',
                "mining.rounds=1",
                "mining.per_round=2000",
                "mining.scale_step=1.15",
                "mining.stride=0.08",
                "data.negative_min_scale=1.0",
                "data.mirror_negatives=false",
                "data.positive_scales=[1.0]",
            ]
            info = train_child(cfg, out, ov, args.threads)
            det_c = load_detector(out)
            m, p = detector_scores(det_c, ts)
            lines.append(
                row(
                    "Chateau et al. (paper setting: grey Haar bank, 40 selected features, "
                    "discrete AdaBoost, 1 mining round)",
                    m,
                    p,
                    args.reps,
                    f"{info['train_s']:.0f} s wall, peak {info['peak_gib']:.2f} GiB",
                )
            )
        if args.hog:
            peer, info = train_hog(name, cfg, args.hog_rounds, log)
            lines.append(
                row(
                    f"HOG + LinearSVC (scikit-image + scikit-learn, {args.hog_rounds} mining "
                    "round(s))",
                    hog_scores(peer, ts),
                    None,
                    args.reps,
                    f"{info['train_s']:.0f} s wall ({info['n_train']} windows)",
                )
            )
        lines.append("")
        lines += reliability
        log("\n".join(lines))
    lines += [f"Load average at the end: {os.getloadavg()[0]:.1f}.", ""]
    from torchtrack.io.atomic import write_text_atomic

    text = "\n".join(lines)
    write_text_atomic(args.out, text)
    print(text)


if __name__ == "__main__":
    main()
