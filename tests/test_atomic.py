import os
import tempfile

import pytest

from torchtrack.errors import ConfigError
from torchtrack.io.atomic import (
    atomic_path,
    atomic_write,
    check_regular_destination,
    uninterrupted,
    write_text_atomic,
)


def test_atomic_write_replaces(tmp_path):
    p = tmp_path / "out.txt"
    write_text_atomic(p, "first")
    write_text_atomic(p, "second")
    assert p.read_text() == "second"
    assert [f.name for f in tmp_path.iterdir()] == ["out.txt"]


def test_atomic_write_keeps_old_file_on_crash(tmp_path):
    p = tmp_path / "out.txt"
    write_text_atomic(p, "good")
    with pytest.raises(RuntimeError), atomic_write(p) as f:
        f.write("half")
        raise RuntimeError("crash")
    assert p.read_text() == "good"
    assert [f.name for f in tmp_path.iterdir()] == ["out.txt"]


def test_atomic_write_uses_umask_permissions(tmp_path):
    import os

    p = tmp_path / "out.txt"
    write_text_atomic(p, "x")
    mask = os.umask(0)
    os.umask(mask)
    assert p.stat().st_mode & 0o777 == 0o666 & ~mask


def test_file_system_refusals_are_config_errors_naming_the_file(tmp_path, monkeypatch):
    """A folder that takes no new file, or a rename that fails late (disk full, the folder
    gone): a ConfigError naming the destination, not a bare OSError; nothing is left."""
    p = tmp_path / "out.txt"

    def refuse(*args, **kwargs):
        raise OSError(28, "No space left on device")

    with monkeypatch.context() as m:
        m.setattr(tempfile, "mkstemp", refuse)
        with pytest.raises(ConfigError, match=r"cannot write '.*out\.txt': No space left"):
            write_text_atomic(p, "x")
    with monkeypatch.context() as m:
        m.setattr(os, "replace", refuse)
        with pytest.raises(ConfigError, match=r"cannot write '.*out\.txt': No space left"):
            with atomic_path(p) as tmp:
                tmp.write_text("x")
    assert list(tmp_path.iterdir()) == []
    # what the writer itself raises passes unchanged
    with pytest.raises(OSError, match="reading an input"), atomic_path(p):
        raise OSError("reading an input")
    assert list(tmp_path.iterdir()) == []


def test_a_pipe_or_device_is_never_replaced(tmp_path):
    """A write by rename onto a named pipe (or /dev/null) would swap it for a plain file."""
    pipe = tmp_path / "pipe"
    os.mkfifo(pipe)
    with pytest.raises(ConfigError, match="exists and is a named pipe"):
        write_text_atomic(pipe, "x")
    with pytest.raises(ConfigError, match="is a device"):
        check_regular_destination("/dev/null")
    import stat

    assert stat.S_ISFIFO(os.stat(pipe).st_mode)
    assert [f.name for f in tmp_path.iterdir()] == ["pipe"]  # no temporary file left
    check_regular_destination(tmp_path / "new.txt")  # nothing there: fine
    check_regular_destination(tmp_path)  # a folder: the callers' own message


def test_uninterrupted_drops_signals_and_restores_the_handlers():
    import signal

    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    with uninterrupted():
        os.kill(os.getpid(), signal.SIGINT)  # ignored: no KeyboardInterrupt here
        os.kill(os.getpid(), signal.SIGTERM)
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
