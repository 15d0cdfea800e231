"""Where independent tasks run: in this process, in a local process pool, or on a Ray cluster.

:func:`run_tasks` calls ``fn(*args)`` once for each ``args`` tuple and hands every result back
to the caller (in this process, in completion order) through ``on_result``. The evaluation
runner (one task per tracker, sequence and seed) and the corpus runner (one task per video)
both go through it, so the two share one pool, one Ray path and one way of reporting failures.

Backends
--------
* ``local``, ``jobs=1``: in this process, one task after the other.
* ``local``, ``jobs=N``: N spawned processes, each limited to one torch / OpenCV thread. A worker
  process that dies (a segfault in native code, a kill) breaks the whole pool; the tasks it took
  down are rerun one process each, so only the culprit is reported as crashed.
* ``ray``: one Ray task per item (``num_cpus`` CPUs each), on a fresh local Ray instance
  (``jobs`` CPUs; all cores when ``None``) or on the cluster at ``address`` (``host:port``,
  ``auto``; the ``RAY_ADDRESS`` environment variable when ``address`` is ``None``). A task whose worker process or node dies is rerun by Ray up to ``max_retries``
  times; one that still dies is reported as crashed. An exception raised by ``fn`` is not
  retried: it is deterministic. A connection to Ray already open in this process (the caller's
  own ``ray.init``) is used as it is and left open.

Failures never raise out of :func:`run_tasks`: they reach ``on_result`` as a
:class:`TaskFailure`. Only bad settings (:class:`~torchtrack.errors.ConfigError`), an unusable
backend (:class:`~torchtrack.errors.BackendError`) and ``KeyboardInterrupt`` do.

``fn`` and its arguments travel to the workers by pickling (the standard library's for the
process pool, cloudpickle for Ray): ``fn`` must be a module-level function (or a
``functools.partial`` of one) importable on every worker. A Ray task runs in the caller's
working directory when that folder exists on its machine (a shared file system), so relative
paths in the arguments mean the same files there, and with the caller's ``TORCHTRACK_*``
environment variables (the model trust policy of ``--trusted-key`` / ``--require-signed``).
"""

from __future__ import annotations

import importlib
import logging
import multiprocessing as mp
import os
import socket
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from torchtrack.errors import BackendError, ConfigError

__all__ = [
    "BACKENDS",
    "CRASH_MESSAGE",
    "Backend",
    "TaskFailure",
    "check_backend",
    "connect_ray",
    "import_ray",
    "run_tasks",
    "worker_info",
]

BACKENDS = ("local", "ray")
CRASH_MESSAGE = "the worker process crashed (killed or a segmentation fault in native code)"
#: The extra that installs Ray (``pip install "torchtrack[ray]"``).
RAY_EXTRA = "ray"


#: the most processes (local) or CPUs (a local Ray instance) --jobs may ask for
MAX_JOBS = 4096


@dataclass(frozen=True)
class Backend:
    """Where and how :func:`run_tasks` runs its tasks (see the module doc).

    Attributes:
        kind: ``"local"`` or ``"ray"``.
        jobs: local: worker processes (``None`` or 1: in this process); ray: CPUs of the local
            Ray instance started when there is no address (``None``: every core); ignored when
            connecting to a cluster.
        address: the Ray cluster (``host:port`` of its head node, or ``auto`` for a cluster
            started with ``ray start`` on this machine); ``None``: the ``RAY_ADDRESS``
            environment variable, else a new local instance.
        max_retries: times Ray reruns a task whose worker process or node died.
        num_cpus: CPUs each Ray task reserves (its torch threads).
        modules: Python modules imported in every worker before its first task (modules that
            register trackers).
        connect_timeout: seconds allowed to reach ``address`` before :class:`BackendError`.
    """

    kind: str = "local"
    jobs: int | None = None
    address: str | None = None
    max_retries: int = 3
    num_cpus: float = 1
    modules: tuple[str, ...] = ()
    connect_timeout: float = 5.0

    def __post_init__(self) -> None:
        if self.kind not in BACKENDS:
            raise ConfigError(f"backend must be one of {', '.join(BACKENDS)}, got {self.kind!r}")
        if self.jobs is not None and self.jobs < 1:
            raise ConfigError(f"--jobs must be >= 1, got {self.jobs}")
        if self.jobs is not None and self.jobs > MAX_JOBS:
            raise ConfigError(f"--jobs must be at most {MAX_JOBS}, got {self.jobs}")
        if self.max_retries < 0:
            raise ConfigError(f"--max-retries must be >= 0, got {self.max_retries}")
        if self.num_cpus <= 0:
            raise ConfigError(f"CPUs per task must be > 0, got {self.num_cpus}")
        if self.kind == "local" and self.address is not None:
            raise ConfigError("--address names a Ray cluster: use it with --backend ray")
        object.__setattr__(self, "modules", tuple(self.modules))

    @property
    def in_process(self) -> bool:
        """Tasks run in this process, one after the other."""
        return self.kind == "local" and (self.jobs or 1) == 1


@dataclass(frozen=True)
class TaskFailure:
    """A task that gave no result.

    Attributes:
        error: ``"Type: message"`` of the exception ``fn`` raised, or :data:`CRASH_MESSAGE`.
        traceback: the worker's traceback when there is one.
        crashed: the worker process died (after Ray's retries).
    """

    error: str
    traceback: str | None = None
    crashed: bool = False


def check_backend(backend: Backend) -> None:
    """Fail early, before any work or output: for Ray, that it is installed, that its address
    (``backend.address`` or ``RAY_ADDRESS``) answers, and that a local instance has the CPUs
    a task needs.

    Raises:
        BackendError: see :func:`connect_ray`.
    """
    if backend.kind != "ray":
        return
    ray = import_ray()
    address = backend.address or os.environ.get("RAY_ADDRESS") or None
    if address is not None and address not in ("auto", "local"):
        probe_address(address, backend.connect_timeout)
    elif (address is None or address == "local") and not ray.is_initialized():
        cpus = backend.jobs or os.cpu_count() or 1
        if cpus < backend.num_cpus:
            raise BackendError(
                f"each task needs {backend.num_cpus:g} CPU(s) (--threads), but the local Ray "
                f"instance gets {cpus} (--jobs): raise --jobs or lower --threads"
            )


def run_tasks(
    fn: Callable[..., Any],
    items: Sequence[tuple],
    backend: Backend,
    on_result: Callable[[int, Any], None],
) -> None:
    """Run ``fn(*items[i])`` for every ``i`` on ``backend``; call ``on_result(i, value)`` in
    this process as each finishes, ``value`` being what ``fn`` returned or a
    :class:`TaskFailure`. Tasks start in the order of ``items`` (put the longest first).

    Raises:
        BackendError: Ray is not installed or its cluster cannot be reached.
        ConfigError: a module of ``backend.modules`` cannot be imported here.
    """
    for mod in backend.modules:
        try:
            importlib.import_module(mod)
        except ImportError as exc:
            raise ConfigError(f"cannot import tracker module {mod!r}: {exc}") from exc
    if not items:
        return
    if backend.kind == "ray":
        _run_ray(fn, items, backend, on_result)
    elif backend.in_process:
        for i, args in enumerate(items):
            try:
                value = fn(*args)
            except Exception as exc:  # one failing task must not stop the others
                value = _failure(exc)
            on_result(i, value)
    else:
        lost = _run_pool(fn, list(enumerate(items)), backend.jobs, backend.modules, on_result)
        # A worker that dies breaks the whole pool and every unfinished task with it; rerun
        # those one process each, so that only the culprit is reported as crashed.
        for i, args in lost:
            if _run_pool(fn, [(i, args)], 1, backend.modules, on_result):
                on_result(i, TaskFailure(CRASH_MESSAGE, crashed=True))


def _failure(exc: BaseException) -> TaskFailure:
    return TaskFailure(f"{type(exc).__name__}: {exc}", traceback.format_exc(limit=8))


# ---------------------------------------------------------------------------------------------
# Worker set-up, shared by the process pool and Ray
# ---------------------------------------------------------------------------------------------
_READY: set[tuple[str, ...]] = set()


def worker_init(modules: tuple[str, ...] = ()) -> None:
    """Make a worker process ready: one torch / OpenCV thread (a task that wants more sets its
    own), and ``modules`` imported. Idempotent. Does not import torch (a task without it starts
    fast) but limits it whether it is loaded already or later."""
    if modules in _READY:
        return
    import sys

    import cv2

    os.environ["OMP_NUM_THREADS"] = "1"  # read by torch if it is imported later
    cv2.setNumThreads(1)
    for m in modules:
        importlib.import_module(m)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)
    _READY.add(modules)


def worker_info() -> dict:
    """Where a task ran: host, process id and the process's peak resident memory so far (MiB)."""
    import sys

    try:
        import resource
    except ImportError:  # pragma: no cover - Windows
        mib = None
    else:
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, B on macOS
        mib = round(rss / 2**20 if sys.platform == "darwin" else rss / 1024, 1)
    return {"host": socket.gethostname(), "pid": os.getpid(), "max_rss_mib": mib}


#: Environment variables of the caller that every Ray task sees (``TORCHTRACK_*``: the model
#: trust policy of ``--trusted-key`` / ``--require-signed``, ``TORCHTRACK_DATA``).
ENV_PREFIX = "TORCHTRACK_"


def _caller_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k.startswith(ENV_PREFIX)}


def _call(
    fn: Callable[..., Any],
    modules: tuple[str, ...],
    args: tuple,
    cwd: str | None = None,
    env: dict[str, str] | None = None,
) -> Any:
    worker_init(modules)
    if cwd is not None and os.path.isdir(cwd):
        # A Ray worker of a `ray start` node runs elsewhere; in the caller's folder (there on a
        # shared file system) the caller's relative paths mean the same files.
        os.chdir(cwd)
    old = {k: os.environ.get(k) for k in env or {}}
    os.environ.update(env or {})  # a worker started before the caller set them lacks them
    try:
        return fn(*args)
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


# ---------------------------------------------------------------------------------------------
# Local process pool
# ---------------------------------------------------------------------------------------------
def _run_pool(fn, indexed: list[tuple[int, tuple]], jobs, modules, on_result) -> list:
    """Run ``indexed`` ``(i, args)`` tasks in a spawned pool; return those lost to a crashed
    worker (not reported)."""
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    lost = []
    ctx = mp.get_context("spawn")
    with ProcessPoolExecutor(jobs, mp_context=ctx) as pool:
        futs = {pool.submit(_call, fn, tuple(modules), args): (i, args) for i, args in indexed}
        for f in as_completed(futs):
            i, args = futs[f]
            try:
                value = f.result()
            except BrokenProcessPool:
                lost.append((i, args))
                continue
            except Exception as exc:  # anything else a worker raised: report, go on
                value = TaskFailure(
                    f"{type(exc).__name__}: {exc}",
                    "".join(traceback.format_exception(exc, limit=8)),
                )
            on_result(i, value)
    return lost


# ---------------------------------------------------------------------------------------------
# Ray
# ---------------------------------------------------------------------------------------------
def import_ray():
    """The ``ray`` module, or :class:`BackendError` naming the extra that installs it."""
    try:
        import ray
    except ImportError as exc:
        raise BackendError(
            f"--backend ray needs Ray, which is not installed ({exc}): "
            f'pip install "torchtrack[{RAY_EXTRA}]" (or pip install ray) on this machine and '
            "on every machine of the cluster"
        ) from None
    return ray


def _split_address(address: str) -> tuple[str, int]:
    """``host:port``, ``[v6]:port`` or ``ray://host:port`` -> ``(host, port)``."""
    rest = address.split("://", 1)[1] if "://" in address else address
    rest = rest.rstrip("/")
    host, sep, port = rest.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise BackendError(
            f"Ray address {address!r} is not host:port (e.g. 10.0.0.5:6379, the address "
            "`ray start --head` prints)"
        )
    return host, int(port)


def probe_address(address: str, timeout: float = 5.0) -> None:
    """Open (and close) a TCP connection to a Ray address: :class:`BackendError` within
    ``timeout`` seconds when nothing listens there (``ray.init`` itself keeps retrying for
    minutes)."""
    host, port = _split_address(address)
    try:
        socket.create_connection((host, port), timeout=timeout).close()
    except OSError as exc:
        reason = "timed out" if isinstance(exc, TimeoutError) else (exc.strerror or str(exc))
        raise BackendError(
            f"cannot reach the Ray cluster at {address} ({reason}, waited up to "
            f"{timeout:g} s): start its head node there with `ray start --head --port={port}`, "
            "or check the address (the one `ray start --head` printed), RAY_ADDRESS and the "
            "firewall"
        ) from None


def connect_ray(
    address: str | None = None, *, num_cpus: int | None = None, timeout: float = 5.0
) -> bool:
    """Connect this process to Ray (see :class:`Backend` for ``address``).

    Returns:
        ``True`` when this call opened the connection (the caller shuts it down), ``False``
        when one was open already.

    Raises:
        BackendError: Ray is not installed, ``address`` cannot be reached within ``timeout``
            seconds, or the cluster refused the connection (e.g. a missing auth token).
    """
    ray = import_ray()
    address = address or os.environ.get("RAY_ADDRESS") or None
    if address is not None and address not in ("auto", "local"):
        probe_address(address, timeout)
    if ray.is_initialized():
        return False
    opts: dict[str, Any] = {"logging_level": logging.WARNING, "log_to_driver": True}
    try:
        if address is None or address == "local":
            # "local": a new instance even when a `ray start` cluster runs on this machine
            # (ray.init() would join the last one recorded in /tmp/ray, stale or not).
            ray.init(address="local", num_cpus=num_cpus, include_dashboard=False, **opts)
        else:
            ray.init(address=address, **opts)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        hint = ""
        if "auth" in repr(exc.__cause__).lower() or "auth" in str(exc).lower():
            hint = (
                " (the cluster uses token authentication: set RAY_AUTH_MODE=token and give "
                "its token in ~/.ray/auth_token or RAY_AUTH_TOKEN)"
            )
        where = address or "a new local instance"
        raise BackendError(f"cannot connect to Ray at {where}: {exc}{hint}") from None
    return True


def _ray_failure(ray, exc: BaseException) -> TaskFailure:
    if isinstance(exc, ray.exceptions.RayTaskError):
        cause = getattr(exc, "cause", None)
        if isinstance(cause, BaseException) and not isinstance(cause, ray.exceptions.RayTaskError):
            return TaskFailure(f"{type(cause).__name__}: {cause}", str(exc))
        return TaskFailure(f"{type(exc).__name__}: {exc}", str(exc))
    # WorkerCrashedError, NodeDiedError, OutOfMemoryError, ...: the process is gone.
    return TaskFailure(f"{CRASH_MESSAGE} [{type(exc).__name__}]", str(exc), crashed=True)


def _check_cpus(ray, need: float) -> None:
    """:class:`BackendError` when no node of the cluster can ever run a task of ``need`` CPUs
    (Ray would keep it pending forever)."""
    nodes = [n for n in ray.nodes() if n.get("Alive")]
    most = max((n.get("Resources", {}).get("CPU", 0.0) for n in nodes), default=0.0)
    if most < need:
        raise BackendError(
            f"each task needs {need:g} CPU(s) (--threads), but the largest node of the Ray "
            f"cluster has {most:g}: add nodes with `ray start --address=...`, give the local "
            "instance more (--jobs), or lower --threads"
        )


def _run_ray(fn, items, backend: Backend, on_result) -> None:
    ray = import_ray()
    opened = connect_ray(backend.address, num_cpus=backend.jobs, timeout=backend.connect_timeout)
    pending: list = []
    try:
        _check_cpus(ray, backend.num_cpus)
        task = ray.remote(_call).options(
            num_cpus=backend.num_cpus, max_retries=backend.max_retries, retry_exceptions=False
        )
        fn_ref = ray.put(fn)  # shipped once, not with every task
        cwd, env = os.getcwd(), _caller_env()
        index = {}
        for i, args in enumerate(items):
            index[task.remote(fn_ref, backend.modules, tuple(args), cwd, env)] = i
        pending = list(index)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            if pending:  # everything else that is ready too, without waiting
                more, pending = ray.wait(pending, num_returns=len(pending), timeout=0)
                done += more
            for ref in done:
                try:
                    value = ray.get(ref)
                except ray.exceptions.RayError as exc:
                    value = _ray_failure(ray, exc)
                on_result(index[ref], value)
    except BaseException:
        for ref in pending:
            try:
                ray.cancel(ref, force=True)
            except Exception:  # already finished or gone
                pass
        raise
    finally:
        if opened:
            ray.shutdown()
