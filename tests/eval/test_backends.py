"""The local backends of torchtrack.eval.backends (in this process, spawned processes) and the
errors of the Ray backend that need no Ray instance (Ray itself: tests/eval/test_ray.py)."""

from __future__ import annotations

import socket
import sys

import pytest

from torchtrack.errors import BackendError, ConfigError
from torchtrack.eval.backends import (
    Backend,
    TaskFailure,
    check_backend,
    connect_ray,
    probe_address,
    run_tasks,
)

from .backend_tasks import task, threads


def collect(fn, items, backend) -> dict:
    got: dict = {}

    def on_result(i, value):
        assert i not in got  # every task reported once
        got[i] = value

    run_tasks(fn, items, backend, on_result)
    return got


def closed_port() -> int:
    """A local port nothing listens on (bound, then released)."""
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def test_in_process_runs_every_task_and_reports_a_raise_as_a_failure():
    got = collect(task, [(k, 2) for k in range(4)], Backend())
    assert [got[i] for i in (0, 1, 3)] == [0, 1, 9]
    assert isinstance(got[2], TaskFailure) and not got[2].crashed
    assert got[2].error == "ValueError: no 2, please" and "in task" in got[2].traceback


def test_process_pool_reports_a_raise_and_isolates_a_crash():
    """A worker dying breaks the pool: the tasks it took down are rerun, and only the one that
    kills its process again is reported as crashed; every task is reported once."""
    got = collect(task, [(k, 1, 2) for k in range(4)], Backend(jobs=2))
    assert got[0] == 0 and got[3] == 9
    assert got[1].error == "ValueError: no 1, please" and not got[1].crashed
    assert got[2].crashed and "crashed" in got[2].error
    assert collect(threads, [()], Backend(jobs=2)) == {0: (1, 1)}  # one thread per worker


def test_bad_settings():
    with pytest.raises(ConfigError, match="backend must be one of local, ray"):
        Backend("dask")
    with pytest.raises(ConfigError, match="--jobs must be >= 1"):
        Backend(jobs=0)
    with pytest.raises(ConfigError, match="--max-retries must be >= 0"):
        Backend("ray", max_retries=-1)
    with pytest.raises(ConfigError, match="--address names a Ray cluster"):
        Backend(address="10.0.0.5:6379")
    with pytest.raises(ConfigError, match="cannot import tracker module 'no_such_mod'"):
        run_tasks(task, [(1,)], Backend(modules=("no_such_mod",)), lambda i, v: None)


@pytest.mark.usefixtures("ray")  # the errors of a Ray that is installed
def test_unreachable_address_is_a_clear_error():
    addr = f"127.0.0.1:{closed_port()}"
    with pytest.raises(BackendError, match=r"cannot reach the Ray cluster at 127\.0\.0\.1:\d+ "):
        probe_address(addr, timeout=2)
    with pytest.raises(BackendError, match="ray start --head"):
        check_backend(Backend("ray", address=f"ray://{addr}"))
    for bad in ("10.0.0.5", "host:port", "host:99999", ":6379"):
        with pytest.raises(BackendError, match="is not host:port"):
            probe_address(bad)


@pytest.mark.usefixtures("ray")  # the errors of a Ray that is installed
def test_ray_address_from_the_environment(monkeypatch):
    monkeypatch.setenv("RAY_ADDRESS", f"127.0.0.1:{closed_port()}")
    with pytest.raises(BackendError, match="cannot reach the Ray cluster"):
        check_backend(Backend("ray"))


def test_ray_not_installed_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # what `import ray` meets without Ray
    with pytest.raises(BackendError, match=r'pip install "torchtrack\[ray\]"'):
        check_backend(Backend("ray"))
    with pytest.raises(BackendError, match="needs Ray, which is not installed"):
        connect_ray()
    check_backend(Backend())  # the local backend does not need it


def test_jobs_are_bounded():
    from torchtrack.errors import ConfigError
    from torchtrack.eval.backends import MAX_JOBS, Backend

    with pytest.raises(ConfigError, match=f"--jobs must be at most {MAX_JOBS}"):
        Backend("local", jobs=10**20)
