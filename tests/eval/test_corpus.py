"""Corpus runs (torchtrack.eval.corpus) on the local backends: finding sources, naming outputs,
atomic outputs, the manifest, resuming a stopped run, failures. Ray: tests/eval/test_ray.py;
the command line: tests/cli/test_corpus.py."""

from __future__ import annotations

import functools
import json
import os
from pathlib import Path

import pytest

from torchtrack.errors import ConfigError
from torchtrack.eval.backends import Backend
from torchtrack.eval.corpus import (
    MANIFEST,
    Manifest,
    OutputKind,
    _locked,
    find_sources,
    output_names,
    run_corpus,
)

from .backend_tasks import size_job

CSV = OutputKind("csv", ".csv", "out")
NOTE = OutputKind("note", ".note.txt", "note")


def touch(path: Path, data: bytes = b"x") -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


@pytest.fixture
def videos(tmp_path) -> Path:
    d = tmp_path / "v"
    for name, size in (("a10.mp4", 3), ("a2.avi", 5), ("bad.mp4", 1), ("c.mkv", 7)):
        touch(d / name, b"v" * size)
    touch(d / "notes.txt")
    touch(d / ".hidden.mp4")
    return d


def calls_of(path: Path) -> list[str]:
    return [Path(p).name for p in path.read_text().splitlines()] if path.exists() else []


# ---------------------------------------------------------------------------------------------
# Sources and names
# ---------------------------------------------------------------------------------------------
def test_find_sources_folders_globs_lists_and_duplicates(videos, tmp_path):
    names = lambda srcs: [Path(s).name for s in srcs]  # noqa: E731
    assert names(find_sources([str(videos)])) == ["a2.avi", "a10.mp4", "bad.mp4", "c.mkv"]
    frames = tmp_path / "frames"
    touch(frames / "0001.jpg")
    assert find_sources([str(frames)]) == [os.path.realpath(frames)]  # one frame-folder source
    logged = []
    got = find_sources([str(tmp_path / "*" / "*"), str(videos / "c.mkv")], log=logged.append)
    assert names(got) == ["a2.avi", "a10.mp4", "bad.mp4", "c.mkv"]  # c.mkv once
    assert logged == ["ignored 2 path(s) matched by a pattern that are not videos or frame folders"]
    os.symlink(videos / "a2.avi", tmp_path / "link.avi")
    lst = touch(tmp_path / "list.txt", b"# mine\n\nv/c.mkv\n  link.avi \nframes\n")
    assert names(find_sources([f"@{lst}"])) == ["c.mkv", "a2.avi", "frames"]


@pytest.mark.parametrize(
    ("spec", "match"),
    [
        ("missing.mp4", "source .*missing.mp4' does not exist"),
        ("0", "'0' is a camera index"),
        ("²", "source .*²' does not exist"),  # a Unicode digit: no camera (it said one)
        ("empty", "holds no video .* and no image"),
        ("*.zzz", r"pattern '\*.zzz' matches nothing"),
        ("v/*.txt", "matches 1 path.* but no video file and no frame folder"),
        ("@nolist.txt", "cannot read source list"),
        ("@blank.txt", "names no source"),
        ("@nested.txt", "entry 1 .* is another list; lists do not nest"),
    ],
)
def test_find_sources_bad_input(videos, tmp_path, monkeypatch, spec, match):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "empty").mkdir()
    touch(tmp_path / "blank.txt", b"# nothing\n\n")
    touch(tmp_path / "nested.txt", b"@blank.txt\n")
    with pytest.raises(ConfigError, match=match):
        find_sources([spec])


def test_output_names_tell_clashing_sources_apart_and_keep_earlier_names():
    srcs = ["/d/cam1/x.mp4", "/d/cam2/x.mp4", "/d/cam2/x.avi", "/d/y.mp4", "/e/Y.mp4"]
    assert output_names(srcs) == {
        "/d/cam1/x.mp4": "cam1_x",
        "/d/cam2/x.mp4": "d_cam2_x_mp4",
        "/d/cam2/x.avi": "d_cam2_x_avi",
        "/d/y.mp4": "d_y",  # y and Y would be one file on a case-insensitive disk
        "/e/Y.mp4": "e_Y",
    }
    taken = {"/old/x.mp4": "x", "/d/cam1/x.mp4": "first", "/o/d_x": "d_x", "/o/dxm": "d_x_mp4"}
    assert output_names(["/d/cam1/x.mp4", "/d/x.mp4"], taken) == {
        "/d/cam1/x.mp4": "first",  # as the manifest has it
        "/d/x.mp4": "x-2",  # x, d_x and d_x_mp4 are taken by sources of an earlier run
    }
    assert output_names(["/a/X.mp4", "/a/x.mp4", "/b/x-2.mp4"]) == {
        "/a/X.mp4": "X-2",  # one file on a case-insensitive disk: numbered
        "/a/x.mp4": "x-3",
        "/b/x-2.mp4": "x-2-2",
    }


# ---------------------------------------------------------------------------------------------
# Runs
# ---------------------------------------------------------------------------------------------
def test_run_writes_outputs_and_manifest_reports_failures(videos, tmp_path):
    out, calls = tmp_path / "out", tmp_path / "calls"
    srcs = find_sources([str(videos)])
    logged = []
    report = run_corpus(
        srcs,
        functools.partial(size_job, str(calls)),
        out,
        [CSV, NOTE],
        settings={"tracker": "t"},
        command="cmd",
        progress=False,
        log=logged.append,
    )
    assert sorted(Path(s).name for s in report.done) == ["a10.mp4", "a2.avi", "c.mkv"]
    assert report.failed == {str(videos / "bad.mp4"): "ValueError: cannot read bad.mp4"}
    assert logged == [f"failed: {videos / 'bad.mp4'}: ValueError: cannot read bad.mp4"]
    assert calls_of(calls) == ["c.mkv", "a2.avi", "a10.mp4", "bad.mp4"]  # biggest first
    assert (out / "a2.csv").read_text() == "a2.avi,5\n" == (out / "a2.note.txt").read_text()
    assert not (out / "bad.csv").exists() and not list(out.glob(".*part*"))
    header, *lines = [json.loads(x) for x in (out / MANIFEST).read_text().splitlines()]
    assert header["settings"] == {"tracker": "t"} and header["command"] == "cmd"
    done = next(e for e in lines if e["name"] == "c")
    assert done["status"] == "done" and done["outputs"] == {"csv": "c.csv", "note": "c.note.txt"}
    assert done["summary"] == {"bytes": 7} and done["worker"]["pid"] == os.getpid()
    assert report.line() == "4 source(s): 3 done, 0 already done (skipped), 1 failed"


def test_a_stopped_run_resumes_where_it_stopped(videos, tmp_path):
    out, calls = tmp_path / "out", tmp_path / "calls"
    touch(videos / "stop.mp4", b"s" * 4)  # the 3rd job by size: Ctrl-C there
    job = functools.partial(size_job, str(calls))
    srcs = find_sources([str(videos)])
    with pytest.raises(KeyboardInterrupt):
        run_corpus(srcs, job, out, [CSV], progress=False)
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [
        "a2.csv", "c.csv", MANIFEST
    ]  # fmt: skip
    assert not list(out.glob(".*part*"))
    stamp = (out / "c.csv").stat().st_mtime_ns
    (videos / "stop.mp4").rename(videos / "later.mp4")  # the next run gets past it
    logged = []
    report = run_corpus(
        find_sources([str(videos)]), job, out, [CSV], progress=False, log=logged.append
    )
    assert sorted(Path(s).name for s in report.skipped) == ["a2.avi", "c.mkv"]
    assert sorted(Path(s).name for s in report.done) == ["a10.mp4", "later.mp4"]
    assert calls_of(calls)[-3:] == ["later.mp4", "a10.mp4", "bad.mp4"]
    assert (out / "c.csv").stat().st_mtime_ns == stamp  # not rewritten
    assert logged[0] == f"skipping 2 source(s) already done ({out / MANIFEST})"
    # A third run: only the failure is tried again; asking for a new kind redoes the rest.
    report = run_corpus(find_sources([str(videos)]), job, out, [CSV], progress=False)
    assert len(report.skipped) == 4 and list(report.failed) == [str(videos / "bad.mp4")]
    report = run_corpus(find_sources([str(videos)]), job, out, [CSV, NOTE], progress=False)
    assert len(report.done) == 4 and (out / "a10.note.txt").is_file()


def test_deleted_output_is_redone_and_empty_output_is_a_failure(videos, tmp_path):
    out, calls = tmp_path / "out", tmp_path / "calls"
    job = functools.partial(size_job, str(calls))
    srcs = [str(videos / "a2.avi"), str(touch(videos / "empty.mp4"))]
    report = run_corpus(srcs, job, out, [CSV], progress=False)
    assert report.failed == {
        srcs[1]: f"DataError: {srcs[1]}: the job finished but wrote no csv output"
    }
    (out / "a2.csv").unlink()
    report = run_corpus(srcs[:1], job, out, [CSV], progress=False)
    assert report.done == srcs[:1] and (out / "a2.csv").is_file()


def test_local_pool_gives_the_same_outputs(videos, tmp_path):
    job = functools.partial(size_job, str(tmp_path / "calls"))
    srcs = find_sources([str(videos)])
    one = run_corpus(srcs, job, tmp_path / "one", [CSV], progress=False)
    two = run_corpus(srcs, job, tmp_path / "two", [CSV], backend=Backend(jobs=2), progress=False)
    assert one.failed == two.failed and sorted(one.done) == sorted(two.done)
    for p in (tmp_path / "one").glob("*.csv"):
        assert (tmp_path / "two" / p.name).read_bytes() == p.read_bytes()


def test_bad_input(videos, tmp_path):
    job = functools.partial(size_job, str(tmp_path / "calls"))
    srcs = find_sources([str(videos)])
    blocker = touch(tmp_path / "file")
    with pytest.raises(ConfigError, match=r"--out-dir .* cannot be written: Not a directory"):
        run_corpus(srcs, job, blocker / "out", [CSV], progress=False)
    with pytest.raises(ConfigError, match="no source"):
        run_corpus([], job, tmp_path / "o", [CSV])
    with pytest.raises(ConfigError, match="output kinds repeat a suffix"):
        run_corpus(srcs, job, tmp_path / "o", [CSV, OutputKind("x", ".csv", "x")])
    out = tmp_path / "out"
    run_corpus(srcs[:1], job, out, [CSV], settings={"seed": 0, "box": "1,2,3,4"}, progress=False)
    with pytest.raises(ConfigError, match=r"other settings \(seed: 0 there, 1 now\): rerun"):
        run_corpus(srcs, job, out, [CSV], settings={"seed": 1, "box": "1,2,3,4"})
    with _locked(out), pytest.raises(ConfigError, match="another corpus run is writing"):
        run_corpus(srcs, job, out, [CSV], settings={"seed": 0, "box": "1,2,3,4"})
    touch(tmp_path / "other" / MANIFEST, b'{"format": "something else"}\n')
    with pytest.raises(ConfigError, match="is not a torchtrack corpus manifest"):
        run_corpus(srcs, job, tmp_path / "other", [CSV])


def test_manifest_drops_a_line_cut_short_by_a_crash(tmp_path):
    m = Manifest(tmp_path / MANIFEST, {"k": 1})
    m.append({"source": "/a", "name": "a", "status": "done", "outputs": {}})
    m.close()
    with open(tmp_path / MANIFEST, "a") as f:
        f.write('{"source": "/b", "name": "b", "sta')  # the process died mid-write
    m = Manifest(tmp_path / MANIFEST, {"k": 1})
    assert list(m.entries) == ["/a"]
    m.append({"source": "/b", "name": "b", "status": "failed"})
    m.close()
    assert list(Manifest(tmp_path / MANIFEST, {"k": 1}).entries) == ["/a", "/b"]


def test_a_cluster_lost_before_any_source_leaves_nothing_behind(videos, tmp_path, monkeypatch):
    """An address that accepts connections but is not Ray passes the early probe and fails in
    run_tasks: a run that recorded nothing removes the manifest it began (and a folder it made);
    an earlier run's manifest stays as it was."""
    import torchtrack.eval.corpus as corpus
    from torchtrack.errors import BackendError

    def unreachable(*_a, **_k):
        raise BackendError("cannot connect to Ray at 10.0.0.5:6379: timed out")

    job = functools.partial(size_job, str(tmp_path / "calls"))
    srcs = find_sources([str(videos)])
    monkeypatch.setattr(corpus, "run_tasks", unreachable)
    fresh = tmp_path / "new" / "out"
    with pytest.raises(BackendError, match="cannot connect to Ray"):
        run_corpus(srcs, job, fresh, [CSV], progress=False)
    assert not fresh.exists() and (tmp_path / "new").is_dir()  # only what the run made is gone
    there = tmp_path / "there"
    there.mkdir()
    with pytest.raises(BackendError):
        run_corpus(srcs, job, there, [CSV], progress=False)
    assert not (there / MANIFEST).exists() and there.is_dir()
    monkeypatch.undo()
    done = tmp_path / "done"
    run_corpus(srcs[:1], job, done, [CSV], progress=False)
    before = (done / MANIFEST).read_bytes()
    monkeypatch.setattr(corpus, "run_tasks", unreachable)
    with pytest.raises(BackendError):
        run_corpus(srcs, job, done, [CSV], progress=False)
    assert (done / MANIFEST).read_bytes() == before  # an earlier run's record is kept
