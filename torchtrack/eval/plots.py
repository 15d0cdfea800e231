"""Success and precision plots (PNG, one curve per tracker), written atomically."""

from __future__ import annotations

import os
from pathlib import Path

from torchtrack.eval.metrics import PRECISION_THRESHOLDS, SUCCESS_THRESHOLDS
from torchtrack.eval.runner import safe_name
from torchtrack.io.atomic import atomic_path

__all__ = ["plot_curves", "write_plots"]


def plot_curves(
    curves: dict[str, list[float]],
    path: str | os.PathLike,
    *,
    kind: str,
    title: str,
) -> Path:
    """Write a success (``kind="success"``) or precision (``kind="precision"``) plot.

    Args:
        curves: tracker label -> curve values (21 success values over IoU 0..1, or 51
            precision values over 0..50 px). ``None`` entries are skipped.
        path: the PNG to write.
        title: the plot title.

    The legend is sorted best first and shows the AUC (success) or the value at 20 px
    (precision), as in the OTB paper.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if kind == "success":
        xs, xlabel, ylabel = SUCCESS_THRESHOLDS.tolist(), "overlap threshold", "success rate"

        def score(c):
            return sum(c) / len(c)
    else:
        xs, xlabel, ylabel = (
            PRECISION_THRESHOLDS.tolist(),
            "location error threshold (px)",
            ("precision"),
        )

        def score(c):
            return c[20]

    items = [(k, c) for k, c in curves.items() if c and all(v is not None for v in c)]
    items.sort(key=lambda kc: -score(kc[1]))
    fig, ax = plt.subplots(figsize=(6, 4.5), dpi=100)
    for label, c in items:
        ax.plot(xs, c, label=f"{label} [{score(c):.3f}]", linewidth=1.8)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_ylim(0, 1.0)
    ax.set_xlim(xs[0], xs[-1])
    ax.grid(alpha=0.3)
    ax.set_title(title)
    if items:
        ax.legend(loc="lower left" if kind == "success" else "lower right", fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return Path(path)


def write_plots(summary: dict, out_dir: str | os.PathLike) -> list[str]:
    """Overall ``success.png`` / ``precision.png`` and per-sequence plots under ``plots/``.

    Returns the written paths relative to ``out_dir``.
    """
    out = Path(out_dir)
    written: list[str] = []
    n = len(summary.get("sequences", []))
    for kind in ("success", "precision"):
        curves = {t: a.get(kind) for t, a in summary.get("overall", {}).items()}
        plot_curves(curves, out / f"{kind}.png", kind=kind, title=f"{kind} plot, OPE, {n} seq.")
        written.append(f"{kind}.png")
        for seq, per in summary.get("per_sequence", {}).items():
            curves = {t: r.get(kind) for t, r in per.items() if not r.get("error")}
            rel = f"plots/{safe_name(seq)}_{kind}.png"
            plot_curves(curves, out / rel, kind=kind, title=f"{kind} plot, {seq}")
            written.append(rel)
    return written
