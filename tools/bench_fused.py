"""Fused tracker vs detector-only vs co-training-only, and calibrated vs raw-margin fusion, on
the pedestrian (Crossing, Couple, Jogging1, bobot_pedestrian) and vehicle (RedTeam) dev
sequences, all in ``torchtrack eval`` runs of the same filter:

* ``fused``: a = b = 1, Platt-calibrated detector probability x co-trained pixel likelihood;
* ``fused:calibration=raw``: the same with the uncalibrated margin min-max rescaled per frame;
* ``fused:calibration=naive``: the same with the paper's naive rescale of the margin by the
  classifier's fixed range (Chateau et al. section 2.4), a fixed map that is not a probability;
* ``fused:cotrain_weight=0``: detector term only (the Chateau filter on the same dynamics);
* ``fused:det_weight=0``: co-training term only (same filter and dynamics).

Reports AUC per sequence and overall, and the frames where a single-cue variant loses the target
(IoU < 1/3) while the fusion does not (and the reverse). Writes ``docs/benchmarks/fused.md``.

    python tools/bench_fused.py [--max-frames N] [--jobs 1]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

from torchtrack.boxes import box_iou
from torchtrack.io.atomic import write_text_atomic
from torchtrack.io.sequences import load_sequence

ROOT = Path(__file__).resolve().parents[1]
PEDESTRIAN = ["otb/Crossing", "otb/Couple", "otb/Jogging1", "bobot_pedestrian"]
VEHICLE = ["otb/RedTeam"]
NOTES_MARKER = "<!-- notes: kept by tools/bench_fused.py -->"
VARIANTS = ["", "calibration=raw", "calibration=naive", "cotrain_weight=0", "det_weight=0"]
LABELS = {
    "": "fused (calibrated)",
    "calibration=raw": "fused (raw margins, min-max)",
    "calibration=naive": "fused (naive fixed-range rescale)",
    "cotrain_weight=0": "detector only",
    "det_weight=0": "co-training only",
}


def _spec(model: str, variant: str) -> str:
    return f"fused:model={model}" + (f",{variant}" if variant else "")


def _run(data: Path, seqs: list[str], model: str, out: Path, a) -> None:
    cmd = [sys.executable, "-m", "torchtrack", "eval", "--sequences",
           *[str(data / s) for s in seqs], "--trackers",
           *[_spec(model, v) for v in VARIANTS], "--out", str(out), "--jobs", str(a.jobs),
           "--seed", str(a.seed), "--no-progress"]  # fmt: skip
    if a.max_frames:
        cmd += ["--max-frames", str(a.max_frames)]
    subprocess.run(cmd, check=True)


def _records(out: Path) -> dict:
    recs: dict = {}
    for f in sorted((out / "sequences").glob("*/*.json")):
        r = json.loads(f.read_text())
        recs.setdefault(r["sequence"], {})[r["tracker"]] = r
    return recs


def render(runs: list[tuple[str, Path, list[str]]], data: Path, command: str) -> str:
    lines = [
        "# Fused tracker: calibrated detector x co-trained pixel likelihood",
        "",
        f"Command: `{command}`",
        "",
        f"All {len(VARIANTS)} variants are the same particle filter (`fused`, Chateau AR dynamics, 300 "
        "particles); only the log-weight differs. Lost = IoU < 1/3 with the ground truth.",
        "",
        "## AUC per sequence",
        "",
        "| sequence | model | frames | " + " | ".join(LABELS[v] for v in VARIANTS) + " |",
        "|---|---|---|" + "---|" * len(VARIANTS),
    ]
    lost_rows = []
    tot = {v: [] for v in VARIANTS}
    for model, out, seqs in runs:
        recs = _records(out)
        gts = {}
        for s in seqs:
            for sq in load_sequence(data / s):
                gts[sq.name] = sq.boxes
        for name in sorted(recs):
            r = recs[name]
            row = [name, model]
            ious = {}
            n = None
            for v in VARIANTS:
                rec = r.get(_spec(model, v))
                if rec is None or rec.get("error"):
                    row.append("failed" if rec else "-")
                    continue
                auc = (rec.get("metrics") or {}).get("auc")
                row.append("-" if auc is None else f"{auc:.3f}")
                if auc is not None:
                    tot[v].append(auc)
                boxes = torch.tensor(rec["boxes"], dtype=torch.float64)
                gt = gts[name][: boxes.shape[0]]
                n = boxes.shape[0]
                ious[v] = box_iou(boxes, gt)
            lines.append(f"| {row[0]} | {row[1]} | {n} | " + " | ".join(row[2:]) + " |")
            if "" in ious:
                present = torch.isfinite(gts[name][:n]).all(1)
                present[0] = False  # the initial frame
                fused_ok = (ious[""] >= 1 / 3) & present
                for v in VARIANTS[1:]:
                    if v not in ious:
                        continue
                    lost = (ious[v] < 1 / 3) & present
                    lost_rows.append(
                        (name, LABELS[v], int(lost.sum()), int((lost & fused_ok).sum()),
                         int(((ious[""] < 1 / 3) & present & (ious[v] >= 1 / 3)).sum()),
                         int(present.sum()))
                    )  # fmt: skip
    lines.append(
        "| **mean** | | | "
        + " | ".join(f"**{sum(t) / len(t):.3f}**" if t else "-" for t in tot.values())
        + " |"
    )
    lines += [
        "",
        "## Frames where one variant loses the target and the calibrated fusion does not",
        "",
        "| sequence | variant | frames it loses | ... of which fusion keeps | "
        "fusion loses, variant keeps | evaluated frames |",
        "|---|---|---|---|---|---|",
    ]
    for row in lost_rows:
        lines.append("| " + " | ".join(str(x) for x in row) + " |")
    lines += [
        "",
        "One seed per run (counts are indicative, not a significance test). The raw-margin and "
        "naive variants keep the same ranking of windows within a frame as the calibrated one "
        "(Platt is monotone), so differences come from the scale of the detector factor: "
        "min-max rescaling always gives the frame's best window 1 whatever the detector sees; "
        "the naive fixed-range rescale squeezes the margins into the middle of [0, 1].",
        "",
    ]
    fps = {v: [] for v in VARIANTS}
    for _model, out, _seqs in runs:
        for r in _records(out).values():
            for v in VARIANTS:
                rec = r.get(_spec(_model, v))
                if rec and not rec.get("error") and rec.get("fps"):
                    fps[v].append(float(rec["fps"]))
    lines += [
        "Mean tracker fps over the sequences (update time only; shared machine): "
        + ", ".join(f"{LABELS[v]} {sum(f) / len(f):.1f}" for v, f in fps.items() if f),
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="/work/shared/data/tracking")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None)
    ap.add_argument("--page", default=str(ROOT / "docs" / "benchmarks" / "fused.md"))
    ap.add_argument("--render-only", action="store_true")
    a = ap.parse_args(argv)
    data = Path(a.data)
    base = Path(a.out or tempfile.mkdtemp(prefix="bench_fused_"))
    runs = [("pedestrian", base / "pedestrian", PEDESTRIAN), ("vehicle", base / "vehicle", VEHICLE)]
    if not a.render_only:
        for model, out, seqs in runs:
            _run(data, seqs, model, out, a)
    command = "python tools/bench_fused.py " + " ".join(argv if argv is not None else sys.argv[1:])
    page = render(runs, data, command)
    old = Path(a.page).read_text() if Path(a.page).is_file() else ""
    if NOTES_MARKER in old:  # hand-written notes below the marker survive a re-run
        page = page.rstrip("\n") + "\n\n" + NOTES_MARKER + old.split(NOTES_MARKER, 1)[1]
    write_text_atomic(a.page, page)
    print(page)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
