"""Tracking benchmark: every available tracker on the whole dev set, side by side.

Runs ``torchtrack.eval.evaluate`` over the 11 OTB sequences and the BoBoT pedestrian sequence
in ``../shared/data/tracking`` (or ``$TORCHTRACK_DATA/tracking``) with every tracker that can be
built here (install the ``peers`` extra, opencv-contrib-python-headless, for KCF / CSRT / the
legacy trackers), then rewrites ``docs/benchmarks/tracking.md`` with the results table, the
per-sequence AUC table, the BoBoT row in Klein et al.'s Table I format and the exact command,
and copies the success / precision plots next to it.

    python tools/bench_tracking.py --jobs 2
    python tools/bench_tracking.py --trackers mil csrt --max-frames 100   # quick look
    python tools/bench_tracking.py --render-only   # rewrite the page from runs/bench_tracking
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from torchtrack.eval.report import (  # noqa: E402
    bachoo_table,
    fmt,
    klein_table_row,
    overall_table,
    per_sequence_table,
)
from torchtrack.eval.runner import evaluate, summarise  # noqa: E402
from torchtrack.io.atomic import write_bytes_atomic, write_text_atomic  # noqa: E402
from torchtrack.io.sequences import find_sequences  # noqa: E402
from torchtrack.track.base import available_trackers  # noqa: E402


def default_data() -> Path:
    env = os.environ.get("TORCHTRACK_DATA")
    return (Path(env) if env else REPO.parent / "shared" / "data") / "tracking"


def speed_table(summary: dict, ref: str = "mil") -> str:
    """fps per tracker: pooled over all frames, median of the per-sequence fps, and the ratio of
    that median to the reference tracker's median (same run, same machine load)."""
    per = summary.get("per_sequence", {})
    med: dict[str, float | None] = {}
    for t in summary["trackers"]:
        vals = [r[t]["fps"] for r in per.values() if t in r and r[t].get("fps")]
        med[t] = statistics.median(vals) if vals else None
    base = med.get(ref)
    rows = [
        f"| tracker | fps (all frames) | median fps over sequences | median / {ref} |",
        "|---|---|---|---|",
    ]
    for t in summary["trackers"]:
        pooled = summary["overall"][t].get("fps")
        ratio = med[t] / base if med[t] and base else None
        rows.append(
            f"| {t} | {fmt(pooled, 1)} | {fmt(med[t], 1)} | "
            f"{fmt(ratio, 2) if ratio is not None else '-'} |"
        )
    return "\n".join(rows)


def render(
    summary: dict, data_name: str, jobs: int | None, wall: float | None, stem: str = "tracking"
) -> str:
    """The benchmark page from a ``results.json`` summary."""
    seqs = summary["sequences"]
    trackers = summary["trackers"]
    cv = summary["versions"]["cv2"]
    has_contrib = any(t in trackers for t in ("csrt", "kcf"))
    bobot = next((s["name"] for s in seqs if s["layout"] == "bobot"), None)
    n_frames = sum(s["n_frames"] for s in seqs)
    env = (
        f"OpenCV {cv}"
        + (" with contrib (`peers` extra)" if has_contrib else " main wheel (no contrib)")
        + f", torch {summary['versions']['torch']}, Python {platform.python_version()}, "
        f"{os.cpu_count()} CPU(s)"
    )
    if jobs:
        env += f", --jobs {jobs} (one thread per process)"
    if wall:
        env += f"; wall time {wall / 60:.1f} min"
    lines = [
        "# Tracking benchmark (dev set)",
        "",
        "Made by (from the repository root):",
        "",
        "```",
        summary.get("command") or "python tools/bench_tracking.py",
        "```",
        "",
        f"{len(seqs)} sequences, {n_frames} frames ({data_name}: "
        + ", ".join(s["name"] for s in seqs)
        + f"); trackers: {', '.join(trackers)}. {env}. Run finished {summary.get('created')}.",
        "",
        "Protocol: one-pass evaluation, every tracker initialised with the first ground-truth "
        "box, the first frame excluded; BoBoT's 23 NaN (target absent) frames are excluded from "
        "the accuracy metrics. AUC = mean of the 21-threshold success curve; prec@20px = "
        "fraction of frames with centre error <= 20 px; mean IoU and miss rate (IoU < 1/3) as in "
        "Klein et al. sec. IV; all averaged over sequences. fps counts tracker `update` time "
        "only (no decoding) on a shared, loaded machine: compare ratios within this run, not "
        "absolute values. `ok=False frames`: frames where the OpenCV tracker reported failure "
        "(its last box is kept and scored). Definitions: [../tracking.md](../tracking.md).",
        "",
        "## Dev-set means",
        "",
        overall_table(summary),
        "",
        f"![success]({stem}_success.png) ![precision]({stem}_precision.png)",
        "",
        "## Speed",
        "",
        speed_table(summary, "mil" if "mil" in trackers else trackers[0]),
        "",
    ]
    if bobot:
        lines += [
            "## BoBoT in Klein et al.'s Table I format (average IoU %, sequence I)",
            "",
            "The first five columns are the paper's published numbers (their trackers, their "
            "run); the others are measured here on the same sequence (# Fr. = evaluated frames, "
            "the first is the initialisation frame).",
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
    return "\n".join(lines)


def write_doc(text: str, out: Path, doc: Path) -> None:
    doc.parent.mkdir(parents=True, exist_ok=True)
    for kind in ("success", "precision"):
        src = out / f"{kind}.png"
        if src.is_file():
            write_bytes_atomic(doc.parent / f"{doc.stem}_{kind}.png", src.read_bytes())
    write_text_atomic(doc, text + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=default_data(), help="dev-set folder")
    ap.add_argument("--trackers", nargs="+", help="default: every available tracker")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--max-frames", type=int, help="first N frames of each sequence only")
    ap.add_argument("--reinit", action="store_true", help="add the Bachoo re-init pass")
    ap.add_argument("--out", type=Path, default=REPO / "runs" / "bench_tracking")
    ap.add_argument("--doc", type=Path, default=REPO / "docs" / "benchmarks" / "tracking.md")
    ap.add_argument(
        "--render-only",
        action="store_true",
        help="rewrite the page from OUT/results.json without running anything",
    )
    ap.add_argument(
        "--from-records",
        action="store_true",
        help="rebuild results.json from the per-run records OUT/sequences*/*/*.json (e.g. of "
        "an interrupted run: missing pairs are listed) and rewrite the page",
    )
    args = ap.parse_args(argv)

    if args.from_records:
        seqs = find_sequences(args.data)
        records = [json.loads(p.read_text()) for p in sorted(args.out.glob("sequences*/*/*.json"))]
        trackers = args.trackers or sorted({r["tracker"] for r in records})
        names = {s.name for s in seqs}
        records = [r for r in records if r["sequence"] in names and r["tracker"] in trackers]
        done = {(r["sequence"], r["tracker"]) for r in records if r["mode"] == "ope"}
        missing = [f"{t} on {s.name}" for s in seqs for t in trackers if (s.name, t) not in done]
        cmd = "python tools/bench_tracking.py " + " ".join(sys.argv[1:] if argv is None else argv)
        summary = summarise(records, seqs, trackers, command=cmd.strip())
        summary["missing_runs"] = missing
        write_text_atomic(args.out / "results.json", json.dumps(summary, indent=1) + "\n")
        text = render(summary, args.data.name, None, None, args.doc.stem)
        if missing:
            text += "\n## Runs missing from this page\n\n" + "\n".join(f"- {m}" for m in missing)
        write_doc(text, args.out, args.doc)
        print(text)
        return 0

    if args.render_only:
        summary = json.loads((args.out / "results.json").read_text())
        text = render(
            summary, args.data.name, summary.get("jobs"), summary.get("wall_seconds"), args.doc.stem
        )
        write_doc(text, args.out, args.doc)
        print(text)
        return 0

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
    summary["wall_seconds"] = wall
    summary["jobs"] = args.jobs
    write_text_atomic(args.out / "results.json", json.dumps(summary, indent=1) + "\n")
    text = render(summary, args.data.name, args.jobs, wall, args.doc.stem)
    write_doc(text, args.out, args.doc)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
