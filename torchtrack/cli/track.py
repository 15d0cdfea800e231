"""``torchtrack track``: detect and track every target of a video, or follow one target.

Examples::

    torchtrack track demo --video tracked.mp4            # every pedestrian of the bundled clip
    torchtrack track clip.mp4 --detect vehicle --mot cars.txt --out cars.csv
    torchtrack track TUD-Stadtmitte/img1 --detections TUD-Stadtmitte/det/det.txt --mot out.txt
    torchtrack track clip.mp4 --box 120,40,56,156 --out boxes.csv     # one target
    torchtrack track footage/ --out-dir runs/tracks --write csv,mot --backend ray  # a corpus
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

from torchtrack.cli._common import integer, number

_EPILOG = """\
examples:
  torchtrack track demo --video tracked.mp4
      every pedestrian of the bundled demo clip, each identity in its own colour with a trail
  torchtrack track clip.mp4 --detect vehicle --out cars.csv --mot cars.txt --scan-every 2
      every car, found by the bundled vehicle detector on every second frame
  torchtrack track frames/ --detections det.txt --mot tracks.txt
      public detections (MOTChallenge det.txt) instead of our scan, through our tracker
  torchtrack track clip.mp4 --box 120,40,56,156 --out boxes.csv --video annotated.mp4
      one target, given on the first frame, with the calibrated-detector tracker
  torchtrack track frames/ --box 120,40,56,156 --tracker histogram --video out.mp4 --particles
  torchtrack track clip.mp4 --box 10,20,40,80 --tracker adaptive-haar --adapt global
  torchtrack track clip.mp4 --detect vehicle --tracker mil
      find the first frame's best car, then follow that one car with MIL
  torchtrack track footage/ 'more/**/*.mp4' @list.txt --out-dir runs/tracks --write csv,mot
      a corpus: every video, one CSV and one MOTChallenge file each, resumable (docs/scale.md)
  torchtrack track footage/ --out-dir runs/tracks --backend ray --address 10.0.0.5:6379
      the same on a Ray cluster, one task per video

modes:
  Without --box (and with --tracker multi, the default then), every target is detected and
  tracked: the --detect model (default: the bundled pedestrian model) scans every --scan-every
  frames, all targets share one batched particle filter whose likelihood is the detector's
  calibrated probability, detections are assigned to targets optimally, new targets are
  confirmed over a few scans and end when lost or out of the frame (at most --max-targets).
  The ground plane (object height against foot row) is learnt from the video's confirmed
  targets: once it holds, the scans skip the windows of the wrong size for their place and
  such detections are dropped (multi:ground_gate=0 turns it off; nothing changes in a scene
  that is not one ground plane). On video where the detector is less sure of everyone (low
  contrast, noise), the birth threshold adapts down to the video's own level, and a new target
  below the usual threshold must be moving (multi:birth_floor=0.9999 keeps it fixed). The
  reported tracks are written 36 frames late: a target hidden for up to 10 frames gets boxes
  interpolated across the gap (detected=0), the boxes are smoothed over time, a new target's
  track is extended back through the detections of the frames before it was confirmed, and
  two identities that came out of a close encounter each on the other's person are swapped
  back (multi:fill_gaps=0,smooth_sigma=0,backfill=0,unswap=0 writes each frame's boxes as
  tracked).
  Options of the multi-target tracker: --tracker multi:key=value,... or --config
  configs/trackers/multi.toml. With --box x,y,w,h (pixels, top-left corner, 0-based, on the first
  readable frame) one target is followed by --tracker (default: detector); a box sticking out of
  the frame is clipped with a warning, one entirely outside is an error.

outputs:
  --out CSV: multi-target: frame,target,x,y,w,h,confidence,detected (one row per reported
  target and frame; frame 0-based, target the identity, detected 1 when a detection was matched
  on that frame); one target: frame,x,y,w,h,confidence,visible (one row per frame; unreadable
  frames keep the previous box with visible=0; a lost target, e.g. one that left the frame, is
  written with visible=0). --mot TXT: MOTChallenge results, frame,id,x,y,w,h,conf,-1,-1,-1
  (frames and pixels 1-based). --video FILE: annotated video (.mp4 or .avi). Boxes are the
  object's box (the person or car), not the detector window. Rows stream into OUT.part and
  are renamed to OUT at the end (also after Ctrl-C or SIGTERM, keeping the rows so far), so
  OUT is never half-written; a run that fails (an error, exit status 1) leaves no output, and
  output paths are checked before any work. Unreadable frames (also truncated
  JPEGs) are counted; a box less than half inside the frame is never visible.
"""


def register(subparsers) -> None:
    from torchtrack.cli._common import (
        add_device,
        add_progress,
        add_threads,
        add_trust,
        seed_value,
    )
    from torchtrack.cli._corpus import add_corpus_options

    p = subparsers.add_parser(
        "track",
        help="detect and track every target of a video, or follow one given target",
        description=(
            "Detect and track every pedestrian or vehicle of SOURCE (a video file, a folder "
            "of frames, a camera index, or 'demo' for the bundled clip) with stable "
            "identities, or follow one target given with --box with any registered tracker "
            "(see `torchtrack eval --list-trackers`). Writes a CSV, a MOTChallenge file and/or "
            "an annotated video, with a progress bar and a final frames-per-second line."
        ),
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "sources",
        nargs="+",
        metavar="SOURCE",
        help="video file, frame folder, camera index (0, 1, ...; a file or folder of that name "
        "comes first) or 'demo' (the bundled clip); several, a folder of videos, a glob or "
        "@list.txt: a corpus run (--out-dir)",
    )
    p.add_argument("--box", metavar="X,Y,W,H", help="follow this one target (first-frame box)")
    p.add_argument(
        "--detect",
        metavar="MODEL",
        help="the detector: a bundled name (pedestrian, vehicle) or a model file (default: "
        "pedestrian)",
    )
    p.add_argument(
        "--tracker",
        default=None,
        metavar="NAME",
        help="tracker, optionally with parameters name:key=value,... (default: multi without "
        "--box, detector with --box)",
    )
    p.add_argument(
        "--adapt",
        choices=("none", "global", "per-particle"),
        help="adaptation mode, passed to trackers that accept it (e.g. adaptive-haar)",
    )
    p.add_argument("--config", metavar="FILE", help="tracker config TOML (configs/trackers/)")
    p.add_argument(
        "--scan-every",
        type=integer,
        metavar="K",
        help="multi-target: scan for detections every K-th frame, or with --detections take "
        "those of every K-th frame (default: the config's, 1)",
    )
    p.add_argument(
        "--max-targets", type=integer, metavar="N", help="multi-target: at most N targets at once"
    )
    p.add_argument(
        "--scan-workers",
        type=integer,
        metavar="N",
        help="multi-target: scan the coming frames in N forked processes while the tracker "
        "steps the current one (the same tracks, faster; default 2 on Linux with two cores "
        "or more, else 0; 0 = scan in this process; corpus runs use 0)",
    )
    p.add_argument(
        "--detections",
        metavar="TXT",
        help="multi-target: detections from this MOTChallenge file (frame,-1,x,y,w,h,score,...) "
        "instead of scanning",
    )
    p.add_argument(
        "--det-calibration",
        metavar="JSON",
        help="map the scores of --detections to probabilities with this calibration (from "
        "`torchtrack calibrate --scores ... --json`); without it scores in [0, 1] are taken as "
        "probabilities and other scores are divided by the file's highest score",
    )
    p.add_argument(
        "--det-min-score",
        type=number,
        metavar="S",
        help="drop --detections scoring below S (in the file's own units)",
    )
    p.add_argument("-o", "--out", metavar="CSV", help="write boxes to this CSV file")
    p.add_argument("--mot", metavar="TXT", help="write the tracks in MOTChallenge format")
    p.add_argument("--video", metavar="FILE", help="write an annotated video (.mp4 / .avi)")
    p.add_argument("--particles", action="store_true", help="draw particles in --video")
    p.add_argument("--max-frames", type=integer, metavar="N", help="stop after N frames")
    p.add_argument(
        "--color",
        choices=("rgb", "gray"),
        default="rgb",
        help="frame colour mode given to the tracker (default rgb; gray frames are replicated)",
    )
    p.add_argument(
        "--seed", type=seed_value, default=0, help="seed of trackers that take a generator"
    )
    add_threads(p, default=1)
    add_device(p)
    add_progress(p)
    add_trust(p)
    add_corpus_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Entry point of ``torchtrack track`` (returns the exit code)."""
    from torchtrack.cli._corpus import run_corpus_command, wants_corpus

    if wants_corpus(args):
        return run_corpus_command(args)
    args.source = args.sources[0]  # one source: the single-source command
    check_args(args)
    summary = track_source(args, args.source, out=args.out, video=args.video, mot=args.mot)
    if summary.ended_early:
        import sys

        print(
            f"warning: {args.source} ended early (truncated or corrupt video): tracked the "
            f"{summary.frames} frame(s) before it",
            file=sys.stderr,
        )
    print(summary.line())
    for path in (args.out, args.mot, args.video):
        if path:
            print(f"wrote {path}")
    return summary.status


def is_multi(args: argparse.Namespace) -> bool:
    """Whether the options ask for multi-target tracking (no --box, --tracker multi or none)."""
    name = (args.tracker or "").partition(":")[0].strip()
    return args.box is None and name in ("", "multi")


def check_args(args: argparse.Namespace) -> None:
    """Validate the options of one ``torchtrack track`` run before any work
    (:class:`ConfigError` naming the option)."""
    import math

    from torchtrack.cli._common import apply_threads, check_scan_workers, device_of
    from torchtrack.errors import ConfigError

    if args.max_frames is not None and args.max_frames < 1:
        raise ConfigError(f"--max-frames must be >= 1, got {args.max_frames}")
    # a corpus run's Backend checks it too, but a single-source run builds no backend
    if args.max_retries < 0:
        raise ConfigError(f"--max-retries must be >= 0, got {args.max_retries}")
    if args.particles and not args.video:
        raise ConfigError("--particles draws into the annotated video: give --video FILE too")
    multi = is_multi(args)
    only_multi = {
        "--scan-every": args.scan_every,
        "--max-targets": args.max_targets,
        "--scan-workers": args.scan_workers,
        "--detections": args.detections,
        "--det-calibration": args.det_calibration,
        "--det-min-score": args.det_min_score,
        "--mot": args.mot,
    }
    if not multi:
        given = [k for k, v in only_multi.items() if v is not None]
        if given:
            why = "with --box" if args.box is not None else f"with --tracker {args.tracker}"
            raise ConfigError(
                f"{', '.join(given)} belong(s) to multi-target tracking (no --box, --tracker "
                f"multi), not to single-target tracking {why}"
            )
    if args.scan_every is not None and args.scan_every < 1:
        raise ConfigError(
            f"--scan-every must be >= 1 (scan every K-th frame), got {args.scan_every}"
        )
    if args.max_targets is not None and args.max_targets < 1:
        raise ConfigError(f"--max-targets must be >= 1, got {args.max_targets}")
    check_scan_workers(args.scan_workers)
    if args.scan_workers and args.detections:
        raise ConfigError("--scan-workers runs our scans: --detections FILE replaces them")
    if args.det_min_score is not None and not math.isfinite(args.det_min_score):
        raise ConfigError(f"--det-min-score must be a finite number, got {args.det_min_score}")
    if (args.det_calibration or args.det_min_score is not None) and not args.detections:
        raise ConfigError("--det-calibration and --det-min-score apply to --detections FILE")
    if args.adapt is not None and multi:
        raise ConfigError("--adapt is an option of single-target trackers (give --box)")
    device_of(args)  # a device this machine has, before any output is opened
    check_track_outputs(args, args.source, args.out, args.video, args.mot)
    apply_threads(args)


def check_track_outputs(args: argparse.Namespace, source: str, out, video, mot=None) -> None:
    """The output paths of one tracked ``source`` (:func:`torchtrack.cli._common` checks),
    before any work: files in existing, writable folders, not folders, the video a .mp4 /
    .avi, no two the same file and none the source itself."""
    import os

    from torchtrack.cli._common import check_distinct, check_output_file, check_spares_inputs

    check_output_file(out, "--out")
    check_output_file(mot, "--mot")
    check_output_file(video, "--video", (".mp4", ".avi"))
    src = source if isinstance(source, str) and os.path.isfile(source) else None
    # the rows stream into PATH.part (_track_io.RowWriter), renamed at the end: -o x.csv.part
    # --mot x.csv wrote the CSV into x.csv and no x.csv.part, saying it wrote both
    staged = {
        f"{option}'s temporary file": f"{os.fspath(path)}.part"
        for option, path in (("--out", out), ("--mot", mot))
        if path
    }
    outputs = {"--out": out, "--mot": mot, "--video": video, **staged}
    check_distinct({"SOURCE": src, **outputs})
    inputs = {"SOURCE": source if isinstance(source, str) else None}
    for option, dest in (("--detections", "detections"), ("--config", "config"),
                         ("--detect", "detect"), ("--det-calibration", "det_calibration")):  # fmt: skip
        inputs[option] = getattr(args, dest, None)
    check_spares_inputs(outputs, inputs)


@dataclass
class TrackSummary:
    """What one tracked source gave: frames tracked, unreadable frames, timings, exit status,
    and for multi-target runs the number of identities."""

    source: str
    frames: int
    unreadable: int
    seconds: float
    tracker_seconds: float
    ended_early: bool
    status: int
    identities: int | None = None
    ground: str | None = None

    @property
    def fps(self) -> float:
        return self.frames / self.tracker_seconds if self.tracker_seconds > 0 else float("inf")

    def line(self) -> str:
        who = "" if self.identities is None else f"; {self.identities} target(s)"
        if self.ground:
            who += f"; {self.ground}"
        return (
            f"tracked {self.frames} frames in {self.seconds:.1f} s: {self.fps:.1f} fps (tracker "
            f"only), {self.frames / max(self.seconds, 1e-9):.1f} fps overall; {self.unreadable} "
            "unreadable frame(s)" + (" (the video ended early)" if self.ended_early else "") + who
        )


def track_source(
    args: argparse.Namespace,
    source: str,
    *,
    out: str | None,
    video: str | None,
    mot: str | None = None,
) -> TrackSummary:
    """Track one ``source`` with the options of ``args`` (the parsed ``torchtrack track``
    namespace, checked by :func:`check_args`; ``args.source``, ``args.out``, ``args.mot`` and
    ``args.video`` are not read), writing the CSV to ``out``, the MOTChallenge file to ``mot``
    and the annotated video to ``video`` (any may be ``None``).

    Raises:
        TorchTrackError: bad options, an unreadable source or a tracker failure.
    """
    from torchtrack.io.video import open_source

    if is_multi(args):
        mt = build_multi(args)
        src = open_source(resolve_source(source), color=args.color)
        return _run_multi(args, mt, src, source, out=out, video=video, mot=mot)
    box = parse_box(args.box) if args.box is not None else None
    tracker = build_tracker(args, auto=box is None)
    src = open_source(resolve_source(source), color=args.color)
    return _run_single(args, tracker, box, src, source, out=out, video=video)


def _with_file(exc, src, i: int):
    """``exc`` with the frame file's name where the source is a folder of images."""
    files = src.files
    if files is None or not 0 <= i < len(files):
        return exc
    return type(exc)(f"{exc} ({files[i]})")


class _Outputs:
    """The end of a tracking loop, for both loops: on Ctrl-C / SIGTERM the rows so far are
    kept (``status`` 130 / 143); on an error nothing is kept (a partial file would look like a
    finished run) and a frame error names the frame's file; otherwise the writers are closed
    once a frame was tracked. The loop sets ``index`` (the frame at hand) and ``tracked``."""

    def __init__(self, src, progress, writers) -> None:
        self.src, self.progress, self.writers = src, progress, writers
        self.index, self.tracked, self.status = -1, 0, 0

    def __enter__(self) -> _Outputs:
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        from torchtrack.errors import ShapeError
        from torchtrack.io.atomic import uninterrupted

        failed = exc_type is not None and not issubclass(exc_type, KeyboardInterrupt)
        with uninterrupted():  # a second Ctrl-C must not leave .part files behind
            self.progress.close()
            keep = self.tracked > 0 and not failed
            for w in (w for w in self.writers if w is not None):
                if keep:
                    w.close()
                else:
                    w.discard()
            self.src.close()
        if exc_type is not None and issubclass(exc_type, KeyboardInterrupt):
            self.status = _interrupted(exc)  # SIGINT, or SIGTERM (torchtrack.cli.Terminated)
            return True
        if isinstance(exc, ShapeError):  # e.g. a frame of another size: name its file
            raise _with_file(exc, self.src, self.index) from None
        return False


def _run_single(args, tracker, box, src, source, *, out, video) -> TrackSummary:
    import time

    from torchtrack.cli._common import device_of
    from torchtrack.cli._track_io import BoxWriter, VideoOut, draw

    device = device_of(args)
    csv = BoxWriter(out) if out else None
    vid = VideoOut(video, src.fps) if video else None
    n_frames, t_track, t0 = 0, 0.0, time.perf_counter()
    last = None
    pending_bad: list[int] = []  # unreadable frames before the first tracked one
    with _Outputs(src, _progress(src, args), (csv, vid)) as run:
        for i, frame in src.items():
            if args.max_frames is not None and i >= args.max_frames:
                break
            run.index = i
            run.progress.update(1)
            if frame is None:
                if csv is not None and last is not None:
                    csv.write_bad(i, last)
                elif last is None:
                    pending_bad.append(i)
                if vid is not None:
                    vid.repeat()  # the video keeps the source's timing
                continue
            t1 = time.perf_counter()
            on = frame.to(device)
            if last is None:
                if box is not None:
                    state = tracker.init(on, _checked_box(box, frame))
                elif getattr(tracker, "auto_init", False):
                    state = tracker.init(on, None)
                else:
                    state = tracker.init(on, detect_box(args.detect, on))
            else:
                state = tracker.update(on)
            state = _on_cpu(state)
            t_track += time.perf_counter() - t1
            if last is None and csv is not None:
                for j in pending_bad:  # frames before the first readable one: no box yet
                    csv.write_state(j, _nan_state(state))
            n_frames += 1
            run.tracked = n_frames
            last = state
            if csv is not None:
                csv.write_state(i, state)
            if vid is not None:
                vid.write(draw(frame, state, tracker if args.particles else None))
    if last is None and run.status == 0:
        raise _no_readable_frame(src)
    return _summary(source, src, n_frames, t0, t_track, run.status)


def _interrupted(exc: BaseException) -> int:
    """The exit status of a run stopped by SIGINT (130) or SIGTERM (143), said on stderr."""
    import sys

    status = getattr(exc, "exit_code", 130)
    what = "interrupted" if status == 130 else "terminated"
    print(f"{what}: keeping the results so far", file=sys.stderr)
    return status


def _no_readable_frame(src) -> Exception:
    """The error of a source none of whose frames could be read, with the first one's reason
    (an image folder of float TIFFs said only 'no readable frame')."""
    from torchtrack.errors import TrackerError

    why = f" ({src.bad_frames[0].reason})" if src.bad_frames else " (it holds no frame)"
    return TrackerError(f"no readable frame in {src.name}: nothing was tracked{why}")


def _summary(
    source, src, n_frames, t0, t_track, status, identities=None, ground=None
) -> TrackSummary:
    import time

    return TrackSummary(
        source=str(source),
        frames=n_frames,
        unreadable=src.n_bad,
        seconds=time.perf_counter() - t0,
        tracker_seconds=t_track,
        ended_early=bool(src.ended_early),
        status=status,
        identities=identities,
        ground=ground,
    )


def _on_cpu(state):
    """``state`` with its tensors on the CPU (writers and drawing read them there)."""
    import dataclasses

    import torch

    if state.box.device.type == "cpu":
        return state
    moved = {
        f.name: getattr(state, f.name).cpu()
        for f in dataclasses.fields(state)
        if isinstance(getattr(state, f.name), torch.Tensor)
    }
    return dataclasses.replace(state, **moved)


def _nan_state(state):
    import dataclasses

    import torch

    return dataclasses.replace(
        state,
        box=torch.full_like(state.box, float("nan")),
        confidence=torch.zeros_like(state.confidence),
        visible=torch.zeros_like(state.visible),
    )


def build_multi(args: argparse.Namespace):
    """The :class:`~torchtrack.track.multi.MultiTargetTracker` of the options (``--detect``,
    ``--config``, ``--tracker multi:key=value``, ``--scan-every``, ``--max-targets``,
    ``--seed``)."""
    import torch

    from torchtrack.errors import ConfigError
    from torchtrack.track.base import parse_tracker_spec
    from torchtrack.track.multi import MultiTargetTracker

    params: dict = {}
    if args.tracker:
        _, params = parse_tracker_spec(args.tracker)
    if "generator" in params:  # was MultiTargetTracker's TypeError 'multiple values'
        raise ConfigError(
            f"--tracker {args.tracker!r}: 'generator' is no key of the multi-target tracker "
            "(--seed seeds its generator)"
        )
    for option, key, value in (
        ("--scan-every", "scan_every", args.scan_every),
        ("--max-targets", "max_targets", args.max_targets),
        ("--detect", "model", args.detect),
        ("--config", "config", args.config),
    ):
        _set_once(params, key, value, option, args.tracker)
    return MultiTargetTracker(generator=torch.Generator().manual_seed(args.seed), **params)


def _set_once(params: dict, key: str, value, option: str, spec: str | None) -> None:
    """``params[key] = value`` (unless ``value`` is ``None``) for the option that sets the
    tracker's ``key``; :class:`ConfigError` when the ``--tracker`` spec sets it too: one of
    the two was dropped without a word (the option for the multi-target tracker, the spec's
    value for the others), or a TypeError for ``config``."""
    from torchtrack.errors import ConfigError

    if value is None:
        return
    if key in params:
        raise ConfigError(
            f"{option} {value} and --tracker {spec!r} ({key}={params[key]}) both set the "
            f"tracker's {key!r}: give it once"
        )
    params[key] = value


def external_detections(args: argparse.Namespace, n_frames: int | None):
    """The ``--detections`` file as a per-frame lookup ``frame -> (boxes, probabilities)``
    (see ``--det-calibration`` / ``--det-min-score`` for the scores), and every box it holds
    ``(K, 4)`` (for :func:`_check_detections_fit`)."""
    import json

    import numpy as np
    import torch

    from torchtrack.errors import ConfigError
    from torchtrack.io.mot import read_mot

    rows = read_mot(args.detections, n_frames=n_frames, kind="det")
    if args.det_min_score is not None:
        rows = rows.select(rows.conf >= args.det_min_score)
    score = torch.from_numpy(rows.conf.astype(np.float64))
    if args.det_calibration:
        from torchtrack.learn import calibrator_from_dict

        try:
            with open(args.det_calibration, encoding="utf-8") as f:
                doc = json.load(f)
            cal = calibrator_from_dict(doc)
        except OSError as exc:
            raise ConfigError(
                f"--det-calibration {args.det_calibration!r} cannot be read: {exc}"
            ) from None
        # ValueError: JSONDecodeError, UnicodeDecodeError, ModelFormatError, and json's own
        # ValueError for an integer of over 4300 digits; RecursionError: arrays nested 1e5 deep
        except (ValueError, RecursionError) as exc:
            raise ConfigError(
                f"--det-calibration {args.det_calibration!r} is not a calibration JSON "
                f"written by `torchtrack calibrate --json` ({exc})"
            ) from None
        from torchtrack.detect.model_checks import LIMITS, platt_slope_ok

        a, cap = getattr(cal, "a_", None), LIMITS.coefficient
        if a is not None and not platt_slope_ok(a):  # the rule of model files
            raise ConfigError(
                f"--det-calibration {args.det_calibration!r}: the Platt slope A = {a:.4g} must "
                f"be in [{-cap:g}, 0): with A >= 0 the probability falls (or stays flat) as the "
                "detection score rises; was it fitted on inverted labels?"
            )
        y = getattr(cal, "y_thresholds_", None)
        if y is not None and len(y) and bool((y == y[0]).all()):  # as a flat Platt, refused
            raise ConfigError(
                f"--det-calibration {args.det_calibration!r}: its isotonic map gives every score "
                f"the probability {float(y[0]):.4g}, so it does not rank the detections; was it "
                "fitted on scores unrelated to the labels?"
            )
        prob = cal.predict_proba(score).to(torch.float64)
    else:
        from torchtrack.track.multi import score_probabilities

        prob = score_probabilities(score)
    boxes = torch.from_numpy(rows.boxes)
    frames = rows.frames
    order = np.argsort(frames, kind="stable")
    uniq, starts = np.unique(frames[order], return_index=True)
    ends = np.append(starts[1:], len(order)) if len(starts) else starts
    table = {
        int(f): (boxes[order[a:b]], prob[order[a:b]])
        for f, a, b in zip(uniq.tolist(), starts.tolist(), ends.tolist(), strict=True)
    }
    empty = (torch.zeros((0, 4), dtype=torch.float64), torch.zeros(0, dtype=torch.float64))
    return (lambda i: table.get(i, empty)), boxes


def _run_multi(args, mt, src, source, *, out, video, mot) -> TrackSummary:
    import collections
    import itertools
    import sys
    import time

    from torchtrack.cli._common import device_of
    from torchtrack.cli._track_io import (
        MotStreamWriter,
        MultiCsvWriter,
        Trails,
        VideoOut,
        draw_multi,
    )
    from torchtrack.track.scan_ahead import ScanAhead, default_scan_batch, default_scan_workers

    device = device_of(args)
    dets, det_boxes = (
        external_detections(args, len(src) or None) if args.detections else (None, None)
    )
    workers = args.scan_workers
    if workers is None:  # scans on a GPU run in this process, next to the filter
        workers = default_scan_workers() if device.type == "cpu" else 0
    csv = MultiCsvWriter(out) if out else None
    motw = MotStreamWriter(mot) if mot else None
    vid = VideoOut(video, src.fps) if video else None
    trails = Trails() if vid is not None else None
    n_frames, t_track, t0 = 0, 0.0, time.perf_counter()
    seen: set[int] = set()
    # the reports pass through the tracker's smoother (gaps filled, boxes smoothed: each
    # frame is written `lag` frames late); the frames wait with them for the video
    smoother = mt.smoother()
    held: collections.deque = collections.deque()

    def emit(i: int, res) -> None:
        frame, parts = held.popleft()
        if res is None:  # an unreadable frame: no rows, the video keeps the source's timing
            if vid is not None:
                vid.repeat()
            return
        seen.update(res.ids.tolist())
        if csv is not None:
            csv.write_targets(i, res)
        if motw is not None:
            motw.write_targets(i, res)
        if vid is not None:
            trails.add(i, res)
            vid.write(draw_multi(frame, res, trails, parts))

    def report(i: int, frame, res) -> None:
        parts = mt.particle_boxes() if (vid is not None and args.particles) else None
        held.append((frame if vid is not None else None, parts))
        dets_i = mt.last_detections if res is not None else None
        for j, r in smoother.push(i, res, offset=mt.camera_offset, detections=dets_i):
            emit(j, r)  # an inactive smoother gives back (i, res)

    def _track_frames(frames) -> None:
        nonlocal n_frames, t_track
        for i, frame, scan in frames:
            run.index = i
            run.progress.update(1)
            if frame is None:
                report(i, None, None)
                continue
            if n_frames == 0 and dets is not None:
                _check_detections_fit(args.detections, det_boxes, frame)
            t1 = time.perf_counter()
            if dets is not None:
                # the detections of the frames the tracker would scan, as track_sequence gives
                # them: the tracker counts its misses so
                res = mt.update(frame.to(device), dets(i) if mt.scans_next() else None)
            else:
                res = mt.update(frame.to(device), scan=scan)
            t_track += time.perf_counter() - t1
            n_frames += 1
            run.tracked = n_frames
            report(i, frame, res)

    n_max = args.max_frames
    items = itertools.takewhile(lambda p: n_max is None or p[0] < n_max, src.items())
    with (
        # without workers the scans run here, on the device, a batch of frames at a time
        ScanAhead(
            mt, workers if dets is None else 0, batch=default_scan_batch(device), device=device
        ) as ahead,
        _Outputs(src, _progress(src, args), (csv, motw, vid)) as run,
    ):
        # With outside detections the tracker does not scan: the frames pass on without one.
        frames = ahead.frames(items) if dets is None else ((i, f, None) for i, f in items)
        try:
            _track_frames(frames)
        except KeyboardInterrupt:  # Ctrl-C / SIGTERM keep the rows so far: the held ones too
            for j, r in smoother.flush():
                emit(j, r)
            raise
        for j, r in smoother.flush():
            emit(j, r)
    status = run.status
    if n_frames == 0 and status == 0:
        raise _no_readable_frame(src)
    if not seen and status == 0:
        what = (
            f"no target was started from --detections {args.detections!r}"
            if getattr(args, "detections", None)
            else f"no {mt.detector.name!r} target was found"
        )
        print(f"{what} in {source} (empty tracks written)", file=sys.stderr)
    t_track += ahead.seconds  # the scans, or the wait for them
    return _summary(
        source,
        src,
        n_frames,
        t0,
        t_track,
        status,
        identities=len(seen),
        ground="; ".join(
            x
            for x in (
                mt.ground_summary(),
                mt.birth_summary(),
                mt.camera_summary(),
                _swap_summary(smoother),
            )
            if x
        )
        or None,
    )


def _swap_summary(smoother) -> str | None:
    """``N identity swap(s) undone ...`` when the smoother's identity repair made any."""
    n = len(smoother.repair.swaps)
    if not n:
        return None
    return f"{n} identity swap(s) undone after close encounters (unswap)"


#: warn when more than this share of the --detections boxes lie wholly outside the frames
OFF_FRAME_SHARE = 0.1


def _check_detections_fit(path: str, boxes, frame) -> None:
    """A warning when more than ``OFF_FRAME_SHARE`` of the ``--detections`` boxes lie wholly
    outside the video's frames: detections of another video, or at another scale."""
    import warnings

    if boxes is None or not len(boxes):
        return
    from torchtrack.boxes import inside_fraction

    fh, fw = (int(v) for v in frame.shape[-2:])
    inside = inside_fraction(boxes, (fh, fw))
    n, mostly = int((inside == 0).sum()), int((inside < 0.5).sum())
    if n > OFF_FRAME_SHARE * len(boxes):
        warnings.warn(
            f"{n} of the {len(boxes)} boxes of --detections {path!r} lie wholly outside the "
            f"{fw}x{fh} frames: detections of another video, or at another scale?",
            UserWarning,
            stacklevel=2,
        )
    elif mostly > OFF_FRAME_SHARE * len(boxes):
        warnings.warn(
            f"{mostly} of the {len(boxes)} boxes of --detections {path!r} "
            f"lie mostly outside the {fw}x{fh} frames (less than half of each inside): "
            "detections of another video, or at another scale?",
            UserWarning,
            stacklevel=2,
        )


def parse_box(text: str):
    """``"x,y,w,h"`` -> ``(4,)`` float64 tensor; :class:`BoxError` for anything else."""
    import math

    import torch

    from torchtrack.errors import BoxError
    from torchtrack.io.text import EMPTY_FIELD, SEPARATORS, text_float

    s = text.strip()
    if EMPTY_FIELD.search(s):  # '10,,20,30,40' was the box 10,20,30,40 (a value skipped)
        raise BoxError(
            f"--box {text!r} has an empty value (a comma first, or two commas with nothing "
            "between): give four numbers x,y,w,h (pixels)"
        )
    parts = [p for p in SEPARATORS.split(s) if p]
    try:  # as the box files read them: '1_0' is no ten
        vals = [text_float(p) for p in parts]
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
    from torchtrack.track.base import (
        create_tracker,
        parse_tracker_spec,
        tracker_info,
        tracker_names,
    )

    name, params = parse_tracker_spec(args.tracker or "detector")
    single = ", ".join(tracker_names())
    if name == "multi":  # is_multi: only with --box
        raise ConfigError(
            "tracker 'multi' finds every target itself and takes no --box: drop --box, or "
            f"give a single-target tracker ({single})"
        )
    if name not in tracker_names():  # the registry's message, with multi (not registered)
        raise ConfigError(
            f"unknown tracker {name!r}; known trackers: multi (the multi-target tracker, the "
            f"default without --box) and, single-target, {single}"
        )
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
        _set_once(params, key, value, opt, args.tracker)
    if "model" in accepted:
        _set_once(params, "model", args.detect, "--detect", args.tracker)
    if info.accepts_generator and "generator" not in params:
        from torchtrack.cli._common import device_of

        params["generator"] = torch.Generator(device=device_of(args)).manual_seed(args.seed)
    tracker = create_tracker(name, **params)
    if args.particles and not hasattr(tracker, "particle_boxes"):  # drew nothing, silently
        raise ConfigError(
            f"--particles draws a particle filter's particles: tracker {name!r} has none (the "
            "particle filters: "
            + ", ".join(
                n for n in tracker_names() if hasattr(tracker_info(n).factory, "particle_boxes")
            )
            + ")"
        )
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
    from torchtrack.errors import ShapeError, TrackerError
    from torchtrack.track.detector_pf import resolve_detector

    det = resolve_detector(model or "pedestrian")
    try:
        boxes, _ = scan(det, frame, threshold=0.5, min_scale=0.5, scale_step=1.15, stride=0.08)
    except ShapeError as exc:  # its 'scan with min_scale <= ...' is no option of this command
        raise ShapeError(
            f"the {det.name!r} detector cannot look for the target on the first frame ({exc}): "
            "give the target's box with --box x,y,w,h"
        ) from None
    if boxes.shape[0] == 0:
        raise TrackerError(
            f"the {det.name!r} detector found nothing on the first frame; give the target's "
            "box with --box x,y,w,h"
        )
    return boxes[0].double()


def _progress(src, args):
    from tqdm import tqdm

    from torchtrack.cli._common import show_progress

    total = len(src) or None
    if args.max_frames is not None:
        total = min(total, args.max_frames) if total else args.max_frames
    return tqdm(total=total, unit="frame", disable=not show_progress(args), leave=False)
