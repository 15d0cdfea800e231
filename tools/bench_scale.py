"""Corpus-scale evaluation: one tracker on the 12 dev sequences with ``--backend local --jobs
1|2`` and on a local Ray instance with 1 and 2 worker CPUs, all in one run.

Prints and writes ``docs/benchmarks/scale.md`` (atomically; hand-written notes below the page's
``<!-- notes -->`` marker are kept): wall time and speed-up of each setting, Ray's overhead per
task, peak memory per worker process, whether every setting wrote the same boxes, and the rate
at which the Ray head schedules tasks, with what it implies for a larger cluster (on paper).

    python tools/bench_scale.py --tracker detector --max-frames 400 --repeats 3

The four settings run back to back, then backwards in the next repeat (ABBA), and every ratio
is taken within one repeat, then summarised as median (min-max): on a shared machine the load
drifts, and a ratio between two settings minutes apart would measure the drift.

Definitions (all from this run):

* wall: seconds inside ``evaluate()``, results written; a Ray setting's instance is started
  before and stopped after (reported apart, and added in "wall with start / stop": a cluster
  is started once for many runs). The local pool's process start-up is inside its wall.
  In-process runs use one torch thread, as every worker does.
* speed-up on 2 workers: wall of the 1-worker setting / wall of the 2-worker setting; next to
  it, the most the task lengths allow (sum of the 1-worker task times / their longest-first
  makespan on 2 workers) and how much the tasks' own time grew on 2 workers (1.00 when each
  worker had a core to itself).
* Ray overhead per task: [(Ray wall - its tasks' time) - (in-process wall - its tasks' time)]
  / tasks, with 1 worker each: what a task costs on Ray outside the tracking that it does not
  in this process (scheduling, shipping the sequence and the result, a worker's start-up and
  imports). Subtracting each run's own task time cancels the load; the plain difference of the
  walls is given too.
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
SETTINGS = (  # label, backend, jobs (local processes or Ray CPUs); run in this order, then
    # backwards (ABBA), so a load that drifts during the run hits each pair alike
    ("local, 1 process", "local", 1),
    ("ray, 1 worker", "ray", 1),
    ("ray, 2 workers", "ray", 2),
    ("local, 2 processes", "local", 2),
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

    res: dict = {"label": label, "backend": backend, "jobs": jobs, "load": [os.getloadavg()[0]]}
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
    res["load"].append(os.getloadavg()[0])
    recs = _records(out)
    res["tasks"] = len(recs)
    res["task_times"] = sorted((r["wall_seconds"] or 0.0 for r in recs), reverse=True)
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


def _med(xs: list) -> float | None:
    xs = [x for x in xs if x is not None]
    return statistics.median(xs) if xs else None


def _span(xs: list, fmt: str = "{:.2f}") -> str:
    """Median, and the range when there are several values."""
    xs = [x for x in xs if x is not None]
    if not xs:
        return "-"
    m = fmt.format(statistics.median(xs))
    return m if len(xs) == 1 else f"{m} ({fmt.format(min(xs))}-{fmt.format(max(xs))})"


def _lpt(times: list[float], workers: int) -> float:
    """Makespan of ``times`` (longest first) handed to ``workers`` as each frees up."""
    free = [0.0] * workers
    for t in sorted(times, reverse=True):
        free[free.index(min(free))] += t
    return max(free)


def render(runs: dict[str, list[dict]], meta: dict) -> str:
    """The page; ratios are taken within each repeat (the settings of one repeat ran back to
    back) and their medians reported."""
    L1, L2 = runs["local, 1 process"], runs["local, 2 processes"]
    R1, R2 = runs["ray, 1 worker"], runs["ray, 2 workers"]
    n = R1[0]["tasks"]
    reps = range(len(R1))
    ray_up = [R1[k]["wall"] / R2[k]["wall"] for k in reps]
    loc_up = [L1[k]["wall"] / L2[k]["wall"] for k in reps]
    ray_vs_loc = [L2[k]["wall"] / R2[k]["wall"] for k in reps]
    over_in = [(R1[k]["wall"] - R1[k]["task_seconds"]) / n for k in reps]
    # Ray's own cost: its time outside the tasks minus the in-process run's (writing results
    # and scoring happen in both), per task; each run subtracts its own task time, so the load
    # during the two runs cancels out of it, unlike a difference of walls.
    over = [over_in[k] - (L1[k]["wall"] - L1[k]["task_seconds"]) / n for k in reps]
    over_wall = [(R1[k]["wall"] - L1[k]["wall"]) / n for k in reps]
    bound = [R1[k]["task_seconds"] / _lpt(R1[k]["task_times"], 2) for k in reps]
    inflate = [R2[k]["task_seconds"] / R1[k]["task_seconds"] for k in reps]
    d = _med([r["task_seconds"] / n for r in R1])
    same = all(r["boxes"] == L1[0]["boxes"] for rs in runs.values() for r in rs)
    o = _med(over)

    def f(v, fmt="{:.1f}"):
        return "-" if v is None else fmt.format(v)

    lines = [
        "# Scale: evaluation on Ray vs local processes",
        "",
        f"One tracker (`{meta['tracker']}`) on the {meta['n_seq']} dev sequences "
        f"({meta['frames']} frames{meta['head']}), one task per (tracker, sequence, seed), "
        f"{meta['repeats']} repeat(s) of the four settings in one run of",
        "",
        "```",
        meta["command"],
        "```",
        "",
        f"Machine: {meta['machine']}; Ray {meta['ray']}, torch {meta['torch']}. Load before: "
        f"`{meta['load_before']}`; after: `{meta['load_after']}`. The 2 cores are shared "
        "with other jobs: absolute times are inflated; the ratios are taken within each "
        "repeat (its settings ran back to back, in the order of the table and then "
        "backwards) and given as median (min-max).",
        "",
        "| setting | wall s | sum of task times s | Ray start / stop s | wall with start / "
        "stop s | worker processes | peak memory per worker MiB | failed tasks | 1-min load "
        "before / after |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for label, rs in runs.items():
        wall = _med([r["wall"] for r in rs])
        if rs[0]["backend"] == "ray":
            start = (
                f"{f(_med([r['startup'] for r in rs]))} / {f(_med([r['shutdown'] for r in rs]))}"
            )
            total = f(_med([r["wall"] + r["startup"] + r["shutdown"] for r in rs]))
        else:
            start, total = "-", f(wall)
        loads = "; ".join(f"{r['load'][0]:.1f} / {r['load'][1]:.1f}" for r in rs)
        lines.append(
            f"| {label} | {f(wall)} | {f(_med([r['task_seconds'] for r in rs]))} | {start} | "
            f"{total} | {max(r['workers'] for r in rs)} | "
            f"{f(max(r['peak_rss'] or 0 for r in rs), '{:.0f}')} | "
            f"{sum(r['failed'] for r in rs)} | {loads} |"
        )
    up = _med(ray_up)
    lines += [
        "",
        f"* **Speed-up on 2 workers: Ray {_span(ray_up)}x**, local processes "
        f"{_span(loc_up)}x (goal >= 1.8x: {'met' if up >= 1.8 else 'missed'}). The task "
        f"lengths allow at most {_span(bound)}x (longest-first on 2 workers, from the "
        "1-worker run's task times). The tasks' own time grew "
        f"{_span(inflate)}x from 1 to 2 Ray workers (1.00 = each worker had a core to itself; "
        "more = the other jobs of the machine took the second core).",
        f"* Ray on 2 workers vs local on 2 processes: {_span(ray_vs_loc)}x the speed (the "
        "local pool's start-up, spawning 2 Python processes that import torch, is inside its "
        "wall; Ray's is in its start-up).",
        f"* **Ray overhead per task: {_span(over, '{:.3f}')} s** (goal <= 1 s: "
        f"{'met' if o is not None and o <= 1.0 else 'missed'}): the Ray 1-worker run's time "
        "outside its tasks minus the in-process run's, per task (scheduling, shipping "
        "sequences and results, a worker's first imports; each run subtracts its own task "
        "time, so the load cancels). The Ray run's own time outside its tasks: "
        f"{_span(over_in, '{:.3f}')} s per task; the difference of the two walls, which the "
        f"load moves: {_span(over_wall, '{:.3f}')} s per task. Mean task: {f(d, '{:.2f}')} s.",
        f"* Same boxes in every setting and repeat: **{'yes' if same else 'NO'}** (every "
        "record's `boxes` compared with the in-process run's).",
    ]
    rate = _med([r.get("rate") for r in R2])
    if rate:
        trip = _med([r.get("round_trip") for r in R2])
        oh = _med(over_in)
        lines += [
            f"* Scheduling: **{rate:.0f} no-op tasks / s** through the 2-CPU instance (2,000 "
            f"at once), round trip of one no-op task {trip * 1000:.1f} ms.",
            "",
            "On paper, for a larger cluster (one head node, every worker asking for its next "
            "task when one ends): a head that schedules R tasks / s keeps about R x d workers "
            "busy on tasks of d seconds, and a worker spends d / (d + o) of its time tracking "
            f"for a per-task overhead o (here o = {oh:.3f} s, the in-run overhead).",
            "",
            "| task length d | workers one head keeps busy (R = measured rate) | "
            "same with R = 1 / o | worker efficiency d / (d + o) |",
            "|---|---|---|---|",
        ]
        for label, dd in (
            (f"{d:.1f} s (this dev set)", d),
            ("60 s (a 1-minute clip)", 60.0),
            ("3600 s (an hour of footage)", 3600.0),
        ):
            lines.append(
                f"| {label} | {rate * dd:,.0f} | {dd / max(oh, 1e-3):,.0f} | "
                f"{dd / (dd + max(oh, 0.0)):.1%} |"
            )
        lines += [
            "",
            "The measured rate is a floor: here the head, its workers, the driver and the "
            "other jobs of the machine share 2 cores. `R = 1 / o` counts all of a task's "
            "overhead as head time (most of it is shipping and worker start-up, spread over "
            "the workers), so it is the pessimistic column.",
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
            order = SETTINGS if k % 2 == 0 else SETTINGS[::-1]
            for label, backend, jobs in order:
                out = root / f"rep{k}" / label.replace(", ", "_").replace(" ", "_")
                r = run_setting(
                    label, backend, jobs, seqs, args.tracker, out, measure_rate=jobs == 2
                )
                print(
                    f"{label}: {r['wall']:.1f} s (load {r['load'][0]:.1f} -> "
                    f"{r['load'][1]:.1f}), {r['tasks']} tasks, peak "
                    f"{r['peak_rss'] or 0:.0f} MiB"
                    + (f", rate {r['rate']:.0f}/s" if r.get("rate") else ""),
                    flush=True,
                )
                runs[label].append(r)
    finally:
        if tmp is not None:
            tmp.cleanup()
    meta["load_after"] = _load()
    page = render(runs, meta)
    path = Path(args.page)
    old = path.read_text() if path.exists() else ""
    if NOTES_MARKER in old:
        page += "\n" + NOTES_MARKER + old.split(NOTES_MARKER, 1)[1]
    write_text_atomic(path, page)
    print(page)
    return 0


if __name__ == "__main__":
    sys.exit(main())
