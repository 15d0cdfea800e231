"""``torchtrack detect``: run a detector over an image, a folder of images or a video.

Writes one JSON line per frame::

    {"frame": 0, "source": "img001.png" | null, "time": 0.0 | null, "width": 480, "height": 360,
     "boxes": [[x, y, w, h], ...], "probabilities": [p, ...]}

(``source``: the image file for folders and single images; ``time``: seconds from the start of
a video, ``frame / fps``). Boxes are the objects' boxes, x, y, w, h in pixels (top-left corner,
0-based): the part of each detection window where the model's training crops hold the object
(:meth:`~torchtrack.detect.Detector.window_to_object`; the pedestrian model's 64x128 window holds
a person 96 px tall with 16 px of margin); ``--windows`` reports the windows themselves.
Probabilities are the model's calibrated P(object | window) (Platt, Chateau et al. eq. 8), sorted
in decreasing order, after non-maximum suppression.

Scales: ``--min-height PX`` (default 32) is the smallest object height looked for, in frame
pixels; ``--min-scale`` (window / model window) overrides it.

Colour: Chateau's grey Haar models work on luma (ITU-R BT.601); channel models trained on colour
(the bundled pedestrian) read LUV, and a grayscale image is taken as R = G = B (no colour
information, so lower scores); a model trained on grayscale crops (the UIUC cars) reads the
luma of colour footage. There is no channel mismatch to report. Annotated output keeps the
input's colours (grayscale images are drawn as gray RGB).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from torchtrack.cli._common import integer, number

# Default scan settings (docs/benchmarks/scan.md says how they were chosen).
THRESHOLD = 0.5
MIN_HEIGHT = 32.0
SCALE_STEP = 1.2
STRIDE = 0.1
NMS_IOU = 0.3
NMS_OVERLAP = "union"
VOTE_IOU = 0.5
PAD = 0.1

_EPILOG = """\
examples:
  torchtrack detect pedestrian street.jpg
  torchtrack detect vehicle photos/ --out cars.jsonl --annotate annotated/
  torchtrack detect pedestrian demo --min-scale 0.35 --threshold 0.9 --video demo_detections.mp4
  torchtrack detect my_model.safetensors clip.avi --stride 0.05 --scale-step 1.1

MODEL is a model file or a bundled name (pedestrian, vehicle). Objects are looked for from
--min-height pixels tall (default 32) up to what fits the frame; --min-scale (window / model
window: pedestrian 128x64 holding a person 96 px tall, vehicle 40x100) sets the range directly.
Unreadable images in a folder are skipped and listed on stderr (--strict: fail instead).
"""


#: the most frames --batch scores together (each holds its channels and window lattice)
MAX_BATCH = 64


def register(subparsers) -> None:
    from torchtrack.cli._common import add_out, add_progress, add_threads, add_trust

    p = subparsers.add_parser(
        "detect",
        help="detect objects in an image, a folder of images or a video (JSON lines)",
        description=(
            "Scan every frame with a calibrated detector at several scales (sliding windows "
            "scored from one integral image per frame, non-maximum suppression) and write one "
            "JSON line per frame with boxes and calibrated probabilities; optionally annotated "
            "images or an annotated video."
        ),
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("model", metavar="MODEL", help="model file or bundled name")
    p.add_argument(
        "source",
        metavar="SOURCE",
        help="image file, folder of images, video file or 'demo' (the bundled clip)",
    )
    add_out(p, "JSONL", "write the JSON lines here (default: stdout)")
    p.add_argument(
        "--threshold",
        type=number,
        default=THRESHOLD,
        metavar="P",
        help=f"keep detections with calibrated probability >= P (default {THRESHOLD:g})",
    )
    p.add_argument("--annotate", metavar="DIR", help="write annotated frames (PNG) to DIR")
    p.add_argument("--video", metavar="MP4", help="write an annotated video (mp4v)")
    p.add_argument(
        "--min-height",
        type=number,
        default=MIN_HEIGHT,
        metavar="PX",
        help=f"smallest object height in frame pixels (default {MIN_HEIGHT:g})",
    )
    p.add_argument(
        "--min-scale",
        type=number,
        help="smallest window / model window, at least 0.0625 (overrides --min-height)",
    )
    p.add_argument("--max-scale", type=number, help="largest window / model window")
    p.add_argument(
        "--scale-step",
        type=number,
        default=SCALE_STEP,
        help=f"ratio of successive scales (default {SCALE_STEP:g})",
    )
    p.add_argument(
        "--stride",
        type=number,
        default=STRIDE,
        help=f"window step / window size (default {STRIDE:g})",
    )
    p.add_argument(
        "--nms-iou",
        type=number,
        default=NMS_IOU,
        help=f"non-maximum suppression overlap threshold (default {NMS_IOU:g}; 1: off)",
    )
    p.add_argument(
        "--nms-overlap",
        choices=("union", "min"),
        default=NMS_OVERLAP,
        help="overlap of two object boxes: intersection over union, or over the smaller box "
        f"(drops detections of body parts inside a detected person; default {NMS_OVERLAP})",
    )
    add_box_refinement(p)
    p.add_argument(
        "--windows",
        action="store_true",
        help="report the detection windows instead of the object boxes",
    )
    p.add_argument(
        "--no-cascade",
        action="store_true",
        help="score every window with every tree (channel models: slower; the soft cascade "
        "drops a window as soon as its running score falls below the model's threshold)",
    )
    p.add_argument(
        "--cascade",
        type=number,
        metavar="MARGIN",
        help="loosen the soft cascade: every tree's threshold lowered to at most this running "
        "margin, e.g. -5 (channel models; more objects found, more false ones, slower; on the "
        "PETS 2009 video 75%% of the people at the model's own cascade, 85%% at -5, "
        "docs/benchmarks/scan.md; default: the model's own)",
    )
    p.add_argument(
        "--batch",
        type=integer,
        default=4,
        metavar="B",
        help=f"frames scored together, 1 to {MAX_BATCH} (default 4)",
    )
    p.add_argument(
        "--scan-workers",
        type=integer,
        metavar="N",
        help="scan the batches in N forked processes while this one reads and writes (the same "
        "detections; default 2 on Linux with two cores or more, else 0 = in this process)",
    )
    p.add_argument("--max-frames", type=integer, metavar="N", help="stop after N frames")
    p.add_argument("--strict", action="store_true", help="fail on an unreadable image")
    add_progress(p)
    add_threads(p, default=2)
    add_trust(p)
    p.set_defaults(func=run)


def add_box_refinement(p: argparse.ArgumentParser) -> None:
    """``--vote-iou`` and ``--pad`` with ``torchtrack detect``'s defaults (also used by the
    benchmark scripts that score its scan)."""
    p.add_argument(
        "--vote-iou",
        type=number,
        default=None,
        help="refine each detection with the windows above --threshold that overlap it by this "
        f"IoU (weighted mean position and scale; the probability stays the best window's; "
        f"default {VOTE_IOU:g}; 0: off)",
    )
    p.add_argument(
        "--pad",
        type=number,
        default=PAD,
        help="let windows hang this fraction of their size over the image's edges (the edge "
        f"pixels continued), to find objects the edge cuts (default {PAD:g}; at most 0.5)",
    )
    p.add_argument(
        "--no-box-regression",
        action="store_true",
        help="report the windows as scanned: without it a model with a box regressor (the "
        "bundled pedestrian model) moves each detection to where its training crops put the "
        "object",
    )


def vote_iou(args: argparse.Namespace) -> float:
    """``--vote-iou`` as the scan uses it: its default (:data:`VOTE_IOU`) when not given; 0:
    off (the scan benchmarks read it through this too)."""
    return VOTE_IOU if args.vote_iou is None else args.vote_iou


def scan_kwargs(args: argparse.Namespace, det) -> dict:
    """The :meth:`Detector.scan` arguments of parsed ``torchtrack detect`` options for ``det``
    (the benchmarks that score the command's scan call this too).

    Raises:
        ConfigError: ``--max-scale`` below the scale of ``--min-height``; ``--min-scale`` or
            ``--min-height`` below the scan's ``MIN_SCALE``.
    """
    from torchtrack.detect.scan import MIN_SCALE
    from torchtrack.errors import ConfigError

    min_scale = args.min_scale
    if min_scale is None:
        min_scale = args.min_height / object_height(det)
        if args.max_scale is not None and args.max_scale < min_scale:
            raise ConfigError(
                f"--max-scale {args.max_scale} is below the scale of --min-height "
                f"{args.min_height:g} px ({min_scale:.3g})"
            )
    if min_scale < MIN_SCALE:  # 0.01 asked for a lattice of tens of GB (a traceback or OOM)
        raise ConfigError(
            (
                f"--min-scale {args.min_scale:g}"
                if args.min_scale is not None
                else f"--min-height {args.min_height:g} px (scale {min_scale:.3g})"
            )
            + f" would upsample the frames {1 / min_scale:.3g}x for the {det.window[0]}x"
            f"{det.window[1]} window; at most {1 / MIN_SCALE:g}x: --min-scale {MIN_SCALE:g} or "
            f"more (--min-height {MIN_SCALE * object_height(det):.3g} px or more)"
        )
    vote = vote_iou(args)
    return {
        "threshold": args.threshold,
        "scale_step": args.scale_step,
        "stride": args.stride,
        "min_scale": min_scale,
        "max_scale": args.max_scale,
        "nms_iou": None if args.nms_iou >= 1.0 else args.nms_iou,
        "nms_overlap": args.nms_overlap,
        "vote_iou": vote if vote > 0 and args.nms_iou < 1.0 else None,
        "pad": args.pad,
        "windows": args.windows,
        "cascade": not args.no_cascade,
        "cascade_threshold": args.cascade,
        "refine": not args.no_box_regression,
    }


def _check_args(args: argparse.Namespace) -> None:
    from torchtrack.cli._common import check_scan_workers
    from torchtrack.errors import ConfigError

    if not 0.0 <= args.threshold <= 1.0:
        raise ConfigError(f"--threshold is a probability in [0, 1], got {args.threshold}")
    if args.min_scale is not None and not 0 < args.min_scale < math.inf:
        raise ConfigError(f"--min-scale must be > 0 and finite, got {args.min_scale}")
    if args.max_scale is not None and not 0 < args.max_scale < math.inf:
        raise ConfigError(f"--max-scale must be > 0 and finite, got {args.max_scale}")
    if not 0 < args.min_height < math.inf:  # inf: a scan of every frame, then 'scale inf'
        raise ConfigError(f"--min-height must be > 0 pixels and finite, got {args.min_height}")
    if (
        args.max_scale is not None
        and args.min_scale is not None
        and args.max_scale < args.min_scale
    ):
        raise ConfigError(f"--max-scale {args.max_scale} is below --min-scale {args.min_scale}")
    if not 0.0 < args.stride <= 1.0:
        raise ConfigError(f"--stride is a fraction of the window in (0, 1], got {args.stride}")
    from torchtrack.detect.scan import MIN_SCALE_STEP

    if not MIN_SCALE_STEP <= args.scale_step < float("inf"):
        raise ConfigError(
            f"--scale-step must be a finite number >= {MIN_SCALE_STEP:g}, got {args.scale_step}"
        )
    if not 0.0 < args.nms_iou <= 1.0:
        raise ConfigError(f"--nms-iou must be in (0, 1], got {args.nms_iou}")
    if not 0.0 <= args.pad <= 0.5:
        raise ConfigError(f"--pad is a fraction of the window in [0, 0.5], got {args.pad}")
    if args.vote_iou is not None and not 0.0 <= args.vote_iou <= 1.0:
        raise ConfigError(f"--vote-iou must be in [0, 1] (0: off), got {args.vote_iou}")
    if args.vote_iou and args.nms_iou >= 1.0:  # the scan drops the vote without NMS, silently
        raise ConfigError(
            f"--vote-iou {args.vote_iou:g} refines the detections non-maximum suppression keeps: "
            "with --nms-iou 1 (off) there is none; drop one of them"
        )
    if args.cascade is not None:
        if not (math.isfinite(args.cascade) and args.cascade <= 0):
            raise ConfigError(
                f"--cascade is a running margin <= 0 (a looser cascade than the model's; 0: the "
                f"model's own), got {args.cascade}"
            )
        if args.no_cascade:
            raise ConfigError(
                "--cascade loosens the soft cascade and --no-cascade turns it off: give one"
            )
    if not 1 <= args.batch <= MAX_BATCH:
        # every frame of a batch holds its channels and lattice at once: 300 PETS frames
        # asked for 2.6 GB in one allocation (a RuntimeError traceback, or out of memory)
        raise ConfigError(f"--batch must be in [1, {MAX_BATCH}], got {args.batch}")
    check_scan_workers(args.scan_workers)
    if args.max_frames is not None and args.max_frames < 1:
        raise ConfigError(f"--max-frames must be >= 1, got {args.max_frames}")
    if args.video is not None and Path(args.video).suffix.lower() != ".mp4":
        raise ConfigError(f"--video writes MPEG-4 (mp4v): give a .mp4 path, got {args.video!r}")
    from torchtrack.cli._common import check_distinct, check_output_dir, check_output_file

    check_output_file(args.out, "--out")
    check_output_file(args.video, "--video", (".mp4",))
    check_output_dir(args.annotate, "--annotate")
    source = args.source if Path(args.source).is_file() else None
    # --annotate's folder is made at the first frame: one path for it and --out ran the whole
    # scan, then failed to write --out there and left the annotated frames
    check_distinct(
        {"SOURCE": source, "--out": args.out, "--video": args.video, "--annotate": args.annotate}
    )
    from torchtrack.cli._common import check_spares_inputs

    check_spares_inputs(
        {"--out": args.out, "--video": args.video, "--annotate": args.annotate},
        {"SOURCE": args.source, "MODEL": args.model},
    )


def object_height(det) -> float:
    """Height in pixels of the object in the detector's window at scale 1 (the whole window
    when the model has no object box)."""
    return det.window[0] * (det.object_box[3] if det.object_box is not None else 1.0)


def _open(source: str):
    from torchtrack.cli.track import resolve_source
    from torchtrack.errors import VideoError
    from torchtrack.io.video import IMAGE_EXTENSIONS, open_source

    p = Path(resolve_source(source))
    if not p.exists():
        raise VideoError(f"source {source!r} does not exist (give an image, a folder or a video)")
    if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS:
        return open_source([p])
    return open_source(p)


def draw_detections(frame, boxes, probs, color=(0, 255, 0)):
    """``frame (C, H, W)`` uint8 RGB or gray -> ``(H, W, 3)`` BGR array with the boxes drawn and
    labelled with their probability."""
    import cv2

    from torchtrack.io.video import to_numpy_bgr

    img = to_numpy_bgr(frame)
    thick = max(1, round(min(img.shape[:2]) / 300))
    for (x, y, w, h), p in zip(boxes.tolist(), probs.tolist(), strict=True):
        p1 = (round(x), round(y))
        p2 = (round(x + w) - 1, round(y + h) - 1)
        cv2.rectangle(img, p1, p2, color, thick, cv2.LINE_AA)
        label = f"{p:.2f}"
        (tw, th), base = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.4, 1)
        ty = max(th + base, p1[1])
        cv2.rectangle(img, (p1[0], ty - th - base), (p1[0] + tw, ty), color, -1)
        cv2.putText(
            img, label, (p1[0], ty - base), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA
        )
    return img


def _check_annotated_names(files: list[Path], annotate: str) -> None:
    """Each frame file is annotated into ``DIR/<its stem>.png``: two of one stem (``0001.jpg``,
    ``0001.png``) would be one PNG, the second written over the first, silently.

    Raises:
        ConfigError: naming both files.
    """
    from torchtrack.errors import ConfigError

    seen: dict[str, Path] = {}
    for f in files:
        first = seen.setdefault(f.stem, f)
        if first is not f:
            raise ConfigError(
                f"--annotate {annotate!r} writes each frame as <its name>.png: {first} and {f} "
                f"would both be {f.stem}.png, the second over the first; rename one of them"
            )


class _Writers:
    """Annotated PNGs (each written atomically) and an annotated video (written to a
    temporary file, renamed on success)."""

    def __init__(self, annotate: str | None, video: str | None, fps: float | None) -> None:
        import contextlib

        self.dir = Path(annotate) if annotate else None  # made at the first frame written
        self.video_path = video
        self.fps = fps or 10.0
        self._stack = contextlib.ExitStack()
        self._tmp = None
        self._writer = None
        self._size = None
        self._warned_size = False
        self._written: list[Path] = []  # annotated PNGs of this run (removed if it fails)
        self._made_dir = False

    def __enter__(self):
        if self.video_path:
            from torchtrack.io.atomic import atomic_path

            self._tmp = self._stack.enter_context(atomic_path(self.video_path))
        return self

    def write(self, index: int, name: str | None, img) -> None:
        import cv2

        from torchtrack.errors import VideoError
        from torchtrack.io.atomic import atomic_path

        if self.dir is not None:
            if not self.dir.exists():
                self.dir.mkdir()
                self._made_dir = True
            stem = Path(name).stem if name else f"frame_{index:06d}"
            dest = self.dir / f"{stem}.png"
            if dest.exists():
                # an earlier run's frame: replaced when this run succeeds (the stack renames
                # its temporary file then), kept when it fails (it was deleted with the rest)
                tmp = self._stack.enter_context(atomic_path(dest))
                if not cv2.imwrite(str(tmp), img):
                    raise VideoError(f"cannot write {dest}")
            else:
                with atomic_path(dest) as tmp:
                    if not cv2.imwrite(str(tmp), img):
                        raise VideoError(f"cannot write {dest}")
                self._written.append(dest)
        if self._tmp is not None:
            h, w = img.shape[:2]
            if self._writer is None:
                from torchtrack.io.video import native_output

                self._size = (w, h)
                with native_output() as log:
                    self._writer = cv2.VideoWriter(
                        str(self._tmp), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, (w, h)
                    )
                    opened = self._writer.isOpened()
                if not opened:
                    detail = log.first_line()
                    raise VideoError(
                        f"OpenCV cannot write an mp4v video to {self.video_path}"
                        + (f" ({detail})" if detail else "")
                    )
            if (w, h) != self._size:  # a video has one frame size: pad or crop to the first
                if not self._warned_size:
                    import warnings

                    warnings.warn(
                        f"--video {self.video_path!r}: frame {index} is {w}x{h}, the video "
                        f"{self._size[0]}x{self._size[1]} (its first frame): frames of another "
                        "size are padded or cropped into it (the JSON boxes are not)",
                        UserWarning,
                        stacklevel=2,
                    )
                    self._warned_size = True
                canvas = cv2.copyMakeBorder(
                    img[: self._size[1], : self._size[0]],
                    0,
                    max(0, self._size[1] - h),
                    0,
                    max(0, self._size[0] - w),
                    cv2.BORDER_CONSTANT,
                )
                img = canvas
            self._writer.write(img)

    def __exit__(self, exc_type, exc, tb):
        if self._writer is not None:
            self._writer.release()
        if exc_type is not None:
            # a failed or interrupted run leaves no output (the JSON lines and the video are
            # discarded too): this run's annotated frames go
            for p in self._written:
                p.unlink(missing_ok=True)
            if self._made_dir and not any(self.dir.iterdir()):
                self.dir.rmdir()
        return self._stack.__exit__(exc_type, exc, tb)


def run(args: argparse.Namespace) -> int:
    import contextlib
    import math

    import torch
    from tqdm import tqdm

    from torchtrack.cli._common import apply_threads, show_progress
    from torchtrack.detect.bundled import load_model
    from torchtrack.detect.scan import MIN_WINDOW_PX
    from torchtrack.errors import ConfigError, DataError, NotFittedError, ShapeError
    from torchtrack.io.atomic import atomic_write
    from torchtrack.track.scan_ahead import Ahead, default_scan_workers

    _check_args(args)
    apply_threads(args)
    det = load_model(args.model)
    if det.calibrator is None:
        raise NotFittedError(
            f"model {args.model!r} has no calibration: run `torchtrack calibrate` first"
        )
    if args.no_cascade or args.cascade is not None:
        from torchtrack.detect.scan import _lattice_capable

        if not _lattice_capable(det):  # the scan ignores both: they did nothing, silently
            raise ConfigError(
                f"{'--no-cascade' if args.no_cascade else '--cascade'} sets the soft cascade of "
                f"channel models (boosted trees): model {args.model!r} ("
                f"{type(det.bank).__name__}, {type(det.classifier).__name__}) has none"
            )
    src = _open(args.source)
    files = src.files
    if args.annotate and files is not None:
        _check_annotated_names(files, args.annotate)
    fps = src.fps
    skipped: list[tuple[int, str]] = []
    n_frames = n_det = 0
    scan_kw = scan_kwargs(args, det)
    workers = args.scan_workers if args.scan_workers is not None else default_scan_workers()
    total = len(src) or None
    if args.max_frames is not None and total is not None:
        total = min(total, args.max_frames)
    out_cm = atomic_write(args.out) if args.out else contextlib.nullcontext(sys.stdout)
    with src, out_cm as out, _Writers(args.annotate, args.video, fps) as writers:
        bar = tqdm(
            total=total,
            unit="frame",
            disable=not show_progress(args),
            desc="detect",
            file=sys.stderr,
        )

        def scan_or_error(frames: torch.Tensor):
            try:
                return det.scan(frames, **scan_kw)
            except ShapeError as exc:  # returned, so that the batches after it go on
                if (
                    args.min_scale is not None
                    or min(frames.shape[-2] / det.window[0], frames.shape[-1] / det.window[1])
                    * det.window[0]
                    < MIN_WINDOW_PX
                ):  # no useful --min-height to suggest
                    return exc
                # the smallest scale came from --min-height: say it in the option's terms
                (wh, ww), (fh, fw) = det.window, frames.shape[-2:]
                most = min(fh / wh, fw / ww) * object_height(det)
                return ShapeError(
                    f"{exc}. That scale is --min-height {args.min_height:g} px: these frames "
                    f"take --min-height {math.floor(most * 10) / 10:g} px or less"
                )

        def batches():
            """Batches of equal-size frames, ``(batch, stacked frames)``; unreadable frames
            are counted as skipped (or stop the run with --strict)."""
            pending: list[tuple[int, torch.Tensor]] = []
            for seen, (i, frame) in enumerate(src.items()):
                if args.max_frames is not None and seen >= args.max_frames:
                    break
                if frame is None:
                    reason = src.bad_frames[-1].reason if src.bad_frames else "unreadable"
                    if args.strict:
                        raise DataError(f"{reason} (--strict)")
                    skipped.append((i, reason))
                    bar.update(1)
                    continue
                if pending and (pending[0][1].shape != frame.shape or len(pending) >= args.batch):
                    yield pending, torch.stack([f for _, f in pending])
                    pending = []
                pending.append((i, frame))
            if pending:
                yield pending, torch.stack([f for _, f in pending])

        try:
            # batches scanned ahead in forked workers (or here, with 0), back in order
            with Ahead(scan_or_error, workers) as ahead:
                scanned = ahead.map(batches(), where=lambda batch: f"frame {batch[0][0]}")
                for batch, results in scanned:
                    if isinstance(results, ShapeError):
                        if files is None or len(files) < 2 or args.strict:
                            raise results
                        # one small image in a folder: skip it like an unreadable one
                        skipped.extend((i, str(results)) for i, _ in batch)
                        bar.update(len(batch))
                        continue
                    for (i, frame), (boxes, probs) in zip(batch, results, strict=True):
                        name = files[i].name if files is not None else None
                        rec = {
                            "frame": i,
                            "source": name,
                            "time": round(i / fps, 6) if fps else None,
                            "width": int(frame.shape[-1]),
                            "height": int(frame.shape[-2]),
                            "boxes": [[round(v, 2) for v in b] for b in boxes.tolist()],
                            "probabilities": [round(p, 6) for p in probs.tolist()],
                        }
                        try:
                            out.write(json.dumps(rec) + "\n")
                        except OSError as exc:  # stdout on a full disk, a closed pipe
                            raise ConfigError(
                                f"cannot write the detections to "
                                f"{args.out or 'standard output'}: {exc.strerror or exc}"
                            ) from None
                        n_frames += 1
                        n_det += len(rec["boxes"])
                        if args.annotate or args.video:
                            writers.write(i, name, draw_detections(frame, boxes, probs))
                    bar.update(len(batch))
        finally:
            bar.close()
        if src.ended_early and args.strict:
            raise DataError(f"{src.bad_frames[-1].reason} in {args.source} (--strict)")
        if n_frames == 0:
            # nothing was written: leave no empty output behind
            # each reason once: three frames too small for the window said it three times
            detail = "; ".join(list(dict.fromkeys(r for _, r in skipped))[:3]) or (
                src.bad_frames[0].reason if src.bad_frames else "it holds no frame"
            )  # a video that ended at once, or of 0 frames: the message said only '()'
            raise DataError(f"no frame of {args.source} could be processed ({detail})")
    if not args.quiet:
        for i, reason in sorted(skipped):
            print(f"skipped frame {i}: {reason}", file=sys.stderr)
        if src.ended_early:
            print(
                f"warning: {src.bad_frames[-1].reason}: {args.source} ended early (truncated "
                "or corrupt video)",
                file=sys.stderr,
            )
        rate = n_det / n_frames if n_frames else math.nan
        print(
            f"{n_frames} frame(s), {n_det} detection(s) ({rate:.2f} per frame) with P >= "
            f"{args.threshold}; {len(skipped)} skipped",
            file=sys.stderr,
        )
    return 0
