"""Markdown tables and plots from a results summary."""

from __future__ import annotations

import cv2

from torchtrack.eval.plots import plot_curves
from torchtrack.eval.report import klein_table_row, overall_table, per_sequence_table

SUMMARY = {
    "trackers": ["a", "b"],
    "overall": {
        "a": {"auc": 0.5, "precision_20": 0.6, "mean_iou": 0.55, "fps": 12.345, "n_failed": 0},
        "b": {"auc": None, "n_failed": 1},
    },
    "per_sequence": {
        "bobot": {
            "a": {"mean_iou": 0.7502, "auc": 0.7, "n_evaluated": 1016, "error": None},
            "b": {"error": "RuntimeError: x"},
        }
    },
}


def test_tables():
    t = overall_table(SUMMARY)
    assert "| a | 0.500 | 0.600 | - | 0.550 | - | 12.3 |" in t
    assert t.splitlines()[-1].endswith("| 1 |")
    p = per_sequence_table(SUMMARY, "auc")
    assert "| bobot | 0.700 | failed |" in p


def test_klein_row_has_paper_numbers_and_ours():
    row = klein_table_row(SUMMARY, "bobot")
    assert "68.94 (paper)" in row and "75.02 (paper)" in row and "56.33 (paper)" in row
    assert row.splitlines()[-1].endswith("| 75.02 | failed |")
    assert "| I. (bobot) | 1016 |" in row


def test_plot_curves_writes_a_png(tmp_path):
    path = plot_curves(
        {"x": [1.0] * 10 + [0.5] * 10 + [0.0], "y": [None] * 21},
        tmp_path / "s.png",
        kind="success",
        title="t",
    )
    img = cv2.imread(str(path))
    assert img is not None and img.shape[2] == 3
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
