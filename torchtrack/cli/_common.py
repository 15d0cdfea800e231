"""Options every subcommand spells the same way.

* ``-o / --out``: the main output (a file, or a folder for ``eval``); ``--output`` is still
  accepted as an old spelling.
* ``--no-progress``: no progress bar; ``-q / --quiet``: no progress bar and no log or summary
  lines on stderr (results and ``wrote ...`` lines still go to stdout).
* ``--threads``: torch threads.
"""

from __future__ import annotations

import argparse

__all__ = ["add_out", "add_progress", "add_threads", "apply_threads", "show_progress"]


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
