"""Bachoo et al.'s metrics for the template tracker on every dev sequence, next to OpenCV
TrackerMIL in the same ``torchtrack eval`` run (one-pass and re-initialising passes).

Writes ``docs/benchmarks/template.md`` (atomically) and prints it.

    python tools/bench_template.py --data /work/shared/data/tracking --max-frames 150 --jobs 2

Track length % and re-initialisations per 100 frames come from the re-initialising pass
(``--reinit``: re-init from the ground truth when the centre error exceeds 100 px, Bachoo
sec. 4); track ratio and the x / y centre errors (mean +- std) while the tracker says it tracks
("target") and while it does not ("no target") from the one-pass run. AUC, precision@20 and
fps from the one-pass run (fps: ratios within this run are what to quote; the machine is
shared).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from torchtrack.io.atomic import write_text_atomic

ROOT = Path(__file__).resolve().parents[1]


def _ms(v) -> str:
    if not v or v[0] is None:
        return "-"
    return f"{v[0]:.1f} ± {v[1]:.1f}"


def _f(v, fmt="{:.3f}") -> str:
    return "-" if v is None else fmt.format(v)


def _full_metrics(out: Path, res: dict) -> dict:
    """Per-sequence metrics with the target / no-target errors (from the per-run records)."""
    full: dict = {}
    for f in sorted((out / "sequences").glob("*/*.json")):
        rec = json.loads(f.read_text())
        full.setdefault(rec["sequence"], {})[rec["tracker"]] = rec.get("metrics") or {
            "error": rec.get("error")
        }
    return full or res["per_sequence"]


def render(res: dict, trackers: list[str], command: str, out: Path) -> str:
    ps, pr = _full_metrics(out, res), res.get("per_sequence_reinit") or {}
    ov, ovr = res["overall"], res.get("overall_reinit") or {}
    lines = [
        "# Template tracker (Bachoo et al. 2011) on the dev sequences",
        "",
        f"Command: `{command}`",
        "",
        f"Evaluator command: `{res['command']}`",
        "",
        "## Dev-set summary (same run)",
        "",
        "| tracker | AUC | prec@20 | fps | fps / MIL | track length % (reinit) | "
        "re-inits / 100 | track ratio % |",
        "|---|---|---|---|---|---|---|---|",
    ]
    mil_fps = ov.get("mil", {}).get("fps")
    for t in trackers:
        o, orr = ov.get(t, {}), ovr.get(t, {})
        ratio = o.get("fps") / mil_fps if mil_fps and o.get("fps") else None
        lines.append(
            f"| {t} | {_f(o.get('auc'))} | {_f(o.get('precision_20'))} | "
            f"{_f(o.get('fps'), '{:.1f}')} | {_f(ratio, '{:.2f}')} | "
            f"{_f(orr.get('track_length'), '{:.1f}')} | {_f(orr.get('reinit_per_100'), '{:.2f}')} | "
            f"{_f(o.get('track_ratio'), '{:.1f}')} |"
        )
    for t in trackers:
        lines += [
            "",
            f"## Bachoo metrics per sequence: `{t}`",
            "",
            "| sequence | n | l % | re-inits / 100 | r % | x err (target) | y err (target) | "
            "x err (no target) | y err (no target) | AUC |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for seq in sorted(ps):
            m = ps[seq].get(t) or {}
            mr = (pr.get(seq) or {}).get(t) or {}
            if m.get("error"):
                lines.append(f"| {seq} | failed: {m['error']} |")
                continue
            lines.append(
                f"| {seq} | {m.get('n_frames', '-')} | {_f(mr.get('track_length'), '{:.0f}')} | "
                f"{_f(mr.get('reinit_per_100'), '{:.2f}')} | {_f(m.get('track_ratio'), '{:.0f}')} | "
                f"{_ms(m.get('x_error_target'))} | {_ms(m.get('y_error_target'))} | "
                f"{_ms(m.get('x_error_no_target'))} | {_ms(m.get('y_error_no_target'))} | "
                f"{_f(m.get('auc'))} |"
            )
    lines += [
        "",
        "Paper (maritime footage, 8-bit grey, Table 1): l 83 / 83 / 16 %, re-inits 0.15 / 0.06 / "
        "0.57 per 100 frames, r 57 / 73 / 53 %, x error when tracking 5.5-6.7 px.",
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="/work/shared/data/tracking")
    ap.add_argument("--trackers", nargs="+", default=["template", "mil"])
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="eval output folder (default: a temp folder)")
    ap.add_argument("--page", default=str(ROOT / "docs" / "benchmarks" / "template.md"))
    ap.add_argument("--render-only", action="store_true", help="reuse OUT/results.json")
    a = ap.parse_args(argv)
    out = Path(a.out or tempfile.mkdtemp(prefix="bench_template_"))
    if "mil" not in a.trackers:
        a.trackers.append("mil")
    if not a.render_only:
        cmd = [
            sys.executable,
            "-m",
            "torchtrack",
            "eval",
            "--sequences",
            a.data,
            "--trackers",
            *a.trackers,
            "--reinit",
            "--out",
            str(out),
            "--jobs",
            str(a.jobs),
            "--seed",
            str(a.seed),
            "--no-progress",
        ]
        if a.max_frames:
            cmd += ["--max-frames", str(a.max_frames)]
        subprocess.run(cmd, check=True)
    res = json.loads((out / "results.json").read_text())
    command = "python tools/bench_template.py " + " ".join(
        x for x in (argv if argv is not None else sys.argv[1:])
    )
    page = render(res, a.trackers, command, out)
    write_text_atomic(a.page, page)
    print(page)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
