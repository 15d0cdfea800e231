"""Markdown tables of evaluation results (``results.md`` and the benchmark page)."""

from __future__ import annotations

__all__ = [
    "bachoo_table",
    "fmt",
    "klein_table_row",
    "overall_table",
    "per_sequence_table",
    "results_markdown",
]

#: Klein et al. 2010, Table I, sequence I (BoBoT, 1016 frames): average IoU in percent.
KLEIN_TABLE_I_SEQ_I = {
    "Histogram": 68.94,
    "Multi-Comp.": 47.63,
    "n. ad. Hcs": 48.97,
    "adapt. Hcs": 75.02,
    "adapt. p. part. Hcs": 56.33,
}


def fmt(v, digits: int = 3, pct: bool = False) -> str:
    """Format a number for a table: ``-`` for missing, percent with 2 decimals if ``pct``."""
    if v is None:
        return "-"
    if isinstance(v, (list, tuple)):
        if not v or v[0] is None:
            return "-"
        return f"{v[0]:.1f} ± {v[1]:.1f}"
    if pct:
        return f"{100 * v:.2f}"
    return f"{v:.{digits}f}"


def overall_table(summary: dict, key: str = "overall") -> str:
    """Per-tracker averages over the sequences as a markdown table."""
    rows = [
        "| tracker | AUC | prec@20px | norm. prec | mean IoU | miss rate | fps | track len % "
        "| track ratio % | ok=False frames | failed seq |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, a in summary.get(key, {}).items():
        failed = str(a.get("n_failed", 0))
        rows.append(
            f"| {name} | {fmt(a.get('auc'))} | {fmt(a.get('precision_20'))} | "
            f"{fmt(a.get('norm_precision'))} | {fmt(a.get('mean_iou'))} | "
            f"{fmt(a.get('miss_rate'))} | {fmt(a.get('fps'), 1)} | "
            f"{fmt(a.get('track_length'), 1)} | {fmt(a.get('track_ratio'), 1)} | "
            f"{a.get('tracker_failures') if a.get('tracker_failures') is not None else '-'} | "
            f"{failed} |"
        )
    return "\n".join(rows)


def per_sequence_table(summary: dict, metric: str = "auc", key: str = "per_sequence") -> str:
    """Sequences x trackers table of one metric (``failed`` where the tracker raised)."""
    trackers = summary.get("trackers", [])
    rows = ["| sequence | " + " | ".join(trackers) + " |", "|---" * (len(trackers) + 1) + "|"]
    for seq, per in summary.get(key, {}).items():
        cells = []
        for t in trackers:
            r = per.get(t)
            if r is None:
                cells.append("")
            elif r.get("error"):
                cells.append("failed")
            else:
                cells.append(fmt(r.get(metric)))
        rows.append(f"| {seq} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def bachoo_table(summary: dict, key: str = "overall_reinit") -> str:
    """Bachoo et al. Table 1 style: track length, re-initialisations per 100 frames, track
    ratio, mean absolute x / y error (sequence means)."""
    rows = [
        "| tracker | track length % | re-inits / 100 fr | track ratio % | fps |",
        "|---|---|---|---|---|",
    ]
    for name, a in summary.get(key, {}).items():
        rows.append(
            f"| {name} | {fmt(a.get('track_length'), 1)} | {fmt(a.get('reinit_per_100'), 2)} | "
            f"{fmt(a.get('track_ratio'), 1)} | {fmt(a.get('fps'), 1)} |"
        )
    return "\n".join(rows)


def klein_table_row(summary: dict, sequence: str) -> str:
    """Klein et al. Table I format for one sequence: average IoU (%) per tracker, with the
    paper's published numbers for their sequence I (BoBoT) alongside."""
    per = summary.get("per_sequence", {}).get(sequence, {})
    names = list(KLEIN_TABLE_I_SEQ_I) + list(per)
    head = "| Seq. | # Fr. | " + " | ".join(names) + " |"
    sep = "|---" * (len(names) + 2) + "|"
    n = next((r.get("n_evaluated") for r in per.values() if r.get("n_evaluated")), None)
    paper = [f"{v:.2f} (paper)" for v in KLEIN_TABLE_I_SEQ_I.values()]
    ours = ["failed" if r.get("error") else fmt(r.get("mean_iou"), pct=True) for r in per.values()]
    return "\n".join(
        [head, sep, f"| I. ({sequence}) | {n or '-'} | " + " | ".join(paper + ours) + " |"]
    )


def results_markdown(summary: dict) -> str:
    """The whole ``results.md``."""
    parts = ["# Tracking evaluation", ""]
    if summary.get("command"):
        parts += ["Command:", "", "```", summary["command"], "```", ""]
    parts += [
        f"{len(summary.get('sequences', []))} sequences; one-pass evaluation (initialised from "
        "the first ground-truth box, first frame excluded). Success AUC over 21 IoU thresholds, "
        "precision at 20 px, normalised precision (AUC on [0, 0.5]), Klein's mean IoU and miss "
        "rate (IoU < 1/3); averages over sequences; fps = tracker update time only.",
        "",
        overall_table(summary),
        "",
        "## AUC per sequence",
        "",
        per_sequence_table(summary, "auc"),
        "",
        "## Mean IoU per sequence",
        "",
        per_sequence_table(summary, "mean_iou"),
        "",
    ]
    if summary.get("overall_reinit"):
        parts += [
            "## Re-initialising pass (Bachoo et al.: re-init from ground truth when the centre "
            "is more than 100 px off)",
            "",
            bachoo_table(summary),
            "",
        ]
    failed = [(t, f) for t, a in summary.get("overall", {}).items() for f in a.get("failed", [])]
    if failed:
        parts += ["## Failed runs", ""]
        parts += [f"- {t} on {f['sequence']} (frame {f['frame']}): {f['error']}" for t, f in failed]
        parts.append("")
    return "\n".join(parts)
