"""The ``torchtrack`` command line: ``torchtrack train | calibrate | detect | track | eval | sign``.

Each subcommand lives in its own module exposing ``register(subparsers)``; the module adds its
parser and sets ``func`` (called with the parsed namespace, returns an exit code). Heavy imports
happen inside ``func`` so that ``--help`` stays fast.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import importlib
import os
import re
import signal
import sys

from torchtrack import __version__
from torchtrack.errors import TorchTrackError

# Subcommand modules, in the order --help lists them.
COMMANDS: list[str] = ["eval", "train", "calibrate", "track", "detect", "sign"]


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where SIGINT would raise :class:`KeyboardInterrupt`, so every command
    ends a terminated run exactly like an interrupted one (results so far kept and finished,
    temporary files removed); the exit code is 143 instead of 130."""

    exit_code = 128 + signal.SIGTERM


def _raise_terminated(signum, frame) -> None:
    raise Terminated()


@contextlib.contextmanager
def _sigterm_as_interrupt():
    """Turn SIGTERM into :class:`Terminated` while a command runs (main thread only)."""
    try:
        old = signal.signal(signal.SIGTERM, _raise_terminated)
    except ValueError:  # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _close_progress_bars() -> None:
    """Close open tqdm bars so an error message starts on a line of its own."""
    tqdm_mod = sys.modules.get("tqdm")
    if tqdm_mod is None:
        return
    for bar in list(getattr(tqdm_mod.tqdm, "_instances", ())):
        with contextlib.suppress(Exception):
            bar.close()


@contextlib.contextmanager
def _plain_warnings(command: str):
    """Warnings printed as one line, ``torchtrack COMMAND: warning: ...``, like the errors (no
    source path and code line of the module that warned). Only the printed form changes:
    filters and recorders (``warnings.catch_warnings(record=True)``) are untouched."""
    import warnings

    old = warnings.formatwarning

    def one_line(message, category, filename, lineno, line=None) -> str:
        return f"torchtrack {command}: warning: {message}\n"

    warnings.formatwarning = one_line
    try:
        yield
    finally:
        warnings.formatwarning = old


def reuse_freed_memory() -> bool:
    """Keep the memory a frame's work frees for the next frame's (glibc's ``mallopt``).

    By default glibc hands a block of more than 128 KiB-32 MiB back to the system when it is
    freed, and the next frame's block of that size comes back as fresh pages, each one a page
    fault and zero-filled by the kernel: on a 1440x1080 video the channel tables of every scan
    (~125 MiB a level) made 15-40% of the command's time system time. Here such blocks stay in
    the process's heap (allocated below 1 GiB, the heap trimmed above 1 GiB free) and are
    reused: ``torchtrack track`` on 40 frames of 1440x1080 in one process, 54.6 / 61.2 s ->
    50.4 / 48.2 s (system time 8.5-9.6 s -> 0.7-0.8 s), peak memory +4-7%; with two scan
    workers the three processes hold ~2.16 GB, flat, against 1.4-1.8 GB (+20% at the peak)
    (docs/multi_target.md). Forked scan workers inherit it. Commands only: a library does not
    change its host's allocator.

    Returns:
        True where it was set (Linux with glibc), False elsewhere (nothing changes).
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    m_trim_threshold, m_mmap_threshold = -1, -3  # <malloc.h>
    return bool(mallopt(m_mmap_threshold, 1 << 30)) and bool(mallopt(m_trim_threshold, 1 << 30))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="torchtrack",
        description="Classical tracking-by-detection in PyTorch.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"torchtrack {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"torchtrack.cli.{name}").register(sub)
    return parser


def _out_of_memory(exc: BaseException) -> str | None:
    """What an allocation failure says (numpy's MemoryError, torch's CPU allocator and CUDA
    out-of-memory errors, both RuntimeErrors), or None for any other error."""
    if isinstance(exc, MemoryError):
        return str(exc) or "no detail"
    text = str(exc)
    if isinstance(exc, RuntimeError) and (
        "can't allocate memory" in text or "out of memory" in text.lower()
    ):
        tried = text.find("you tried to allocate")
        return text[tried:].split(".")[0] if tried >= 0 else text.splitlines()[0][:200]
    return None


#: a value of ``--box`` whose first number is negative (a target partly left of or above the
#: frame): argparse reads ``-10,20,30,40`` as an unknown option, not as the box
_NEGATIVE_LIST = re.compile(r"^-(\d|\.\d)[\d.eE+\-_ ,;]*$")


def _joined_negative_boxes(argv: list[str]) -> list[str]:
    """``["--box", "-10,20,30,40"]`` -> ``["--box=-10,20,30,40"]``, so that a box that starts
    off the frame's left or top edge is read as the box (argparse took the value for an option
    and said "expected one argument"); every other argument as it is."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        a = argv[i]
        if a == "--box" and i + 1 < len(argv) and _NEGATIVE_LIST.match(argv[i + 1]):
            out.append(f"--box={argv[i + 1]}")
            i += 2
            continue
        out.append(a)
        i += 1
    return out


def main(argv: list[str] | None = None) -> int:
    # OpenCV reads its log level once, at import: warnings it would print before our own
    # clean error message are noise (errors still show). Set first, before anything a
    # command does could import OpenCV.
    os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")
    parser = build_parser()
    args = parser.parse_args(_joined_negative_boxes(sys.argv[1:] if argv is None else argv))
    if getattr(args, "func", None) is None:
        parser.print_help(sys.stderr)
        return 2
    reuse_freed_memory()
    from torchtrack.cli._common import trust_scope

    try:
        with _sigterm_as_interrupt(), trust_scope(args), _plain_warnings(args.command):
            return int(args.func(args) or 0)
    except TorchTrackError as exc:
        _close_progress_bars()
        print(f"torchtrack {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except (MemoryError, RuntimeError) as exc:
        what = _out_of_memory(exc)
        if what is None:  # not an allocation: a bug, with its traceback
            raise
        # the outputs of the run were removed on the way out, as for any failed run
        _close_progress_bars()
        print(
            f"torchtrack {args.command}: error: out of memory ({what}); smaller frames, fewer "
            "particles or targets, fewer --jobs / --scan-workers, or a machine with more memory",
            file=sys.stderr,
        )
        return 1
    except KeyboardInterrupt as exc:
        _close_progress_bars()
        code = getattr(exc, "exit_code", 130)
        print("terminated" if code != 130 else "interrupted", file=sys.stderr)
        return code


if __name__ == "__main__":
    sys.exit(main())
