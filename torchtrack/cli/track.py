"""``torchtrack track``: track objects in a video, a frame folder or a camera.

Examples::

    torchtrack track demo --video tracked.mp4          # bundled clip, bundled pedestrian model
    torchtrack track clip.mp4 --box 120,40,56,156 --out boxes.csv
    torchtrack track frames/ --tracker histogram --box 120,40,56,156 --video out.mp4 --particles
    torchtrack track 0 --detect vehicle --max-frames 500          # camera 0, scan for a car
    torchtrack track footage/ --out-dir runs/tracks --write csv,video --backend ray  # a corpus
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

_EPILOG = """\
examples:
  torchtrack track demo --video tracked.mp4
      the bundled demo clip, the target found by the bundled pedestrian detector
  torchtrack track clip.mp4 --box 120,40,56,156 --out boxes.csv --video annotated.mp4
      track the box given on the first frame with the calibrated-detector tracker
  torchtrack track frames/ --tracker histogram --box 120,40,56,156 --video out.mp4 --particles
      colour-histogram particle filter, particles drawn in the video
  torchtrack track clip.mp4 --detect vehicle --tracker mil
      find the first frame's best car with the bundled vehicle detector, then track it with MIL
  torchtrack track clip.mp4 --box 10,20,40,80 --tracker adaptive-haar --adapt global
  torchtrack track clip.mp4 --box 10,20,40,80 --tracker detector:n_particles=500,model=my.safetensors
  torchtrack track footage/ 'more/**/*.mp4' @list.txt --out-dir runs/tracks --write csv,video
      a corpus: every video, one CSV and one annotated video each, resumable (docs/scale.md)
  torchtrack track footage/ --out-dir runs/tracks --backend ray --address 10.0.0.5:6379
      the same on a Ray cluster, one task per video

initialisation:
  --box x,y,w,h is the target on the first readable frame (pixels, top-left corner, 0-based).
  A box of zero size, with a non-number, or entirely outside the frame is an error (BoxError);
  a box that only sticks out of the frame is clipped to it, with a warning. Without --box the
  first frame is scanned with the --detect model (default: the bundled pedestrian model): the
  detector tracker initialises its particles from the scan (Chateau et al. sec. 4.2), other
  trackers start from the best detection.

output:
  --out writes a CSV with the header frame,x,y,w,h,confidence,visible and one row per frame
  of the source (a column 'target' after 'frame' when several targets are tracked). Rows are
  flushed as they are produced into OUT.part next to OUT; at the end (also after an error or
  Ctrl-C) the file is fsynced and renamed to OUT, so OUT is never half-written and an early end
  keeps the rows so far. Unreadable frames get the previous box with visible=0 and are counted.
  A target the tracker has lost (left the frame, occluded) is written with visible=0.
"""


def register(subparsers) -> None:
    from torchtrack.cli._common import add_progress, add_threads
    from torchtrack.cli._corpus import add_corpus_options

    p = subparsers.add_parser(
        "track",
        help="track objects in a video, a frame folder or a camera",
        description=(
            "Track a target through SOURCE (a video file, a folder of frames, a camera index, "
            "or 'demo' for the bundled clip) with any registered tracker (--tracker; "
            "see `torchtrack eval --list-trackers`). Writes boxes as CSV and/or an annotated "
            "video, with a progress bar and a final frames-per-second line."
        ),
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "sources",
        nargs="+",
        metavar="SOURCE",
        help="video file, frame folder, camera index (0, 1, ...) or 'demo' (the bundled clip); "
        "several, a folder of videos, a glob or @list.txt: a corpus run (--out-dir)",
    )
    p.add_argument("--box", metavar="X,Y,W,H", help="target box on the first frame (pixels)")
    p.add_argument(
        "--detect",
        metavar="MODEL",
        help="detector for initialisation without --box and for the detector tracker: a "
        "bundled name (pedestrian, vehicle) or a model file (default: pedestrian)",
    )
    p.add_argument(
        "--tracker",
        default="detector",
        metavar="NAME",
        help="tracker name, optionally with parameters name:key=value,... (default: detector)",
    )
    p.add_argument(
        "--adapt",
        choices=("none", "global", "per-particle"),
        help="adaptation mode, passed to trackers that accept it (e.g. adaptive-haar)",
    )
    p.add_argument("--config", metavar="FILE", help="tracker config TOML (configs/trackers/)")
    p.add_argument("-o", "--out", metavar="CSV", help="write boxes to this CSV file")
    p.add_argument("--video", metavar="FILE", help="write an annotated video (.mp4 / .avi)")
    p.add_argument("--particles", action="store_true", help="draw particles in --video")
    p.add_argument("--max-frames", type=int, metavar="N", help="stop after N frames")
    p.add_argument(
        "--color",
        choices=("rgb", "gray"),
        default="rgb",
        help="frame colour mode given to the tracker (default rgb; gray frames are replicated)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of trackers that take a generator")
    add_threads(p, default=1)
    add_progress(p)
    add_corpus_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Entry point of ``torchtrack track`` (returns the exit code)."""
    from torchtrack.cli._corpus import run_corpus_command, wants_corpus

    if wants_corpus(args):
        return run_corpus_command(args)
    check_args(args)
    summary = track_source(args, args.sources[0], out=args.out, video=args.video)
    print(summary.line())
    for path in (args.out, args.video):
        if path:
            print(f"wrote {path}")
    return summary.status


def check_args(args: argparse.Namespace) -> None:
    """Validate the options of one ``torchtrack track`` run before any work
    (:class:`ConfigError` naming the option)."""
    from torchtrack.cli._common import apply_threads
    from torchtrack.errors import ConfigError

    if args.max_frames is not None and args.max_frames < 1:
        raise ConfigError(f"--max-frames must be >= 1, got {args.max_frames}")
    if args.particles and not args.video:
        raise ConfigError("--particles draws into the annotated video: give --video FILE too")
    apply_threads(args)


@dataclass
class TrackSummary:
    """What one tracked source gave: frames tracked, unreadable frames, timings, exit status."""

    source: str
    frames: int
    unreadable: int
    seconds: float
    tracker_seconds: float
    ended_early: bool
    status: int

    @property
    def fps(self) -> float:
        return self.frames / self.tracker_seconds if self.tracker_seconds > 0 else float("inf")

    def line(self) -> str:
        return (
            f"tracked {self.frames} frames in {self.seconds:.1f} s: {self.fps:.1f} fps (tracker "
            f"only), {self.frames / max(self.seconds, 1e-9):.1f} fps overall; {self.unreadable} "
            "unreadable frame(s)" + (" (the video ended early)" if self.ended_early else "")
        )


def track_source(
    args: argparse.Namespace, source: str, *, out: str | None, video: str | None
) -> TrackSummary:
    """Track one ``source`` with the options of ``args`` (the parsed ``torchtrack track``
    namespace; ``args.sources``, ``args.out`` and ``args.video`` are not read), writing the box
    CSV to ``out`` and the annotated video to ``video`` (either may be ``None``).

    Raises:
        TorchTrackError: bad options, an unreadable source or a tracker failure.
    """
    import sys
    import time

    from torchtrack.errors import TrackerError
    from torchtrack.io.video import open_source

    box = parse_box(args.box) if args.box is not None else None
    tracker = build_tracker(args, auto=box is None)
    src = open_source(resolve_source(source), color=args.color)
    csv = BoxWriter(out) if out else None
    writer = None
    n_frames, t_track, t0 = 0, 0.0, time.perf_counter()
    last = None
    status = 0
    progress = _progress(src, args)
    try:
        for i, frame in src.items():
            if args.max_frames is not None and i >= args.max_frames:
                break
            progress.update(1)
            if frame is None:
                if csv is not None:
                    csv.write_bad(i, last)
                continue
            if last is None:
                t1 = time.perf_counter()
                if box is not None:
                    init_box = _checked_box(box, frame)
                    state = tracker.init(frame, init_box)
                elif getattr(tracker, "auto_init", False):
                    state = tracker.init(frame, None)
                else:
                    state = tracker.init(frame, detect_box(args.detect, frame))
                t_track += time.perf_counter() - t1
            else:
                t1 = time.perf_counter()
                state = tracker.update(frame)
                t_track += time.perf_counter() - t1
            n_frames += 1
            last = state
            if csv is not None:
                csv.write(i, state)
            if video:
                if writer is None:
                    writer = _open_video(video, frame, src.fps)
                writer.write(draw(frame, state, tracker if args.particles else None))
    except KeyboardInterrupt:
        status = 130
        print("interrupted: keeping the results so far", file=sys.stderr)
    finally:
        progress.close()
        if csv is not None:
            csv.close()
        if writer is not None:
            writer.release()
        src.close()
    elapsed = time.perf_counter() - t0
    if last is None and status == 0:
        raise TrackerError(f"no readable frame in {src.name}: nothing was tracked")
    return TrackSummary(
        source=str(source),
        frames=n_frames,
        unreadable=src.n_bad,
        seconds=elapsed,
        tracker_seconds=t_track,
        ended_early=bool(src.ended_early),
        status=status,
    )


def parse_box(text: str):
    """``"x,y,w,h"`` -> ``(4,)`` float64 tensor; :class:`BoxError` for anything else."""
    import math

    import torch

    from torchtrack.errors import BoxError

    parts = [p.strip() for p in text.replace(" ", ",").split(",") if p.strip()]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise BoxError(f"--box must be four numbers x,y,w,h (pixels), got {text!r}") from None
    if len(vals) != 4:
        raise BoxError(f"--box must be four numbers x,y,w,h (pixels), got {len(vals)}: {text!r}")
    if not all(math.isfinite(v) for v in vals):
        raise BoxError(f"--box must be finite numbers, got {text!r}")
    if vals[2] <= 0 or vals[3] <= 0:
        raise BoxError(f"--box {text!r} has zero or negative size: width and height must be > 0")
    return torch.tensor(vals, dtype=torch.float64)


def _checked_box(box, frame):
    """The init box, clipped to the frame (with a warning) when it only sticks out of it;
    :class:`BoxError` when it lies entirely outside or is left under one pixel."""
    import sys

    from torchtrack.boxes import check_boxes, clip_boxes

    h, w = int(frame.shape[-2]), int(frame.shape[-1])
    check_boxes(box[None], (h, w), name="--box")
    clipped = clip_boxes(box[None], (h, w))[0]
    if not bool((clipped == box).all()):
        check_boxes(clipped[None], (h, w), name="--box (clipped to the frame)")
        print(
            f"warning: --box {box.tolist()} sticks out of the {w}x{h} frame; clipped to "
            f"{[round(v, 2) for v in clipped.tolist()]}",
            file=sys.stderr,
        )
    return clipped


def resolve_source(source: str):
    """``"demo"`` (when no such file exists) -> the bundled demo clip; otherwise unchanged."""
    import os

    if source == "demo" and not os.path.exists(source):
        from torchtrack.data import demo_clip_path  # the bundled clip (torchtrack/data)

        return demo_clip_path()
    return source


def build_tracker(args: argparse.Namespace, auto: bool):
    """The tracker of ``--tracker`` with ``--adapt`` / ``--config`` / ``--detect`` / ``--seed``
    passed to the factory where it takes them (:class:`ConfigError` where it does not)."""
    import inspect

    import torch

    from torchtrack.errors import ConfigError
    from torchtrack.track.base import create_tracker, parse_tracker_spec, tracker_info

    name, params = parse_tracker_spec(args.tracker)
    info = tracker_info(name)
    try:
        accepted = set(inspect.signature(info.factory).parameters)
    except (TypeError, ValueError):
        accepted = set()
    for opt, key, value in (
        ("--adapt", "adapt", args.adapt),
        ("--config", "config", args.config),
    ):
        if value is None:
            continue
        if key not in accepted:
            raise ConfigError(f"tracker {name!r} does not take {opt}")
        params.setdefault(key, value)
    if args.detect is not None and "model" in accepted:
        params.setdefault("model", args.detect)
    if info.accepts_generator and "generator" not in params:
        params["generator"] = torch.Generator().manual_seed(args.seed)
    tracker = create_tracker(name, **params)
    if not auto and args.detect is not None and "model" not in accepted:
        raise ConfigError(
            f"--detect is used to find the target when no --box is given and by trackers that "
            f"take a model; tracker {name!r} with --box uses neither"
        )
    return tracker


def detect_box(model, frame):
    """The best detection of ``model`` (default: bundled pedestrian) on ``frame`` as a ``(4,)``
    box; :class:`TrackerError` when nothing scores at least 0.5."""
    from torchtrack.detect.scan import scan
    from torchtrack.errors import TrackerError
    from torchtrack.track.detector_pf import resolve_detector

    det = resolve_detector(model or "pedestrian")
    boxes, _ = scan(det, frame, threshold=0.5, min_scale=0.5, scale_step=1.15, stride=0.08)
    if boxes.shape[0] == 0:
        raise TrackerError(
            f"the {det.name!r} detector found nothing on the first frame; give the target's "
            "box with --box x,y,w,h"
        )
    return boxes[0].double()


class BoxWriter:
    """CSV of per-frame boxes, flushed row by row into ``PATH.part`` and renamed to ``PATH``
    (after an fsync) by :meth:`close`."""

    def __init__(self, path: str) -> None:
        import os

        self.path = path
        folder = os.path.dirname(os.path.abspath(path))
        if not os.path.isdir(folder):
            from torchtrack.errors import ConfigError

            raise ConfigError(f"--out folder {folder!r} does not exist")
        self.part = path + ".part"
        self._f = open(self.part, "w", encoding="utf-8", newline="")
        self._multi: bool | None = None

    def _header(self, b: int) -> None:
        if self._multi is None:
            self._multi = b > 1
            cols = "frame,target," if self._multi else "frame,"
            self._f.write(cols + "x,y,w,h,confidence,visible\n")

    def write(self, i: int, state) -> None:
        box = state.box.tolist()
        conf = state.confidence.tolist()
        vis = state.visible.tolist()
        self._header(len(box))
        for t, (b, c, v) in enumerate(zip(box, conf, vis, strict=True)):
            lead = f"{i},{t}," if self._multi else f"{i},"
            self._f.write(
                lead + ",".join(f"{x:.2f}" for x in b) + f",{float(c):.4f},{int(bool(v))}\n"
            )
        self._f.flush()

    def write_bad(self, i: int, last) -> None:
        """Row(s) for an unreadable frame: the previous box, confidence 0, not visible."""
        if last is None:
            self._header(1)
            lead = f"{i},0," if self._multi else f"{i},"
            self._f.write(lead + "nan,nan,nan,nan,0.0000,0\n")
            self._f.flush()
            return
        import dataclasses

        import torch

        self.write(
            i,
            dataclasses.replace(
                last,
                confidence=torch.zeros_like(last.confidence),
                visible=torch.zeros_like(last.visible),
            ),
        )

    def close(self) -> None:
        import os

        if self._f.closed:
            return
        self._header(1)
        self._f.flush()
        os.fsync(self._f.fileno())
        self._f.close()
        os.replace(self.part, self.path)


def _progress(src, args):
    from tqdm import tqdm

    from torchtrack.cli._common import show_progress

    total = len(src) or None
    if args.max_frames is not None:
        total = min(total, args.max_frames) if total else args.max_frames
    return tqdm(total=total, unit="frame", disable=not show_progress(args), leave=False)


def _open_video(path: str, frame, fps: float | None):
    import os

    import cv2

    from torchtrack.errors import VideoError

    h, w = int(frame.shape[-2]), int(frame.shape[-1])
    ext = os.path.splitext(path)[1].lower()
    fourcc = cv2.VideoWriter_fourcc(*("MJPG" if ext == ".avi" else "mp4v"))
    writer = cv2.VideoWriter(path, fourcc, float(fps or 25.0), (w, h))
    if not writer.isOpened():
        raise VideoError(f"cannot write video {path!r} (use .mp4 or .avi)")
    return writer


#: BGR colours: a visible target, a lost one, particles.
_GREEN, _RED, _PARTICLE = (60, 220, 60), (40, 40, 230), (230, 200, 40)


def draw(frame, state, tracker=None, max_particles: int = 200):
    """An annotated BGR image ``(H, W, 3)`` of ``frame (C, H, W)``: each target's box (green
    when visible, red when lost) with its confidence, and, given a ``tracker`` with
    ``particle_boxes()``, the centres of up to ``max_particles`` particles per target."""
    import cv2

    from torchtrack.io.video import to_numpy_bgr

    img = to_numpy_bgr(frame).copy()
    if tracker is not None and hasattr(tracker, "particle_boxes"):
        pb = tracker.particle_boxes()
        step = max(1, pb.shape[1] // max_particles)
        centres = (pb[:, ::step, :2] + pb[:, ::step, 2:] / 2).round().long().tolist()
        for row in centres:
            for cx, cy in row:
                cv2.circle(img, (cx, cy), 1, _PARTICLE, -1, lineType=cv2.LINE_AA)
    for b, c, v in zip(
        state.box.tolist(), state.confidence.tolist(), state.visible.tolist(), strict=True
    ):
        if any(t != t for t in b):  # NaN box: nothing to draw
            continue
        x, y, w, h = (round(t) for t in b)
        col = _GREEN if v else _RED
        cv2.rectangle(img, (x, y), (x + w, y + h), col, 2, lineType=cv2.LINE_AA)
        label = f"{float(c):.2f}" + ("" if v else " lost")
        cv2.putText(
            img, label, (x, max(12, y - 4)), cv2.FONT_HERSHEY_SIMPLEX, 0.45, col, 1, cv2.LINE_AA
        )
    return img
