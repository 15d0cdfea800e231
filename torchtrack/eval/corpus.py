"""Corpus runs: one job per source video, one set of output files per source, resumable.

:func:`run_corpus` runs ``job(source, **outputs)`` for every source of a corpus (videos or frame
folders, from :func:`find_sources`) on a :mod:`~torchtrack.eval.backends` backend (this process,
local processes or Ray) and keeps, in ``out_dir``:

* one file per source and output kind, named after the source (:func:`output_names`):
  ``<name>.csv``, ``<name>.mp4``, ... (:class:`OutputKind`). The job writes into temporary
  files beside them (``.<name>.csv.<token>.part.csv``); only a job that finishes has its files
  renamed into place, so a file under its final name is always complete, and a job that fails
  or dies leaves none;
* ``manifest.jsonl``: a header line (the settings of the run) and one line per finished
  source, appended as it finishes: ``status`` ``done`` (with its ``outputs``, the job's
  ``summary`` and the ``worker`` that ran it) or ``failed`` (with the ``error``).

Run again with the same ``out_dir`` and the same settings, a corpus run skips every source whose
latest manifest line is ``done`` with all the requested outputs on disk, and reruns the rest
(failed, never started, or stopped half-way): a stopped run resumes where it was. Different
settings are refused (:class:`~torchtrack.errors.ConfigError`): the folder would mix two runs.
A source keeps its output name across runs, whatever other sources are added.

Only this process writes the manifest and the final names (a job's worker renames its own
temporary files on success, then this process records it), so a task that Ray reruns after its
worker died is recorded once, and its files are written whole, once, under their final names.
A lock on ``out_dir`` keeps two corpus runs from writing into one folder at the same time.

Example::

    from torchtrack.eval.backends import Backend
    from torchtrack.eval.corpus import OutputKind, find_sources, run_corpus

    report = run_corpus(find_sources(["videos/"]), my_job, "out/",
                        [OutputKind("csv", ".csv", "out")], backend=Backend("ray"))
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import glob
import json
import os
import time
import uuid
from collections.abc import Callable, Iterator
from collections.abc import Sequence as Sequence_
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from torchtrack.errors import BackendError, ConfigError, DataError
from torchtrack.eval.backends import Backend, TaskFailure, check_backend, run_tasks, worker_info
from torchtrack.eval.output_kind import OutputKind
from torchtrack.io.atomic import check_writable_dir
from torchtrack.io.video import IMAGE_EXTENSIONS, VIDEO_EXTENSIONS, natural_key

__all__ = [
    "MANIFEST",
    "CorpusReport",
    "Manifest",
    "OutputKind",
    "find_sources",
    "output_names",
    "run_corpus",
]

MANIFEST = "manifest.jsonl"
_FORMAT = "torchtrack-corpus"
_VERSION = 1
_GLOB_CHARS = frozenset("*?[")


# ---------------------------------------------------------------------------------------------
# Sources
# ---------------------------------------------------------------------------------------------
def _is_frame_folder(d: Path) -> bool:
    return any(
        p.suffix.lower() in IMAGE_EXTENSIONS and not p.name.startswith(".") for p in d.iterdir()
    )


def _videos_in(d: Path) -> list[Path]:
    return sorted(
        (
            p
            for p in d.iterdir()
            if p.suffix.lower() in VIDEO_EXTENSIONS and not p.name.startswith(".") and p.is_file()
        ),
        key=lambda p: natural_key(p.name),
    )


def _expand(spec: str, base: Path | None, from_list: str | None) -> tuple[list[Path], int]:
    """One source argument -> (sources, number of glob matches ignored as not a video)."""
    where = f" (in {from_list})" if from_list else ""
    path = Path(spec).expanduser()
    if base is not None and not path.is_absolute():
        path = base / path
    if spec.isascii() and spec.isdigit() and not path.exists():
        raise ConfigError(
            f"source {spec!r}{where} is a camera index: a corpus run takes videos and frame "
            "folders (a camera never ends)"
        )
    if path.is_dir():
        videos = _videos_in(path)
        if videos:
            return videos, 0
        if _is_frame_folder(path):
            return [path], 0
        raise ConfigError(
            f"folder {str(path)!r}{where} holds no video ({', '.join(sorted(VIDEO_EXTENSIONS))}) "
            "and no image: nothing to track"
        )
    if path.is_file():
        return [path], 0
    if _GLOB_CHARS & set(spec):
        matches = sorted(glob.glob(str(path), recursive=True), key=natural_key)
        if not matches:
            raise ConfigError(f"pattern {spec!r}{where} matches nothing")
        keep, ignored = [], 0
        for m in map(Path, matches):
            if (m.is_file() and m.suffix.lower() in VIDEO_EXTENSIONS) or (
                m.is_dir() and _is_frame_folder(m)
            ):
                keep.append(m)
            else:
                ignored += 1
        if not keep:
            raise ConfigError(
                f"pattern {spec!r}{where} matches {len(matches)} path(s) but no video "
                "file and no frame folder"
            )
        return keep, ignored
    raise ConfigError(f"source {str(path)!r}{where} does not exist")


def find_sources(specs: Sequence_[str], *, log: Callable[[str], None] | None = None) -> list[str]:
    """The sources of a corpus, in order, each once (by real path).

    Each spec is one of:

    * a video file (any format OpenCV reads; one that is not a video fails as that source's
      job, reported, while the others run);
    * a folder: the video files directly in it (natural order), or, when it holds none but
      images, the folder itself as one frame-folder source;
    * a glob pattern (quote it for the shell; ``**`` recurses): the video files and frame
      folders it matches (other matches are ignored and counted);
    * ``@list.txt``: one spec per line (no nested ``@``); blank lines and lines starting with
      ``#`` are skipped; relative paths are relative to the list file's folder.

    Returns:
        Absolute real paths (symlinks resolved), first occurrence kept.

    Raises:
        ConfigError: a path that does not exist, a pattern that matches no video, a folder with
            neither videos nor images, a camera index, an unreadable or empty list file.
    """
    out: list[str] = []
    seen: set[str] = set()
    ignored = 0

    def add(paths: list[Path]) -> None:
        for p in paths:
            real = os.path.realpath(p)
            if real not in seen:
                seen.add(real)
                out.append(real)

    for spec in specs:
        if spec.startswith("@"):
            list_file = Path(spec[1:]).expanduser()
            try:
                lines = list_file.read_text(encoding="utf-8").splitlines()
            except (OSError, UnicodeDecodeError) as exc:
                raise ConfigError(f"cannot read source list {str(list_file)!r}: {exc}") from None
            entries = [ln.strip() for ln in lines]
            entries = [e for e in entries if e and not e.startswith("#")]
            if not entries:
                raise ConfigError(f"source list {str(list_file)!r} names no source")
            for k, e in enumerate(entries):
                if e.startswith("@"):
                    raise ConfigError(
                        f"source list {str(list_file)!r}: entry {k + 1} ({e!r}) is another "
                        "list; lists do not nest"
                    )
                paths, n = _expand(e, list_file.parent, str(list_file))
                ignored += n
                add(paths)
        else:
            paths, n = _expand(spec, None, None)
            ignored += n
            add(paths)
    if ignored and log is not None:
        log(f"ignored {ignored} path(s) matched by a pattern that are not videos or frame folders")
    return out


def _stem(source: str) -> str:
    p = Path(source)
    return p.name if p.is_dir() else p.stem


def output_names(sources: Sequence_[str], taken: dict[str, str] | None = None) -> dict[str, str]:
    """A file name (without suffix) for every source, unique ignoring case.

    A source's name is its file stem (a frame folder's name); sources whose stems clash take
    as many parent folder names as it needs to tell them apart (``cam1_0001``, ``cam2_0001``);
    when no folder does, every parent folder and the extension (``/data/x/clip.mp4``,
    ``/data/x/clip.avi`` -> ``data_x_clip_mp4``, ``data_x_clip_avi``), then a number
    (``clip-2``). ``taken`` maps sources to the names an
    earlier run gave them (the manifest): those are kept, and no other source gets them.
    """
    from torchtrack.eval.runner import safe_name

    taken = dict(taken or {})

    def candidates(src: str) -> list[str]:
        p = Path(src)
        parents = p.parent.parts[1:]  # without the root
        stem = _stem(src)
        out = [stem] + ["_".join((*parents[-k:], stem)) for k in range(1, len(parents) + 1)]
        if p.suffix and not p.is_dir():
            out.append(out[-1] + "_" + p.suffix.lstrip("."))
        return [safe_name(c) for c in out]

    names: dict[str, str] = {s: taken[s] for s in sources if s in taken}
    reserved = {n.casefold() for n in taken.values()}
    new = [s for s in sources if s not in names]
    cands = {s: candidates(s) for s in new}
    level = dict.fromkeys(new, 0)
    while True:
        current = {s: cands[s][level[s]] for s in new}
        groups: dict[str, list[str]] = {}
        for s, n in current.items():
            groups.setdefault(n.casefold(), []).append(s)
        bumped = False
        for key, members in groups.items():
            if len(members) > 1 or key in reserved:
                for s in members:
                    if level[s] + 1 < len(cands[s]):
                        level[s] += 1
                        bumped = True
        if not bumped:
            break
    clash = [cands[s][level[s]].casefold() for s in new]
    used = set(reserved)
    for s in new:
        n = cands[s][level[s]]
        if n.casefold() in used or clash.count(n.casefold()) > 1:
            # No folder tells it apart: number the stem (x-2, x-3, ...).
            k = 2
            while f"{cands[s][0]}-{k}".casefold() in used:
                k += 1
            n = f"{cands[s][0]}-{k}"
        used.add(n.casefold())
        names[s] = n
    return {s: names[s] for s in sources}


# ---------------------------------------------------------------------------------------------
# Manifest
# ---------------------------------------------------------------------------------------------
class Manifest:
    """``manifest.jsonl`` of a corpus folder: the run's settings and a line per finished
    source (the module doc). Lines are appended, flushed and fsynced one by one; a line cut
    short by a crash is dropped when the manifest is opened again.

    Raises:
        ConfigError: the file is not a corpus manifest, or was written with other settings.
    """

    def __init__(self, path: str | os.PathLike, settings: dict, command: str | None = None):
        self.path = Path(path)
        self.entries: dict[str, dict] = {}
        settings = json.loads(json.dumps(settings, default=str))  # as it reads back
        if self.path.exists():
            self._read(settings)
        else:
            header = {
                "format": _FORMAT,
                "version": _VERSION,
                "created": _now(),
                "command": command,
                "settings": settings,
            }
            with open(self.path, "w", encoding="utf-8") as f:
                f.write(json.dumps(header) + "\n")
                f.flush()
                os.fsync(f.fileno())
        self._f = open(self.path, "a", encoding="utf-8")

    def _read(self, settings: dict) -> None:
        raw = self.path.read_bytes()
        if raw and not raw.endswith(b"\n"):  # a line cut short by a crash: drop it
            raw = raw[: raw.rfind(b"\n") + 1]
            with open(self.path, "r+b") as f:
                f.truncate(len(raw))
        lines = raw.decode("utf-8").splitlines()
        try:
            header = json.loads(lines[0]) if lines else None
        except json.JSONDecodeError:
            header = None
        if not isinstance(header, dict) or header.get("format") != _FORMAT:
            raise ConfigError(f"{self.path} is not a torchtrack corpus manifest")
        if header.get("version") != _VERSION:
            raise ConfigError(
                f"{self.path} is a corpus manifest of version {header.get('version')!r}; this "
                f"torchtrack reads version {_VERSION}"
            )
        old = header.get("settings") or {}
        if old != settings:
            diff = [
                f"{k}: {old.get(k)!r} there, {settings.get(k)!r} now"
                for k in sorted(set(old) | set(settings))
                if old.get(k) != settings.get(k)
            ]
            raise ConfigError(
                f"{self.path.parent} holds a corpus run made with other settings ("
                + "; ".join(diff)
                + "): rerun with the same options to resume it, or use another --out-dir"
            )
        for k, line in enumerate(lines[1:], start=2):
            try:
                entry = json.loads(line)
                self.entries[entry["source"]] = entry
            except (json.JSONDecodeError, KeyError, TypeError):
                raise ConfigError(f"{self.path}, line {k}: not a manifest entry") from None

    @property
    def names(self) -> dict[str, str]:
        """Source -> output name, as earlier runs gave them."""
        return {s: e["name"] for s, e in self.entries.items()}

    def complete(self, source: str, kinds: Sequence_[OutputKind]) -> bool:
        """The source's latest line is ``done`` with every kind of ``kinds`` on disk."""
        e = self.entries.get(source)
        if e is None or e.get("status") != "done":
            return False
        outputs = e.get("outputs") or {}
        return all(
            k.name in outputs and (self.path.parent / outputs[k.name]).is_file() for k in kinds
        )

    def append(self, entry: dict) -> None:
        self._f.write(json.dumps(entry) + "\n")
        self._f.flush()
        os.fsync(self._f.fileno())
        self.entries[entry["source"]] = entry

    def close(self) -> None:
        self._f.close()


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


@contextlib.contextmanager
def _locked(folder: Path) -> Iterator[None]:
    """An exclusive lock on ``folder/.manifest.lock`` for the whole run."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows: no lock
        yield
        return
    with open(folder / ".manifest.lock", "w") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise ConfigError(
                f"another corpus run is writing into {folder} (its .manifest.lock is held): "
                "wait for it, or use another --out-dir"
            ) from None
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


# ---------------------------------------------------------------------------------------------
# One source (runs on a worker)
# ---------------------------------------------------------------------------------------------
def _temp_path(out_dir: Path, final: str, token: str, suffix: str) -> Path:
    return out_dir / f".{final}.{token}.part{suffix}"


def _source_task(
    job: Callable[..., Any], source: str, name: str, kinds: tuple[OutputKind, ...], out_dir: str
) -> dict:
    """Run ``job`` on one source into temporary files, then rename them into place."""
    folder = Path(out_dir)
    token = uuid.uuid4().hex[:10]
    tmp = {k.name: _temp_path(folder, name + k.suffix, token, k.suffix) for k in kinds}
    t0 = time.perf_counter()
    try:
        summary = job(source, **{k.keyword: str(tmp[k.name]) for k in kinds})
        for k in kinds:
            if not tmp[k.name].is_file():
                raise DataError(f"{source}: the job finished but wrote no {k.name} output")
        for k in kinds:
            with open(tmp[k.name], "rb+") as f:  # on disk before it gets its final name
                os.fsync(f.fileno())
            os.replace(tmp[k.name], folder / (name + k.suffix))
    finally:
        for p in tmp.values():
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
    return {
        "summary": summary,
        "outputs": {k.name: name + k.suffix for k in kinds},
        "seconds": round(time.perf_counter() - t0, 3),
        "worker": worker_info(),
    }


def _sweep(out_dir: Path, names: Sequence_[str], kinds: Sequence_[OutputKind]) -> None:
    """Remove temporary files left by jobs of these sources whose worker died."""
    for n in names:
        for k in kinds:
            for p in out_dir.glob(glob.escape(f".{n}{k.suffix}.") + "*.part*"):
                with contextlib.suppress(OSError):
                    p.unlink()


# ---------------------------------------------------------------------------------------------
# The whole corpus
# ---------------------------------------------------------------------------------------------
@dataclass
class CorpusReport:
    """What a corpus run did.

    Attributes:
        names: source -> output name.
        done: sources finished in this run; skipped: done by an earlier run;
        failed: source -> ``"Type: message"``.
        manifest: the manifest file.
    """

    out_dir: Path
    manifest: Path
    names: dict[str, str]
    done: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)

    def line(self) -> str:
        return (
            f"{len(self.names)} source(s): {len(self.done)} done, {len(self.skipped)} already "
            f"done (skipped), {len(self.failed)} failed"
        )


def run_corpus(
    sources: Sequence_[str],
    job: Callable[..., Any],
    out_dir: str | os.PathLike,
    kinds: Sequence_[OutputKind],
    *,
    backend: Backend | None = None,
    settings: dict | None = None,
    command: str | None = None,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> CorpusReport:
    """Run ``job`` over every source (module doc).

    Args:
        sources: source paths (:func:`find_sources`).
        job: ``job(source, **{kind.keyword: path})`` writes each output to its path and returns
            a JSON-ready summary; it raises for a source it cannot do. It runs in a worker
            (pickled: a module-level function or a ``functools.partial`` of one).
        out_dir: the corpus folder (created).
        kinds: the outputs every source gets.
        backend: where the jobs run (default: in this process).
        settings: what the outputs depend on (JSON-ready); a rerun must give the same.
        command: the command line, recorded in the manifest.
        progress: a tqdm bar over the sources.
        log: where progress lines go (skipped sources, failures as they happen).

    Returns:
        A :class:`CorpusReport` (failures are in it: they do not raise).

    Raises:
        ConfigError: no source, no or duplicate output kinds, ``out_dir`` cannot be written or
            holds a run with other settings, another run holds its lock.
        BackendError: Ray is not installed or its cluster cannot be reached.
    """
    backend = backend or Backend()
    kinds = tuple(kinds)
    if not sources:
        raise ConfigError("no source to run on")
    if not kinds:
        raise ConfigError("no output kind asked for")
    for attr in ("name", "suffix", "keyword"):
        vals = [getattr(k, attr) for k in kinds]
        if len(set(vals)) != len(vals):
            raise ConfigError(f"output kinds repeat a {attr}: {vals}")
    check_backend(backend)
    created = not Path(out_dir).exists()
    folder = check_writable_dir(out_dir, "--out-dir")
    fresh = not (folder / MANIFEST).exists()
    say = log or (lambda _msg: None)
    recorded: list[str] = []  # sources this run wrote a manifest line for
    try:
        return _run_locked(
            folder, sources, job, kinds, backend, settings, command, progress, say, recorded
        )
    except BackendError:
        # The cluster could not be reached after all (an address that accepts connections
        # but is not Ray passes check_backend's probe): a run that recorded nothing leaves
        # nothing behind, not a manifest of no source or a folder it made.
        if fresh and not recorded:
            _remove_unused(folder, created)
        raise


def _remove_unused(folder: Path, created: bool) -> None:
    """Remove the manifest a failed run began in ``folder`` and, when the run ``created`` the
    folder, its lock file and the folder (if nothing else is in it)."""
    with contextlib.suppress(OSError):
        (folder / MANIFEST).unlink()
    if created:
        with contextlib.suppress(OSError):
            (folder / ".manifest.lock").unlink()
        with contextlib.suppress(OSError):
            folder.rmdir()


def _run_locked(
    folder: Path,
    sources: Sequence_[str],
    job: Callable[..., dict],
    kinds: tuple,
    backend: Backend,
    settings: dict | None,
    command: str | None,
    progress: bool,
    say: Callable[[str], None],
    recorded: list[str],
) -> CorpusReport:
    """:func:`run_corpus` once its arguments are checked: under the folder's lock."""
    from tqdm import tqdm

    with _locked(folder):
        manifest = Manifest(folder / MANIFEST, settings or {}, command)
        try:
            names = output_names(list(sources), manifest.names)
            report = CorpusReport(folder, manifest.path, names)
            todo = []
            for s in sources:
                (report.skipped if manifest.complete(s, kinds) else todo).append(s)
            if report.skipped:
                say(f"skipping {len(report.skipped)} source(s) already done ({manifest.path})")
            # Biggest files first: the last jobs to start are short ones.
            todo.sort(key=lambda s: -os.path.getsize(s) if os.path.isfile(s) else 0)
            bar = tqdm(total=len(todo), unit="source", desc="corpus", disable=not progress)

            def finished(i: int, value: Any) -> None:
                src = todo[i]
                entry: dict[str, Any] = {"source": src, "name": names[src], "finished": _now()}
                if isinstance(value, TaskFailure):
                    entry.update(status="failed", error=value.error)
                    report.failed[src] = value.error
                    say(f"failed: {src}: {value.error}")
                else:
                    entry.update(status="done", **value)
                    report.done.append(src)
                manifest.append(entry)
                recorded.append(src)
                bar.update(1)
                bar.set_postfix_str(f"{len(report.failed)} failed", refresh=False)

            items = [(job, s, names[s], kinds, os.path.abspath(folder)) for s in todo]
            try:
                run_tasks(_source_task, items, backend, finished)
            finally:
                bar.close()
                _sweep(folder, [names[s] for s in todo], kinds)
        finally:
            manifest.close()
    return report
