"""The GPU path against the CPU path, in one run: the three speed checks of the speed issue.

1. **SIR step**, 32 Haar features, ``(B, N) = (100, 1000)``: the step of
   ``tools/bench_filter.py`` (Klein AR motion, systematic resampling, the
   :class:`~torchtrack.observe.haar_box.HaarBoxLikelihood` on one BoBoT frame's integral image),
   the same tensors on the CPU (``--threads`` threads) and on CUDA. Medians over ``--reps``
   steps; a CUDA step is timed to its end (``torch.cuda.synchronize``).
2. **A 100-target multi-object frame**: :class:`~torchtrack.track.multi.MultiTargetTracker`
   with 100 confirmed targets on a 1920x1080 frame (the demo clip's first frame tiled 4 x 3),
   fed 100 outside detections a frame (a 10 x 10 grid of 24 x 72 people drifting one pixel a
   frame, probability 0.99999): the per-frame time of ``update`` once every target is
   confirmed (the scan is not in it: detections come from outside).
3. **A 1,000-frame eval**: :func:`~torchtrack.eval.runner.run_sequence` of ``--tracker`` on
   BoBoT's pedestrian (1,017 frames), decoding included; fps counts ``tracker.update`` only (as
   ``torchtrack eval`` does), wall time the whole run; the AUC of both runs (their random
   streams differ between devices, so the AUCs differ by the spread over seeds, not more).

4. **The main job** on PETS09-S2L1's first ``--mainjob-frames`` frames (``track_sequence``,
   scans in this process): frames per second with one frame a scan and with ``--scan-batch``
   frames scanned together (what a GPU does by default), and the boxes reported.

Usage::

    python tools/bench_gpu.py                       # all three, CPU and CUDA side by side
    python tools/bench_gpu.py --only sir multi      # a subset
    python tools/bench_gpu.py --devices cpu         # the CPU rows alone (no GPU here)
    python tools/bench_gpu.py --only sir --profile  # + where the time goes (torch.profiler)

Prints a markdown table (medians, CUDA / CPU ratios) and writes nothing else.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tools"))

from bench_filter import haar_likelihood  # noqa: E402

from torchtrack.device import check_device  # noqa: E402
from torchtrack.filter import KleinAR, sir_step, uniform_log_weights  # noqa: E402


def _data() -> Path:
    env = os.environ.get("TORCHTRACK_DATA")
    return Path(env) if env else REPO.parent / "shared" / "data"


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


#: set by --profile: wrap the timed work in torch.profiler and print its table
PROFILE = False


def _profiled(label: str, fn, dev: torch.device) -> None:
    """Run ``fn`` once under :mod:`torch.profiler` and print the ops that took the most time
    (device time on CUDA) and how often the host waited for the device."""
    from torch.profiler import ProfilerActivity, profile

    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev.type == "cuda" else [])
    with profile(activities=acts) as prof:
        fn()
        _sync(dev)
    ka = prof.key_averages()
    key = "self_device_time_total" if dev.type == "cuda" else "self_cpu_time_total"
    print(f"\n## profile: {label} on {dev}")
    print(ka.table(sort_by=key, row_limit=20))
    waits = sum(e.count for e in ka if "Synchronize" in e.key or "Memcpy" in e.key)
    print(f"host waits / copies (cudaStreamSynchronize, cudaMemcpy*): {waits}")
    if dev.type == "cuda":
        _syncs(label, fn)


def _syncs(label: str, fn) -> None:
    """Run ``fn`` once more with torch's CUDA sync debug mode and print where the host waited
    for the device (the innermost torchtrack or tools line of each synchronising call)."""
    import collections
    import traceback
    import warnings

    where: collections.Counter = collections.Counter()

    def show(message, category, filename, lineno, file=None, line=None):
        for fr in reversed(traceback.extract_stack()[:-1]):
            if "/torchtrack/" in fr.filename or "/tools/" in fr.filename:
                where[f"{Path(fr.filename).name}:{fr.lineno}  {fr.line}"] += 1
                return
        where[f"{Path(filename).name}:{lineno}"] += 1

    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = show
        torch.cuda.set_sync_debug_mode("warn")
        try:
            fn()
        finally:
            torch.cuda.set_sync_debug_mode("default")
    print(f"host syncs of one call ({label}): {sum(where.values())}")
    for k, v in where.most_common(40):
        print(f"  {v:4d}  {k}")


def _timed(fn, dev: torch.device, reps: int) -> list[float]:
    out = []
    for _ in range(reps):
        _sync(dev)
        t = time.perf_counter()
        fn()
        _sync(dev)
        out.append(time.perf_counter() - t)
    return out


def bench_sir(dev: torch.device, b: int, n: int, reps: int, graphed: bool = False) -> dict:
    import cv2

    from torchtrack.features.integral import integral_image

    seq = _data() / "tracking" / "bobot_pedestrian"
    img = cv2.imread(str(seq / "frames" / "img0002.jpg"), cv2.IMREAD_GRAYSCALE)
    x1, y1, x2, y2 = (float(v) for v in (seq / "gt.txt").read_text().splitlines()[0].split(","))
    frame = torch.from_numpy(img)[None, None].to(torch.float64)
    ii = integral_image(frame - frame.mean())[0, 0].to(dev)
    box = torch.tensor([[x1, y1, x2 - x1, y2 - y1]], device=dev)
    motion = KleinAR()
    lik = haar_likelihood(ii, motion)
    g = torch.Generator(device=dev).manual_seed(0)
    x = motion.init(box.repeat(b, 1), n, g)
    state = [sir_step(x, uniform_log_weights(x), motion, lik, generator=g)]
    for _ in range(3):  # warm-up (CUDA kernels loaded, caches filled)
        state[0] = sir_step(state[0].states, state[0].log_weights, motion, lik, generator=g)

    if graphed:  # the same step recorded once as a CUDA graph (torchtrack.filter.graph)
        from torchtrack.filter.graph import GraphedSIR

        r = state[0]
        runner = GraphedSIR(r.states, r.log_weights, motion, lik, generator=g)
        for _ in range(3):
            runner.step()

        def step():
            state[0] = runner.step()

    else:

        def step():
            r = state[0]
            state[0] = sir_step(r.states, r.log_weights, motion, lik, generator=g)

    t = _timed(step, dev, reps)
    assert state[0].states.device.type == dev.type
    if PROFILE:
        _profiled(f"SIR step (100, 1000){' graphed' if graphed else ''}", step, dev)
    return {"ms": 1e3 * statistics.median(t), "reps": reps}


def _tiled_frame() -> torch.Tensor:
    import itertools

    from torchtrack.data import demo_clip_path
    from torchtrack.io.video import open_source

    src = open_source(demo_clip_path())
    try:
        _, f = next(itertools.islice(src.items(), 1))
    finally:
        src.close()
    return f.repeat(1, 3, 4)  # (3, 1080, 1920)


def bench_multi(dev: torch.device, targets: int, frames: int) -> dict:
    from torchtrack.track.multi import MultiTargetTracker

    frame = _tiled_frame().to(dev)
    side = round(targets**0.5)
    xs = torch.arange(side, dtype=torch.float64) * (1920 - 100) / side + 30
    ys = torch.arange(side, dtype=torch.float64) * (1080 - 140) / side + 20
    gx, gy = torch.meshgrid(xs, ys, indexing="xy")
    base = torch.stack(
        [
            gx.reshape(-1),
            gy.reshape(-1),
            torch.full((side * side,), 24.0),
            torch.full((side * side,), 72.0),
        ],
        1,
    )[:targets]
    p = torch.full((targets,), 0.99999, dtype=torch.float64)
    mt = MultiTargetTracker(
        "pedestrian", generator=torch.Generator().manual_seed(0), max_targets=2 * targets
    )
    times = []
    out = None
    for t in range(frames):
        boxes = base + torch.tensor([float(t), 0.5 * t, 0.0, 0.0], dtype=torch.float64)
        dets = (boxes.to(dev), p.to(dev))
        _sync(dev)
        t0 = time.perf_counter()
        out = mt.update(frame, detections=dets)
        _sync(dev)
        if int(mt.confirmed.sum()) >= targets:
            times.append(time.perf_counter() - t0)
    if len(times) < 3:
        raise SystemExit(f"multi: only {int(mt.confirmed.sum())} targets confirmed on {dev}")
    times = times[1:]  # the first frame with every target confirmed still warms up
    if PROFILE:
        t = frames
        boxes = base + torch.tensor([float(t), 0.5 * t, 0.0, 0.0], dtype=torch.float64)
        dets = (boxes.to(dev), p.to(dev))
        _profiled(f"multi-target frame, {targets} targets", lambda: mt.update(frame, dets), dev)
    return {"ms": 1e3 * statistics.median(times), "frames": len(times), "reported": len(out)}


def bench_eval(dev: torch.device, spec: str) -> dict:
    from torchtrack.eval.metrics import evaluate_sequence
    from torchtrack.eval.runner import run_sequence
    from torchtrack.io.sequences import load_sequence

    seq = load_sequence(_data() / "tracking" / "bobot_pedestrian")[0]
    t0 = time.perf_counter()
    res = run_sequence(spec, seq, device=dev)
    wall = time.perf_counter() - t0
    if res.error:
        raise SystemExit(f"eval on {dev}: {res.error}\n{res.traceback}")
    m = evaluate_sequence(res.boxes, seq.boxes, res.visible)
    return {
        "frames": len(seq),
        "fps": res.n_updates / max(res.update_seconds, 1e-9),
        "wall_s": wall,
        "auc": float(m.auc),
    }


def bench_mainjob(dev: torch.device, batch: int, frames: int) -> dict:
    """The main job's frame rate (scan and tracking, in this process) over the first ``frames``
    frames of PETS09-S2L1: ``track_sequence`` with the scans of ``batch`` frames together."""
    from torchtrack.io.video import open_source
    from torchtrack.track.multi import MultiTargetTracker, track_sequence

    clip = _data() / "videos" / "pets2009_s2l1_vtest" / "vtest.avi"
    mt = MultiTargetTracker("pedestrian", generator=torch.Generator().manual_seed(0))
    with open_source(clip) as src:  # warm-up: kernels loaded, model moved
        track_sequence(mt, src, max_frames=8, scan_workers=0, device=dev, scan_batch=batch)
    mt = MultiTargetTracker("pedestrian", generator=torch.Generator().manual_seed(0))
    with open_source(clip) as src:
        t0 = time.perf_counter()
        rows = track_sequence(
            mt, src, max_frames=frames, scan_workers=0, device=dev, scan_batch=batch
        )
        wall = time.perf_counter() - t0
    return {"fps": frames / wall, "frames": frames, "batch": batch, "rows": len(rows)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--devices", nargs="+", default=["cpu", "cuda"])
    ap.add_argument(
        "--only",
        nargs="+",
        choices=["sir", "sir-graph", "multi", "eval", "mainjob"],
        default=["sir", "sir-graph", "multi", "eval", "mainjob"],
        help="sir-graph: the SIR step replayed from a CUDA graph (GraphedSIR; CUDA only); "
        "mainjob: the main job on PETS's first --mainjob-frames frames, scans in this process "
        "one frame at a time and --scan-batch frames together",
    )
    ap.add_argument("--mainjob-frames", type=int, default=200)
    ap.add_argument("--scan-batch", type=int, default=8)
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads (default 2)")
    ap.add_argument("--reps", type=int, default=31)
    ap.add_argument("--targets", type=int, default=100)
    ap.add_argument("--multi-frames", type=int, default=25)
    ap.add_argument("--tracker", default="adaptive-haar")
    ap.add_argument(
        "--profile", action="store_true", help="also print a torch.profiler table of each check"
    )
    args = ap.parse_args(argv)
    global PROFILE
    PROFILE = args.profile
    torch.set_num_threads(args.threads)
    devs = [check_device(d) for d in args.devices]
    rows: list[tuple[str, str, dict]] = []
    for what in args.only:
        for dev in devs:
            if what == "sir-graph" and dev.type != "cuda":
                continue  # a CUDA graph: nothing to record on the CPU
            if what in ("sir", "sir-graph"):
                r = bench_sir(dev, 100, 1000, args.reps, graphed=what == "sir-graph")
            elif what == "multi":
                r = bench_multi(dev, args.targets, args.multi_frames)
            elif what == "mainjob":
                for b in (1, args.scan_batch):
                    r = bench_mainjob(dev, b, args.mainjob_frames)
                    rows.append((what, str(dev), r))
                    print(what, dev, r, flush=True)
                continue
            else:
                r = bench_eval(dev, args.tracker)
            rows.append((what, str(dev), r))
            print(what, dev, r, flush=True)
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none"
    print(
        f"\n{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, torch "
        f"{torch.__version__}, {args.threads} CPU thread(s), GPU: {gpu}\n"
    )
    print("| check | device | median | detail | CPU / this |")
    print("|---|---|---|---|---|")
    base = {what: r for what, d, r in rows if d == "cpu" and r.get("batch", 1) == 1}
    if "sir" in base:
        base["sir-graph"] = base["sir"]
    for what, d, r in rows:
        if what == "eval":
            val, key = f"{r['fps']:.1f} fps (tracker only)", "fps"
            detail = f"{r['frames']} frames, wall {r['wall_s']:.1f} s, AUC {r['auc']:.3f}"
            ratio = r["fps"] / base[what]["fps"] if what in base else float("nan")
        elif what == "mainjob":
            val = f"{r['fps']:.1f} fps"
            detail = f"{r['frames']} frames, {r['batch']} frame(s) a scan, {r['rows']} boxes"
            ratio = r["fps"] / base[what]["fps"] if what in base else float("nan")
        else:
            val, key = f"{r['ms']:.2f} ms", "ms"
            detail = (
                f"(B, N) = (100, 1000), {r['reps']} steps"
                if what.startswith("sir")
                else f"{args.targets} targets, {r['frames']} frames, {r['reported']} reported"
            )
            ratio = base[what][key] / r[key] if what in base else float("nan")
        label = {
            "sir": "SIR step, 32 Haar features",
            "sir-graph": "SIR step, 32 Haar features, CUDA graph",
            "multi": "multi-target frame",
            "eval": f"1,000-frame eval, {args.tracker}",
            "mainjob": "main job, PETS (scan + tracking, one process)",
        }[what]
        print(f"| {label} | {d} | {val} | {detail} | {ratio:.2f}x |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
