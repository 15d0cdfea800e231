"""Options every subcommand spells the same way.

* ``-o / --out``: the main output (a file, or a folder for ``eval``); ``--output`` is still
  accepted as an old spelling.
* ``--no-progress``: no progress bar; ``-q / --quiet``: no progress bar and no log or summary
  lines on stderr (results and ``wrote ...`` lines still go to stdout).
* ``--threads``: torch threads.
* ``--backend local|ray``, ``--jobs``, ``--address``, ``--max-retries``: where many runs go
  (:mod:`torchtrack.eval.backends`; ``eval`` and corpus ``track``).
"""

from __future__ import annotations

import argparse

__all__ = [
    "add_backend",
    "add_out",
    "add_progress",
    "add_threads",
    "apply_threads",
    "backend_from_args",
    "show_progress",
]


def add_out(p: argparse.ArgumentParser, metavar: str, help: str, required: bool = False) -> None:
    """``-o/--out METAVAR`` (dest ``out``), plus the hidden old spelling ``--output``."""
    p.add_argument("-o", "--out", metavar=metavar, help=help, required=required, dest="out")
    p.add_argument("--output", dest="out", help=argparse.SUPPRESS)


def add_progress(p: argparse.ArgumentParser) -> None:
    """``--no-progress`` and ``-q/--quiet``."""
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "-q", "--quiet", action="store_true", help="no progress bar and no log lines on stderr"
    )


def add_threads(p: argparse.ArgumentParser, default: int = 1) -> None:
    p.add_argument(
        "--threads",
        type=int,
        default=default,
        metavar="N",
        help=f"torch threads (default {default})",
    )


def show_progress(args: argparse.Namespace) -> bool:
    """Whether to draw progress bars (neither ``--no-progress`` nor ``--quiet``)."""
    return not (getattr(args, "no_progress", False) or getattr(args, "quiet", False))


def apply_threads(args: argparse.Namespace) -> None:
    """Set torch's thread count from ``--threads`` (:class:`ConfigError` below 1)."""
    from torchtrack.errors import ConfigError

    n = getattr(args, "threads", None)
    if n is None:
        return
    if n < 1:
        raise ConfigError(f"--threads must be >= 1, got {n}")
    import torch

    torch.set_num_threads(n)


def add_backend(p: argparse.ArgumentParser, unit: str) -> None:
    """``--backend``, ``--jobs``, ``--address``, ``--max-retries`` (one task per ``unit``)."""
    g = p.add_argument_group(
        "where the work runs",
        f"One task per {unit}, in this process (default), in --jobs local processes, or on "
        "Ray (needs the extra: pip install 'torchtrack[ray]'): a new local Ray instance, or "
        "the cluster at --address / $RAY_ADDRESS (see docs/scale.md).",
    )
    g.add_argument(
        "--backend",
        choices=("local", "ray"),
        default="local",
        help="local processes (default) or Ray tasks",
    )
    g.add_argument(
        "--jobs",
        type=int,
        metavar="N",
        help="local: parallel processes (default 1 = in this process); ray: CPUs of the local "
        "Ray instance started without --address (default: all cores)",
    )
    g.add_argument(
        "--address",
        metavar="HOST:PORT",
        help="Ray cluster to run on: the head node's address (`ray start --head` prints it) "
        "or 'auto' (a `ray start` cluster on this machine); default $RAY_ADDRESS, else a new "
        "local instance",
    )
    g.add_argument(
        "--max-retries",
        type=int,
        default=3,
        metavar="N",
        help="times Ray reruns a task whose worker process or node died (default 3)",
    )


def backend_from_args(args: argparse.Namespace, *, num_cpus: float = 1, modules=()):
    """The :class:`~torchtrack.eval.backends.Backend` of :func:`add_backend`'s options
    (:class:`ConfigError` for bad values)."""
    from torchtrack.eval.backends import Backend

    return Backend(
        args.backend,
        jobs=args.jobs,
        address=args.address,
        max_retries=args.max_retries,
        num_cpus=num_cpus,
        modules=tuple(modules),
    )
