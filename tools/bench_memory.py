"""Memory of long tracks: resident memory after 10%, 50% and 100% of a 10,000-frame track, for
torchtrack's trackers next to OpenCV's, each in its own process, in one run.

    python tools/bench_memory.py                          # 10,000 frames, default trackers
    python tools/bench_memory.py --frames 2000 --trackers adaptive-haar mil
    /work/peers-venv/bin/python tools/bench_memory.py     # adds CSRT (opencv-contrib)

The stream: BoBoT's pedestrian sequence (320x240, ``../shared/data/tracking/bobot_pedestrian``)
played forwards, then backwards, then forwards ... until ``--frames`` frames (the motion stays
continuous at the turns, so the target is followed, not lost at frame 1,000). The frames are
decoded once and held before the first measurement, so they are part of every process's
baseline and none of its growth. Each tracker starts from the sequence's first ground-truth box
and writes its box of every frame to a CSV file as ``torchtrack track --out`` does.

``multi`` is the multi-target tracker (``torchtrack track --detect pedestrian``), with its own
detector scan on every ``--multi-scan-every``-th frame of the same stream; its frames are far
more expensive, so it runs ``--multi-frames`` frames (default 2,000).

``command`` is that job as a user runs it: ``torchtrack track VIDEO --detect pedestrian --mot
OUT`` in its own process, with what the command does and a library call does not (two scan
workers forked from it, the heap memory it keeps for the next frame: ``reuse_freed_memory``).
The same ``--multi-frames`` frames of the stream are written to a video file first (MJPG);
the memory is the proportional set size (``Pss``, ``/proc/PID/smaps_rollup``: pages shared by
the forked workers counted once) of the command and its workers together, sampled every 0.25
s, and a mark is the sample nearest to that share of the run after start-up (frames go at a
steady rate; start-up is the run's time minus the frames' time the command reports).

Reported per tracker: ``VmRSS`` (resident memory now, from ``/proc/self/status``) after 1%
(the baseline, once the tracker has warmed up), 10%, 50% and 100% of the frames, the growth
from 10% to 100%, and ``VmHWM`` (peak). Flat memory means a growth near zero: a few MiB of
allocator noise, not one that scales with the number of frames. Linux only (``/proc``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # the checkout's torchtrack, also from a peers' environment

from bench_filter import _status_mib  # noqa: E402  (VmRSS / VmHWM from /proc, in MiB)

DATA = Path(os.environ.get("TORCHTRACK_DATA", REPO.parent / "shared" / "data"))
MARKS = (0.01, 0.10, 0.50, 1.00)


def _stream(n: int) -> tuple[list, list[float]]:
    """``n`` frames of BoBoT ping-pong (``(C, H, W)`` uint8 tensors) and the first GT box."""
    from torchtrack.io.sequences import load_sequence

    seq = load_sequence(DATA / "tracking" / "bobot_pedestrian")[0]
    with seq.open("rgb") as src:
        imgs = [f for _i, f in src.items()]
    cycle = imgs + imgs[-2:0:-1]  # forwards, then backwards without repeating the ends
    return [cycle[i % len(cycle)] for i in range(n)], [float(v) for v in seq.boxes[0]]


def _tree_pss_mib(pid: int) -> tuple[float, int]:
    """Proportional set size of ``pid`` and its descendants (MiB) and how many processes
    were read."""
    total, todo, n = 0.0, [pid], 0
    while todo:
        p = todo.pop()
        try:
            for line in Path(f"/proc/{p}/smaps_rollup").read_text().splitlines():
                if line.startswith("Pss:"):
                    total += float(line.split()[1]) / 1024.0
                    n += 1
                    break
            kids = Path(f"/proc/{p}/task/{p}/children").read_text().split()
        except OSError:  # ended between two reads
            continue
        todo += [int(k) for k in kids]
    return total, n


def command(frames: int, threads: int) -> dict:
    """``torchtrack track --detect pedestrian`` on ``frames`` frames of the stream, as a video
    file; the Pss of its processes over the run (see the module docstring)."""
    import re
    import threading

    import cv2

    stream, _ = _stream(frames)
    with tempfile.TemporaryDirectory() as tmp:
        video, mot = Path(tmp) / "stream.avi", Path(tmp) / "out.txt"
        h, w = stream[0].shape[-2:]
        vw = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (w, h))
        for f in stream:
            vw.write(f.permute(1, 2, 0).numpy()[:, :, ::-1].copy())
        vw.release()
        del stream
        cmd = [sys.executable, "-m", "torchtrack", "track", str(video), "--detect", "pedestrian"]
        cmd += ["--seed", "0", "--mot", str(mot), "--no-progress", "--threads", str(threads)]
        samples: list[tuple[float, float, int]] = []
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

        def sample() -> None:
            while proc.poll() is None:
                samples.append((time.perf_counter() - t0, *_tree_pss_mib(proc.pid)))
                time.sleep(0.25)

        th = threading.Thread(target=sample, daemon=True)
        th.start()
        out, err = proc.communicate()
        wall = time.perf_counter() - t0
        th.join()
        if proc.returncode != 0:
            raise RuntimeError(f"torchtrack track failed ({proc.returncode}): {err[-2000:]}")
        m = re.search(r"tracked (\d+) frames .*?, ([\d.]+) fps overall", out + err)
        if m is None:
            raise RuntimeError(f"no summary line in the command's output: {(out + err)[-2000:]}")
        run = int(m.group(1)) / float(m.group(2))  # the frames' time
    start = max(0.0, wall - run)
    # marks read samples taken while every process of the run was up (the scan workers end
    # before the command has written its files)
    full = max(s[2] for s in samples)
    samples = [s for s in samples if s[2] == full]
    rss = {}
    for mk in MARKS:
        at = start + mk * run
        rss[f"{mk:.2f}"] = min(samples, key=lambda s: abs(s[0] - at))[1]
    return {
        "spec": "command",
        "frames": frames,
        "rss_mib": rss,
        "peak_mib": max(s[1] for s in samples),
        "processes": full,
        "seconds": wall,
    }


def worker(spec: str, frames: int, threads: int, scan_every: int) -> dict:
    if spec == "command":
        return command(frames, threads)
    import cv2
    import torch

    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)
    stream, box = _stream(frames)
    marks: dict[int, list[float]] = {}  # frame -> the marks measured there (short runs share)
    for m in MARKS:
        marks.setdefault(max(1, round(m * frames)), []).append(m)
    rss: dict[str, float] = {}
    t0 = time.perf_counter()
    with tempfile.NamedTemporaryFile("w", suffix=".csv") as out:
        if spec == "multi":
            from torchtrack.track.multi import MultiTargetTracker

            tr = MultiTargetTracker(
                "pedestrian", scan_every=scan_every, generator=torch.Generator().manual_seed(0)
            )
            for k, f in enumerate(stream, 1):
                st = tr.update(f)
                for i, b in zip(st.ids.tolist(), st.boxes.tolist(), strict=True):
                    out.write(f"{k},{i},{b[0]:.2f},{b[1]:.2f},{b[2]:.2f},{b[3]:.2f}\n")
                for m in marks.get(k, ()):
                    rss[f"{m:.2f}"] = _status_mib("VmRSS")
        else:
            from torchtrack.track.base import create_tracker, parse_tracker_spec

            name, params = parse_tracker_spec(spec)
            if name in ("adaptive-haar", "cotrain", "detector", "fused", "histogram"):
                params.setdefault("generator", torch.Generator().manual_seed(0))
            tr = create_tracker(name, **params)
            tr.init(stream[0], torch.tensor(box))
            for k, f in enumerate(stream[1:], 2):
                r = tr.update(f)
                b = r.box.reshape(-1, 4)[0].tolist()
                out.write(f"{k},1,{b[0]:.2f},{b[1]:.2f},{b[2]:.2f},{b[3]:.2f}\n")
                for m in marks.get(k, ()):
                    rss[f"{m:.2f}"] = _status_mib("VmRSS")
    return {
        "spec": spec,
        "frames": frames,
        "rss_mib": rss,
        "peak_mib": _status_mib("VmHWM"),
        "seconds": time.perf_counter() - t0,
    }


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--frames", type=int, default=10_000)
    ap.add_argument("--multi-frames", type=int, default=2_000)
    ap.add_argument("--multi-scan-every", type=int, default=1)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument(
        "--trackers", nargs="+", default=["adaptive-haar", "multi", "command", "mil", "csrt"]
    )
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks" / "memory.md")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        n = args.multi_frames if args.worker in ("multi", "command") else args.frames
        print(json.dumps(worker(args.worker, n, args.threads, args.multi_scan_every)))
        return
    if not Path("/proc/self/status").exists():
        raise SystemExit("bench_memory.py reads /proc/self/status: Linux only")
    import cv2

    specs = [s for s in args.trackers if s != "csrt" or hasattr(cv2, "TrackerCSRT")]
    rows = []
    for spec in specs:
        r = subprocess.run(
            [sys.executable, __file__, "--worker", spec, "--frames", str(args.frames),
             "--multi-frames", str(args.multi_frames), "--threads", str(args.threads),
             "--multi-scan-every", str(args.multi_scan_every)],
            capture_output=True, text=True, check=False,
        )  # fmt: skip
        if r.returncode != 0:
            print(f"{spec}: failed\n{r.stderr[-3000:]}", file=sys.stderr)
            continue
        d = json.loads(r.stdout.strip().splitlines()[-1])
        rows.append(d)
        print(json.dumps(d), flush=True)
    cmd = "python tools/bench_memory.py " + " ".join(sys.argv[1:])
    lines = [
        "# Memory of long tracks",
        "",
        f"Command: `{cmd.strip()}` ({time.strftime('%Y-%m-%d')}; {args.threads} thread(s)).",
        "",
        "BoBoT pedestrian (320x240) played forwards and backwards into one long stream; each "
        "tracker in its own process; resident memory (VmRSS, MiB) after 1% (baseline), 10%, 50% "
        "and 100% of its frames, and the peak (VmHWM). The decoded frames are held before the "
        "first mark, so they are in every baseline. The `command` row is the whole command with "
        "its scan workers: their proportional set size together, sampled every 0.25 s, the "
        "peak the largest sample (it holds no decoded stream).",
        "",
        "| tracker | frames | 1% | 10% | 50% | 100% | growth 10% -> 100% | peak | seconds |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for d in rows:
        m = d["rss_mib"]
        v = [m.get(f"{x:.2f}", float("nan")) for x in MARKS]
        label = (
            "command (`torchtrack track`, Pss of it and its scan workers)"
            if d["spec"] == "command"
            else d["spec"]
        )
        lines.append(
            f"| {label} | {d['frames']:,} | {v[0]:.0f} | {v[1]:.0f} | {v[2]:.0f} | {v[3]:.0f} "
            f"| {v[3] - v[1]:+.1f} | {d['peak_mib']:.0f} | {d['seconds']:.0f} |"
        )
    text = "\n".join(lines) + "\n"
    marker = "<!-- notes: kept by tools/bench_memory.py -->"
    if args.out.exists() and marker in args.out.read_text():  # hand-written notes survive
        text += "\n" + marker + args.out.read_text().split(marker, 1)[1]
    from torchtrack.io.atomic import write_text_atomic

    write_text_atomic(args.out, text)
    print(text)


if __name__ == "__main__":
    main()
