"""Corpus-scale evaluation: one tracker on the 12 dev sequences with ``--backend local --jobs
1|2`` and on a local Ray instance with 1 and 2 worker CPUs, all in one run.

Prints and writes ``docs/benchmarks/scale.md`` (atomically; hand-written notes below the page's
``<!-- notes -->`` marker are kept): wall time and speed-up of each setting, Ray's overhead per
task, peak memory per worker process, whether every setting wrote the same boxes, and the rate
at which the Ray head schedules tasks, with what it implies for a larger cluster (on paper).

    python tools/bench_scale.py --tracker detector --repeats 1

Definitions (all from this run):

* wall: seconds inside ``evaluate()``, results written; a Ray setting's instance is started
  before and stopped after (reported apart, and added in "wall with start / stop": a cluster
  is started once for many runs). The local pool's process start-up is inside its wall.
  In-process runs use one torch thread, as every worker does.
* speed-up on 2 workers: wall of the 1-worker setting / wall of the 2-worker setting.
* Ray overhead per task: (Ray wall - in-process wall) / tasks, with 1 worker each: everything a
  task costs on Ray that it does not in this process (scheduling, shipping the sequence and the
  result, worker start-up and imports). Also given: (Ray wall - sum of task times) / tasks.
* peak memory per worker: the largest ``ru_maxrss`` any worker process reported (each record
  carries its worker's), so the in-process setting reports this whole process.
* scheduling rate: no-op tasks per second through the 2-CPU instance (2,000 submitted at once),
  and the round trip of one no-op task; a head that schedules R tasks / s keeps about R * d
  workers busy on tasks of d seconds (every worker asks for its next task each d seconds).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NOTES_MARKER = "<!-- notes -->"
SETTINGS = (  # label, backend, jobs (local processes or Ray CPUs)
    ("local, 1 process", "local", 1),
    ("ray, 1 worker", "ray", 1),
    ("local, 2 processes", "local", 2),
    ("ray, 2 workers", "ray", 2),
)


def _load() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def _records(out: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted((out / "sequences").rglob("*.json"))]


def _schedule_rate(ray, n: int = 2000) -> tuple[float, float]:
    """(no-op tasks per second with ``n`` submitted at once, median round trip of one, s)."""

    @ray.remote(num_cpus=1)
    def noop() -> None:
        return None

    ray.get([noop.remote() for _ in range(200)])  # workers up
    t0 = time.perf_counter()
    ray.get([noop.remote() for _ in range(n)])
    rate = n / (time.perf_counter() - t0)
    trips = []
    for _ in range(50):
        t0 = time.perf_counter()
        ray.get(noop.remote())
        trips.append(time.perf_counter() - t0)
    return rate, statistics.median(trips)


def run_setting(label, backend, jobs, seqs, tracker, out: Path, measure_rate: bool) -> dict:
    from torchtrack.eval.runner import evaluate

    res: dict = {"label": label, "backend": backend, "jobs": jobs}
    ray = None
    if backend == "ray":
        import ray

        t0 = time.perf_counter()
        ray.init(
            address="local", num_cpus=jobs, include_dashboard=False, logging_level=logging.ERROR
        )
        res["startup"] = time.perf_counter() - t0
    try:
        t0 = time.perf_counter()
        evaluate(seqs, [tracker], out, backend=backend, jobs=jobs, progress=False, seed=0)
        res["wall"] = time.perf_counter() - t0
        if ray is not None and measure_rate:
            res["rate"], res["round_trip"] = _schedule_rate(ray)
    finally:
        if ray is not None:
            t0 = time.perf_counter()
            ray.shutdown()
            res["shutdown"] = time.perf_counter() - t0
    recs = _records(out)
    res["tasks"] = len(recs)
    res["failed"] = sum(1 for r in recs if r["error"])
    res["task_seconds"] = sum(r["wall_seconds"] or 0.0 for r in recs)
    per_pid: dict[int, float] = {}
    for r in recs:
        w = r["worker"] or {}
        if w.get("max_rss_mib") is not None:
            per_pid[w["pid"]] = max(per_pid.get(w["pid"], 0.0), w["max_rss_mib"])
    res["workers"] = len(per_pid)
    res["peak_rss"] = max(per_pid.values()) if per_pid else None
    res["boxes"] = {(r["sequence"], r["tracker"]): r["boxes"] for r in recs}
    return res


def _median_runs(runs: list[dict]) -> dict:
    """One setting over repeats: medians of the timings, the worst memory."""
    out = dict(runs[0])
    for k in ("wall", "startup", "shutdown", "task_seconds", "rate", "round_trip"):
        vals = [r[k] for r in runs if r.get(k) is not None]
        out[k] = statistics.median(vals) if vals else None
    out["peak_rss"] = max((r["peak_rss"] or 0.0) for r in runs) or None
    out["walls"] = [r["wall"] for r in runs]
    return out


def render(res: dict[str, dict], meta: dict) -> str:
    l1, l2 = res["local, 1 process"], res["local, 2 processes"]
    r1, r2 = res["ray, 1 worker"], res["ray, 2 workers"]
    n = r1["tasks"]
    over = (r1["wall"] - l1["wall"]) / n
    over_in = (r1["wall"] - r1["task_seconds"]) / n
    d = r1["task_seconds"] / n
    same = all(r["boxes"] == l1["boxes"] for r in res.values())

    def f(v, fmt="{:.1f}"):
        return "-" if v is None else fmt.format(v)

    lines = [
        "# Scale: evaluation on Ray vs local processes",
        "",
        f"One tracker (`{meta['tracker']}`) on the {meta['n_seq']} dev sequences "
        f"({meta['frames']} frames{meta['head']}), one task per (tracker, sequence, seed), "
        "each setting in the same run of",
        "",
        "```",
        meta["command"],
        "```",
        "",
        f"Machine: {meta['machine']}. Load before: `{meta['load_before']}`; after: "
        f"`{meta['load_after']}` (2 cores shared with other jobs: absolute times are "
        "inflated, compare the ratios). "
        f"Repeats: {meta['repeats']} (medians). Ray {meta['ray']}, torch {meta['torch']}.",
        "",
        "| setting | wall s | speed-up vs 1 | Ray start / stop s | wall with start / stop s | "
        "worker processes | peak memory per worker MiB | failed tasks |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for label, r in res.items():
        base = l1 if r["backend"] == "local" else r1
        start = f"{f(r.get('startup'))} / {f(r.get('shutdown'))}" if r["backend"] == "ray" else "-"
        lines.append(
            f"| {label} | {f(r['wall'])} | {base['wall'] / r['wall']:.2f}x | {start} | "
            f"{r['workers']} | {f(r['peak_rss'], '{:.0f}')} | {r['failed']} |"
        )
    rate = r2.get("rate")
    lines += [
        "",
        f"* **Speed-up on 2 workers: Ray {r1['wall'] / r2['wall']:.2f}x**, local processes "
        f"{l1['wall'] / l2['wall']:.2f}x (goal >= 1.8x: "
        f"{'met' if r1['wall'] / r2['wall'] >= 1.8 else 'missed'}). Ray on 2 workers vs "
        f"local on 2 processes: {l2['wall'] / r2['wall']:.2f}x the speed.",
        f"* **Ray overhead per task: {over:.3f} s** (Ray 1 worker vs in-process, {n} tasks; "
        f"goal <= 1 s: {'met' if over <= 1.0 else 'missed'}); inside the Ray run, wall minus "
        f"the tasks' own time: {over_in:.3f} s per task. Mean task: {d:.2f} s.",
        f"* Same boxes in every setting: **{'yes' if same else 'NO'}** (every record's "
        "`boxes` compared with the in-process run's).",
    ]
    if rate:
        lines += [
            f"* Scheduling: **{rate:.0f} no-op tasks / s** through the 2-CPU instance (2,000 "
            f"at once), round trip of one no-op task {r2['round_trip'] * 1000:.1f} ms.",
            "",
            "On paper, for a larger cluster (one head node, every worker asking for its next "
            "task when one ends): a head that schedules R tasks / s keeps about R x d workers "
            "busy on tasks of d seconds, and a worker spends d / (d + o) of its time tracking "
            "for a per-task overhead o.",
            "",
            "| task length d | workers one head keeps busy (R = measured rate) | "
            "same with R = 1 / overhead | worker efficiency d / (d + o) |",
            "|---|---|---|---|",
        ]
        for label, dd in (
            (f"{d:.1f} s (this dev set)", d),
            ("60 s (a 1-minute clip)", 60.0),
            ("3600 s (an hour of footage)", 3600.0),
        ):
            lines.append(
                f"| {label} | {rate * dd:,.0f} | {dd / max(over, 1e-9):,.0f} | "
                f"{dd / (dd + max(over, 0.0)):.1%} |"
            )
        lines += [
            "",
            "The measured rate is a floor: here the head, its workers, the driver and the "
            "other jobs of the machine share 2 cores. `R = 1 / overhead` counts all of a task's "
            "overhead as head time (most of it is worker start-up and shipping, spread over the "
            "workers), so it is the pessimistic column.",
        ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    import torch

    from torchtrack.io.atomic import write_text_atomic
    from torchtrack.io.sequences import find_sequences

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "tracking"))
    ap.add_argument("--tracker", default="detector")
    ap.add_argument("--max-frames", type=int, help="first N frames of each sequence")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--out", help="keep the eval outputs here (default: a temporary folder)")
    ap.add_argument("--page", default=str(ROOT / "docs" / "benchmarks" / "scale.md"))
    args = ap.parse_args(argv)

    import ray

    torch.set_num_threads(1)  # in-process runs as one worker
    seqs = find_sequences(args.data)
    if args.max_frames:
        seqs = [s.head(args.max_frames) for s in seqs]
    command = "python tools/bench_scale.py " + " ".join(
        shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:])
    )
    meta = {
        "tracker": args.tracker,
        "n_seq": len(seqs),
        "frames": sum(len(s) for s in seqs),
        "head": f", first {args.max_frames} of each" if args.max_frames else ", full length",
        "command": command.strip(),
        "repeats": args.repeats,
        "machine": f"{os.cpu_count()} cores, {platform.machine()}, Python "
        f"{platform.python_version()}",
        "ray": ray.__version__,
        "torch": torch.__version__,
        "load_before": _load(),
    }
    print(f"load: {meta['load_before']}", flush=True)
    tmp = tempfile.TemporaryDirectory() if args.out is None else None
    root = Path(args.out or tmp.name)
    runs: dict[str, list[dict]] = {label: [] for label, _, _ in SETTINGS}
    try:
        for k in range(args.repeats):
            for label, backend, jobs in SETTINGS:  # interleaved: load drifts hit every setting
                out = root / f"rep{k}" / label.replace(", ", "_").replace(" ", "_")
                r = run_setting(
                    label, backend, jobs, seqs, args.tracker, out, measure_rate=jobs == 2
                )
                print(
                    f"{label}: {r['wall']:.1f} s, {r['tasks']} tasks, peak "
                    f"{r['peak_rss'] or 0:.0f} MiB"
                    + (f", rate {r['rate']:.0f}/s" if r.get("rate") else ""),
                    flush=True,
                )
                runs[label].append(r)
    finally:
        if tmp is not None:
            tmp.cleanup()
    meta["load_after"] = _load()
    res = {label: _median_runs(rs) for label, rs in runs.items()}
    page = render(res, meta)
    path = Path(args.page)
    old = path.read_text() if path.exists() else ""
    if NOTES_MARKER in old:
        page += "\n" + NOTES_MARKER + old.split(NOTES_MARKER, 1)[1]
    write_text_atomic(path, page)
    print(page)
    return 0


if __name__ == "__main__":
    sys.exit(main())
