"""The Ray backend against a real local Ray instance (started once for the module, 2 CPUs) on
real data: evaluation and corpus runs give the same boxes as the local backend, byte for byte;
a worker that dies is retried by Ray and recorded once; a CLI in another process joins the
instance by its address. Needs the ``ray`` extra (CI installs it)."""

from __future__ import annotations

import json
import logging
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from torchtrack.cli import build_parser, main
from torchtrack.data import demo_clip_path
from torchtrack.eval.backends import Backend, run_tasks
from torchtrack.eval.corpus import MANIFEST, run_corpus
from torchtrack.eval.runner import evaluate
from torchtrack.io.sequences import load_sequence

TESTS = Path(__file__).resolve().parents[1]
REPO = TESTS.parent
BOX = "200,100,30,60"  # inside the 480x360 frames of both PETS clips


def import_ray():
    try:
        import ray
    except ImportError:
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail("Ray is not installed: CI installs the ray extra (pip install .[ray])")
        pytest.skip("Ray is not installed (pip install 'torchtrack[ray]')")
    return ray


@pytest.fixture(scope="module")
def ray_address():
    """A local Ray instance with 2 CPUs whose workers can import the test modules; yields its
    address."""
    ray = import_ray()
    saved = dict(os.environ)
    os.environ["PYTHONPATH"] = os.pathsep.join(
        p for p in (str(TESTS), saved.get("PYTHONPATH")) if p
    )  # the raylet, and so every worker, inherits it
    ray.init(address="local", num_cpus=2, include_dashboard=False, logging_level=logging.WARNING)
    try:
        yield ray.get_runtime_context().gcs_address
    finally:
        ray.shutdown()
        os.environ.clear()
        os.environ.update(saved)


def closed_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def test_a_local_instance_too_small_for_a_task_is_refused_before_it_starts(tmp_path, capsys):
    ray = import_ray()
    assert not ray.is_initialized()  # first in the module: before the fixture's instance
    rc = track([str(demo_clip_path())], tmp_path / "p", "--backend", "ray", "--jobs", "1",
               "--threads", "2")  # fmt: skip
    assert rc == 1 and "the local Ray instance gets 1 (--jobs)" in capsys.readouterr().err
    assert not (tmp_path / "p").exists() and not ray.is_initialized()


def records(out: Path) -> dict[str, dict]:
    return {
        str(p.relative_to(out)): json.loads(p.read_text())
        for p in sorted((out / "sequences").rglob("*.json"))
    }


def test_eval_on_ray_equals_local(ray_address, data_dir, tmp_path):
    seqs = [
        s.head(8)
        for name in ("otb/Crossing", "bobot_pedestrian")
        for s in load_sequence(data_dir / "tracking" / name)
    ]
    trackers = ["histogram:n_particles=200", "camshift"]
    local = evaluate(seqs, trackers, tmp_path / "local", progress=False, seed=3)
    on_ray = evaluate(seqs, trackers, tmp_path / "ray", backend="ray", progress=False, seed=3)
    a, b = records(tmp_path / "local"), records(tmp_path / "ray")
    assert sorted(a) == sorted(b) and len(a) == 4  # the same result files
    for key in a:
        assert b[key]["error"] is None
        for field in ("boxes", "visible", "confidence", "metrics", "bad_frames"):
            assert b[key][field] == a[key][field], (key, field)
        assert b[key]["worker"]["pid"] != os.getpid() == a[key]["worker"]["pid"]
    for seq, row in local["per_sequence"].items():
        for spec, r in row.items():
            r2 = on_ray["per_sequence"][seq][spec]
            assert {k: v for k, v in r2.items() if k != "fps"} == {
                k: v for k, v in r.items() if k != "fps"
            }


def test_a_worker_dying_is_retried_once_and_a_crashing_one_recorded(
    ray_address, data_dir, tmp_path
):
    (seq,) = load_sequence(data_dir / "tracking" / "otb" / "Crossing")
    marker = tmp_path / "died"
    once = f"test-die-once:marker={marker}"
    out = tmp_path / "ray"
    summary = evaluate(
        [seq.head(5)],
        [once, "test-crash"],
        out,
        backend="ray",
        max_retries=1,
        progress=False,
        modules=["eval.crash_tracker"],
    )
    assert marker.is_file()  # a worker did die on it ...
    per = summary["per_sequence"]["Crossing"]
    assert per[once]["error"] is None  # ... and its task was rerun
    (path,) = (out / "sequences" / "Crossing").glob("test-die-once*.json")
    rec = json.loads(path.read_text())
    assert rec["boxes"] == [[204.0, 150.0, 17.0, 50.0]] * 5  # the static box, every frame once
    assert "crashed" in per["test-crash"]["error"]  # dies every time: recorded after 1 retry
    assert summary["overall"]["test-crash"]["n_failed"] == 1
    assert len(list((out / "sequences").rglob("*.json"))) == 2  # one record per task


@pytest.fixture
def corpus(data_dir, tmp_path):
    """Two real clips, a second clip with a clashing name in another folder (given through a
    list file), and a corrupt video."""
    root = tmp_path / "videos"
    (root / "cam2").mkdir(parents=True)
    shutil.copy(data_dir / "videos" / "pets2009_s2l1_vtest" / "vtest.avi", root / "vtest.avi")
    shutil.copy(demo_clip_path(), root / "clip.mp4")
    shutil.copy(demo_clip_path(), root / "cam2" / "clip.mp4")
    (root / "broken.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + b"\x00" * 64)
    (tmp_path / "list.txt").write_text("# the second camera\nvideos/cam2/clip.mp4\n")
    return [str(root), f"@{tmp_path / 'list.txt'}"]


def track(sources, out, *extra):
    return main(
        ["track", *sources, "--out-dir", str(out), "--tracker", "histogram:n_particles=200",
         "--box", BOX, "--max-frames", "6", "--seed", "1", "--no-progress", *extra]
    )  # fmt: skip


def test_corpus_on_ray_equals_local(ray_address, corpus, tmp_path, capsys):
    assert track(corpus, tmp_path / "local", "--write", "csv,video") == 1  # broken.mp4 failed
    assert track(corpus, tmp_path / "ray", "--write", "csv,video", "--backend", "ray") == 1
    err = capsys.readouterr().err
    assert err.count("failed: ") == 2 and "broken.mp4: VideoError" in err
    names = ["cam2_clip", "videos_clip", "vtest"]  # clashing stems both take their folder
    for run in ("local", "ray"):
        out = tmp_path / run
        assert sorted(p.stem for p in out.glob("*.csv")) == names
        assert sorted(p.stem for p in out.glob("*.mp4")) == names
        assert not list(out.glob(".*.part*"))
        entries = [json.loads(line) for line in (out / MANIFEST).read_text().splitlines()[1:]]
        assert len(entries) == 4 and len({e["source"] for e in entries}) == 4
        assert [e["status"] for e in entries].count("failed") == 1
    for n in names:
        local = (tmp_path / "local" / f"{n}.csv").read_bytes()
        assert (tmp_path / "ray" / f"{n}.csv").read_bytes() == local
        assert len(local.splitlines()) == 7
    assert (tmp_path / "ray" / "videos_clip.csv").read_bytes() == (
        tmp_path / "ray" / "cam2_clip.csv"
    ).read_bytes()  # the same clip twice: two outputs, neither overwritten


def test_corpus_worker_death_is_retried_without_loss_or_duplicates(ray_address, data_dir, tmp_path):
    from torchtrack.cli._corpus import OUTPUT_KINDS, _JobOf

    srcs = [str(demo_clip_path()), str(data_dir / "videos" / "pets2009_s2l1_vtest" / "vtest.avi")]
    marker = tmp_path / "died"
    args = build_parser().parse_args(
        ["track", *srcs, "--out-dir", "x", "--tracker", f"test-die-once:marker={marker}",
         "--box", BOX, "--max-frames", "5"]
    )  # fmt: skip
    args.no_progress = True
    kinds = OUTPUT_KINDS[:1]
    report = run_corpus(
        srcs,
        _JobOf(args),
        tmp_path / "out",
        kinds,
        backend=Backend("ray", max_retries=2, modules=("eval.crash_tracker",)),
        progress=False,
    )
    assert marker.is_file() and not report.failed and len(report.done) == 2
    lines = (tmp_path / "out" / MANIFEST).read_text().splitlines()
    assert len(lines) == 3  # the header and one line per source
    for name in ("pets2009_s2l1_demo", "vtest"):
        rows = (tmp_path / "out" / f"{name}.csv").read_text().splitlines()
        assert rows[1:] == [f"{i},200.00,100.00,30.00,60.00,1.0000,1" for i in range(5)]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        ".manifest.lock", MANIFEST, "pets2009_s2l1_demo.csv", "vtest.csv"
    ]  # fmt: skip


def test_tasks_run_in_the_callers_folder_and_trust_policy(ray_address, tmp_path, monkeypatch):
    """Workers started elsewhere (here: before the chdir) resolve relative paths as the caller,
    and see its TORCHTRACK_* variables (--require-signed travels as one) only during a task."""
    from torchtrack.detect.signing import ENV_REQUIRE

    from .backend_tasks import cwd, getenv

    monkeypatch.chdir(tmp_path)
    got = {}
    run_tasks(cwd, [(), ()], Backend("ray"), got.__setitem__)
    assert got == {0: str(tmp_path), 1: str(tmp_path)}
    monkeypatch.setenv(ENV_REQUIRE, "1")
    run_tasks(getenv, [(ENV_REQUIRE,)], Backend("ray"), got.__setitem__)
    assert got[0] == "1"
    monkeypatch.delenv(ENV_REQUIRE)
    run_tasks(getenv, [(ENV_REQUIRE,)], Backend("ray"), got.__setitem__)
    assert got[0] is None  # restored after the task


def test_a_cli_in_another_process_joins_the_cluster_by_address(ray_address, tmp_path):
    env = dict(os.environ, RAY_ADDRESS=ray_address, PYTHONPATH=str(REPO))
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "torchtrack", "track", str(demo_clip_path()), "--out-dir",
           str(out), "--backend", "ray", "--box", BOX, "--max-frames", "3", "--no-progress"]  # fmt: skip
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "1 source(s): 1 done" in r.stdout
    assert len((out / "pets2009_s2l1_demo.csv").read_text().splitlines()) == 4


def test_a_task_no_node_can_hold_is_an_error_not_a_hang(ray_address, tmp_path, capsys):
    rc = track([str(demo_clip_path())], tmp_path / "o", "--backend", "ray", "--threads", "3")
    assert rc == 1  # the fixture's instance has 2 CPUs
    assert "each task needs 3 CPU(s) (--threads), but the largest node" in capsys.readouterr().err


def test_unreachable_address_fails_fast_with_a_clear_message(tmp_path, capsys):
    import_ray()
    addr = f"127.0.0.1:{closed_port()}"
    rc = main(
        ["eval", "--sequences", str(tmp_path / "nowhere"), "--trackers", "camshift", "--out",
         str(tmp_path / "o"), "--backend", "ray", "--address", addr]
    )  # fmt: skip
    assert rc == 1
    assert f"cannot reach the Ray cluster at {addr}" in capsys.readouterr().err
    rc = track([str(demo_clip_path())], tmp_path / "c", "--backend", "ray", "--address", addr)
    assert rc == 1 and "ray start --head" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()  # nothing written
