"""Options every subcommand spells the same way.

* ``-o / --out``: the main output (a file, or a folder for ``eval``); ``--output`` is still
  accepted as an old spelling.
* ``--no-progress``: no progress bar; ``-q / --quiet``: no progress bar and no log or summary
  lines on stderr (results and ``wrote ...`` lines still go to stdout).
* ``--threads``: torch threads.
* ``--backend local|ray``, ``--jobs``, ``--address``, ``--max-retries``: where many runs go
  (:mod:`torchtrack.eval.backends`; ``eval`` and corpus ``track``).
* ``--trusted-key`` / ``--require-signed``: which model files to trust (subcommands that load
  models); :func:`trust_scope` applies them.

Output paths are checked by :func:`check_output_file` / :func:`check_output_dir` (and
:func:`check_distinct`) in every subcommand's argument check, before any work, so a bad path
fails at once and never after a long run.
"""

from __future__ import annotations

import argparse

__all__ = [
    "add_backend",
    "add_out",
    "add_progress",
    "add_threads",
    "add_trust",
    "apply_threads",
    "backend_from_args",
    "check_distinct",
    "check_output_dir",
    "check_output_file",
    "check_scan_workers",
    "check_spares_inputs",
    "integer",
    "number",
    "seed_value",
    "show_progress",
    "trust_scope",
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


def integer(text: str) -> int:
    """An integer option's value (argparse ``type``), read as the data files read numbers
    (:func:`torchtrack.io.text.text_int`): ``--max-frames 1_0`` was 10 frames."""
    from torchtrack.io.text import text_int

    try:
        return text_int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None


def number(text: str) -> float:
    """A real-valued option's value (argparse ``type``): ``float()`` less its underscores
    (:func:`torchtrack.io.text.text_float`): ``--det-min-score 0_5`` was 5."""
    from torchtrack.io.text import text_float

    try:
        return text_float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None


def seed_value(text: str) -> int:
    """``--seed``: an integer in ``[0, 2^63 - 1]`` (what a torch generator takes); argparse
    reports anything else as a usage error naming the option."""
    n = integer(text)
    if not 0 <= n < 2**63:
        raise argparse.ArgumentTypeError(f"must be in [0, 2^63 - 1], got {text}")
    return n


def add_threads(p: argparse.ArgumentParser, default: int = 1) -> None:
    p.add_argument(
        "--threads",
        type=integer,
        default=default,
        metavar="N",
        help=f"torch threads (default {default})",
    )


def add_device(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--device",
        default="cpu",
        metavar="DEV",
        help="where the trackers run: cpu (default), cuda or cuda:N (an NVIDIA GPU; frames are "
        "copied there, outputs come back)",
    )


def device_of(args: argparse.Namespace):
    """The checked ``--device`` as a :class:`torch.device` (:class:`ConfigError` for a device
    this machine does not have)."""
    from torchtrack.device import check_device

    return check_device(getattr(args, "device", None))


def show_progress(args: argparse.Namespace) -> bool:
    """Whether to draw progress bars (neither ``--no-progress`` nor ``--quiet``)."""
    return not (getattr(args, "no_progress", False) or getattr(args, "quiet", False))


def apply_threads(args: argparse.Namespace) -> None:
    """Set torch's thread count from ``--threads`` (:class:`ConfigError` below 1 or above 4
    per CPU core, as ``--scan-workers``)."""
    from torchtrack.errors import ConfigError

    n = getattr(args, "threads", None)
    if n is None:
        return
    if n < 1:
        raise ConfigError(f"--threads must be >= 1, got {n}")
    import os

    cores = os.cpu_count() or 1
    if n > 4 * cores:
        raise ConfigError(
            f"--threads {n} is more than 4 per CPU core ({cores} here): threads beyond the "
            "cores only take turns"
        )
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
        type=integer,
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
        type=integer,
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


def check_scan_workers(n: int | None) -> None:
    """``--scan-workers``: 0 (scan in this process) up to 4 per CPU core (each worker holds a
    model and a queue of frames; past the cores they only take turns). ``None``: the default.

    Raises:
        ConfigError: naming the option.
    """
    import os

    from torchtrack.errors import ConfigError

    if n is None:
        return
    if n < 0:
        raise ConfigError(f"--scan-workers must be >= 0 (0: scan in this process), got {n}")
    cores = os.cpu_count() or 1
    if n > 4 * cores:
        raise ConfigError(
            f"--scan-workers {n} is more than 4 per CPU core ({cores} here): workers beyond the "
            "cores only take turns (the default uses the cores there are)"
        )


# ------------------------------------------------------------------------------ output paths
def check_output_file(path: str | None, option: str, suffixes: tuple[str, ...] = ()):
    """Check an output file path before any work: not empty, not an existing folder nor an
    existing device, pipe or socket (the output would replace it), its folder exists and a
    file can be created there (tried), and (given ``suffixes``) one of those extensions.

    Returns:
        the path as a :class:`~pathlib.Path` (``None`` for ``None``).

    Raises:
        ConfigError: naming ``option`` and what is wrong.
    """
    import os
    from pathlib import Path

    from torchtrack.errors import ConfigError

    if path is None:
        return None
    if not str(path).strip():
        raise ConfigError(f"{option} is an empty path")
    p = Path(path)
    if p.is_dir():
        raise ConfigError(f"{option} {str(p)!r} is an existing folder; give a file name")
    text = os.fspath(path)
    if text.endswith(os.sep) or (os.altsep and text.endswith(os.altsep)):
        # Path() drops the slash: 'runs/' (a folder not made yet) was written as a file 'runs'
        raise ConfigError(f"{option} {text!r} ends in {text[-1]!r}, a folder; give a file name")
    if suffixes and p.suffix.lower() not in suffixes:
        raise ConfigError(
            f"{option} {str(p)!r} must end in {' or '.join(suffixes)}, got {p.suffix or 'none'}"
        )
    from torchtrack.io.atomic import check_regular_destination

    check_regular_destination(p, f"{option} {str(p)!r}")
    _check_parent(p, option)
    if p.exists() and not os.access(p, os.W_OK):
        raise ConfigError(f"{option} {str(p)!r} exists and is not writable")
    return p


def check_output_dir(path: str | None, option: str):
    """Check an output folder path before any work: not an existing file; a file must be
    creatable (tried) in an existing folder, or in a new one's parent, which must exist (the
    folder itself is made by the run).

    Raises:
        ConfigError: naming ``option`` and what is wrong.
    """
    from pathlib import Path

    from torchtrack.errors import ConfigError

    if path is None:
        return None
    if not str(path).strip():
        raise ConfigError(f"{option} is an empty path")
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ConfigError(f"{option} {str(p)!r} is an existing file; give a folder")
    if p.is_dir():
        why = _cannot_create_in(p)
        if why:
            raise ConfigError(f"{option} folder {str(p)!r} is not writable ({why})")
        return p
    _check_parent(p, option)
    return p


def removed_if_left_empty(path: str | None):
    """A context for a run that makes the output folder ``path``: when the run fails (an
    error, Ctrl-C) and the folder, absent before, is still empty, it is removed, so that a
    failed run leaves nothing behind (a folder that existed, or that holds results, stays)."""
    import contextlib
    from pathlib import Path

    @contextlib.contextmanager
    def scope():
        p = None if path is None else Path(path)
        new = p is not None and not p.exists()
        try:
            yield
        except BaseException:
            if new and p.is_dir() and not any(p.iterdir()):
                with contextlib.suppress(OSError):
                    p.rmdir()
            raise

    return scope()


def _cannot_create_in(folder) -> str | None:
    """Why no file can be created in ``folder`` (``None`` when one can): a uniquely named file
    is made there and removed. Permission bits alone do not tell (root passes ``os.access``
    on ``/proc``; a read-only mount)."""
    import os
    import tempfile

    try:
        fd, probe = tempfile.mkstemp(prefix=".write-test.", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        return exc.strerror or str(exc)
    return None


def _check_parent(p, option: str) -> None:
    from torchtrack.errors import ConfigError

    parent = p.parent if str(p.parent) else type(p)(".")
    if not parent.exists():
        raise ConfigError(f"{option} {str(p)!r}: folder {str(parent)!r} does not exist")
    if not parent.is_dir():
        raise ConfigError(f"{option} {str(p)!r}: {str(parent)!r} is not a folder")
    why = _cannot_create_in(parent)
    if why:
        raise ConfigError(f"{option} {str(p)!r}: folder {str(parent)!r} is not writable ({why})")


def check_distinct(paths: dict[str, str | None]) -> None:
    """Different options must not name the same output (or an input) file: ``{option: path}``.

    Raises:
        ConfigError: two options name one file.
    """
    from torchtrack.errors import ConfigError
    from torchtrack.io.atomic import path_key

    seen: dict[str, str] = {}
    for option, path in paths.items():
        if not path:
            continue
        key = path_key(path)
        if key in seen:
            raise ConfigError(f"{seen[key]} and {option} name the same file {path!r}")
        seen[key] = option


def check_spares_inputs(outputs: dict[str, str | None], inputs: dict[str, object]) -> None:
    """No output may be one of the command's input files or lie inside an input folder (it
    would overwrite, or add to, what the command reads): ``{option: path}`` each, an input may
    be a list of paths; inputs that do not exist (a bundled model's name, a camera index) are
    not paths and are passed over.

    Raises:
        ConfigError: an output that is an input, or inside an input folder, both named.
    """
    import os

    from torchtrack.errors import ConfigError
    from torchtrack.io.atomic import path_key

    key = path_key

    for out_opt, out in outputs.items():
        if not out:
            continue
        o = key(out)
        for in_opt, given in inputs.items():
            for path in given if isinstance(given, (list, tuple)) else [given]:
                if not path or not os.path.exists(path):
                    continue
                i = key(path)
                if o == i:
                    what = "folder " if os.path.isdir(i) else ""
                    raise ConfigError(
                        f"{out_opt} {os.fspath(out)!r} is the input {what}{in_opt} "
                        f"{os.fspath(path)!r}: it would be overwritten; write the output elsewhere"
                    )
                if os.path.isdir(i) and o.startswith(i.rstrip(os.sep) + os.sep):
                    raise ConfigError(
                        f"{out_opt} {os.fspath(out)!r} lies inside the input folder {in_opt} "
                        f"{os.fspath(path)!r}: write the output elsewhere, outside what is read"
                    )


# ------------------------------------------------------------------------------ model trust
def add_trust(p: argparse.ArgumentParser) -> None:
    """``--trusted-key FILE`` (repeatable) and ``--require-signed``."""
    p.add_argument(
        "--trusted-key",
        action="append",
        default=None,
        metavar="PUB",
        help="accept model files signed by this Ed25519 public key (repeatable) and refuse "
        "unsigned ones or ones signed by other keys (the bundled models' key stays trusted)",
    )
    p.add_argument(
        "--require-signed",
        action="store_true",
        help="refuse model files without a valid signature of a trusted key",
    )


def trust_scope(args: argparse.Namespace):
    """A context in which model loading follows ``--trusted-key`` / ``--require-signed``.

    The policy travels as the environment variables of :mod:`torchtrack.detect.signing`, so
    worker processes (``eval --jobs``) follow it too; they are restored on exit. The key files
    are read once here, so a bad one fails before any work (:class:`ConfigError`).
    """
    import contextlib
    import os

    keys = getattr(args, "trusted_key", None) or []
    require = bool(keys) or bool(getattr(args, "require_signed", False))
    if not keys and not require:
        return contextlib.nullcontext()
    from torchtrack.detect.signing import ENV_KEYS, ENV_REQUIRE, TrustPolicy

    TrustPolicy.build(keys, require=True)  # fail early on an unreadable key
    old = {k: os.environ.get(k) for k in (ENV_KEYS, ENV_REQUIRE)}
    paths = [os.path.abspath(k) for k in keys]
    if old[ENV_KEYS]:
        paths.append(old[ENV_KEYS])

    @contextlib.contextmanager
    def scope():
        os.environ[ENV_KEYS] = os.pathsep.join(paths)
        os.environ[ENV_REQUIRE] = "1"
        try:
            yield
        finally:
            for k, v in old.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v

    return scope()
