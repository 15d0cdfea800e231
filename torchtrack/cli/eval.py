"""``torchtrack eval``: run trackers over tracking sequences and score them, or score
multi-target tracking results (MOTChallenge files) with HOTA / MOTA / IDF1.

Examples::

    torchtrack eval --sequences ../shared/data/tracking --trackers mil camshift \\
        --out runs/eval --plots --jobs 2
    torchtrack eval --sequences ../shared/data/tracking --trackers mil camshift \\
        --out runs/eval --backend ray --address 10.0.0.5:6379      # on a Ray cluster
    torchtrack eval --mot ../shared/data/mot/TUD-Stadtmitte --results tud.txt
    torchtrack eval --mot ../shared/data/videos/pets2009_s2l1_vtest/vtest.avi \\
        --gt ../shared/data/mot/PETS09-S2L1/gt/gt.txt --results pets.txt -o runs/mot
"""

from __future__ import annotations

import argparse

from torchtrack.cli._common import integer
from torchtrack.io.atomic import path_key


def register(subparsers) -> None:
    from torchtrack.cli._common import (
        add_backend,
        add_device,
        add_progress,
        add_trust,
        seed_value,
    )

    p = subparsers.add_parser(
        "eval",
        help="evaluate trackers on tracking sequences (OTB / BoBoT / VOT / CSV), or score "
        "multi-target results on MOTChallenge sequences (--mot)",
        description=(
            "Single target (--sequences, --trackers): run every tracker on every sequence with "
            "the same initialisation (the first ground-truth box) and write per-sequence and "
            "overall JSON, a markdown table and, with --plots, success / precision plots. A "
            "tracker that raises on a sequence is recorded as failed there; the run goes on. "
            "Exit status: 0, or 1 when no run succeeded.\n\n"
            "Multi-target (--mot, --results): score MOTChallenge results files with TrackEval's "
            "HOTA, CLEAR (MOTA, MOTP, ID switches, FP, FN, fragmentations) and Identity (IDF1) "
            "metrics, MOT15 conventions (GT rows with conf 0 ignored). Prints a table; with "
            "-o/--out also writes results.json and results.md."
        ),
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--sequences",
        nargs="+",
        action="extend",
        metavar="PATH",
        help="sequence folders, folders of sequences (searched 3 levels deep), or videos with a "
        "same-stem .csv",
    )
    p.add_argument(
        "--trackers",
        nargs="+",
        action="extend",
        metavar="NAME",
        help="tracker names, optionally with parameters: name:key=value,key=value "
        "(see --list-trackers)",
    )
    mot = p.add_argument_group("multi-target (MOTChallenge) scoring")
    mot.add_argument(
        "--mot",
        nargs="+",
        action="extend",
        metavar="SEQ",
        help="MOTChallenge sequence folders (seqinfo.ini, gt/gt.txt, img1/), folders holding "
        "them (e.g. MOT15/train), or videos and folders of frames whose ground truth --gt "
        "gives",
    )
    mot.add_argument(
        "--results",
        nargs="+",
        action="extend",
        metavar="FILE_OR_DIR",
        help="one per tracker: a MOT results file (one sequence) or a folder with "
        "<sequence name>.txt per sequence",
    )
    mot.add_argument(
        "--public-detections",
        action="store_true",
        help="with --mot and --trackers multi...: the tracker takes each sequence's "
        "det/det.txt instead of scanning (scores relative to the file's best)",
    )
    mot.add_argument(
        "--gt",
        nargs="+",
        action="extend",
        metavar="FILE",
        default=[],
        help="ground-truth file of each video or folder of frames in --mot, in order",
    )
    mot.add_argument(
        "--gt-scale",
        metavar="S",
        default="auto",
        help="multiply the ground-truth boxes by S (e.g. 0.625: PETS09-S2L1's 768x576 GT on the "
        "480x360 video); default 'auto': for a video, its width over the imWidth of the "
        "seqinfo.ini beside the GT, else 1",
    )
    from torchtrack.cli._common import add_out

    add_out(p, "DIR", "output folder (required with --sequences; optional with --mot)")
    p.add_argument("--plots", action="store_true", help="write success / precision PNG plots")
    p.add_argument(
        "--reinit",
        action="store_true",
        help="add a re-initialising pass (Bachoo et al.: re-init from ground truth when the "
        "centre is >100 px off) for track length / re-inits per 100 frames",
    )
    p.add_argument(
        "--invisible",
        choices=("box", "miss"),
        default="box",
        help="how a frame where the target is present but the tracker says not visible is "
        "scored: its box as is (default, OTB protocol) or as a miss",
    )
    p.add_argument(
        "--max-frames",
        type=integer,
        metavar="N",
        help="use only the first N frames of each sequence",
    )
    p.add_argument(
        "--on-mismatch",
        choices=("error", "truncate"),
        default="error",
        help="ground truth with more/fewer rows than frames: fail (default) or keep the common "
        "prefix",
    )
    p.add_argument(
        "--import",
        dest="modules",
        action="append",
        default=[],
        metavar="MODULE",
        help="import a Python module that registers your own trackers (register_tracker); "
        "repeatable; also imported by --jobs workers",
    )
    p.add_argument(
        "--seed", type=seed_value, default=0, help="seed for trackers that take a generator"
    )
    add_backend(p, "(tracker, sequence, seed)")
    add_device(p)
    add_progress(p)
    add_trust(p)
    p.add_argument("--list-trackers", action="store_true", help="list tracker names and exit")
    p.set_defaults(func=run)


_EPILOG = """\
examples:
  torchtrack eval --sequences ../shared/data/tracking --trackers mil camshift --out runs/eval
  torchtrack eval --mot ../shared/data/mot/TUD-Stadtmitte --results tud.txt
  torchtrack eval --mot MOT15/train --results runs/mine runs/other -o runs/mot
      two trackers' result folders (<sequence name>.txt each) on every MOT15 training sequence
  torchtrack eval --mot ../shared/data/videos/pets2009_s2l1_vtest/vtest.avi \\
      --gt ../shared/data/mot/PETS09-S2L1/gt/gt.txt --results pets.txt
      a video and its MOT ground truth; the GT scale (x0.625) comes from its seqinfo.ini

MOT results files: frame,id,x,y,w,h,conf[,...] per line, frames and pixels numbered from 1, in
the video's pixels (`torchtrack track --mot` writes them). A file with no rows scores as an
empty tracker. Malformed rows, rows beyond the sequence's frames and results that do not match
the sequences' names are errors naming the file and line.
"""


def run(args: argparse.Namespace) -> int:
    import importlib

    from torchtrack.cli._common import show_progress
    from torchtrack.errors import ConfigError
    from torchtrack.track.base import available_trackers, tracker_info, tracker_names

    for mod in args.modules:
        # '' and '.rel' were importlib's ValueError / TypeError tracebacks
        if not all(part.isidentifier() for part in mod.split(".")):
            raise ConfigError(
                f"--import {mod!r} is not a module name (dotted Python names, e.g. mypkg.trackers)"
            )
        try:
            importlib.import_module(mod)
        except (ImportError, SyntaxError) as exc:  # SyntaxError: says its file and line
            raise ConfigError(f"cannot import tracker module {mod!r}: {exc}") from exc
    if args.list_trackers:
        avail = set(available_trackers())
        for n in tracker_names():
            info = tracker_info(n)
            note = "" if n in avail else f"  [unavailable: needs {info.requirement}]"
            print(f"{n:12s} {info.description}{note}")
        return 0
    if args.mot or args.results:
        return run_mot(args)
    if args.gt or args.gt_scale != "auto":
        raise ConfigError("--gt and --gt-scale go with --mot")
    missing = [f"--{k}" for k in ("sequences", "trackers", "out") if not getattr(args, k)]
    if missing:
        raise ConfigError(f"torchtrack eval needs {', '.join(missing)}")
    if args.max_frames is not None and args.max_frames < 2:
        raise ConfigError(f"--max-frames must be >= 2, got {args.max_frames}")
    if any(t.partition(":")[0].strip() == "multi" for t in args.trackers):
        raise ConfigError(
            "tracker 'multi' (the multi-target tracker) is scored on MOT sequences: "
            "torchtrack eval --mot SEQ ... --trackers multi -o DIR; --sequences takes "
            "single-target trackers"
        )
    from torchtrack.cli._common import (
        backend_from_args,
        check_output_dir,
        check_spares_inputs,
        device_of,
        removed_if_left_empty,
    )
    from torchtrack.eval.backends import check_backend

    device = device_of(args)
    check_output_dir(args.out, "--out")
    check_spares_inputs({"--out": args.out}, {"--sequences": args.sequences})
    from torchtrack.eval.report import overall_table
    from torchtrack.eval.runner import evaluate
    from torchtrack.io.sequences import find_sequences

    check_backend(backend_from_args(args))  # Ray installed, its address answering: fail fast

    seqs = []
    given: dict[str, str] = {}  # a ground-truth file -> the --sequences path that found it
    for path in args.sequences:
        for s in find_sequences(path, on_mismatch=args.on_mismatch):
            # one sequence twice (a path repeated, or a folder and a sequence inside it):
            # scored twice, it would weigh double in every overall number
            k = path_key(s.gt_path)
            if k in given:
                raise ConfigError(
                    f"--sequences gives sequence {s.name!r} ({s.gt_path}) twice: through "
                    f"{given[k]!r} and {path!r}; each sequence is scored once"
                )
            given[k] = path
            seqs.append(s)
    if args.max_frames:
        seqs = [s.head(args.max_frames) for s in seqs]
    command = _command_line(args)
    with removed_if_left_empty(args.out):  # a run stopped before any result leaves no folder
        summary = evaluate(
            seqs,
            list(args.trackers),
            args.out,
            plots=args.plots,
            jobs=args.jobs,
            backend=args.backend,
            address=args.address,
            max_retries=args.max_retries,
            reinit=args.reinit,
            invisible=args.invisible,
            seed=args.seed,
            progress=show_progress(args),
            command=command,
            modules=args.modules,
            device=str(device),
        )
    print(overall_table(summary))
    print(f"results: {args.out}/results.json, {args.out}/results.md")
    n_ok = sum(
        1
        for per in summary.get("per_sequence", {}).values()
        for r in per.values()
        if not r["error"]
    )
    return 0 if n_ok else 1


def load_mot_sequences(paths: list[str], gts: list[str], gt_scale: str = "auto") -> list:
    """The sequences of ``--mot`` / ``--gt`` / ``--gt-scale``: MOTChallenge folders (or folders
    holding them) and videos, each video taking the next ``--gt`` file.

    Raises:
        ConfigError: a bad scale, ``--gt`` files that do not pair with the videos, a folder
            without MOTChallenge sequences.
    """
    import math
    from pathlib import Path

    from torchtrack.errors import ConfigError
    from torchtrack.io.mot import (
        SCALE_RANGE,
        find_mot_sequences,
        is_frame_folder,
        is_mot_folder,
        load_mot_sequence,
    )
    from torchtrack.io.text import text_float
    from torchtrack.io.video import VIDEO_EXTENSIONS

    scale = None
    if gt_scale != "auto":
        try:
            scale = text_float(gt_scale)  # float() reads 0_625 as 625, a scale in range
        except ValueError:
            scale = math.nan
        lo, hi = SCALE_RANGE
        if not (math.isfinite(scale) and lo <= scale <= hi):
            raise ConfigError(
                f"--gt-scale must be 'auto' or a number in [{lo:g}, {hi:g}], got {gt_scale!r}"
            )
    # the sources --gt pairs with: videos, and folders of frames (what `torchtrack track`
    # reads; a MOTChallenge folder carries its own gt/gt.txt)
    videos = [
        p
        for p in paths
        if Path(p).suffix.lower() in VIDEO_EXTENSIONS or (gts and is_frame_folder(p))
    ]
    if len(gts) != len(videos):
        raise ConfigError(
            f"--gt gives {len(gts)} file(s) for {len(videos)} video(s) or frame folder(s) in "
            "--mot: one ground-truth file per video or folder of frames, in order "
            "(MOTChallenge folders carry their own gt/gt.txt)"
        )
    gt_of = dict(zip(videos, gts, strict=True))
    seqs = []
    for p in paths:
        if p in gt_of:
            seqs.append(load_mot_sequence(p, gt=gt_of[p], scale=scale))
            continue
        found = find_mot_sequences(p) if Path(p).is_dir() else []
        if Path(p).is_dir() and not found:
            hint = ""
            if is_frame_folder(p):  # the frames `track` read: the sequence is the folder above
                parent = Path(p).parent
                hint = (
                    f"; it is a folder of frames: give its ground truth with --gt, or the "
                    f"MOTChallenge folder {parent}"
                    if is_mot_folder(parent)
                    else "; it is a folder of frames: give its ground truth with --gt"
                )
            raise ConfigError(
                f"{p} holds no MOTChallenge sequence (a folder with gt/gt.txt and seqinfo.ini or "
                f"img1/, or a folder of such folders){hint}"
            )
        for d in found or [p]:
            seqs.append(load_mot_sequence(d, scale=scale))
    import sys

    for seq in seqs:
        # the scoring's rule (TrackEval's): a row is ignored when its conf, truncated to an
        # integer, is 0, so conf 0.5 is ignored too (the warning below tested conf != 0)
        conf = seq.gt.conf
        fractional = int(((conf > 0) & (conf < 1)).sum())
        if fractional:
            print(
                f"warning: {fractional} ground-truth row(s) of {seq.name} ({seq.gt_path}) have "
                "a conf in (0, 1): ground truth's conf is a 0/1 flag, truncated to an integer, "
                "so they are ignored",
                file=sys.stderr,
            )
        if len(seq.gt) == 0 or not (conf.astype(int) != 0).any():
            print(
                f"warning: the ground truth of {seq.name} has no scored row (empty, or every "
                "row marked conf 0): every reported box counts as a false positive",
                file=sys.stderr,
            )
    return seqs


def _single_target_options(args: argparse.Namespace) -> list[tuple[str, bool]]:
    """The options only a ``--sequences`` run reads, each with whether it was given: ``--mot``
    scores (or tracks, one sequence after another in this process) without them, and took
    them silently."""
    return [
        ("--invisible", args.invisible != "box"),
        ("--on-mismatch", args.on_mismatch != "error"),
        ("--backend", args.backend != "local"),
        ("--jobs", args.jobs is not None),
        ("--address", args.address is not None),
        ("--max-retries", args.max_retries != 3),
    ]


def run_mot(args: argparse.Namespace) -> int:
    """``torchtrack eval --mot SEQ ... --results FILE_OR_DIR ...``: score MOT results files."""
    from torchtrack.cli._common import check_output_dir, check_spares_inputs
    from torchtrack.errors import ConfigError

    check_output_dir(args.out, "--out")  # before any work, on both MOT paths
    check_spares_inputs(
        {"--out": args.out},
        {"--mot": args.mot or [], "--results": args.results or [], "--gt": args.gt or []},
    )

    if args.mot and args.trackers and not args.results:
        return run_mot_trackers(args)
    if args.public_detections:
        raise ConfigError("--public-detections goes with --mot SEQ ... --trackers multi")
    if not args.mot or not args.results:
        raise ConfigError(
            "MOT scoring needs --mot SEQ ... and either --results FILE_OR_DIR ... (score "
            "files) or --trackers multi... (run the multi-target tracker, then score)"
        )
    clash = [
        flag
        for flag, used in (
            ("--sequences", args.sequences),
            ("--trackers", args.trackers),
            ("--plots", args.plots),
            ("--reinit", args.reinit),
            ("--max-frames", args.max_frames),
            ("--device", args.device not in (None, "cpu")),
            ("--seed", args.seed != 0),
            *_single_target_options(args),
        )
        if used
    ]
    if clash:
        tracking = {"--trackers", "--max-frames", "--device", "--seed"} & set(clash)
        raise ConfigError(
            f"{', '.join(clash)} do(es) not apply to scoring existing results files (--mot "
            "with --results)"
            + (
                "; to run the multi-target tracker and score it, give --mot and --trackers "
                "multi without --results"
                if tracking
                else ""
            )
        )
    seen: dict[str, str] = {}  # one results file or folder given twice would be two trackers
    for r in args.results:
        k = path_key(r)
        if k in seen:
            raise ConfigError(
                f"--results gives {seen[k]!r} twice (as {r!r}): each results file or folder "
                "is one tracker, scored once"
            )
        seen[k] = r
    from torchtrack.cli._common import removed_if_left_empty
    from torchtrack.eval.mot import evaluate_mot, mot_table

    seqs = load_mot_sequences(args.mot, args.gt, args.gt_scale)
    with removed_if_left_empty(args.out):
        summary = evaluate_mot(seqs, args.results, args.out, command=_mot_command_line(args))
    print(mot_table(summary))
    if args.out:
        print(f"results: {args.out}/results.json, {args.out}/results.md")
    return 0


def run_mot_trackers(args: argparse.Namespace) -> int:
    """``torchtrack eval --mot SEQ ... --trackers multi[:key=value,...] ... -o DIR``: run the
    multi-target tracker on every sequence (``DIR/<tracker>/<sequence>.txt``), then score."""
    import dataclasses
    import re
    from pathlib import Path

    import torch

    from torchtrack.cli._common import device_of
    from torchtrack.errors import ConfigError
    from torchtrack.eval.mot import evaluate_mot, mot_table
    from torchtrack.io.mot import write_mot
    from torchtrack.track.base import parse_tracker_spec
    from torchtrack.track.multi import MultiTargetTracker, score_probabilities, track_sequence
    from torchtrack.track.scan_ahead import default_scan_workers

    device = device_of(args)
    if not args.out:
        raise ConfigError("running trackers with --mot needs -o/--out DIR for their results")
    clash = [f for f, used in (("--sequences", args.sequences), ("--plots", args.plots),
                               ("--reinit", args.reinit), *_single_target_options(args))
             if used]  # fmt: skip
    if clash:
        raise ConfigError(f"{', '.join(clash)} do(es) not apply to --mot")
    specs = []
    for spec in args.trackers:
        name, params = parse_tracker_spec(spec)
        if name != "multi":
            raise ConfigError(
                f"--mot runs the multi-target tracker ('multi' or 'multi:key=value,...'), got "
                f"{spec!r}"
            )
        specs.append((spec, params))
    # one folder name each: a path in the spec (multi:model=models/m.safetensors) made nested
    # folders under --out (and with '..' ones outside it), left behind by a failed run
    labels = [
        re.sub(r"[/\\]", "_", spec.replace(":", "_").replace(",", "_").replace("=", "-"))
        for spec, _ in specs
    ]
    if len(set(labels)) != len(labels):
        raise ConfigError(f"--trackers given twice: {args.trackers}")
    seqs = load_mot_sequences(args.mot, args.gt, args.gt_scale)
    full = {s.name: s for s in seqs}
    n = args.max_frames
    if n is not None:
        if n < 2:
            raise ConfigError(f"--max-frames must be >= 2, got {n}")
        seqs = [
            dataclasses.replace(s, n_frames=min(n, s.n_frames), gt=s.gt.select(s.gt.frames < n))
            for s in seqs
        ]
    # everything that can be wrong is found before the first sequence is tracked and written:
    # every tracker's settings, every sequence's detections file
    from torchtrack.track.config import MultiTrackerConfig, resolve_tracker_config

    for spec, params in specs:
        p = dict(params)
        resolve_tracker_config(MultiTrackerConfig, p.pop("config", None), p, where=spec)
    public = {}
    if args.public_detections:
        for seq in seqs:
            d = full[seq.name].detections()
            d = d.select(d.frames < seq.n_frames)
            public[seq.name] = dataclasses.replace(d, conf=score_probabilities(
                torch.from_numpy(d.conf)).numpy())  # fmt: skip
    out = Path(args.out)
    # what this run makes, removed again if it fails: a half set of tracks looks finished.
    # The tracks are written once every sequence is tracked: a run stopped on its second
    # sequence deleted the first one's file that an earlier run had written
    made = [d for d in (out, *(out / label for label in labels)) if not d.exists()]
    tracked: list[tuple[Path, object]] = []
    written: list[Path] = []  # the files this run created (not those it replaced)
    try:
        for (spec, params), label in zip(specs, labels, strict=True):
            for seq in seqs:
                dets = public.get(seq.name)
                mt = MultiTargetTracker(
                    generator=torch.Generator().manual_seed(args.seed), **params
                )
                with seq.open() as src:
                    rows = track_sequence(
                        mt,
                        src,
                        dets,
                        max_frames=seq.n_frames,
                        # a GPU scans in this process, next to the filter
                        scan_workers=default_scan_workers() if device.type == "cpu" else 0,
                        device=device,
                    )
                tracked.append((out / label / f"{seq.name}.txt", rows))
                print(f"{spec} on {seq.name}: {len(rows)} boxes, {mt.stats['confirmed']} targets")
        for path, rows in tracked:
            new_file = not path.exists()
            write_mot(path, rows)
            written += [path] if new_file else []
        summary = evaluate_mot(
            seqs,
            [out / label for label in labels],
            args.out,
            labels=labels,
            command=_mot_command_line(args),
        )
    except BaseException:
        import contextlib

        for f in written:
            f.unlink(missing_ok=True)
        for d in reversed(made):  # the label folders first, then the output folder
            with contextlib.suppress(OSError):
                d.rmdir()
        raise
    print(mot_table(summary))
    print(f"results: {args.out}/results.json, {args.out}/results.md")
    return 0


def _mot_command_line(args: argparse.Namespace) -> str:
    import shlex

    parts = ["torchtrack", "eval", "--mot", *args.mot]
    if args.gt:
        parts += ["--gt", *args.gt]
    if args.gt_scale != "auto":
        parts += ["--gt-scale", args.gt_scale]
    if args.results:
        parts += ["--results", *args.results]
    if args.trackers:
        parts += ["--trackers", *args.trackers]
    if args.public_detections:
        parts.append("--public-detections")
    if args.max_frames:
        parts += ["--max-frames", str(args.max_frames)]
    if args.seed:
        parts += ["--seed", str(args.seed)]
    if args.out:
        parts += ["--out", args.out]
    return " ".join(shlex.quote(str(p)) for p in parts)


def _command_line(args: argparse.Namespace) -> str:
    """The equivalent command line, recorded in the results."""
    import shlex

    parts = ["torchtrack", "eval", "--sequences", *args.sequences, "--trackers", *args.trackers]
    parts += ["--out", args.out]
    if args.plots:
        parts.append("--plots")
    if args.backend != "local":
        parts += ["--backend", args.backend]
    if args.jobs is not None:
        parts += ["--jobs", str(args.jobs)]
    if args.address:
        parts += ["--address", args.address]
    if args.max_retries != 3:
        parts += ["--max-retries", str(args.max_retries)]
    if args.reinit:
        parts.append("--reinit")
    if args.invisible != "box":
        parts += ["--invisible", args.invisible]
    if args.max_frames:
        parts += ["--max-frames", str(args.max_frames)]
    if args.on_mismatch != "error":
        parts += ["--on-mismatch", args.on_mismatch]
    for m in args.modules:
        parts += ["--import", m]
    if args.seed:
        parts += ["--seed", str(args.seed)]
    return " ".join(shlex.quote(str(p)) for p in parts)
