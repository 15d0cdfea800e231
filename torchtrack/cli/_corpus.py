"""``torchtrack track`` over many sources: ``--out-dir``, ``--write``, ``--backend``.

The single-source command (``torchtrack track SOURCE --out CSV --video FILE``) does one source
with :func:`torchtrack.cli.track.track_source`; a corpus run (``--out-dir DIR``, needed as soon
as the SOURCE arguments name more than one video) calls that same function once per source
through :func:`torchtrack.eval.corpus.run_corpus`, which names the outputs, writes them
atomically, keeps the manifest and skips what an earlier run finished.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import os
import sys
import tempfile

from torchtrack.eval.output_kind import OutputKind

#: The per-source outputs of a corpus run: the ``--write`` name, the file's ending, and the
#: keyword of :func:`~torchtrack.cli.track.track_source` that receives its path (also the
#: ``dest`` of the single-source option: ``--out``, ``--video``). A new kind is one line.
OUTPUT_KINDS: tuple[OutputKind, ...] = (
    OutputKind("csv", ".csv", "out"),
    OutputKind("mot", ".mot.txt", "mot"),
    OutputKind("video", ".mp4", "video"),
)

#: Options that do not change what a source's outputs hold (left out of the manifest's
#: settings, so a stopped run may be resumed with other values).
_NOT_SETTINGS = frozenset(
    {"sources", "source", "out_dir", "write", "backend", "jobs", "address", "max_retries"}
    | {"no_progress", "quiet", "threads", "func", "command", "trusted_key", "require_signed"}
    | {"scan_workers"}
    | {k.keyword for k in OUTPUT_KINDS}
)

_GLOB_CHARS = frozenset("*?[")


def add_corpus_options(p: argparse.ArgumentParser) -> None:
    """``--out-dir``, ``--write`` and the backend options of a corpus run."""
    from torchtrack.cli._common import add_backend

    g = p.add_argument_group(
        "many sources (a corpus)",
        "Several SOURCE arguments, a folder of videos, a quoted glob ('footage/**/*.mp4') or "
        "@list.txt (one source per line) make a corpus run: it needs --out-dir, writes "
        + ", ".join(f"<name>{k.suffix}" for k in OUTPUT_KINDS)
        + " per source (--write; name = the file's stem, plus parent folders where stems "
        "clash) and manifest.jsonl, and skips sources an earlier run finished.",
    )
    g.add_argument(
        "--out-dir",
        metavar="DIR",
        help="corpus run: write one set of outputs per source into DIR (resumable)",
    )
    g.add_argument(
        "--write",
        metavar="KIND[,KIND]",
        help="outputs of each source in a corpus run: "
        + ", ".join(f"{k.name} (<name>{k.suffix})" for k in OUTPUT_KINDS)
        + "; default csv",
    )
    add_backend(p, "source (corpus runs)")


def wants_corpus(args: argparse.Namespace) -> bool:
    """Whether ``args`` asks for a corpus run (:class:`ConfigError` when it names several
    sources without ``--out-dir``, or corpus options without it)."""
    from torchtrack.errors import ConfigError

    if args.out_dir is not None:
        return True
    specs = args.sources
    many = _names_many(specs[0]) if len(specs) == 1 else f"{len(specs)} sources"
    if many:
        raise ConfigError(
            f"{many} make a corpus run: give --out-dir DIR for the per-source outputs "
            "(--write csv,video picks them)"
        )
    corpus_only = [
        opt
        for opt, given in (
            ("--write", args.write is not None),
            ("--backend ray", args.backend != "local"),
            ("--jobs", args.jobs is not None),
            ("--address", args.address is not None),
        )
        if given
    ]
    if corpus_only:
        raise ConfigError(f"only corpus runs use {', '.join(corpus_only)}: give --out-dir DIR")
    return False


def _names_many(spec: str) -> str | None:
    """What makes ``spec`` many sources (a list file, a folder of videos, a glob), or
    ``None`` (a frame folder is one source)."""
    if spec.startswith("@"):
        return f"the sources listed in {spec[1:]!r}"
    if os.path.isdir(spec):
        from pathlib import Path

        from torchtrack.eval.corpus import _videos_in

        return f"the videos in folder {spec!r}" if _videos_in(Path(spec)) else None
    if not os.path.exists(spec) and _GLOB_CHARS & set(spec):
        return f"the paths matched by {spec!r}"
    return None


def _kinds(text: str | None) -> tuple[OutputKind, ...]:
    from torchtrack.errors import ConfigError

    by_name = {k.name: k for k in OUTPUT_KINDS}
    names = [t.strip() for t in (text or "csv").split(",") if t.strip()]
    bad = [n for n in names if n not in by_name]
    if bad or not names:
        raise ConfigError(
            f"--write takes a comma-separated list of {', '.join(by_name)}, got {text!r}"
        )
    return tuple(by_name[n] for n in dict.fromkeys(names))


def run_corpus_command(args: argparse.Namespace) -> int:
    """``torchtrack track ... --out-dir DIR``: every source, one output set each."""
    from tqdm import tqdm

    from torchtrack.cli._common import backend_from_args, check_output_dir, show_progress
    from torchtrack.cli.track import (
        build_multi,
        build_tracker,
        check_args,
        is_multi,
        parse_box,
        resolve_source,
    )
    from torchtrack.errors import ConfigError
    from torchtrack.eval.corpus import find_sources, run_corpus

    check_output_dir(args.out_dir, "--out-dir")
    given = [f"--{k.keyword}" for k in OUTPUT_KINDS if getattr(args, k.keyword, None)]
    if given:
        raise ConfigError(
            f"with --out-dir the output files are named after the sources: choose them with "
            f"--write (e.g. --write csv,video), not {', '.join(given)}"
        )
    kinds = _kinds(args.write)
    if args.particles and not any(k.keyword == "video" for k in kinds):
        raise ConfigError("--particles draws into the annotated video: add it with --write video")
    if getattr(args, "detections", None):
        raise ConfigError(
            "--detections gives the detections of one source; a corpus run cannot use one "
            "file for every source (run each source with its own --detections)"
        )
    # Check the single-source options once, as they will be used for every source; the
    # output names stand in for each source's files (which go in --out-dir, checked later).
    one = copy.copy(args)
    one.source = args.sources[0]
    for k in kinds:
        setattr(one, k.keyword, os.path.join(tempfile.gettempdir(), "torchtrack-check" + k.suffix))
    check_args(one)
    # the tracker of those options, once: a bad --tracker key or --box failed every source
    # in turn (each reported failed, a manifest left) instead of the run, before any work
    if is_multi(one):
        build_multi(one)
    else:
        if one.box is not None:
            parse_box(one.box)
        build_tracker(one, auto=one.box is None)
    quiet = bool(getattr(args, "quiet", False))

    def log(msg: str) -> None:
        if not quiet:
            tqdm.write(msg, file=sys.stderr)

    specs = [str(resolve_source(s)) for s in args.sources]
    sources = find_sources(specs, log=log)
    worker_args = copy.copy(args)
    worker_args.no_progress = True  # one bar, over the corpus
    worker_args.func = None
    settings = {k: v for k, v in sorted(vars(args).items()) if k not in _NOT_SETTINGS}
    report = run_corpus(
        sources,
        _JobOf(worker_args),
        args.out_dir,
        kinds,
        backend=backend_from_args(args, num_cpus=args.threads),
        settings=settings,
        command=_command_line(args, kinds),
        progress=show_progress(args),
        log=log,
    )
    print(report.line())
    if quiet:  # otherwise each failure was logged as it happened
        for src, err in report.failed.items():
            print(f"failed: {src}: {err}", file=sys.stderr)
    print(f"outputs: {report.out_dir}, manifest: {report.manifest}")
    return 1 if report.failed else 0


class _JobOf:
    """``track_source`` with the run's options, as a picklable job for
    :func:`~torchtrack.eval.corpus.run_corpus`: ``job(source, out=..., video=...)``."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = argparse.Namespace(**vars(args))
        if getattr(self.args, "scan_workers", None) is None:
            # the corpus already runs sources side by side: no scan workers inside a job
            self.args.scan_workers = 0

    def __call__(self, source: str, **outputs: str) -> dict:
        from torchtrack.cli._common import apply_threads
        from torchtrack.cli.track import track_source

        apply_threads(self.args)
        paths: dict[str, str | None] = {k.keyword: None for k in OUTPUT_KINDS}
        paths.update(outputs)
        summary = track_source(self.args, source, **paths)
        if summary.status == 130:  # Ctrl-C inside the source: stop the corpus, keep the rest
            raise KeyboardInterrupt
        return dataclasses.asdict(summary)


def _command_line(args: argparse.Namespace, kinds) -> str:
    """The sources and outputs of the run (the other options are the manifest's settings)."""
    import shlex

    parts = ["torchtrack", "track", *args.sources, "--out-dir", args.out_dir]
    parts += ["--write", ",".join(k.name for k in kinds)]
    return " ".join(shlex.quote(str(p)) for p in parts)
