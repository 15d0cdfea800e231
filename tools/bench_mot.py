"""Multi-target tracking on PETS09-S2L1 and TUD-Stadtmitte: torchtrack next to its peers, in one
run, every pipeline scored by ``torchtrack.eval.mot`` (TrackEval, MOT15 conventions).

Run it with the peers venv (opencv-contrib for ``cv2.HOGDescriptor``, boxmot and norfair
installed ``--no-deps``, plus their real needs ``lap``, ``rich`` and norfair's ``filterpy``),
nice'd on a shared machine::

    /work/peers-venv/bin/pip install --no-deps boxmot==25.0.0 norfair==2.3.0 && \\
        /work/peers-venv/bin/pip install lap rich filterpy
    nice -n 10 /work/peers-venv/bin/python tools/bench_mot.py
    nice -n 10 /work/peers-venv/bin/python tools/bench_mot.py --sequences TUD-Stadtmitte --repeats 1

Pipelines (detector + tracker):

* OpenCV HOG people detector (``HOGDescriptor_getDefaultPeopleDetector``, frames upscaled by
  ``--hog-upscale``, boxes scaled back) + ByteTrack (boxmot, defaults) and + a SORT-style
  tracker (norfair: Kalman filter, IoU distance, ``distance_threshold=0.7``, defaults
  otherwise); once with HOG's boxes as it returns them (its 64x128 window, a ~32x96 person
  inside) and once shrunk to the person (Dalal & Triggs' 16 px margin, the margin our own
  detector removes);
* scores in [0, 1] for ByteTrack (it refuses others): HOG's SVM margins and the public
  detector's scores divided by their largest value in the sequence (``--score-map``);
* the MOT15 public detections (``det/det.txt``, TUD only) + ByteTrack;
* the ground-truth boxes with 10% dropped and 2 px Gaussian jitter on x, y, w, h + ByteTrack
  (the tracker's ceiling; ``--seeds`` seeds, mean and spread);
* ``torchtrack detect`` (the CLI, JSON lines) + ByteTrack: separates our detector from the
  association. Windows are turned into object boxes with the model's ``object_box`` when the
  file holds windows (an older ``torchtrack detect``);
* our own pipeline through the CLI, as a user runs it: ``torchtrack track SOURCE --detect
  pedestrian --mot OUT.txt`` and ``torchtrack track TUD/img1 --detections TUD/det/det.txt --mot
  OUT.txt``, when the installed ``torchtrack track --help`` offers ``--mot`` (the rows say "not
  available in this version" otherwise).

Detections are cached under ``runs/bench_mot/cache`` (MOT det files; HOG over 795 frames upscaled
2.5x is minutes of CPU), results under ``runs/bench_mot/results/<pipeline>/<sequence>.txt`` (score
them again with ``torchtrack eval --mot ... --results DIR``). Timings, all with ``--threads``
torch / OpenCV threads: detector ms per frame = median over ``--repeats`` passes on
``--timing-frames`` frames spread over the sequence (decoded beforehand; HOG includes its
upscaling; ours is ``Detector.scan`` with the CLI's settings); tracker ms per frame = median over
``--repeats`` full passes on cached detections; CLI rows: wall time of the whole command per
frame (start-up, decoding and writing included) and the CLI's own summary line.

Writes ``docs/benchmarks/mot.md`` atomically and prints it; notes below the page's
``<!-- notes -->`` marker are kept when the page is rebuilt.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as _dt
import hashlib
import io
import json
import logging
import os
import re
import shlex
import shutil
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # the peers venv does not have torchtrack installed

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from torchtrack.eval.mot import gt_as_detections, import_trackeval, score_sequence  # noqa: E402
from torchtrack.io.atomic import write_text_atomic  # noqa: E402
from torchtrack.io.mot import MotRows, MotSequence, load_mot_sequence, read_mot, write_mot  # noqa: E402
from torchtrack.io.video import to_numpy_bgr  # noqa: E402

NOTES_MARKER = "<!-- notes -->"

#: Issue 11's table (an earlier run, same data): HOTA, MOTA, IDF1, detector ms / frame.
ISSUE_TABLE = {
    ("PETS09-S2L1", "hog+bytetrack"): "38.3 / 35.4 / 54.6, 384 ms",
    ("PETS09-S2L1", "hog+norfair"): "32.3 / 35.6 / 43.1, 384 ms",
    ("PETS09-S2L1", "gt+bytetrack"): "74.2 / 88.7 / 86.8",
    (
        "PETS09-S2L1",
        "ttdetect+bytetrack",
    ): "windows 24.2 / -73.2 / 11.9; object boxes 32.5 / 25.0 / 44.4; 236 ms",
    ("TUD-Stadtmitte", "hog+bytetrack"): "HOTA 30.7",
    ("TUD-Stadtmitte", "public+bytetrack"): "HOTA 41.2",
}


# ---------------------------------------------------------------------------------------------
# Sequences and settings
# ---------------------------------------------------------------------------------------------
@dataclass
class SeqSpec:
    name: str
    source: Path  # what the CLI reads: the video or the img1 folder
    hog_upscale: float
    det_args: list[str]  # torchtrack detect / scan settings
    seq: MotSequence | None = None


def sequences(data: Path, upscales: dict[str, float]) -> dict[str, SeqSpec]:
    pets_video = data / "videos" / "pets2009_s2l1_vtest" / "vtest.avi"
    tud = data / "mot" / "TUD-Stadtmitte"
    specs = {
        # PETS people are 35-90 px tall in the 480x360 video: below both detectors' windows
        "PETS09-S2L1": SeqSpec(
            "PETS09-S2L1",
            pets_video,
            upscales.get("PETS09-S2L1", 2.5),
            ["--min-scale", "0.4", "--threshold", "0.99"],
        ),
        # TUD people are 122-246 px tall at 640x480: native scale for both
        "TUD-Stadtmitte": SeqSpec(
            "TUD-Stadtmitte",
            tud / "img1",
            upscales.get("TUD-Stadtmitte", 1.0),
            ["--min-scale", "1.0", "--threshold", "0.99"],
        ),
    }
    specs["PETS09-S2L1"].seq = load_mot_sequence(
        pets_video, gt=data / "mot" / "PETS09-S2L1" / "gt" / "gt.txt"
    )
    specs["TUD-Stadtmitte"].seq = load_mot_sequence(tud)
    return specs


def read_frames(seq: MotSequence) -> list[np.ndarray]:
    """Every frame as a BGR array (decoded once; the detectors are timed without decoding)."""
    with seq.open() as src:
        return [to_numpy_bgr(f) for f in src]


def rel(p) -> str:
    """A path as the page shows it: relative to the repository root (commands run there)."""
    return os.path.relpath(p, REPO)


def cache_key(*parts) -> str:
    return hashlib.sha1(json.dumps([str(p) for p in parts]).encode()).hexdigest()[:10]


# ---------------------------------------------------------------------------------------------
# Detectors
# ---------------------------------------------------------------------------------------------
def hog_detector():
    if not hasattr(cv2, "HOGDescriptor"):
        raise SystemExit(
            "cv2.HOGDescriptor is missing (OpenCV 5 main wheel): run with opencv-contrib-python-"
            "headless, e.g. /work/peers-venv/bin/python tools/bench_mot.py"
        )
    hog = cv2.HOGDescriptor()
    hog.setSVMDetector(cv2.HOGDescriptor_getDefaultPeopleDetector())
    return hog


def hog_frame(hog, img: np.ndarray, up: float) -> tuple[np.ndarray, np.ndarray]:
    """HOG people boxes ``(K, 4)`` x, y, w, h in the frame's pixels and their SVM scores."""
    im = cv2.resize(img, None, fx=up, fy=up, interpolation=cv2.INTER_LINEAR) if up != 1 else img
    rects, weights = hog.detectMultiScale(im, winStride=(8, 8), padding=(8, 8), scale=1.05)
    boxes = np.asarray(rects, dtype=float).reshape(-1, 4) / up
    return boxes, np.asarray(weights, dtype=float).reshape(-1)


def hog_detections(spec: SeqSpec, frames, cache: Path) -> MotRows:
    path = cache / f"hog_{spec.name}_{cache_key(spec.hog_upscale, cv2.__version__)}.txt"
    if path.is_file():
        return read_mot(path, n_frames=spec.seq.n_frames, kind="det")
    hog = hog_detector()
    f_, b_, c_ = [], [], []
    t0 = time.perf_counter()
    for t, img in enumerate(frames):
        boxes, scores = hog_frame(hog, img, spec.hog_upscale)
        f_ += [t] * len(boxes)
        b_.append(boxes)
        c_.append(scores)
        if t % 100 == 0:
            print(f"  HOG {spec.name}: frame {t}/{len(frames)}", file=sys.stderr)
    rows = MotRows.from_arrays(f_, np.full(len(f_), -1), np.concatenate(b_), np.concatenate(c_))
    write_mot(path, rows, kind="det")
    print(f"  HOG {spec.name}: {time.perf_counter() - t0:.0f} s, cached {path}", file=sys.stderr)
    return read_mot(path, n_frames=spec.seq.n_frames, kind="det")


#: Dalal & Triggs' people window is 64x128 around a ~32x96 person (16 px margin on every side):
#: the person's box as fractions (x, y, w, h) of the window, as in the bundled pedestrian model.
DALAL_TRIGGS_PERSON = (0.25, 0.125, 0.5, 0.75)


def hog_person_boxes(det: MotRows) -> MotRows:
    """HOG windows shrunk to the person inside them (:data:`DALAL_TRIGGS_PERSON`)."""
    fx, fy, fw, fh = DALAL_TRIGGS_PERSON
    b = det.boxes
    boxes = np.stack(
        (b[:, 0] + fx * b[:, 2], b[:, 1] + fy * b[:, 3], fw * b[:, 2], fh * b[:, 3]), 1
    )
    return MotRows(det.frames, det.ids, boxes, det.conf, det.extra, det.lines, det.path)


def torchtrack_cmd(arg: str | None) -> list[str]:
    if arg:
        return shlex.split(arg)
    for cand in (REPO / ".venv" / "bin" / "torchtrack", shutil.which("torchtrack")):
        if cand and Path(cand).is_file():
            return [str(cand)]
    raise SystemExit("no torchtrack command found: give --torchtrack 'PATH/TO/torchtrack'")


def our_detections(
    spec: SeqSpec, tt: list[str], threads: int, cache: Path
) -> tuple[MotRows, str, list[str]]:
    """``torchtrack detect pedestrian SOURCE ... -o X.jsonl`` (cached) as object boxes.

    Returns the rows, how the boxes were read, and the command."""
    from torchtrack.cli import build_parser
    from torchtrack.cli import detect as detect_cli
    from torchtrack.detect.bundled import load_model, resolve_model
    from torchtrack.detect.model_file import read_model_metadata

    version = subprocess.run([*tt, "--version"], capture_output=True, text=True).stdout.strip()
    # the scan the command makes is the key (its defaults included): a changed default rescans,
    # and so does a changed model (the digest of its tensors and description, not its signature)
    det = load_model("pedestrian")
    model = read_model_metadata(resolve_model("pedestrian"))["sha256"]
    args = build_parser().parse_args(["detect", "pedestrian", str(spec.source), *spec.det_args])
    scan_kw = detect_cli.scan_kwargs(args, det)
    key = cache_key(spec.det_args, version, tt, model, *sorted(scan_kw.items()))
    jsonl = cache / f"ttdetect_{spec.name}_{key}.jsonl"
    cmd = [*tt, "detect", "pedestrian", str(spec.source), *spec.det_args, "--threads", str(threads)]
    cmd += ["--no-progress", "-o", str(jsonl)]
    if not jsonl.is_file():
        print(f"  {shlex.join(cmd)}", file=sys.stderr)
        subprocess.run(cmd, check=True)
    f_, b_, c_ = [], [], []
    for line in jsonl.read_text().splitlines():
        rec = json.loads(line)
        boxes = np.asarray(rec["boxes"], dtype=float).reshape(-1, 4)
        f_ += [rec["frame"]] * len(boxes)
        b_.append(boxes)
        c_ += rec["probabilities"]
    boxes = np.concatenate(b_) if b_ else np.zeros((0, 4))
    how = "object boxes as written"
    wh, ww = det.window
    if det.object_box is not None and len(boxes):
        ratio = boxes[:, 2] / boxes[:, 3]
        if np.allclose(ratio, ww / wh, rtol=1e-2):  # every box has the window's shape
            boxes = det.window_to_object(torch.from_numpy(boxes)).numpy()
            how = "windows as written, shrunk to object boxes by the bench (Detector.window_to_object)"
    return MotRows.from_arrays(f_, np.full(len(f_), -1), boxes, c_), how, cmd


# ---------------------------------------------------------------------------------------------
# Trackers (peers)
# ---------------------------------------------------------------------------------------------
@contextlib.contextmanager
def quiet():
    """boxmot logs its settings on construction."""
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        yield


def unit_scores(det: MotRows, how: str) -> MotRows:
    """Scores in [0, 1], which ByteTrack requires (its high / low split at 0.45 / 0.1): HOG's SVM
    margins (0-5) and the MOT15 public detector's scores (-0.15-122) are divided by the
    sequence's largest score (``max``, default) or clipped to [0, 1] (``clip``). Probabilities
    (our detector) and the GT boxes (1) pass unchanged."""
    if len(det) == 0 or (det.conf.min() >= 0 and det.conf.max() <= 1):
        return det
    c = np.clip(det.conf / det.conf.max(), 0, 1) if how == "max" else np.clip(det.conf, 0, 1)
    return MotRows(det.frames, det.ids, det.boxes, c, det.extra, det.lines, det.path)


def run_bytetrack(det: MotRows, n_frames: int, size: tuple[int, int]) -> MotRows:
    from boxmot import ByteTrack

    with quiet():
        tracker = ByteTrack()
    img = np.zeros((size[1], size[0], 3), np.uint8)
    f_, i_, b_, c_ = [], [], [], []
    for t, idx in enumerate(det.split(n_frames)):
        b = det.boxes[idx]
        d = np.concatenate(
            (b[:, :2], b[:, :2] + b[:, 2:], det.conf[idx, None], np.zeros((len(idx), 1))), axis=1
        )
        out = tracker.update(d.reshape(-1, 6), img)
        for x1, y1, x2, y2, tid, conf, *_ in out:
            f_.append(t)
            i_.append(int(tid))
            b_.append((x1, y1, x2 - x1, y2 - y1))
            c_.append(conf)
    return MotRows.from_arrays(f_, i_, np.asarray(b_).reshape(-1, 4), c_)


def run_norfair(det: MotRows, n_frames: int, size: tuple[int, int]) -> MotRows:
    from norfair import Detection, Tracker

    tracker = Tracker(distance_function="iou", distance_threshold=0.7)
    f_, i_, b_, c_ = [], [], [], []
    for t, idx in enumerate(det.split(n_frames)):
        ds = [
            Detection(np.array([[x, y], [x + w, y + h]]), scores=np.array([s, s]))
            for (x, y, w, h), s in zip(det.boxes[idx], det.conf[idx], strict=True)
        ]
        for obj in tracker.update(ds):
            (x1, y1), (x2, y2) = obj.estimate
            if x2 - x1 <= 0 or y2 - y1 <= 0:
                continue
            f_.append(t)
            i_.append(int(obj.id))
            b_.append((x1, y1, x2 - x1, y2 - y1))
            c_.append(1.0)
    return MotRows.from_arrays(f_, i_, np.asarray(b_).reshape(-1, 4), c_)


TRACKERS = {"bytetrack": run_bytetrack, "norfair": run_norfair}


# ---------------------------------------------------------------------------------------------
# Our pipeline through the CLI
# ---------------------------------------------------------------------------------------------
def cli_offers(tt: list[str], *flags: str) -> bool:
    out = subprocess.run([*tt, "track", "--help"], capture_output=True, text=True)
    return out.returncode == 0 and all(
        re.search(rf"(^|\s){re.escape(f)}\b", out.stdout) for f in flags
    )


def run_cli(cmd: list[str], repeats: int) -> tuple[float, str]:
    """Median wall seconds of ``cmd`` and its last output lines."""
    times, tail = [], ""
    for _ in range(repeats):
        print(f"  {shlex.join(cmd)}", file=sys.stderr)
        t0 = time.perf_counter()
        p = subprocess.run(cmd, capture_output=True, text=True)
        times.append(time.perf_counter() - t0)
        if p.returncode != 0:
            raise RuntimeError(
                f"{shlex.join(cmd)} failed ({p.returncode}): {p.stderr.strip()[-500:]}"
            )
        tail = " / ".join(line.strip() for line in (p.stdout + p.stderr).strip().splitlines()[-3:])
    return statistics.median(times), tail


# ---------------------------------------------------------------------------------------------
# Timing
# ---------------------------------------------------------------------------------------------
def median_ms(fn, n_items: int, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append((time.perf_counter() - t0) * 1000 / max(n_items, 1))
    return statistics.median(ts)


def timing_frames(frames: list[np.ndarray], n: int) -> list[np.ndarray]:
    idx = np.linspace(0, len(frames) - 1, min(n, len(frames))).round().astype(int)
    return [frames[i] for i in idx]


def time_our_scan(spec: SeqSpec, sample: list[np.ndarray], repeats: int) -> float:
    """``Detector.scan`` as ``torchtrack detect`` runs it with ``spec.det_args`` (batches of 4
    frames)."""
    from torchtrack.cli import build_parser
    from torchtrack.cli import detect as detect_cli
    from torchtrack.detect.bundled import load_model

    det = load_model("pedestrian")
    args = build_parser().parse_args(["detect", "pedestrian", str(spec.source), *spec.det_args])
    kw = detect_cli.scan_kwargs(args, det)
    tensors = [
        torch.from_numpy(np.ascontiguousarray(im[:, :, ::-1].transpose(2, 0, 1))) for im in sample
    ]

    def run():
        for i in range(0, len(tensors), 4):
            det.scan(torch.stack(tensors[i : i + 4]), **kw)

    return median_ms(run, len(sample), repeats)


# ---------------------------------------------------------------------------------------------
# The run
# ---------------------------------------------------------------------------------------------
@dataclass
class Row:
    sequence: str
    key: str
    pipeline: str
    metrics: list[dict] = field(default_factory=list)  # one per seed / run
    det_ms: float | None = None
    trk_ms: float | None = None
    note: str = ""
    results: Path | None = None
    available: bool = True


def score(spec: SeqSpec, rows: MotRows, out: Path) -> dict:
    write_mot(out, rows)
    return score_sequence(spec.seq, out).to_dict()


def track_and_score(spec, size, det: MotRows, tracker: str, out: Path, repeats: int):
    """Scores of ``tracker`` on ``det`` (results written to ``out``) and its median ms / frame."""
    n = spec.seq.n_frames
    rows = TRACKERS[tracker](det, n, size)
    ms = median_ms(lambda: TRACKERS[tracker](det, n, size), n, repeats)
    return score(spec, rows, out), ms


def bench_sequence(spec: SeqSpec, args, tt, cache, results, has_mot, has_dets):
    """Every pipeline on one sequence: the table rows and the commands behind them."""
    name, seq = spec.name, spec.seq
    rows: list[Row] = []
    commands: dict[str, str] = {}
    print(f"{name}: decoding {seq.n_frames} frames", file=sys.stderr)
    frames = read_frames(seq)
    size = (frames[0].shape[1], frames[0].shape[0])
    sample = timing_frames(frames, args.timing_frames)
    hog = hog_detector()
    hog_ms = median_ms(
        lambda: [hog_frame(hog, im, spec.hog_upscale) for im in sample], len(sample), args.repeats
    )
    our_ms = time_our_scan(spec, sample, args.repeats)
    dets = {"hog": unit_scores(hog_detections(spec, frames, cache), args.score_map)}
    dets["ttdetect"], how, dcmd = our_detections(spec, tt, args.threads, cache)
    commands[f"torchtrack detect ({name})"] = shlex.join(
        ["torchtrack", *(rel(c) if os.path.isabs(c) else c for c in dcmd[len(tt) :])]
    )
    dets["hogperson"] = hog_person_boxes(dets["hog"])
    if seq.det_path is not None:
        dets["public"] = unit_scores(seq.detections(), args.score_map)
    up = f"x{spec.hog_upscale:g}"
    person = "HOG windows shrunk to the person (Dalal-Triggs 16 px margin)"
    plan = [
        ("hog+bytetrack", f"OpenCV HOG ({up}) + ByteTrack", "hog", "bytetrack", hog_ms, ""),
        ("hog+norfair", f"OpenCV HOG ({up}) + norfair (SORT-style)", "hog", "norfair", hog_ms, ""),
        (
            "hogperson+bytetrack",
            f"OpenCV HOG ({up}), person boxes + ByteTrack",
            "hogperson",
            "bytetrack",
            hog_ms,
            person,
        ),
        (
            "hogperson+norfair",
            f"OpenCV HOG ({up}), person boxes + norfair",
            "hogperson",
            "norfair",
            hog_ms,
            person,
        ),
    ]
    if "public" in dets:
        plan.append(
            (
                "public+bytetrack",
                "MOT15 public detections + ByteTrack",
                "public",
                "bytetrack",
                None,
                "",
            )
        )
    plan.append(
        (
            "ttdetect+bytetrack",
            "`torchtrack detect` + ByteTrack",
            "ttdetect",
            "bytetrack",
            our_ms,
            how,
        )
    )
    for key, label, det_key, tracker, det_ms, note in plan:
        out = results / key / f"{name}.txt"
        m, trk_ms = track_and_score(spec, size, dets[det_key], tracker, out, args.repeats)
        rows.append(Row(name, key, label, [m], det_ms, trk_ms, note, out.parent))
    # the ceiling: GT boxes, 10% dropped, 2 px jitter, over seeds
    ceiling = Row(name, "gt+bytetrack", "GT boxes, 10% dropped, 2 px jitter + ByteTrack")
    times = []
    for s in args.seeds:
        out = results / f"gt+bytetrack_seed{s}" / f"{name}.txt"
        m, ms = track_and_score(spec, size, gt_as_detections(seq.gt, s), "bytetrack", out, 1)
        ceiling.metrics.append(m)
        times.append(ms)
    ceiling.trk_ms = statistics.median(times)  # one pass per seed
    ceiling.note = f"seeds {', '.join(map(str, args.seeds))}: mean (min-max)"
    ceiling.results = results / f"gt+bytetrack_seed{args.seeds[0]}"
    rows.append(ceiling)

    # our pipeline, as a user runs it
    cli_rows = [
        (
            "tt-track-detect",
            "`torchtrack track --detect pedestrian`",
            ["--detect", "pedestrian"],
            has_mot,
        )
    ]
    if cli_offers(tt, "--scan-workers"):  # the same command with its scans in this process
        cli_rows.append(
            (
                "tt-track-detect-inprocess",
                "`torchtrack track --detect pedestrian --scan-workers 0`",
                ["--detect", "pedestrian", "--scan-workers", "0"],
                has_mot,
            )
        )
    if seq.det_path is not None:
        cli_rows.append(
            (
                "tt-track-public",
                "`torchtrack track --detections det.txt` (public detections)",
                ["--detections", str(seq.det_path)],
                has_dets,
            )
        )
    for key, label, extra, ok in cli_rows:
        out = results / key / f"{name}.txt"
        cmd = [*tt, "track", str(spec.source), *extra, "--mot", str(out)]
        cmd += ["--threads", str(args.threads), "--no-progress"]
        commands[f"{label} ({name})"] = shlex.join(
            ["torchtrack", *(rel(c) if os.path.isabs(c) else c for c in cmd[len(tt) :])]
        )
        if not ok:
            rows.append(
                Row(name, key, label, note="not available in this version", available=False)
            )
            continue
        out.parent.mkdir(parents=True, exist_ok=True)  # the CLI refuses a missing folder
        wall, tail = run_cli(cmd, args.cli_repeats)
        m = score_sequence(seq, out).to_dict()
        note = f"whole command {1000 * wall / seq.n_frames:.0f} ms/frame wall; CLI: {tail}"
        rows.append(Row(name, key, label, [m], None, None, note, out.parent))
    return rows, commands


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--data",
        type=Path,
        default=Path(os.environ.get("TORCHTRACK_DATA", REPO.parent / "shared" / "data")),
    )
    ap.add_argument("--sequences", nargs="+", default=["PETS09-S2L1", "TUD-Stadtmitte"])
    ap.add_argument("--threads", type=int, default=2, help="torch and OpenCV threads (default 2)")
    ap.add_argument("--repeats", type=int, default=3, help="timing passes (medians)")
    ap.add_argument(
        "--cli-repeats", type=int, default=1, help="runs of each torchtrack track command"
    )
    ap.add_argument(
        "--timing-frames", type=int, default=24, help="frames the detectors are timed on"
    )
    ap.add_argument(
        "--seeds", type=int, nargs="+", default=[0, 1, 2], help="seeds of the GT-box ceiling"
    )
    ap.add_argument(
        "--hog-upscale",
        nargs="+",
        default=[],
        metavar="SEQ=F",
        help="HOG upscaling per sequence (default PETS09-S2L1=2.5 TUD-Stadtmitte=1.0)",
    )
    ap.add_argument(
        "--score-map",
        choices=("max", "clip"),
        default="max",
        help="how HOG and public scores become [0, 1] for ByteTrack (default: / sequence max)",
    )
    ap.add_argument(
        "--torchtrack", help="the torchtrack command (default: the repo's .venv, else PATH)"
    )
    ap.add_argument("--work", type=Path, default=REPO / "runs" / "bench_mot")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks" / "mot.md")
    args = ap.parse_args()

    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    logging.getLogger().setLevel(logging.WARNING)
    upscales = {k: float(v) for k, v in (s.split("=", 1) for s in args.hog_upscale)}
    specs = sequences(args.data, upscales)
    unknown = set(args.sequences) - set(specs)
    if unknown:
        raise SystemExit(f"unknown sequence(s) {sorted(unknown)}; known: {sorted(specs)}")
    cache, results = args.work / "cache", args.work / "results"
    cache.mkdir(parents=True, exist_ok=True)
    tt = torchtrack_cmd(args.torchtrack)
    has_mot = cli_offers(tt, "--mot")
    has_dets = cli_offers(tt, "--mot", "--detections")
    load_before = os.getloadavg()
    started = time.time()
    rows: list[Row] = []
    commands: dict[str, str] = {}

    for name in args.sequences:
        r, c = bench_sequence(specs[name], args, tt, cache, results, has_mot, has_dets)
        rows += r
        commands.update(c)
    page = render(args, rows, commands, specs, load_before, time.time() - started, tt)
    old = args.out.read_text() if args.out.is_file() else ""
    if NOTES_MARKER in old:
        page += "\n" + NOTES_MARKER + old.split(NOTES_MARKER, 1)[1]
    write_text_atomic(args.out, page)
    print(page)


def _fmt_metric(ms: list[dict], key: str, pct: bool = True) -> str:
    vals = [m[key] * (100 if pct else 1) for m in ms]
    if not vals:
        return "-"
    if len(vals) == 1:
        return f"{vals[0]:.1f}" if pct else f"{vals[0]:.0f}"
    mean = statistics.fmean(vals)
    return (
        f"{mean:.1f} ({min(vals):.1f}-{max(vals):.1f})"
        if pct
        else f"{mean:.0f} ({min(vals):.0f}-{max(vals):.0f})"
    )


def render(args, rows: list[Row], commands: dict, specs, load_before, seconds, tt) -> str:
    from importlib.metadata import version

    def v(pkg):
        try:
            return version(pkg)
        except Exception:
            return "?"

    trackeval = import_trackeval()
    load_after = os.getloadavg()
    cmd = shlex.join(["python", "tools/bench_mot.py", *sys.argv[1:]])
    lines = [
        "# Multi-target tracking: PETS09-S2L1 and TUD-Stadtmitte, torchtrack next to its peers",
        "",
        f"Command: `nice -n 10 /work/peers-venv/bin/{cmd}` ({_dt.date.today().isoformat()}, "
        f"{seconds / 60:.0f} min). {args.threads} torch / OpenCV thread(s); load average "
        f"{load_before[0]:.1f} at the start, {load_after[0]:.1f} at the end (2-core machine shared "
        "with other jobs: absolute times are inflated, compare within a row set).",
        "",
        f"Versions: torch {torch.__version__}, OpenCV {cv2.__version__} (contrib), boxmot "
        f"{v('boxmot')}, norfair {v('norfair')}, TrackEval {trackeval.__version__}; torchtrack "
        f"CLI `{shlex.join(tt)}`.",
        "",
        "Scores by `torchtrack.eval.mot` (TrackEval HOTA / CLEAR / Identity, MOT15 conventions: "
        "GT rows with conf 0 ignored, a box on them is a false positive; IoU >= 0.5 for MOTA and "
        "IDF1). PETS09-S2L1: the shared 480x360 video, GT x0.625; TUD-Stadtmitte: 640x480 "
        "frames. Detector ms / frame: median of "
        f"{args.repeats} passes over {args.timing_frames} frames spread over the sequence; "
        f"tracker ms / frame: median of {args.repeats} full passes on the cached detections.",
        "",
    ]
    for name in args.sequences:
        spec = specs[name]
        lines += [
            f"## {name} ({spec.seq.n_frames} frames; HOG on frames x{spec.hog_upscale:g}; ours "
            f"`{' '.join(spec.det_args)}`)",
            "",
            "| pipeline | HOTA | DetA | AssA | MOTA | IDF1 | IDsw | FP | FN | detector ms / frame "
            "| tracker ms / frame | issue 11's table (HOTA / MOTA / IDF1) | notes |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in (r for r in rows if r.sequence == name):
            issue = ISSUE_TABLE.get((name, r.key), "")
            if not r.available:
                lines.append(
                    f"| {r.pipeline} | " + " | ".join(["-"] * 10) + f" | {issue} | {r.note} |"
                )
                continue
            ms = r.metrics
            cells = [_fmt_metric(ms, k) for k in ("hota", "deta", "assa", "mota", "idf1")]
            cells += [_fmt_metric(ms, k, pct=False) for k in ("id_switches", "fp", "fn")]
            cells += [
                "-" if r.det_ms is None else f"{r.det_ms:.0f}",
                "-" if r.trk_ms is None else f"{r.trk_ms:.2f}",
            ]
            lines.append(f"| {r.pipeline} | " + " | ".join(cells) + f" | {issue} | {r.note} |")
        lines.append("")
    lines += ["## Commands", "", "Detections and our pipeline (what the bench runs):", "", "```"]
    lines += list(commands.values())
    lines += [
        "```",
        "",
        "Score any result set again (the bench writes them under `runs/bench_mot/results/`):",
        "",
        "```",
    ]
    keys = sorted({r.results.name for r in rows if r.results is not None})
    seq_args = []
    for name in args.sequences:
        s = specs[name].seq
        seq_args.append(rel(s.video) if s.video else rel(s.gt_path.parent.parent))
    gts = [rel(specs[n].seq.gt_path) for n in args.sequences if specs[n].seq.video]
    for k in keys:
        parts = ["torchtrack", "eval", "--mot", *seq_args]
        if gts:
            parts += ["--gt", *gts]
        parts += ["--results", f"runs/bench_mot/results/{k}"]
        lines.append(shlex.join(parts))
    lines += ["```", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
