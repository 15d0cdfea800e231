"""Tracking benchmark: every available tracker on the whole dev set, side by side.

Runs ``torchtrack.eval.evaluate`` over the 11 OTB sequences and the BoBoT pedestrian sequence
in ``../shared/data/tracking`` (or ``$TORCHTRACK_DATA/tracking``) with every tracker that can be
built here (install the ``peers`` extra, opencv-contrib-python-headless, for KCF / CSRT / the
legacy trackers), then rewrites ``docs/benchmarks/tracking.md`` with the results table, the
per-sequence AUC table, the BoBoT row in Klein et al.'s Table I format and the exact command,
and copies the success / precision plots next to it.

    python tools/bench_tracking.py --jobs 2
    python tools/bench_tracking.py --trackers mil csrt --max-frames 100   # quick look
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from torchtrack.eval.report import (  # noqa: E402
    bachoo_table,
    klein_table_row,
    overall_table,
    per_sequence_table,
)
from torchtrack.eval.runner import evaluate  # noqa: E402
from torchtrack.io.atomic import write_text_atomic  # noqa: E402
from torchtrack.io.sequences import find_sequences  # noqa: E402
from torchtrack.track.base import available_trackers  # noqa: E402


def default_data() -> Path:
    env = os.environ.get("TORCHTRACK_DATA")
    return (Path(env) if env else REPO.parent / "shared" / "data") / "tracking"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=default_data(), help="dev-set folder")
    ap.add_argument("--trackers", nargs="+", help="default: every available tracker")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--max-frames", type=int, help="first N frames of each sequence only")
    ap.add_argument("--reinit", action="store_true", help="add the Bachoo re-init pass")
    ap.add_argument("--out", type=Path, default=REPO / "runs" / "bench_tracking")
    ap.add_argument("--doc", type=Path, default=REPO / "docs" / "benchmarks" / "tracking.md")
    args = ap.parse_args(argv)

    trackers = args.trackers or available_trackers()
    seqs = find_sequences(args.data)
    if args.max_frames:
        seqs = [s.head(args.max_frames) for s in seqs]
    cmd = "python tools/bench_tracking.py " + " ".join(sys.argv[1:] if argv is None else argv)
    t0 = time.perf_counter()
    summary = evaluate(
        seqs,
        trackers,
        args.out,
        plots=True,
        jobs=args.jobs,
        reinit=args.reinit,
        command=cmd.strip(),
    )
    wall = time.perf_counter() - t0

    import cv2

    has_contrib = hasattr(cv2, "TrackerCSRT_create") or hasattr(cv2, "TrackerCSRT")
    bobot = next((s.name for s in seqs if s.layout == "bobot"), None)
    n_frames = sum(len(s) for s in seqs)
    lines = [
        "# Tracking benchmark (dev set)",
        "",
        "Made by (from the repository root):",
        "",
        "```",
        cmd.strip(),
        "```",
        "",
        f"{len(seqs)} sequences, {n_frames} frames ({args.data.name}: "
        + ", ".join(s.name for s in seqs)
        + f"); trackers: {', '.join(trackers)}. OpenCV {cv2.__version__}"
        + (" with contrib (`peers` extra)" if has_contrib else " main wheel (no contrib)")
        + f", torch {summary['versions']['torch']}, Python {platform.python_version()}, "
        f"{os.cpu_count()} CPU(s), --jobs {args.jobs} (one thread per process); wall time "
        f"{wall / 60:.1f} min.",
        "",
        "Protocol: one-pass evaluation, every tracker initialised with the first ground-truth "
        "box, the first frame excluded; BoBoT's 23 NaN (target absent) frames are excluded from "
        "the accuracy metrics. AUC = mean of the 21-threshold success curve; prec@20px = "
        "fraction of frames with centre error <= 20 px; mean IoU and miss rate (IoU < 1/3) as in "
        "Klein et al. sec. IV; all averaged over sequences. fps counts tracker `update` time "
        "only (no decoding) on a shared 2-core machine: compare ratios within this run, not "
        "absolute values. `ok=False frames`: frames where the OpenCV tracker reported failure "
        "(its last box is kept and scored).",
        "",
        "## Dev-set means",
        "",
        overall_table(summary),
        "",
        "![success](tracking_success.png) ![precision](tracking_precision.png)",
        "",
    ]
    if bobot:
        lines += [
            "## BoBoT in Klein et al.'s Table I format (average IoU %, sequence I)",
            "",
            "The first five columns are the paper's published numbers (their trackers, their "
            "run); the others are measured here on the same sequence.",
            "",
            klein_table_row(summary, bobot),
            "",
        ]
    lines += ["## AUC per sequence", "", per_sequence_table(summary, "auc"), ""]
    lines += ["## Mean IoU per sequence", "", per_sequence_table(summary, "mean_iou"), ""]
    if summary.get("overall_reinit"):
        lines += [
            "## Re-initialising pass (Bachoo et al. sec. 4)",
            "",
            bachoo_table(summary),
            "",
        ]
    failed = [(t, f) for t, a in summary["overall"].items() for f in a.get("failed", [])]
    if failed:
        lines += ["## Failed runs", ""]
        lines += [f"- {t} on {f['sequence']}: {f['error']}" for t, f in failed]
        lines.append("")
    text = "\n".join(lines)
    args.doc.parent.mkdir(parents=True, exist_ok=True)
    for kind in ("success", "precision"):
        src = args.out / f"{kind}.png"
        if src.is_file():
            dst = args.doc.parent / f"tracking_{kind}.png"
            tmp = dst.with_suffix(".png.tmp")
            shutil.copyfile(src, tmp)
            os.replace(tmp, dst)
    write_text_atomic(args.doc, text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
