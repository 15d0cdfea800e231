import os
import tempfile

import pytest

from torchtrack.errors import ConfigError
from torchtrack.io.atomic import atomic_path, atomic_write, write_text_atomic


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
