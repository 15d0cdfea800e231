"""Single-object trackers over seeds: mean and spread, leave-one-sequence-out, BoBoT Table I.

Reads ``torchtrack eval`` output folders, one per seed (every folder the same trackers and
sequences, e.g. ``for s in 0 1 2 3 4; do torchtrack eval ... --seed $s --out runs/dev/seed$s``;
folders of the same name, such as ``runs/dev/seed0`` and ``runs/mot_sot/seed0``, are one seed's
runs split over several calls and are merged) and writes a markdown page:

* **Dev set over seeds**: per tracker the mean AUC over the sequences of each seed run, then the
  mean and standard deviation of that over the seeds; precision@20, the median fps, losses
  and re-acquisitions (:func:`torchtrack.eval.metrics.losses_and_reacquisitions`) summed over
  the sequences; a per-sequence table (mean over seeds).
* **Leave one sequence out** (``--loso NAME=SPEC ...``): each candidate is a tracker spec of the
  runs; for every sequence the candidate with the best mean AUC on the *other* sequences
  (averaged over seeds) is chosen and scored on the held-out one; the page gives the held-out
  scores, their mean, median and worst sequence, and which candidate each fold chose.
* **BoBoT Table I** (``--bobot DIR ...``): mean IoU % on the BoBoT sequence per tracker, mean and
  standard deviation over the seed folders, against Klein et al.'s numbers.

    python tools/bench_sot.py --results runs/dev/seed* --out docs/benchmarks/sot.md \\
        --loso robust=adaptive-haar paper=adaptive-haar:config=configs/trackers/adaptive_haar_paper.toml

Losses and re-acquisitions are recomputed from the stored boxes and the ground truth (``--data``)
so that runs made before the metric existed are counted the same way.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PAPER_TABLE_I = {"histogram": 68.94, "adaptive-haar:adapt=none": 48.97,
                 "adaptive-haar:adapt=global": 75.02, "adaptive-haar:adapt=per-particle": 56.33}  # fmt: skip


def load_runs(folders: list[Path]) -> dict[str, dict[str, dict[str, dict]]]:
    """``{seed: {tracker: {sequence: record}}}`` of the OPE records under each folder.

    Folders with the same name (``runs/dev/seed0`` and ``runs/heldout/seed0``) are one seed's
    runs split over several ``torchtrack eval`` calls (other trackers, other sequences) and
    are merged; a record found twice keeps the last folder's."""
    out: dict[str, dict[str, dict[str, dict]]] = {}
    for d in folders:
        files = sorted((d / "sequences").glob("*/*.json"))
        if not files:
            sys.exit(f"no sequence results under {d}")
        runs = out.setdefault(d.name, {})
        for f in files:
            rec = json.loads(f.read_text())
            runs.setdefault(rec["tracker"], {})[rec["sequence"]] = rec
    return out


def _gt(data: list[Path]) -> dict:
    from torchtrack.io.sequences import find_sequences

    return {s.name: s.boxes for d in data if d.exists() for s in find_sequences(d)}


def _loss_counts(rec: dict, gt) -> tuple[int, int]:
    import torch

    from torchtrack.eval.metrics import MISS_IOU, frame_ious, losses_and_reacquisitions

    if rec.get("error") or not rec.get("boxes") or gt is None:
        return 0, 0
    b = torch.tensor([[math.nan if v is None else v for v in r] for r in rec["boxes"]])
    g = gt[: b.shape[0]].to(torch.float64)
    iou = frame_ious(b.to(torch.float64), g)
    ev = torch.ones(len(iou), dtype=torch.bool)
    for i in rec.get("init_frames") or [0]:
        ev[i] = False
    iou = iou[ev & torch.isfinite(iou)]
    return losses_and_reacquisitions(iou >= MISS_IOU)


def _f(v: float | None, nd: int = 3) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{nd}f}"


def _ms(vals: list[float], nd: int = 3, scale: float = 1.0) -> str:
    if not vals:
        return "-"
    m = statistics.mean(vals) * scale
    if len(vals) == 1:
        return f"{m:.{nd}f} (1 run)"
    return f"{m:.{nd}f} ± {statistics.stdev(vals) * scale:.{nd}f}"


def seed_means(runs, tracker: str, seqs: list[str], key: str = "auc") -> list[float]:
    """The mean of ``key`` over ``seqs`` in every seed folder holding them all."""
    out = []
    for per in runs.values():
        recs = per.get(tracker, {})
        vals = [recs[s]["metrics"][key] for s in seqs if s in recs and recs[s].get("metrics")]
        if len(vals) == len(seqs):
            out.append(statistics.mean(vals))
    return out


def dev_table(runs, trackers: list[str], seqs: list[str], gt) -> list[str]:
    lines = [
        "| tracker | mean AUC (mean ± sd over seeds) | per seed | precision@20 | median fps "
        "| losses / re-acquisitions (all sequences, mean over seeds) |",
        "|---|---|---|---|---|---|",
    ]
    for t in trackers:
        aucs = seed_means(runs, t, seqs)
        p20 = seed_means(runs, t, seqs, "precision_20")
        fps = [r["fps"] for per in runs.values() for r in per.get(t, {}).values() if r.get("fps")]
        lost, found = [], []
        for per in runs.values():
            if not all(s in per.get(t, {}) for s in seqs):
                continue  # a seed this tracker was not run on (a deterministic peer: one run)
            counts = [_loss_counts(per[t][s], gt.get(s)) for s in seqs]
            lost.append(sum(c[0] for c in counts))
            found.append(sum(c[1] for c in counts))
        lines.append(
            f"| {t} | **{_ms(aucs)}** | {' / '.join(f'{a:.3f}' for a in aucs)} | {_ms(p20)} | "
            f"{_f(statistics.median(fps), 1) if fps else '-'} | "
            f"{statistics.mean(lost):.1f} / {statistics.mean(found):.1f} |"
            if lost
            else "- |"
        )
    lines += ["", "| sequence | " + " | ".join(trackers) + " |", "|---" * (len(trackers) + 1) + "|"]
    for s in seqs:
        cells = [_ms(seed_means(runs, t, [s]), 3) for t in trackers]
        lines.append(f"| {s} | " + " | ".join(cells) + " |")
    return lines


def loso(runs, candidates: dict[str, str], seqs: list[str]) -> list[str]:
    """Leave-one-sequence-out choice among ``candidates`` (label -> tracker spec)."""
    held, rows = [], []
    for s in seqs:
        rest = [x for x in seqs if x != s]
        score = {}
        for label, spec in candidates.items():
            v = seed_means(runs, spec, rest)
            score[label] = statistics.mean(v) if v else -math.inf
        pick = max(score, key=score.get)
        out = seed_means(runs, candidates[pick], [s])
        val = statistics.mean(out) if out else math.nan
        held.append(val)
        rows.append(f"| {s} | {pick} | {_f(score[pick])} | **{_f(val)}** |")
    worst = min(range(len(seqs)), key=lambda i: held[i])
    lines = [
        "| held-out sequence | chosen on the other sequences | its mean AUC there | held-out AUC |",
        "|---|---|---|---|",
        *rows,
        "",
        f"Held-out AUC over the {len(seqs)} folds: mean **{statistics.mean(held):.3f}**, median "
        f"**{statistics.median(held):.3f}**, worst **{held[worst]:.3f}** ({seqs[worst]}).",
        "",
        "Candidates: " + "; ".join(f"`{k}` = `{v}`" for k, v in candidates.items()) + ".",
    ]
    return lines


def bobot_table(runs, trackers: list[str]) -> list[str]:
    lines = [
        "| tracker | mean IoU % (mean ± sd over seeds) | per seed | paper % |",
        "|---|---|---|---|",
    ]
    for t in trackers:
        vals = [
            per[t][s]["metrics"]["mean_iou"] * 100
            for per in runs.values()
            for s in per.get(t, {})
            if "bobot" in s.lower() and per[t][s].get("metrics")
        ]
        paper = PAPER_TABLE_I.get(t.replace("adaptive-haar", "adaptive-haar:adapt=global"), None)
        paper = PAPER_TABLE_I.get(t, paper)
        lines.append(
            f"| {t} | **{_ms(vals, 1)}** | {' / '.join(f'{v:.1f}' for v in vals)} | "
            f"{_f(paper, 2)} |"
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--results", nargs="*", type=Path, default=[], help="dev-set folders, one per seed"
    )
    ap.add_argument("--bobot", nargs="*", type=Path, default=[], help="BoBoT folders, one per seed")
    ap.add_argument("--loso", nargs="*", default=[], metavar="LABEL=SPEC")
    ap.add_argument(
        "--data",
        nargs="+",
        type=Path,
        default=[REPO.parent / "shared" / "data" / "tracking"],
        help="the sequences' folders (ground truth for losses and re-acquisitions)",
    )
    ap.add_argument("--title", default="Single-object trackers over seeds")
    ap.add_argument("--note", default="", help="text under the title (command, load, machine)")
    ap.add_argument("--out", type=Path, default=None, help="markdown page to write")
    a = ap.parse_args(argv)
    lines = [f"# {a.title}", ""]
    if a.note:
        lines += [a.note, ""]
    if a.results:
        runs = load_runs(a.results)
        trackers = list(dict.fromkeys(t for per in runs.values() for t in per))
        seqs = sorted({s for per in runs.values() for t in per.values() for s in t})
        gt = _gt(a.data)
        lines += [f"## {len(seqs)} sequences, {len(runs)} seeds", ""]
        lines += [*dev_table(runs, trackers, seqs, gt), ""]
        if a.loso:
            cands = dict(x.split("=", 1) for x in a.loso)
            lines += ["## Leave one sequence out", "", *loso(runs, cands, seqs), ""]
    if a.bobot:
        runs = load_runs(a.bobot)
        trackers = list(next(iter(runs.values())))
        lines += [f"## BoBoT (Klein et al. Table I, sequence I), {len(runs)} seeds", ""]
        lines += [*bobot_table(runs, trackers), ""]
    text = "\n".join(lines) + "\n"
    if a.out:
        from torchtrack.io.atomic import write_text_atomic

        write_text_atomic(a.out, text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
