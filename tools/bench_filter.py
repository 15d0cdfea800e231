"""Benchmark the batched particle filter: resampling vs filterpy and `particles`, and a full
SIR step with a 32-feature Haar-like likelihood read from an integral image.

Usage:
    python tools/bench_filter.py                 # everything, writes docs/benchmarks/filter.md
    python tools/bench_filter.py --quick         # smaller N / fewer repeats (smoke run)
    python tools/bench_filter.py --resampling-only 100000   # resampling at these N only; prints
    python tools/bench_filter.py --sir-one B N   # one SIR config in this process; prints JSON
                                                 # with median ms and peak RSS (used internally)

Resampling: each repetition runs torchtrack (1 intra-op thread), `particles` (numba) and
filterpy once in turn (round-robin), so load changes on a shared machine hit all of them alike;
medians over repetitions. torchtrack with 2 threads is timed in a separate pass afterwards
(idle OpenMP workers spin after a parallel region and would slow the next implementation).
filterpy and `particles` are single-threaded.

SIR step: B independent targets in one 320x240 BoBoT frame (integral image from
torchtrack.features.integral), N particles each, Klein AR motion, systematic resampling,
likelihood ``log sigmoid(w . f / area + b)`` over 32 two-rectangle Haar features placed
relative to each particle's box (16 horizontal, 16 vertical; 6 integral-image reads each).
Each (B, N) runs in a fresh subprocess so that its peak RSS is its own.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from torchtrack.filter import KleinAR, sir_step, uniform_log_weights  # noqa: E402
from torchtrack.filter.resample import RESAMPLERS  # noqa: E402
from torchtrack.io.atomic import write_text_atomic  # noqa: E402
from torchtrack.observe.haar_box import HaarBoxFeatures, HaarBoxLikelihood  # noqa: E402

SCHEMES = ["systematic", "stratified", "residual", "multinomial"]
NOTES_MARKER = "<!-- notes: kept by tools/bench_filter.py -->"
DATA = REPO.parent / "shared" / "data" / "tracking" / "bobot_pedestrian"


# --------------------------------------------------------------------------------------------
# Resampling
# --------------------------------------------------------------------------------------------
def bench_resampling(ns: list[int], reps_for) -> list[dict]:
    import filterpy.monte_carlo as fpm
    import particles.resampling as pr

    rows = []
    rng = np.random.default_rng(0)
    for n in ns:
        w = rng.random(n) ** 4  # skewed weights, as after a sharp likelihood
        w /= w.sum()
        wt = torch.from_numpy(w).unsqueeze(0)
        g = torch.Generator().manual_seed(0)
        for scheme in SCHEMES:
            ours = RESAMPLERS[scheme]
            peer_p = getattr(pr, scheme)
            peer_f = getattr(fpm, f"{scheme}_resample")

            def t1(ours=ours, wt=wt, g=g):
                torch.set_num_threads(1)
                ours(wt, g)

            def t2(ours=ours, wt=wt, g=g):
                torch.set_num_threads(2)
                ours(wt, g)

            impls = {
                "torchtrack_1t": t1,
                "particles": lambda peer_p=peer_p, w=w, n=n: peer_p(w, n),
                "filterpy": lambda peer_f=peer_f, w=w: peer_f(w),
            }
            for f in impls.values():  # warm-up (numba compiles on first call)
                f()
            times: dict[str, list[float]] = {k: [] for k in impls}
            cpu: dict[str, list[float]] = {k: [] for k in impls}
            reps, reps_filterpy = reps_for(n)
            for r in range(reps):
                for k, f in impls.items():
                    if k == "filterpy" and r >= reps_filterpy:
                        continue
                    t, c = time.perf_counter(), time.thread_time()
                    f()
                    cpu[k].append(time.thread_time() - c)
                    times[k].append(time.perf_counter() - t)
            # 2 threads in a separate pass: idle OpenMP workers spin for a while after a
            # parallel region and would slow whatever runs next in a round-robin.
            times["torchtrack_2t"] = []
            t2()  # warm-up
            for _ in range(reps):
                t = time.perf_counter()
                t2()
                times["torchtrack_2t"].append(time.perf_counter() - t)
            torch.set_num_threads(1)
            med = {k: statistics.median(v) * 1e3 for k, v in times.items()}
            # CPU time of the timing thread (all three run on it at 1 thread): time spent waiting
            # for a core on a loaded machine does not count, so its ratio is steadier than wall's.
            med_cpu = {f"{k}_cpu": statistics.median(v) * 1e3 for k, v in cpu.items()}
            rows.append(
                {"n": n, "scheme": scheme, **med, **med_cpu, "reps": reps, "reps_fp": reps_filterpy}
            )
            print(
                f"N={n:>8} {scheme:12s} "
                + " ".join(f"{k}={v:.3f}ms" for k, v in {**med, **med_cpu}.items()),
                flush=True,
            )
    torch.set_num_threads(2)
    return rows


# --------------------------------------------------------------------------------------------
# Haar-like likelihood on an integral image
# --------------------------------------------------------------------------------------------
def haar_likelihood(ii: torch.Tensor, motion, n_features=32, seed=0, compile=False):
    """The library's :class:`~torchtrack.observe.haar_box.HaarBoxLikelihood`: ``log sigmoid(
    alpha . f / area + bias)`` over F two-rectangle features, F/2 horizontal and F/2 vertical,
    six integral-image reads each, at fractions drawn from a generator seeded ``seed``."""
    g = torch.Generator().manual_seed(seed)
    feats = HaarBoxFeatures.random(n_features, g)
    alpha = torch.randn(n_features, generator=g) * 4
    return HaarBoxLikelihood(ii, motion.to_boxes, feats, alpha, 0.0, compile=compile)


def _frame_and_box():
    import cv2

    from torchtrack.features.integral import integral_image

    img = cv2.imread(str(DATA / "frames" / "img0002.jpg"), cv2.IMREAD_GRAYSCALE)
    x1, y1, x2, y2 = (float(v) for v in (DATA / "gt.txt").read_text().splitlines()[0].split(","))
    frame = torch.from_numpy(img)[None, None].to(torch.float64)
    frame = frame - frame.mean()
    ii = integral_image(frame)[0, 0]
    return ii, torch.tensor([[x1, y1, x2 - x1, y2 - y1]]), frame[0, 0]


def check_haar(
    lik: HaarBoxLikelihood, frame: torch.Tensor, n_boxes: int = 20
) -> tuple[float, float]:
    """Max abs differences between the likelihood's features and direct pixel sums (slow
    reference), and between its log-likelihood (eager or compiled, as configured) and
    ``logsigmoid(alpha . f_ref + bias)``."""
    g = torch.Generator().manual_seed(1)
    h, w = frame.shape
    feats = lik.features
    err = ll_err = 0.0
    for _ in range(n_boxes):
        bw, bh = (torch.rand(2, generator=g) * torch.tensor([w / 2, h / 2]) + 8).tolist()
        bx, by = (torch.rand(2, generator=g) * torch.tensor([w - bw, h - bh])).tolist()
        box = torch.tensor([[bx, by, bw, bh]], dtype=torch.float32)
        got = lik.features_of(box)[0].double()
        ref = []
        for i in range(len(feats)):
            s3, s2 = feats.split[i].tolist(), feats.span[i].tolist()
            if i < feats.n_horizontal:
                xs = [min(max(round(bx + a * bw), 0), w) for a in s3]
                ys = [min(max(round(by + a * bh), 0), h) for a in s2]
                v = (
                    frame[ys[0] : ys[1], xs[0] : xs[1]].sum()
                    - frame[ys[0] : ys[1], xs[1] : xs[2]].sum()
                )
            else:
                ys = [min(max(round(by + a * bh), 0), h) for a in s3]
                xs = [min(max(round(bx + a * bw), 0), w) for a in s2]
                v = (
                    frame[ys[0] : ys[1], xs[0] : xs[1]].sum()
                    - frame[ys[1] : ys[2], xs[0] : xs[1]].sum()
                )
            ref.append(float(v) / max(bw * bh, 1.0))
        ref_t = torch.tensor(ref, dtype=torch.float64)
        err = max(err, (got - ref_t).abs().max().item())
        ll = lik.log_likelihood_of_boxes(box)[0].double()
        ll_ref = torch.nn.functional.logsigmoid(ref_t @ lik.alpha.double() + lik.bias)
        ll_err = max(ll_err, abs(ll.item() - ll_ref.item()))
    return err, ll_err


def _status_mib(key: str) -> float:
    """``VmRSS`` / ``VmHWM`` of this process from /proc (Linux), in MiB; NaN elsewhere.

    ``getrusage``'s ru_maxrss is not used: Linux carries the parent's high-water mark across
    fork + exec, so a subprocess would report its parent's peak.
    """
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def _reset_peak_rss() -> bool:
    """Reset VmHWM to the current RSS (Linux >= 4.0: write 5 to clear_refs)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def sir_one(b: int, n: int, reps: int, threads: int, compile: bool = False) -> dict:
    torch.set_num_threads(threads)
    ii, box, frame = _frame_and_box()
    motion = KleinAR()
    lik = haar_likelihood(ii, motion, compile=compile)
    haar_err, ll_err = check_haar(lik, frame)
    # float32 table reads: features to ~1e-4; the log-likelihood sums 32 of them times |alpha|
    if haar_err > 1e-3 or ll_err > 1e-2:
        raise SystemExit(
            f"Haar likelihood disagrees with direct pixel sums: max feature error {haar_err}, "
            f"max log-likelihood error {ll_err}"
        )
    zero = lambda s: torch.zeros(s.shape[:2], dtype=s.dtype)  # noqa: E731
    g = torch.Generator().manual_seed(0)
    reset = _reset_peak_rss()
    rss0 = _status_mib("VmRSS" if reset else "VmHWM")
    x = motion.init(box.repeat(b, 1), n, g)
    lw = uniform_log_weights(x)
    r = sir_step(x, lw, motion, lik, generator=g)  # warm-up
    t_step, t_lik, t_filter, c_step = [], [], [], []
    for _ in range(reps):
        t, c = time.perf_counter(), time.thread_time()
        r = sir_step(r.states, r.log_weights, motion, lik, generator=g)
        t_step.append(time.perf_counter() - t)
        c_step.append(time.thread_time() - c)
        t = time.perf_counter()
        lik(r.states)
        t_lik.append(time.perf_counter() - t)
        t = time.perf_counter()
        sir_step(r.states, r.log_weights, motion, zero, generator=g)
        t_filter.append(time.perf_counter() - t)
    return {
        "B": b,
        "N": n,
        "threads": threads,
        "path": "compiled" if lik.compile else "eager",
        "step_ms": statistics.median(t_step) * 1e3,
        "step_cpu_ms": statistics.median(c_step) * 1e3,
        "likelihood_ms": statistics.median(t_lik) * 1e3,
        "filter_only_ms": statistics.median(t_filter) * 1e3,
        "rss_before_mib": rss0,
        "peak_rss_mib": _status_mib("VmHWM"),
        "reps": reps,
        "haar_max_err": haar_err,
        "loglik_max_err": ll_err,
    }


def bench_sir(runs: list[tuple[int, int, int, int, bool]]) -> list[dict]:
    """``runs``: (B, N, threads, repetitions, compiled), each in a fresh subprocess."""
    rows = []
    for b, n, threads, reps, compiled in runs:
        cmd = [sys.executable, __file__, "--sir-one", str(b), str(n)]
        cmd += ["--reps", str(reps), "--threads", str(threads)]
        cmd += ["--compile"] if compiled else []
        out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
        row = json.loads(out.strip().splitlines()[-1])
        rows.append(row)
        print(
            f"SIR B={b} N={n} threads={threads} {row['path']}: step {row['step_ms']:.2f} ms "
            f"(likelihood {row['likelihood_ms']:.2f}, filter only {row['filter_only_ms']:.2f}), "
            f"peak RSS {row['peak_rss_mib']:.0f} MiB",
            flush=True,
        )
    return rows


# --------------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------------
def _load() -> str:
    try:
        return f"{os.getloadavg()[0]:.1f}"
    except OSError:
        return "n/a"


def resampling_table(res_rows) -> list[str]:
    lines = [
        "## Resampling, B = 1 (median ms; ratio = peer time / torchtrack time, > 1 means faster)",
        "",
        "Wall-clock medians, and in the last column the ratio of medians of CPU time of the "
        "timing thread (torchtrack at 1 thread, `particles` and filterpy are single-threaded): "
        "time spent waiting for a core on the shared machine does not count there. The goals "
        "use the 1-thread columns; with 2 threads on a loaded 2-core machine, torchtrack's "
        "second OpenMP thread mostly waits for a core, so that column measures the load more "
        "than the code.",
        "",
        "| N | scheme | torchtrack 1 thread | torchtrack 2 threads | particles (numba) | filterpy "
        "| vs filterpy (1t) | vs particles (1t) | vs particles (1t, CPU time) |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in res_rows:
        lines.append(
            f"| {r['n']:,} | {r['scheme']} | {r['torchtrack_1t']:.3f} | {r['torchtrack_2t']:.3f} "
            f"| {r['particles']:.3f} | {r['filterpy']:.3f} "
            f"| {r['filterpy'] / r['torchtrack_1t']:.1f}x "
            f"| {r['particles'] / r['torchtrack_1t']:.2f}x "
            f"| {r['particles_cpu'] / r['torchtrack_1t_cpu']:.2f}x |"
        )
    return lines


def resampling_goals(res_rows) -> list[str]:
    lines = []
    for r in res_rows:
        if r["n"] != 10**5:
            continue
        vs_fp = r["filterpy"] / r["torchtrack_1t"]
        vs_p = r["torchtrack_1t"] / r["particles"]
        vs_p_cpu = r["torchtrack_1t_cpu"] / r["particles_cpu"]
        lines.append(
            f"- N = 10^5, {r['scheme']}: {vs_fp:.1f}x faster than filterpy (goal >= 10x: "
            f"{'met' if vs_fp >= 10 else 'missed'}); {vs_p:.2f}x the time of `particles` "
            f"(goal <= 1.5x: {'met' if vs_p <= 1.5 else 'missed'}; CPU time {vs_p_cpu:.2f}x)"
        )
    return lines


def report(res_rows, sir_rows, cmd: str, load_before: str) -> str:
    lines = [
        "# Particle filter benchmark",
        "",
        f"Command: `{cmd}`",
        "",
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores "
        f"shared with other jobs (1-min load average {load_before} at start, {_load()} at end); "
        f"torch {torch.__version__}, Python {platform.python_version()}. Medians over "
        "repetitions; absolute times are noisy on a shared machine, the ratios within one run "
        "are the numbers to quote.",
        "",
        *resampling_table(res_rows),
    ]
    lines += [
        "",
        "## SIR step with a 32-feature Haar likelihood (median ms per step)",
        "",
        "`filter only` = the same step with a constant likelihood (resample + predict + "
        "normalise + estimate); `likelihood` = the Haar likelihood alone. Each row runs in its "
        "own subprocess; `before` is its RSS after imports and the frame's integral image, when "
        "the peak (VmHWM) is reset; `peak` is the high-water mark after the timed steps. The "
        "likelihood (`torchtrack.observe.haar_box.HaarBoxLikelihood`) works in chunks of 2048 "
        "particles (eager) or 4096 (compiled), so its workspace is bounded and the growth per "
        "particle should stay flat as B * N grows. `compiled` rows use its `torch.compile` "
        "path (compiled in the warm-up step, not timed); `step (CPU time)` is the timing "
        "thread's CPU time, which does not count waiting for a core on a loaded machine.",
        "",
        "| B | N | B*N | threads | likelihood path | step | step (CPU time) | likelihood "
        "| filter only | peak RSS MiB | before MiB | (peak - before) bytes per particle |",
        "|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in sir_rows:
        per = (r["peak_rss_mib"] - r["rss_before_mib"]) * 2**20 / (r["B"] * r["N"])
        lines.append(
            f"| {r['B']} | {r['N']:,} | {r['B'] * r['N']:,} | {r['threads']} | {r['path']} "
            f"| {r['step_ms']:.2f} | {r['step_cpu_ms']:.2f} "
            f"| {r['likelihood_ms']:.2f} | {r['filter_only_ms']:.2f} | {r['peak_rss_mib']:.0f} "
            f"| {r['rss_before_mib']:.0f} | {per:.0f} |"
        )
    lines += ["", "## Goals (computed from the tables above)", "", *resampling_goals(res_rows)]
    for r in sir_rows:
        if (r["B"], r["N"]) == (100, 1000):
            lines.append(
                f"- SIR step (B, N) = (100, 1000), {r['threads']} thread(s), {r['path']} "
                "likelihood: "
                f"{r['step_ms']:.1f} ms median (goal < 10 ms: "
                f"{'met' if r['step_ms'] < 10 else 'missed'}); the filter alone: "
                f"{r['filter_only_ms']:.1f} ms"
            )
    big = [r for r in sir_rows if r["B"] * r["N"] == 10**6]
    if big:
        per = ", ".join(
            f"(B, N) = ({r['B']}, {r['N']:,}): "
            f"{(r['peak_rss_mib'] - r['rss_before_mib']) * 2**20 / 10**6:.0f} B"
            for r in big
        )
        lines.append(f"- Memory at B * N = 10^6, growth per particle: {per}")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes, few repetitions")
    ap.add_argument("--sir-one", nargs=2, type=int, metavar=("B", "N"))
    ap.add_argument("--reps", type=int, default=15)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument(
        "--compile",
        action="store_true",
        help="with --sir-one: the likelihood's torch.compile path (default: eager)",
    )
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks" / "filter.md")
    ap.add_argument(
        "--resampling-only",
        nargs="+",
        type=int,
        metavar="N",
        help="only the resampling comparison at these N (41 repetitions each); prints its "
        "table, writes nothing",
    )
    args = ap.parse_args(argv)
    if args.sir_one:
        print(json.dumps(sir_one(*args.sir_one, args.reps, args.threads, args.compile)))
        return 0
    load_before = _load()
    if args.resampling_only:
        res = bench_resampling(args.resampling_only, lambda n: (41, 5))
        print(f"\n1-min load average {load_before} at start, {_load()} at end\n")
        print("\n".join([*resampling_table(res), "", *resampling_goals(res)]))
        return 0
    if args.quick:
        ns = [10**3, 10**4]
        res = bench_resampling(ns, lambda n: (5, 2))
        sir = bench_sir([(1, 2000, 1, 3, False), (10, 1000, 1, 3, False), (10, 1000, 2, 3, False)])
    else:
        ns = [10**3, 10**4, 10**5, 10**6]
        res = bench_resampling(
            ns, lambda n: {10**3: (51, 21), 10**4: (31, 11), 10**5: (41, 5), 10**6: (9, 3)}[n]
        )
        small = [(1, 2000), (10, 1000), (100, 1000)]
        runs = [(b, n, t, 15, c) for c in (False, True) for t in (1, 2) for b, n in small]
        # 10^6 particles: 1 thread only (2 threads on a loaded 2-core machine mostly waits)
        runs += [(1, 10**6, 1, 3, c) for c in (False, True)]
        runs += [(1000, 1000, 1, 3, c) for c in (False, True)]
        sir = bench_sir(runs)
    cmd = "python tools/bench_filter.py" + (" --quick" if args.quick else "")
    text = report(res, sir, cmd, load_before)
    if args.out.exists():  # hand-written notes below the marker survive a re-run
        old = args.out.read_text()
        if NOTES_MARKER in old:
            text += "\n" + NOTES_MARKER + old.split(NOTES_MARKER, 1)[1]
    write_text_atomic(args.out, text)
    print("\n" + text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
