import pytest

from torchtrack.io.atomic import atomic_write, write_text_atomic


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
