"""``torchtrack eval``: run trackers over tracking sequences and score them.

Example::

    torchtrack eval --sequences ../shared/data/tracking --trackers mil camshift \\
        --out runs/eval --plots --jobs 2
    torchtrack eval --sequences ../shared/data/tracking --trackers mil camshift \\
        --out runs/eval --backend ray --address 10.0.0.5:6379      # on a Ray cluster
"""

from __future__ import annotations

import argparse


def register(subparsers) -> None:
    from torchtrack.cli._common import add_backend, add_progress

    p = subparsers.add_parser(
        "eval",
        help="evaluate trackers on tracking sequences (OTB / BoBoT / VOT / CSV)",
        description=(
            "Run every tracker on every sequence with the same initialisation (the first "
            "ground-truth box) and write per-sequence and overall JSON, a markdown table and, "
            "with --plots, success / precision plots. A tracker that raises on a sequence is "
            "recorded as failed there; the run goes on. Exit status: 0, or 1 when no run "
            "succeeded."
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--sequences",
        nargs="+",
        metavar="PATH",
        help="sequence folders, folders of sequences (searched 3 levels deep), or videos with a "
        "same-stem .csv",
    )
    p.add_argument(
        "--trackers",
        nargs="+",
        metavar="NAME",
        help="tracker names, optionally with parameters: name:key=value,key=value "
        "(see --list-trackers)",
    )
    p.add_argument("-o", "--out", metavar="DIR", help="output folder")
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
        "--max-frames", type=int, metavar="N", help="use only the first N frames of each sequence"
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
    p.add_argument("--seed", type=int, default=0, help="seed for trackers that take a generator")
    add_backend(p, "(tracker, sequence, seed)")
    add_progress(p)
    p.add_argument("--list-trackers", action="store_true", help="list tracker names and exit")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import importlib

    from torchtrack.cli._common import show_progress
    from torchtrack.errors import ConfigError
    from torchtrack.track.base import available_trackers, tracker_info, tracker_names

    for mod in args.modules:
        try:
            importlib.import_module(mod)
        except ImportError as exc:
            raise ConfigError(f"cannot import tracker module {mod!r}: {exc}") from exc
    if args.list_trackers:
        avail = set(available_trackers())
        for n in tracker_names():
            info = tracker_info(n)
            note = "" if n in avail else f"  [unavailable: needs {info.requirement}]"
            print(f"{n:12s} {info.description}{note}")
        return 0
    missing = [f"--{k}" for k in ("sequences", "trackers", "out") if not getattr(args, k)]
    if missing:
        raise ConfigError(f"torchtrack eval needs {', '.join(missing)}")
    if args.max_frames is not None and args.max_frames < 2:
        raise ConfigError(f"--max-frames must be >= 2, got {args.max_frames}")

    from torchtrack.cli._common import backend_from_args
    from torchtrack.eval.backends import check_backend
    from torchtrack.eval.report import overall_table
    from torchtrack.eval.runner import evaluate
    from torchtrack.io.sequences import find_sequences

    check_backend(backend_from_args(args))  # Ray installed, its address answering: fail fast

    seqs = []
    for path in args.sequences:
        seqs.extend(find_sequences(path, on_mismatch=args.on_mismatch))
    if args.max_frames:
        seqs = [s.head(args.max_frames) for s in seqs]
    command = _command_line(args)
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
