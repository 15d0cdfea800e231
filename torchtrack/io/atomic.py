"""Atomic file writes: a crash never leaves half a file behind."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

__all__ = [
    "atomic_path",
    "atomic_write",
    "check_regular_destination",
    "check_writable_dir",
    "path_key",
    "uninterrupted",
    "write_bytes_atomic",
    "write_error",
    "write_text_atomic",
]


def path_key(path: str | os.PathLike) -> str:
    """What two names of one file or folder have in common: the real path (links, ``..`` and
    a trailing ``/`` resolved), case-folded where the file system ignores case."""
    return os.path.normcase(os.path.realpath(os.fspath(path)))


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def uninterrupted() -> Iterator[None]:
    """Ignore SIGINT and SIGTERM while the block runs (in the main thread; elsewhere nothing
    changes), then restore their handlers: the end of a run that is finishing its outputs
    (after an error, or after a first Ctrl-C asked it to stop and keep the results so far) is
    not cut short by a second signal, which would leave partial files or a half shut pool of
    worker processes behind. A signal that arrives meanwhile is dropped: the run is ending."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {s: signal.signal(s, signal.SIG_IGN) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def check_regular_destination(path: str | os.PathLike, what: str | None = None) -> None:
    """Refuse to write onto ``path`` when it exists and is not a regular file: a write by
    rename would replace a device (``/dev/null``), a named pipe or a socket with a plain file.

    Raises:
        ConfigError: naming ``what`` (default: the path) and what is there.
    """
    import stat

    from torchtrack.errors import ConfigError

    try:
        mode = os.stat(path).st_mode
    except OSError:  # nothing there (or nothing we may look at): the write itself will say
        return
    if stat.S_ISREG(mode) or stat.S_ISDIR(mode):  # a folder: the caller's own message
        return
    kind = (
        "a named pipe"
        if stat.S_ISFIFO(mode)
        else "a socket"
        if stat.S_ISSOCK(mode)
        else "a device"
        if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
        else "not a regular file"
    )
    name = what or repr(os.fspath(path))
    raise ConfigError(
        f"{name} exists and is {kind}: outputs are written to a temporary file renamed into "
        "place, which would replace it; give a regular file name"
    )


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path in the destination's folder; on success rename it onto ``path``.

    For writers that want a file name (``cv2.imwrite``, ``safetensors.save_file``,
    ``matplotlib.savefig``). ``suffix`` defaults to the destination's, so writers that pick a
    format from the extension still work. On error the temporary file is removed and ``path``
    is untouched.

    Raises:
        ConfigError: naming ``path``, when it exists and is not a regular file (a device, a
            pipe: :func:`check_regular_destination`), or when the file system refuses to make
            the temporary file (the folder cannot be made or written) or to rename it into
            place. What the
            writer itself raises passes unchanged.
    """
    dest = Path(path)
    check_regular_destination(dest)
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(
            prefix=f".{dest.name}.",
            suffix=dest.suffix if suffix is None else suffix,
            dir=dest.parent,
        )
        os.close(fd)
    except OSError as exc:
        raise write_error(dest, exc) from None
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        try:
            # mkstemp creates 0600; give the result the permissions a plain open() would.
            os.chmod(tmp_path, 0o666 & ~_umask())
            os.replace(tmp_path, dest)
        except OSError as exc:
            raise write_error(dest, exc) from None
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def write_error(dest: str | os.PathLike, exc: OSError):
    """The :class:`ConfigError` of a file system's refusal to write ``dest`` (raise it)."""
    from torchtrack.errors import ConfigError

    return ConfigError(f"cannot write {str(dest)!r}: {exc.strerror or exc}")


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w", **kwargs) -> Iterator[IO]:
    """Open a temporary file for writing; flush, fsync and rename onto ``path`` on success."""
    if not mode.startswith("w"):
        raise ValueError(f"atomic_write only writes (mode 'w' or 'wb'), got mode={mode!r}")
    with atomic_path(path) as tmp, open(tmp, mode, **kwargs) as f:
        yield f
        try:
            f.flush()
            os.fsync(f.fileno())
        except OSError as exc:  # e.g. the disk is full
            raise write_error(path, exc) from None


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically (:class:`ConfigError` when the file
    system refuses it)."""
    with atomic_write(path, "w", encoding="utf-8") as f:
        try:
            f.write(text)
        except OSError as exc:
            raise write_error(path, exc) from None


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (:class:`ConfigError` when the file system
    refuses it)."""
    with atomic_write(path, "wb") as f:
        try:
            f.write(data)
        except OSError as exc:
            raise write_error(path, exc) from None


def check_writable_dir(path: str | os.PathLike, what: str = "output folder") -> Path:
    """Create ``path`` (with its parents) and check a file can be written in it, before any
    work starts.

    Raises:
        ConfigError: naming ``what`` (the option) and why the folder cannot be written.
    """
    from torchtrack.errors import ConfigError

    d = Path(path)
    try:
        d.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".write-test.", dir=d)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise ConfigError(
            f"{what} {str(d)!r} cannot be written: {exc.strerror or exc}"
            + (f" ({exc.filename})" if exc.filename and str(exc.filename) != str(d) else "")
        ) from None
    return d
